"""A run: ``engine`` (spec to store), ``master`` (scheduling), ``worker`` (one task), ``comm``
(transports), ``launch`` (one MPI world or none), ``walltime`` (the job's deadline) and ``slurm``
(submission scripts). Imports from ``campaign.plan`` and ``campaign.storage``."""
