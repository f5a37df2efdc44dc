"""The campaign store's HDF5 layout: its names and types, the format version, creating a
fresh file, checking an existing one against a spec, and salvaging a damaged one.

``campaign.store`` (the master's writer) and the readers use these; everything here is
re-exported by ``campaign.store``. The layout itself is documented in docs/STORE.md.

Creating and salvaging write a new file under a temporary name (``OUT.tmp``), reserve the
space they need first (``campaign.faults.reserve``), and rename it into place only when it
is complete and durable: a full disk at any point leaves the existing store as it was and
removes the temporary file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from campaign.errors import UserError
from campaign.faults import GuardedFile, release, reserve, write_fault

SCHEMA = "jamming-campaign/1"
#: Layout version of the store (root attribute ``format_version``). 1 (no attribute): dense
#: histograms, journal holding every row, A_G and A_V absolute areas, rattlers without the
#: half-plane rule. 2: chunked compressed rows, checkpointed journal, A_G and A_V as
#: fractions of the box area, a grain whose contacts lie in a closed half-plane is a rattler.
FORMAT_VERSION = 2
PENDING, DONE, FAILED = 0, 1, 2
HOST_LEN, ERROR_LEN, VARIANT_LEN = 64, 512, 64
TASK_FIELDS = ("id", "variant", "N", "E", "seed", "status", "attempts", "wall", "rank", "host", "error")
ROW_FIELDS = ("attempts", "wall", "rank", "host", "error")  # written when a task finishes
COMPRESSION = dict(compression="gzip", compression_opts=1, shuffle=True)
CHUNK_CACHE = 1 << 20  # HDF5 chunk cache per open dataset (whole blocks are written; little to cache)
#: Bytes kept free on top of every estimate of what an HDF5 write needs (object headers,
#: chunk indices and symbol tables that grow or move while it writes; the store adds more
#: per dataset and for large files).
SLACK = 32 << 10


def fill_value(name):
    return {"attempts": 0, "wall": np.nan, "rank": -1, "host": b"", "error": b""}[name]


def row_dtype(name):
    return {"attempts": np.int32, "wall": np.float64, "rank": np.int32, "host": f"S{HOST_LEN}",
            "error": f"S{ERROR_LEN}"}[name]


def fixed(text: str, n: int) -> bytes:
    return text.encode("utf-8", "replace")[:n]


def fsync_path(path):
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def dataset_kwargs(B, shape, fill):
    chunks = (B,) + tuple(shape[1:])
    return dict(shape=shape, chunks=chunks, fillvalue=fill, **COMPRESSION)


# --------------------------------------------------------------------------- format version

OLD_FORMAT_HELP = (
    "this version writes store format {new} (chunked, compressed rows and a checkpointed journal); "
    "besides the layout, the per-packing results changed meaning: A_G and A_V are now fractions of the "
    "box area (they were absolute areas) and a grain whose contacts lie in a closed half-plane is now a "
    "rattler, so the old rows cannot be converted. Run the spec again into a new file (packings are pure "
    "functions of the spec, so the rerun is reproducible; a few jams stop at another step than before, "
    "since the force residual uses the new rattler rule): campaign run SPEC --out NEW.h5 (or --new to "
    "replace this file); the spec is stored in the file's 'spec_yaml' attribute")


def format_problem(attrs, path) -> str | None:
    """Why a campaign file of another store format cannot be used (None if it can)."""
    schema = attrs.get("schema")
    if isinstance(schema, bytes):
        schema = schema.decode(errors="replace")
    if schema != SCHEMA:
        return (f"{str(path)!r} is not a campaign store of this program (schema {schema!r}, expected "
                f"{SCHEMA!r})")
    try:
        version = int(attrs.get("format_version", 1))
    except (TypeError, ValueError):
        version = -1
    if version == FORMAT_VERSION:
        return None
    if version < FORMAT_VERSION:
        return (f"{str(path)!r} was written in store format {version}, which this version no longer reads; "
                + OLD_FORMAT_HELP.format(new=FORMAT_VERSION))
    return (f"{str(path)!r} was written in store format {version} by a newer version of this program "
            f"(this one reads format {FORMAT_VERSION}); upgrade jamming-campaign to read it")


def check_format(attrs, path):
    """Raise UserError (exit 2) for a file of another schema or store format."""
    problem = format_problem(attrs, path)
    if problem is not None:
        raise UserError(problem)


# --------------------------------------------------------------------------- checking

def check_file(path, spec_hash, tasks, edges, B, touched=()):
    """None if the file is a valid store of this spec; 'refuse:...' if it belongs to another;
    else what is wrong with it (it is then salvaged).

    ``touched``: the blocks the journal's records go to, the only ones a killed run can
    have been writing; each of their chunks must decompress.
    """
    import h5py

    T = len(tasks)
    try:
        with h5py.File(path, "r", locking=False) as f:
            problem = format_problem(f.attrs, path)
            if problem is not None:
                return "refuse:" + problem
            if f.attrs.get("spec_hash") != spec_hash:
                return (f"refuse:{str(path)!r} was written by a different spec (name "
                        f"{f.attrs.get('name')!r}, spec hash {f.attrs.get('spec_hash')}; this spec's hash is "
                        f"{spec_hash}); rerun with --new to overwrite it, or choose another --out")
            for name in TASK_FIELDS:
                if f[f"tasks/{name}"].shape != (T,):
                    return f"tasks/{name} has the wrong shape"
            ids = f["tasks/id"]
            for lo in range(0, T, 65536):
                hi = min(lo + 65536, T)
                want = np.array([t.id.encode() for t in tasks[lo:hi]], "S32")
                if not np.array_equal(ids[lo:hi], want):
                    return "its task ids differ from the spec's"
            for h, e in edges.items():
                if f[f"histograms/{h}/counts"].shape != (T, len(e) - 1):
                    return f"histograms/{h}/counts has the wrong shape"
                if not np.array_equal(f[f"histograms/{h}/edges"][:], e):
                    return (f"refuse:the bin edges of histogram {h!r} in {str(path)!r} differ from "
                            "the ones this installation would use (the default bins changed?); pin them "
                            "in the spec's 'bins', or rerun with --new")
            for name in f["scalars"]:
                if f[f"scalars/{name}"].shape != (T,):
                    return f"scalars/{name} has the wrong shape"
            # groups written under a SIGKILL can be torn (unreadable, or missing a dataset)
            for tid, g in (f["configurations"].items() if "configurations" in f else ()):
                for k in ("positions", "radii", "box", "species"):
                    if k not in g:
                        return f"configurations/{tid} lacks {k}"
                    g[k].shape
            for g in (f["failures"].values() if "failures" in f else ()):
                dict(g.attrs)
            names = [f"tasks/{n}" for n in ROW_FIELDS] + [f"scalars/{n}" for n in f["scalars"]]
            names += [f"histograms/{h}/counts" for h in edges]
            for name in names:
                ds = f[name]
                for b in sorted(touched):
                    ds[b * B:(b + 1) * B]
            f["tasks/status"][:]
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as exc:
        return f"{type(exc).__name__}: {exc}"
    return None


def load_state(path, status, attempts, wall):
    """The scheduler's columns of a valid store, read into the given arrays."""
    import h5py

    with h5py.File(path, "r", locking=False) as f:
        status[:] = f["tasks/status"][:]
        attempts[:] = f["tasks/attempts"][:]
        wall[:] = f["tasks/wall"][:]


