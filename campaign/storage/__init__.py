"""The store: one HDF5 file per campaign (``store``: the writer; ``layout``: its layout;
``space``: its space accounting, what a write may add and its reservation), its write-ahead
``journal``, the guarded file writes and failures (``faults``), ``checksums``, ``integrity``
(verify's scan, the readers' error) with its findings (``damage``) and their ``repair``, the
progress sidecar (``progress``) and configurations of other programs (``configio``). Imports from
``campaign.plan`` and nothing later on the data's path."""
