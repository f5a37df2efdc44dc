"""What the launcher of this process says: MPI or not, and how many tasks it started.

Standard library only: ``campaign run`` asks before it imports anything heavy, so that all tasks of
a refused launch reach the refusal within moments of each other.
"""

from __future__ import annotations

import os


def mpi_env_detected() -> bool:
    """True when this process was started by an MPI launcher (mpiexec, srun with PMI)."""
    keys = ("PMI_RANK", "PMI_SIZE", "PMIX_RANK", "OMPI_COMM_WORLD_SIZE", "MPI_LOCALNRANKS", "PMI_FD",
            "HYDRA_CONTROL_FD")
    return any(k in os.environ for k in keys)


# Variables in which a launcher says how many tasks it started, and which one it is.
_TASK_COUNTS = (("SLURM_STEP_NUM_TASKS", "srun"), ("PMI_SIZE", "a PMI launcher such as Hydra's mpiexec"),
                ("OMPI_COMM_WORLD_SIZE", "Open MPI's mpirun"), ("PMIX_SIZE", "a PMIx launcher"))
_TASK_RANKS = ("SLURM_PROCID", "PMI_RANK", "OMPI_COMM_WORLD_RANK", "PMIX_RANK")


def launched_tasks(environ=None) -> tuple[int, str | None]:
    """How many tasks the launcher of this process says it started, and which launcher said so.

    (1, None) when no launcher variable says more than one. Under Hydra's mpiexec inside a SLURM
    job, srun starts one proxy per node (SLURM_STEP_NUM_TASKS = nodes) and PMI_SIZE counts the
    ranks: the largest count is the one that matters.
    """
    environ = os.environ if environ is None else environ
    best, who = 1, None
    for key, name in _TASK_COUNTS:
        try:
            k = int(environ.get(key, ""))
        except ValueError:
            continue
        if k > best:
            best, who = k, f"{key}={k}, set by {name}"
    return best, who


def split_launch_error(world: int, environ=None) -> str | None:
    """The message refusing a split launch, or None: the launcher started K > 1 tasks, MPI sees ``world``.

    Each task would then be a master of its own (a world of 1 runs local workers): several masters
    on one file. Every task refuses before it opens the store.
    """
    k, who = launched_tasks(environ)
    if k <= 1 or world > 1:
        return None
    environ = os.environ if environ is None else environ
    rank = next((f" (task {environ[r]})" for r in _TASK_RANKS if r in environ), "")
    return (f"split launch: the launcher says {k} tasks were started ({who}), but this one{rank} is alone "
            f"in its MPI world, so every task would be a master of its own. The launcher did not connect the "
            "tasks to the MPI library: under SLURM start them with `srun --mpi=pmi2` (the MPICH the "
            "package installs; `srun --mpi=list` shows what the cluster offers; `campaign slurm` "
            "writes it), or with the MPI library's own mpiexec; an Open MPI or site MPI needs the srun "
            "--mpi type it was built for (see slurm/README.md). Nothing was written.")