# --------------------------------------------------------------------------- creating, salvaging

def creation_bytes(T, edges, salvage_from=None) -> int:
    """A generous estimate of the bytes a new store of T tasks takes (plus the damaged
    store's size when its rows are salvaged into it)."""
    raw = T * (32 + VARIANT_LEN + 8 + 8 + 8 + 1) + 64 * (T // 256 + 1) * 16
    raw += sum(8 * len(e) for e in edges.values())
    extra = 0
    if salvage_from is not None:
        try:
            extra = os.stat(salvage_from).st_size
        except OSError:
            extra = 0
    return int(1.05 * (raw + extra)) + 8 * SLACK


def create_file(path, spec, tasks, edges, B, *, salvage=False, state=None):
    """A fresh store at ``path``, created under a temporary name and renamed into place.

    With ``salvage``, the committed rows that can still be read from the damaged file at
    ``path`` are copied into it (block by block; a block that cannot be read is lost and its
    tasks are pending again), and ``state`` (status, attempts, wall arrays) gets their values.
    The space it needs is reserved first; a full disk (OutOfSpace) or any other fault
    removes the temporary file and leaves ``path`` as it was.
    """
    import h5py

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    if tmp.exists():
        tmp.unlink()
    need = creation_bytes(len(tasks), edges, path if salvage else None)
    what = "salvaging the damaged store into a new file" if salvage else "creating the store"
    f = io = None
    try:
        io = GuardedFile(tmp, create=True)
        reserved = reserve(io.fd, need, tmp, what)  # before HDF5 writes its first byte
        f = h5py.File(io, "w")
        _write_layout(f, spec, tasks, edges, B)
        if salvage:
            _salvage_into(f, path, tasks, edges, B, state)
        f.flush()
        if io.failed is not None:
            raise io.failed
        f.close()
        f = None
        if io.failed is not None:
            raise io.failed
        release(io.fd, reserved)
        os.fsync(io.fd)
        io.close()
        os.replace(tmp, path)
    except BaseException as exc:
        if f is not None:
            io.discard()
            try:
                f.close()
            except Exception:  # noqa: BLE001 - its writes go nowhere
                pass
        if io is not None:
            io.close()
        try:
            tmp.unlink()
        except OSError:
            pass
        fault = write_fault(exc, tmp, what, needed=need)
        if fault is not None and fault is not exc:
            raise fault from None
        raise


def _write_layout(f, spec, tasks, edges, B):
    T = len(tasks)
    g = f.create_group("tasks")
    cols = {"id": "S32", "variant": f"S{VARIANT_LEN}", "N": np.int64, "E": np.float64, "seed": np.int64}
    for name, dt in cols.items():
        g.create_dataset(name, dtype=dt, **dataset_kwargs(B, (T,), None))
    for lo in range(0, T, 65536):
        part = tasks[lo:lo + 65536]
        hi = lo + len(part)
        g["id"][lo:hi] = np.array([t.id.encode() for t in part], "S32")
        g["variant"][lo:hi] = np.array([fixed(t.variant, VARIANT_LEN) for t in part], f"S{VARIANT_LEN}")
        g["N"][lo:hi] = np.array([t.N for t in part], np.int64)
        g["E"][lo:hi] = np.array([t.E for t in part], np.float64)
        g["seed"][lo:hi] = np.array([t.seed for t in part], np.int64)
    g.create_dataset("status", shape=(T,), dtype=np.int8)  # contiguous: the commit marker
    for name in ROW_FIELDS:
        g.create_dataset(name, dtype=row_dtype(name), **dataset_kwargs(B, (T,), fill_value(name)))
    f.create_group("scalars")
    hg = f.create_group("histograms")
    for h, e in edges.items():
        hg.create_dataset(f"{h}/edges", data=e)
        hg.create_dataset(f"{h}/counts", dtype=np.int64, **dataset_kwargs(B, (T, len(e) - 1), 0))
    if spec.configurations:
        f.create_group("configurations")
    f.create_group("failures")
    f.attrs["schema"] = SCHEMA
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["spec_hash"] = spec.hash
    f.attrs["name"] = spec.name
    f.attrs["spec_yaml"] = spec.text


def _salvage_into(f, old_path, tasks, edges, B, state):
    """Copy every readable committed row of the damaged store ``old_path`` into ``f``."""
    import h5py

    T = len(tasks)
    status, attempts, wall = state
    try:
        old = h5py.File(old_path, "r", locking=False)
    except (OSError, ValueError, RuntimeError):
        return
    with old:
        try:
            attrs = dict(old.attrs)
            if "runs" in attrs:
                f.attrs["runs"] = attrs["runs"]
        except (OSError, KeyError, ValueError, RuntimeError):
            pass
        try:
            scalar_names = list(old["scalars"].keys())
        except (OSError, KeyError, ValueError, RuntimeError):
            scalar_names = []
        for lo in range(0, T, B):
            hi = min(lo + B, T)
            try:
                st = old["tasks/status"][lo:hi]
                rows = np.flatnonzero(st != PENDING)
                if not len(rows):
                    continue
                data = {f"tasks/{n}": old[f"tasks/{n}"][lo:hi] for n in ROW_FIELDS}
                for n in scalar_names:
                    data[f"scalars/{n}"] = old[f"scalars/{n}"][lo:hi]
                for h in edges:
                    data[f"histograms/{h}/counts"] = old[f"histograms/{h}/counts"][lo:hi]
                extra = {}
                for r in rows:
                    tid = tasks[lo + r].id
                    if "configurations" in old and tid in old["configurations"]:
                        g = old[f"configurations/{tid}"]
                        extra[("c", tid)] = {k: g[k][()] for k in ("positions", "radii", "box", "species")}
                    if st[r] == FAILED and "failures" in old and tid in old["failures"]:
                        extra[("f", tid)] = dict(old[f"failures/{tid}"].attrs)
            except (OSError, KeyError, ValueError, RuntimeError, TypeError):
                continue  # this block is lost: its tasks are pending again
            for name, a in data.items():
                if name.startswith("scalars/") and name not in f:
                    f["scalars"].create_dataset(name[8:], dtype=np.float64, **dataset_kwargs(B, (T,), np.nan))
                f[name][lo:hi] = a
            for (kind, tid), v in extra.items():
                if kind == "c":
                    g = f.require_group("configurations").create_group(tid)
                    for k, a in v.items():
                        g.create_dataset(k, data=a)
                else:
                    g = f["failures"].create_group(tid)
                    for k, a in v.items():
                        g.attrs[k] = a
            f["tasks/status"][lo:hi] = st
            status[lo:hi] = st
            attempts[lo:hi] = data["tasks/attempts"]
            wall[lo:hi] = data["tasks/wall"]
