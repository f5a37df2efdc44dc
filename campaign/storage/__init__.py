"""The store: one HDF5 file per campaign (``store``: the master's writer, a run's start included;
``layout``: its layout, the task status codes, a run's one look at a file, the stored spec; ``space``:
its space accounting, what a write may add and its reservation), its write-ahead ``journal``, the
guarded file writes and failures (``faults``), ``checksums``, ``reader`` (reading a store from outside
its run: the one checked open, the readers' error), ``integrity`` (verify's scan) on ``blockscan``
(its reading of the block datasets), with its findings (``damage``) and their ``repair``, ``salvage``
(a damaged store's readable rows into a new file), the progress sidecar (``progress``) and
configurations of other programs (``configio``). Imports from ``campaign.plan`` and nothing later on
the data's path."""
