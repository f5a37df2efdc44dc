"""A campaign's results as tables: pandas DataFrames, read from the store in blocks of rows.

``read_packings(path, variant=None, good=True)``
    one row per finished packing (index ``row``: the store's task row), columns ``id``,
    ``variant``, ``N``, ``E``, ``seed``, ``status`` and every stored scalar under its store
    name (``A_G``, ``N_G``, ``psi_O``, ``gamma`` and ``sigma_xy`` (the cell's tilt and residual
    shear stress; absent from stores written before them), ...). ``good=True`` keeps exactly the packings the
    reducer uses (``campaign.results.finished.first_done`` and ``usable_mask``: done, first row of its
    task id, ``jam_status == 0``, ``identities_ok == 1``); ``good=False`` every finished row.
``read_cells(path)``
    the reducer's per-(variant, N, E) table (``/reduced/cells``), computed by the reducer.
``Packings(path, variant=None, good=True)``
    the rows of ``read_packings`` as blocks of NumPy columns, without pandas (what
    ``campaign export`` streams).

The store is opened read-only with ``locking=False`` (fine while a run writes it), the task
table and the scalars are read in blocks of ``BLOCK_ROWS`` rows, and the histograms are never
read: a store of 10^6 packings loads in the memory of its scalars and task ids. The scalar ``N`` (the
analysis' disk count) is the task's ``N`` and is not repeated. pandas comes with the
``frames`` (or ``export``) extra; without it these functions raise ``MissingExtra``.
"""

from __future__ import annotations

import os

import h5py
import numpy as np

from campaign.errors import UserError, require
from campaign.storage.layout import DONE
from campaign.storage.reader import open_store, read_failure

#: The task table's columns, in this order, before the scalars.
TASK_COLUMNS = ("id", "variant", "N", "E", "seed", "status")
#: Rows read at once: a multiple of the store's 256-row chunks.
BLOCK_ROWS = 65536


def _strings(a) -> np.ndarray:
    """A column of fixed-length bytes (``S``), variable-length strings or bytes (``O``) as an
    object array of ``str``; equal values share one object (a variant column costs 8 bytes
    a row, not its 64)."""
    a = np.asarray(a)
    if a.size == 0:
        return np.empty(a.shape, dtype=object)
    if a.dtype.kind == "S":
        values, inverse = np.unique(a, return_inverse=True)
        names = np.array([v.decode("utf-8", "replace") for v in values], dtype=object)
        return names[inverse.reshape(a.shape)]
    if a.dtype.kind == "O":
        return np.array([x.decode("utf-8", "replace") if isinstance(x, bytes) else str(x) for x in a],
                        dtype=object)
    return a.astype(str).astype(object)


