"""Parallel ensemble campaigns of jammed frictionless disk packings.

Orchestration lives here (spec, tasks, worker, comm, master, store, reduce,
plots, cli); the numerical work lives in the sibling package ``kernels``.

``campaign.read_packings(path)`` and ``campaign.read_cells(path)`` give a store's
results as pandas DataFrames (``campaign.frames``, the ``frames`` extra); they are
imported on first use, so ``import campaign`` stays cheap.
"""

#: The package version, the one place it is written (pyproject.toml reads it; stores record it as
#: ``package_version``). How it changes: docs/DEVELOPMENT.md, "Versions and the changelog".
__version__ = "0.2.4"

_FRAMES = ("read_packings", "read_cells")


def __getattr__(name):
    if name in _FRAMES:
        from campaign import frames

        return getattr(frames, name)
    raise AttributeError(f"module 'campaign' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_FRAMES))
