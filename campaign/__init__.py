"""Parallel ensemble campaigns of jammed frictionless disk packings.

Orchestration lives here, in wings along the data's path (docs/DEVELOPMENT.md, "The house"):
``plan`` (the spec, its tasks, their cost) -> ``storage`` (the HDF5 store, its journal, checksums,
progress file) -> ``run`` (engine, master, workers, transports, launch, SLURM) and ``results``
(reducer, fits, figures, frames, exports) -> ``commands`` (one per subcommand) -> ``cli``. A wing
imports only from itself and the wings before it; ``errors`` and ``version`` serve all. The
numerical work lives in the sibling package ``kernels``.

``campaign.read_packings(path)`` and ``campaign.read_cells(path)`` give a store's
results as pandas DataFrames (``campaign.report.frames``, the ``frames`` extra); they are
imported on first use, so ``import campaign`` stays cheap.
"""

from campaign.version import __version__  # noqa: F401 - campaign.__version__

_FRAMES = ("read_packings", "read_cells")


def __getattr__(name):
    if name in _FRAMES:
        from campaign.report import frames

        return getattr(frames, name)
    raise AttributeError(f"module 'campaign' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_FRAMES))