class Packings:
    """The finished packings of one campaign store, read in blocks of rows.

    ``with Packings(path, variant, good) as pk: for block in pk.blocks(): ...``: each block is
    a dict ``{column: (n,) array}`` over ``pk.columns`` (``row`` first, then ``TASK_COLUMNS``,
    then the scalars), in store order. ``variant``: a name, a list of names, or None (all).
    Problems with the file raise ``UserError``.
    """

    def __init__(self, path, variant=None, good=True, *, block=BLOCK_ROWS):
        self.path = os.fspath(path)
        self.good = bool(good)
        self.block = int(block)
        if self.block <= 0:
            raise ValueError(f"block: expected a positive number of rows, got {block}")
        self._f = open_store(self.path, accept="layout")  # a file of the layout without a schema is read too
        try:
            self._setup(variant)
        except UserError:
            self._f.close()
            raise
        except Exception as exc:  # noqa: BLE001 - read_failure says which failures are the file's
            err = self._failure(exc, ["tasks", "scalars"])
            self._f.close()
            if err is None:
                raise
            raise err from None
        except BaseException:
            self._f.close()
            raise

    def _failure(self, exc, patterns):
        return read_failure(self.path, exc, self._f, patterns)

    # ------------------------------------------------------------------ opening
    def _setup(self, variant):
        f = self._f
        if not isinstance(f.get("tasks"), h5py.Group):
            raise UserError(f"{self.path}: not a campaign store (no /tasks table of datasets); expected the "
                            "layout of docs/STORE.md")
        t = f["tasks"]
        missing = [k for k in ("status", "id", "N", "E") if k not in t]
        if missing:
            raise UserError(f"{self.path}: /tasks has no column {missing[0]!r}; expected the layout of "
                            "docs/STORE.md")
        self.attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        self.n_tasks = int(t["status"].shape[0])
        self.scalar_names = sorted(f["scalars"].keys()) if "scalars" in f else []
        self._own_scalars = [n for n in self.scalar_names if n not in TASK_COLUMNS]
        dt = {"N": t["N"].dtype, "E": t["E"].dtype, "status": t["status"].dtype,
              "seed": t["seed"].dtype if "seed" in t else np.dtype(np.int64)}
        self.columns = ([("row", np.dtype(np.int64)), ("id", np.dtype(object)), ("variant", np.dtype(object))]
                        + [(k, dt[k]) for k in ("N", "E", "seed", "status")]
                        + [(n, f[f"scalars/{n}"].dtype) for n in self._own_scalars])
        self.variants = None
        if variant is None:
            self._wanted = None
        else:
            wanted = [variant] if isinstance(variant, str) else [str(v) for v in variant]
            present = self._all_variants()
            unknown = [v for v in wanted if v not in present]
            if unknown:
                raise UserError(f"{self.path}: no variant {unknown[0]!r} in the store (its variants: "
                                f"{', '.join(sorted(present)) or 'none'})")
            self._wanted = np.array(wanted, dtype=object)

    def _all_variants(self) -> set:
        t = self._f["tasks"]
        if "variant" not in t:
            return {"default"}
        out = set()
        for lo in range(0, self.n_tasks, self.block):
            out.update(np.unique(_strings(t["variant"][lo:lo + self.block])).tolist())
        self.variants = sorted(out)
        return out

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        self._f.close()

    # ------------------------------------------------------------------ reading
    def blocks(self):
        """Yield the selected packings block by block (see the class docstring)."""
        from campaign.results.finished import first_done, usable_mask

        f, t = self._f, self._f["tasks"]
        try:
            status = np.asarray(t["status"][...])  # one byte a task; read first: the commit marker
            seen = set()
            for lo in range(0, self.n_tasks, self.block):
                hi = min(lo + self.block, self.n_tasks)
                st = status[lo:hi]
                if not np.any(st == DONE):
                    continue
                ids = _strings(t["id"][lo:hi])
                keep = first_done(ids, st, seen)
                var = (_strings(t["variant"][lo:hi]) if "variant" in t
                       else np.full(hi - lo, "default", dtype=object))
                if self._wanted is not None:
                    keep &= np.isin(var, self._wanted)
                idx = np.flatnonzero(keep)
                if idx.size == 0:
                    continue
                scal = {n: np.asarray(f[f"scalars/{n}"][lo:hi])[idx] for n in self.scalar_names}
                if self.good:
                    ok, _ = usable_mask(scal, idx.size)
                    idx = idx[ok]
                    scal = {n: v[ok] for n, v in scal.items()}
                    if idx.size == 0:
                        continue
                out = {"row": (lo + idx).astype(np.int64), "id": ids[idx], "variant": var[idx],
                       "N": np.asarray(t["N"][lo:hi])[idx], "E": np.asarray(t["E"][lo:hi])[idx],
                       "seed": (np.asarray(t["seed"][lo:hi])[idx] if "seed" in t
                                else np.full(idx.size, -1, np.int64)),
                       "status": st[idx]}
                out.update((n, scal[n]) for n in self._own_scalars)
                yield out
        except Exception as exc:  # noqa: BLE001 - read_failure says which failures are the file's
            err = self._failure(exc, ["tasks", "scalars"])
            if err is None:
                raise
            raise err from None

    @property
    def n_configurations(self) -> int:
        """How many packings of the store keep their configuration (``/configurations/<id>``)."""
        try:
            g = self._f.get("configurations")
            return len(g) if g is not None else 0
        except Exception as exc:  # noqa: BLE001 - read_failure says which failures are the file's
            err = self._failure(exc, ["configurations"])
            if err is None:
                raise
            raise err from None

    def configuration(self, task_id):
        """The stored configuration of a task: ``{"positions", "radii", "box", "species"}`` (float64,
        species int; ``box`` is ``[Lx, Ly]``, or ``[Lx, Ly, xy]`` for a tilted cell), or None when the
        store did not keep it."""
        from campaign.storage.checksums import check_configuration

        name = f"configurations/{task_id}"
        try:
            g = self._f.get(name)
        except Exception as exc:  # noqa: BLE001 - read_failure says which failures are the file's
            err = self._failure(exc, [name])
            if err is None:
                raise
            raise err from None
        if g is None:
            return None
        got = check_configuration(g, self.path, name)  # StoreDamaged if it fails its checksum
        try:
            out = {k: np.asarray(got[k]) for k in ("positions", "radii", "box")}
            n = out["radii"].shape[0]
            out["species"] = (np.asarray(got["species"]).astype(np.int64) if "species" in got
                              else np.zeros(n, np.int64))
        except (KeyError, ValueError, IndexError) as exc:  # the writer writes all four: the store is damaged
            from campaign.errors import StoreDamaged
            from campaign.storage.checksums import damaged_message

            raise StoreDamaged(damaged_message(self.path, f"{name} (the configuration of task {task_id!r})",
                                               f"is incomplete ({type(exc).__name__}: {exc})")) from None
        return out

    def read_all(self) -> dict:
        """Every selected packing: ``{column: array}`` (the blocks concatenated)."""
        parts = {name: [] for name, _ in self.columns}
        for b in self.blocks():
            for name in parts:
                parts[name].append(b[name])
        return {name: (np.concatenate(parts[name]) if parts[name] else np.empty(0, dtype))
                for name, dtype in self.columns}


