"""The store: one HDF5 file per campaign (``store``: the writer; ``storefile``: its layout;
``storespace``: what a write may add), its write-ahead ``journal``, the guarded file writes and
failures (``faults``), ``checksums`` and ``integrity`` (verify, repair, the readers' error), the
progress sidecar (``progress``) and configurations of other programs (``configio``). Imports from
``campaign.plan`` and nothing later on the data's path."""
