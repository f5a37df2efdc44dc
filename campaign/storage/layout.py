"""The campaign store's HDF5 layout: its names and types, the format version, a block of rows
built from the tasks' records, creating a fresh file, and checking an existing one against a spec.

``campaign.storage.store`` (the master's writer), ``campaign.storage.space`` (the space
accounting), ``campaign.storage.salvage`` (a damaged store's readable rows copied into a new file)
and the readers use these; nothing here imports them back. The store re-exports the names it held
before the layout was split out. The layout itself is documented in docs/STORE.md.

A block's columns are built once, here, for both who need them: the writer (``column_block`` of
``block_values``), and the space accounting, which compresses the same arrays to estimate a first
write's size.

Creating writes a new file under a temporary name (``OUT.tmp``), reserves the space it needs
first (``campaign.storage.faults.reserve``), and renames it into place only when it is complete
and durable: a full disk at any point leaves the existing store as it was and removes the
temporary file. Salvaging creates its file the same way (``create_file``'s ``fill``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaign.errors import UserError
from campaign.plan.parse import parse_spec
from campaign.storage.checksums import (PROTECTION_ATTR, _text, block_sums, checksums_on, create_fill_sums,
                                        create_sums, protection_text, write_sums)
from campaign.storage.faults import GuardedFile, release, reserve, write_fault

BLOCK_ROWS = 256        # rows per chunk of every per-task dataset

SCHEMA = "jamming-campaign/1"
#: Layout version of the store (root attribute ``format_version``). 1 (no attribute): dense
#: histograms, journal holding every row, A_G and A_V absolute areas, rattlers without the
#: half-plane rule. 2: chunked compressed rows, checkpointed journal, A_G and A_V as
#: fractions of the box area, a grain whose contacts lie in a closed half-plane is a rattler.
FORMAT_VERSION = 2
#: A task row's status (``tasks/status``, the commit marker), defined here once for every wing.
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


def status_counts(status) -> dict:
    """How many rows of a status column say done, failed and pending (in that order)."""
    st = np.asarray(status)
    return {"done": int(np.count_nonzero(st == DONE)), "failed": int(np.count_nonzero(st == FAILED)),
            "pending": int(np.count_nonzero(st == PENDING))}


def fill_value(name):
    return {"attempts": 0, "wall": np.nan, "rank": -1, "host": b"", "error": b""}[name]


def row_dtype(name):
    return {"attempts": np.int32, "wall": np.float64, "rank": np.int32, "host": f"S{HOST_LEN}",
            "error": f"S{ERROR_LEN}"}[name]


def fixed(text: str, n: int) -> bytes:
    return text.encode("utf-8", "replace")[:n]


def row_values(meta, arrays, edges, columns=None):
    """The values a task's journal record (``meta``, ``arrays``) puts into its row, per dataset
    name (``edges``: the histograms' bin edges); with ``columns``, those datasets' values only,
    a missing one as the dataset's fill (histogram rows as zeros, scalars as NaN, else None)."""
    status = int(meta["status"])
    out = {"tasks/attempts": int(meta["attempts"]), "tasks/wall": float(meta["wall"]),
           "tasks/rank": int(meta["rank"]), "tasks/host": fixed(meta["host"], HOST_LEN),
           "tasks/error": fixed(meta["message"], ERROR_LEN) if status == FAILED else b""}
    if "scalar_names" in meta:
        names = meta["scalar_names"].split(",") if meta["scalar_names"] else []
        sc = dict(zip(names, arrays["s"].tolist()))
    else:
        sc = meta.get("scalars", {})
    for name, v in sc.items():
        out[f"scalars/{name}"] = float(v)
    for h, e in edges.items():
        a = arrays.get("h/" + h)
        out[f"histograms/{h}/counts"] = a if a is not None and a.shape == (len(e) - 1,) else None
    if columns is not None:
        res = {}
        for c in columns:
            if c in out:
                res[c] = np.zeros(len(edges[c.split("/")[1]]) - 1, np.int64) if out[c] is None else out[c]
            elif c.startswith("scalars/"):
                res[c] = np.nan
            else:
                res[c] = None
        return res
    return out


def column_layout(name, edges):
    """(dtype, fill value, row shape) of the per-task column ``name`` a task's row goes to
    (``tasks/<field>``, ``scalars/<name>``, ``histograms/<h>/counts``)."""
    if name.startswith("histograms/"):
        return np.dtype(np.int64), 0, (len(edges[name.split("/")[1]]) - 1,)
    if name.startswith("scalars/"):
        return np.dtype(np.float64), np.nan, ()
    field = name[len("tasks/"):]
    return np.dtype(row_dtype(field)), fill_value(field), ()


def block_values(rows, lo, edges):
    """The rows of one block as the columns take them: (their offsets in the block, from ``lo``;
    their values per dataset name, ``row_values``), in ``rows``' order (row -> its journal
    record (meta, arrays))."""
    idx = np.fromiter(rows, np.int64, len(rows)) - lo
    return idx, [row_values(m, a, edges) for m, a in rows.values()]


def column_block(name, n, idx, values, edges, block=None):
    """Column ``name`` of a block of ``n`` rows with the rows ``idx`` set to their ``values``
    (``block_values``); a row without a value gets the column's fill (a histogram row, zeros).
    The other rows are the column's fill, or those of ``block`` (the block as the file holds it,
    set in place) when given."""
    dtype, fill, shape = column_layout(name, edges)
    if block is None:
        block = np.full((n,) + shape, fill, dtype=dtype)
    col = [v.get(name) for v in values]
    if shape:  # histogram rows
        zero = np.zeros(shape, dtype)
        block[idx] = np.stack([zero if x is None else x for x in col])
    else:
        block[idx] = np.array([fill if x is None else x for x in col], dtype=dtype)
    return block


def fsync_path(path):
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def dataset_kwargs(B, shape, fill):
    """A per-task block dataset: chunks of ``B`` rows, shuffled, deflated, and HDF5's fletcher32
    checksum on each chunk (written last, checked first on every read; ``campaign.storage.checksums``)."""
    chunks = (B,) + tuple(shape[1:])
    return dict(shape=shape, chunks=chunks, fillvalue=fill, fletcher32=checksums_on(), **COMPRESSION)


def edges_kwargs(e):
    """A histogram's bin edges: one chunk with its checksum (contiguous without checksums)."""
    e = np.asarray(e, np.float64)
    if checksums_on():
        return dict(data=e, chunks=e.shape, fletcher32=True)
    return dict(data=e)


# --------------------------------------------------------------------------- format version

OLD_FORMAT_HELP = (
    "this version writes store format {new} (chunked, compressed rows and a checkpointed journal); "
    "besides the layout, the per-packing results changed meaning: A_G and A_V are now fractions of the "
    "box area (they were absolute areas) and a grain whose contacts lie in a closed half-plane is now a "
    "rattler, so the old rows cannot be converted. Run the spec again into a new file (packings are pure "
    "functions of the spec, so the rerun is reproducible; a few jams stop at another step than before, "
    "since the force residual uses the new rattler rule): campaign run SPEC --out NEW.h5 (or --new to "
    "replace this file); the spec is stored in the file's 'spec_yaml' attribute")


class ForeignStore(UserError):
    """A file no run or reader of this program may use as the store it was given: another program's
    file, a store of another format, or (for a run) a store of another spec or other bins. Exit status
    2; the message says what it is and what to do."""


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


def _before_gpu_block(attrs) -> bool:
    """Whether a store's ``device: gpu`` packings are the first GPU block's, which no protocol key
    named: a store written before 0.3.0 (its ``package_version``; the block was rewritten then and
    named ``gpu_block``, ``campaign.plan.spec.GPU_BLOCK``). A store without a readable version is
    taken as the present one's."""
    version = _text(attrs.get("package_version")) or ""
    try:
        return tuple(int(p) for p in version.split(".")[:3]) < (0, 3, 0)
    except ValueError:
        return False


def stored_spec(source, *, verified=False, strict=False, name="the stored spec"):
    """The spec that wrote a store: its root attribute ``spec_yaml`` parsed (``campaign.plan.parse.parse_spec``),
    the one place that reads it. ``source``: the store's root attributes (a mapping), or an open h5py
    file (its ``attrs``).

    None when the store holds no spec text, or one that does not parse (a spec of another version or
    program, a damaged attribute): each caller says what it does without (the paper's system, no
    check). ``verified``: None also when the spec does not hash to the store's ``spec_hash`` (a file
    made otherwise, by hand or by another program, whose spec does not describe it). ``strict``: a
    text that does not parse raises its UserError, ``name`` saying whose spec it is."""
    attrs = getattr(source, "attrs", source)
    text = _text(attrs.get("spec_yaml"))
    if text is None:
        return None
    try:
        spec = parse_spec(text, name, first_gpu_block=_before_gpu_block(attrs))
    except UserError:
        if strict:
            raise
        return None
    if verified and spec.hash != _text(attrs.get("spec_hash")):
        return None
    return spec


def check_format(attrs, path):
    """Raise ForeignStore (exit 2) for a file of another schema or store format."""
    problem = format_problem(attrs, path)
    if problem is not None:
        raise ForeignStore(problem)


# --------------------------------------------------------------------------- checking

@dataclass(frozen=True)
class Verdict:
    """What a run's start does with the file at its store's path (``inspect``): ``"keep"`` it (its
    ``state`` read), ``"salvage"`` its readable rows into a new file (``problem``: what is wrong with
    it), or ``"create"`` one."""

    action: str
    problem: str | None = None
    state: State | None = None


def inspect(path, spec_hash, tasks, edges, B, touched=()) -> Verdict:
    """One read-only look at the file a run of the spec ``spec_hash`` starts from: kept (with the
    scheduler's ``State`` read) when it is a sound store of the spec, salvaged when it is damaged,
    created when there is none. ForeignStore when it belongs to another program, store format or
    spec, or has other bin edges; a sound store whose state cannot be read raises what h5py raised
    (the caller names the damage).

    ``touched``: the blocks the journal's records go to, the only ones a killed run can
    have been writing; each of their chunks must decompress.
    """
    import h5py  # here, not with the module: the layout's names serve readers of no HDF5 (see create_file)

    if not Path(path).exists():
        return Verdict("create")
    try:
        f = h5py.File(path, "r", locking=False)
    except Exception as exc:  # noqa: BLE001 - a file HDF5 cannot open: salvage it
        return Verdict("salvage", f"{type(exc).__name__}: {exc}")
    with f:
        problem = _problem(f, path, spec_hash, tasks, edges, B, touched)
        if problem is not None:
            return Verdict("salvage", problem)
        return Verdict("keep", state=State.read(f))


def _problem(f, path, spec_hash, tasks, edges, B, touched):
    """What is wrong with the store ``f`` at ``path`` (None: nothing); ForeignStore when it is not
    this spec's store at all."""
    T = len(tasks)
    try:
        check_format(f.attrs, path)
        if f.attrs.get("spec_hash") != spec_hash:
            raise ForeignStore(f"{str(path)!r} was written by a different spec (name "
                               f"{f.attrs.get('name')!r}, spec hash {f.attrs.get('spec_hash')}; this spec's hash "
                               f"is {spec_hash}); rerun with --new to overwrite it, or choose another --out")
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
                raise ForeignStore(f"the bin edges of histogram {h!r} in {str(path)!r} differ from the ones this "
                                   "installation would use (the default bins changed?); pin them in the spec's "
                                   "'bins', or rerun with --new")
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
            dict(g.attrs)  # an object that is not a group (a damaged header) fails here too
        names = [f"tasks/{n}" for n in ROW_FIELDS] + [f"scalars/{n}" for n in f["scalars"]]
        names += [f"histograms/{h}/counts" for h in edges]
        for name in names:
            ds = f[name]
            for b in sorted(touched):
                ds[b * B:(b + 1) * B]
        f["tasks/status"][:]
    except ForeignStore:
        raise
    except Exception as exc:  # noqa: BLE001 - whatever a damaged file makes h5py raise: salvage it
        return f"{type(exc).__name__}: {exc}"
    return None


@dataclass
class State:
    """The scheduler's columns of a store, one value a task: ``status`` (int8), ``attempts`` (int32)
    and ``wall`` (float64, seconds). The master keeps them in memory; everything else is read from
    the file when asked."""

    status: np.ndarray
    attempts: np.ndarray
    wall: np.ndarray

    @classmethod
    def fresh(cls, T) -> "State":
        """Every task pending: the fill values of a new store."""
        return cls(np.zeros(T, np.int8), np.zeros(T, np.int32), np.full(T, np.nan))

    @classmethod
    def read(cls, f) -> "State":
        """The columns of the open store ``f``."""
        return cls(f["tasks/status"][:], f["tasks/attempts"][:], f["tasks/wall"][:])

    def counts(self) -> list:
        """``[pending, done, failed]``: rows of each status (a list indexed by the codes)."""
        return [int(np.count_nonzero(self.status == k)) for k in (PENDING, DONE, FAILED)]


# --------------------------------------------------------------------------- creating

def creation_bytes(T, edges, extra=0) -> int:
    """A generous estimate of the bytes a new store of T tasks takes (plus ``extra``: what is
    copied into it, a damaged store's size when its rows are salvaged into it)."""
    raw = T * (32 + VARIANT_LEN + 8 + 8 + 8 + 1) + 64 * (T // 256 + 1) * 16
    raw += sum(8 * len(e) for e in edges.values())
    columns = len(TASK_FIELDS) + 2 * len(edges)  # their block checksums: 8 bytes a block, and a header
    raw += columns * (8 * (T // 256 + 1) + 1024)
    return int(1.05 * (raw + extra)) + 8 * SLACK


def create_file(path, spec, tasks, edges, B, *, fill=None, extra=0, what="creating the store"):
    """A fresh store at ``path``, created under a temporary name and renamed into place.

    ``fill(f)``, when given, writes into the new file (the open h5py File, its layout written)
    before it is made durable, ``extra`` bytes on top of the layout's (``creation_bytes``):
    ``campaign.storage.salvage`` copies a damaged store's readable rows this way. ``what`` names
    the step in a fault's message. The space it needs is reserved first; a full disk (OutOfSpace)
    or any other fault removes the temporary file and leaves ``path`` as it was.
    """
    # imported here, not with the module: its names and the stored spec serve commands that read no
    # HDF5 (the command line's closing note, campaign analyze of a text configuration, validate)
    import h5py

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    if tmp.exists():
        tmp.unlink()
    need = creation_bytes(len(tasks), edges, extra)
    f = io = None
    try:
        io = GuardedFile(tmp, create=True)
        reserved = reserve(io.fd, need, tmp, what)  # before HDF5 writes its first byte
        f = h5py.File(io, "w")
        _write_layout(f, spec, tasks, edges, B)
        if fill is not None:
            fill(f)
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


def block_sums_of(e):
    """The checksum of a dataset read whole (a histogram's bin edges: one block)."""
    return block_sums(e, max(1, len(e)))


def _write_layout(f, spec, tasks, edges, B):
    T = len(tasks)
    g = f.create_group("tasks")
    cols = {"id": "S32", "variant": f"S{VARIANT_LEN}", "N": np.int64, "E": np.float64, "seed": np.int64}
    sums = {}
    for name, dt in cols.items():
        g.create_dataset(name, dtype=dt, **dataset_kwargs(B, (T,), None))
        sums[name] = create_fill_sums(f, f"tasks/{name}", T, B, (), dt, None)
    step = max(B, 65536 // B * B)  # whole blocks: each block's checksum from the values written
    for lo in range(0, T, step):
        part = tasks[lo:lo + step]
        hi = lo + len(part)
        values = {"id": np.array([t.id.encode() for t in part], "S32"),
                  "variant": np.array([fixed(t.variant, VARIANT_LEN) for t in part], f"S{VARIANT_LEN}"),
                  "N": np.array([t.N for t in part], np.int64), "E": np.array([t.E for t in part], np.float64),
                  "seed": np.array([t.seed for t in part], np.int64)}
        for name, v in values.items():
            g[name][lo:hi] = v
            write_sums(sums[name], lo, v, B)
    g.create_dataset("status", shape=(T,), dtype=np.int8)  # contiguous: the commit marker
    create_fill_sums(f, "tasks/status", T, B, (), np.int8, 0)
    for name in ROW_FIELDS:
        g.create_dataset(name, dtype=row_dtype(name), **dataset_kwargs(B, (T,), fill_value(name)))
        create_fill_sums(f, f"tasks/{name}", T, B, (), row_dtype(name), fill_value(name))
    f.create_group("scalars")
    hg = f.create_group("histograms")
    for h, e in edges.items():
        hg.create_dataset(f"{h}/edges", **edges_kwargs(e))
        e = np.asarray(e, np.float64)
        create_sums(f, f"histograms/{h}/edges", max(1, len(e)), block_sums_of(e))
        hg.create_dataset(f"{h}/counts", dtype=np.int64, **dataset_kwargs(B, (T, len(e) - 1), 0))
        create_fill_sums(f, f"histograms/{h}/counts", T, B, (len(e) - 1,), np.int64, 0)
    if spec.configurations:
        f.create_group("configurations")
    f.create_group("failures")
    f.attrs["schema"] = SCHEMA
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["spec_hash"] = spec.hash
    f.attrs["name"] = spec.name
    f.attrs["spec_yaml"] = spec.text
    if checksums_on():
        f.attrs[PROTECTION_ATTR] = protection_text()