def read_packings(path, variant=None, good=True, *, block=BLOCK_ROWS):
    """The finished packings of a campaign store as a pandas DataFrame (see the module docstring).

    ``variant``: a variant's name (or a list of names) to keep; None keeps all. ``good``: True
    keeps the packings the reducer uses, False every finished row (then ``jam_status`` and
    ``identities_ok`` say which are which). The index is the store's task row.
    """
    pd = require("pandas", "frames", "campaign.read_packings")
    with Packings(path, variant, good, block=block) as pk:
        cols = pk.read_all()
        attrs = {"path": pk.path, "name": str(pk.attrs.get("name", "")), "good": pk.good}
    index = pd.Index(cols.pop("row"), name="row")
    df = pd.DataFrame(cols, index=index)
    df.attrs.update(attrs)
    return df


def read_cells(path, settings=None):
    """The reducer's per-(variant, N, E) table as a pandas DataFrame: the columns of
    ``/reduced/cells`` (docs/REDUCED.md: ``n_packings``, ``n_excluded``, ``n_pending``,
    ``n_failed``, ``n_tasks``, ``mean_``/``std_``/``sem_`` of every scalar, the Gaussian fit of
    P(A_G)), computed by ``campaign.results.reduce.reduce_campaign`` itself (without the histograms and
    without bootstrap resamples, which the cells do not use). ``path`` may be a list of stores,
    pooled as ``campaign reduce`` pools them."""
    pd = require("pandas", "frames", "campaign.read_cells")
    from campaign.results.reduce import Settings, reduce_campaign

    red = reduce_campaign(path, settings or Settings(n_boot=0), distributions=False)
    df = pd.DataFrame({k: np.asarray(v) for k, v in red.cells.items()})
    df.attrs.update(path=[str(p) for p in red.meta["sources"]], name=str(red.meta.get("name", "")))
    return df
