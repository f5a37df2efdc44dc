"""The campaign's HDF5 store and its journal (the layout is documented in docs/STORE.md).

Two files per campaign, written only by the master:

* ``OUT`` (HDF5): the store users read with plain h5py. Every per-task dataset has
  T rows (T known from the spec), chunked by blocks of ``block`` rows and compressed
  (shuffle + deflate), so the file grows with the finished packings, not with the
  grid; a chunk never written costs nothing. ``tasks/status`` (one byte a task, not
  compressed) is the commit marker: a row counts once its status says so.
* ``OUT.journal``: a write-ahead log. One length-prefixed, CRC-checked record per
  finished task, written with a single ``write()`` before anything touches the
  HDF5 file. At a *checkpoint* (when the journal passes ``JOURNAL_BYTES``, and when
  a run ends) every staged row is written into the store, the store is flushed and
  ``fsync``ed, and only then is the journal cut back to its header: it never holds
  what the store already holds.

The master keeps O(1) per task in memory: status, attempts and wall time (the
scheduler and the wall-time model need them). A finished task's scalars and
histograms wait in a staging buffer only until the block of rows they belong to is
complete (or ``HOLD_SECONDS`` have passed, or the buffer passes ``BUFFER_BYTES``),
then go to disk: data first, ``flush``, then the status column, ``flush`` again.
Writing whole blocks keeps each compressed chunk written about once. A chunk rewritten
whole could lose its committed rows to a write cut by SIGKILL, so before a block is
written again, its committed rows that are no longer in the journal are appended to it
again (from the store).

On every start the journal is replayed into the store (idempotent: a row is a pure
function of its last record). A damaged journal keeps every intact record (a record
that fails its checksum is skipped up to the next intact one) and says how many
were lost; their tasks are pending again and run again. If the store is unreadable,
every readable committed row is salvaged into a new file (created under a temporary
name and renamed into place), the journal is replayed on top, and the rows lost
with the damage are counted and run again: packings are pure functions of the spec.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import struct
import sys
import time
import zlib
from pathlib import Path

import numpy as np

from campaign.errors import UserError

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
FLUSH_SECONDS = 0.5     # staged complete blocks are written at least this often
HOLD_SECONDS = 2.0      # a block still partly pending is written after waiting this long
BUFFER_BYTES = 96 << 20  # staged rows beyond this are written whether their block is complete or not
JOURNAL_BYTES = 64 << 20  # checkpoint when the journal grows past this
BLOCK_ROWS = 256        # rows per chunk of every per-task dataset
COMPRESSION = dict(compression="gzip", compression_opts=1, shuffle=True)
CHUNK_CACHE = 1 << 20  # HDF5 chunk cache per open dataset (whole blocks are written; little to cache)


def _fill(name):
    return {"attempts": 0, "wall": np.nan, "rank": -1, "host": b"", "error": b""}[name]


def _dtype(name):
    return {"attempts": np.int32, "wall": np.float64, "rank": np.int32, "host": f"S{HOST_LEN}",
            "error": f"S{ERROR_LEN}"}[name]


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


# --------------------------------------------------------------------------- journal

_HEAD = struct.Struct("<4sII")  # magic, payload length, crc32(payload)
_MAGIC = b"JCJ1"
MAX_RECORD = 1 << 31


def encode_record(rec: dict, arrays: dict | None = None) -> bytes:
    """One journal record: JSON metadata plus raw array bytes, framed and checksummed."""
    arrays = arrays or {}
    meta = dict(rec)
    blobs = []
    desc = []
    for key, a in arrays.items():
        a = np.ascontiguousarray(a)
        desc.append([key, a.dtype.str, list(a.shape)])
        blobs.append(a.tobytes())
    meta["arrays"] = desc
    js = json.dumps(meta, separators=(",", ":")).encode()
    payload = struct.pack("<I", len(js)) + js + b"".join(blobs)
    return _HEAD.pack(_MAGIC, len(payload), zlib.crc32(payload)) + payload


def decode_payload(payload: bytes):
    (n,) = struct.unpack_from("<I", payload, 0)
    meta = json.loads(payload[4:4 + n])
    pos = 4 + n
    arrays = {}
    for key, dtype, shape in meta.pop("arrays"):
        dt = np.dtype(dtype)
        count = int(np.prod(shape)) if shape else 1
        arrays[key] = np.frombuffer(payload, dt, count, pos).reshape(shape).copy()
        pos += count * dt.itemsize
    if pos != len(payload):
        raise ValueError("record length does not match its arrays")
    return meta, arrays


def _record_at(data, pos):
    """The decoded record starting at ``pos`` and its end, or None if none starts there."""
    if pos + _HEAD.size > len(data):
        return None
    magic, n, crc = _HEAD.unpack_from(data, pos)
    end = pos + _HEAD.size + n
    if magic != _MAGIC or end > len(data):
        return None
    payload = data[pos + _HEAD.size:end]
    if zlib.crc32(payload) != crc:
        return None
    try:
        return decode_payload(bytes(payload)), end
    except Exception:  # noqa: BLE001 - a record we cannot decode is not a record
        return None


def scan_journal(data: bytes):
    """Every intact record of a journal's bytes, and its damage.

    Returns ``(records, good_end, damaged)``: ``good_end`` is the end of the last intact
    record (bytes after it are a torn tail); ``damaged`` lists ``(offset, length,
    records_lost)`` for each damaged stretch *between* intact records (flipped bytes, a
    record cut short): reading resumes at the next intact record. ``records_lost`` counts
    the record headers inside the stretch (at least one).
    """
    out, damaged = [], []
    pos = good_end = 0
    view = memoryview(data)
    while pos < len(data):
        got = _record_at(view, pos)
        if got is not None:
            out.append(got[0])
            pos = good_end = got[1]
            continue
        # damage at pos: find the next intact record
        nxt = data.find(_MAGIC, pos + 1)
        while nxt != -1 and _record_at(view, nxt) is None:
            nxt = data.find(_MAGIC, nxt + 1)
        if nxt == -1:
            break  # nothing intact after it: a torn tail
        stretch = data[pos:nxt]
        lost = max(1, stretch.count(_MAGIC))
        damaged.append((pos, nxt - pos, lost))
        pos = nxt
    return out, good_end, damaged


def read_journal(data: bytes):
    """All intact records of a journal's bytes, and the end of the last one."""
    records, good_end, _ = scan_journal(data)
    return records, good_end


class Journal:
    """The write-ahead journal, locked for the lifetime of a run (one writer per store)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                os.close(self.fd)
                raise UserError(f"another run is writing {str(self.path)[:-len('.journal')]!r} (its journal "
                                f"{str(self.path)!r} is locked); wait for it to finish or stop it first") from None
            # a file system without flock (some Lustre mounts): carry on, unprotected
            print(f"campaign: warning: cannot lock {self.path} ({exc.strerror}); make sure no other run "
                  "writes this file at the same time", file=sys.stderr)
        size = os.fstat(self.fd).st_size
        data = os.pread(self.fd, size, 0) if size else b""
        self.records, good, self.damaged = scan_journal(data)
        del data
        self.torn = size - good
        if self.torn:
            os.ftruncate(self.fd, good)
        self.size = good
        os.lseek(self.fd, 0, os.SEEK_END)
        self.dirty = False

    def rewrite(self, records):
        """Replace the journal's content by ``records`` ((meta, arrays) pairs), durably.

        Called only when everything else the journal held is safely in the store: a kill
        between the truncation and the write leaves an empty journal, which the next start
        recreates from the store.
        """
        data = b"".join(encode_record(m, a) for m, a in records)
        os.ftruncate(self.fd, 0)
        os.lseek(self.fd, 0, os.SEEK_SET)
        self.size = 0
        self._write(data)
        os.fsync(self.fd)
        self.dirty = False
        self.records = []

    def _write(self, data):
        n = os.write(self.fd, data)
        while n < len(data):  # a short write (full disk, signal): finish it or fail loudly
            n += os.write(self.fd, data[n:])
        self.size += len(data)

    def append(self, rec: dict, arrays: dict | None = None):
        self._write(encode_record(rec, arrays))
        self.dirty = True

    def sync(self):
        if self.dirty:
            os.fsync(self.fd)
            self.dirty = False

    def close(self):
        if self.fd is not None:
            self.sync()
            os.close(self.fd)  # releases the lock
            self.fd = None


# --------------------------------------------------------------------------- the store

def _fixed(text: str, n: int) -> bytes:
    return text.encode("utf-8", "replace")[:n]


def _fsync_path(path):
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class Store:
    """The master's view of one campaign file. Not thread-safe; one per process.

    In memory per task: ``status`` (int8), ``attempts`` (int32), ``wall`` (float64).
    Everything else is read from the file (or the staging buffer) when asked:
    ``read(column, index)``, ``configuration(index)``.
    """

    def __init__(self, path, spec, tasks, edges: dict, *, new=False, provenance=None, log=None):
        import h5py  # noqa: F401 - fail early and clearly if missing

        self.path = Path(path)
        self.spec, self.tasks = spec, tasks
        self.T = len(tasks)
        self.B = max(1, min(BLOCK_ROWS, self.T))
        self.edges = {k: np.asarray(v, np.float64) for k, v in sorted(edges.items())}
        self.log = log or (lambda msg: print(msg, file=sys.stderr))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.f = None
        self.journal = Journal(Path(str(self.path) + ".journal"))
        try:
            self._open(new, provenance or {})
        except BaseException:
            if self.f is not None:
                self.f.close()
                self.f = None
            self.journal.close()
            raise

    # ---- opening, refusing, salvaging, replaying
    def _open(self, new, provenance):
        import h5py

        spec_hash = self.spec.hash
        records = self.journal.records
        self.journal.records = []
        if new:
            self.journal.rewrite([])
            records = []
            self.journal.damaged = []
            self.journal.torn = 0
            if self.path.exists():
                self.path.unlink()
        header = records[0][0] if records else None
        if header is not None and (header.get("type") != "header" or header.get("spec_hash") != spec_hash):
            raise UserError(f"{str(self.journal.path)!r} belongs to a different spec (or a different "
                            f"program); rerun with --new to start {str(self.path)!r} afresh, or choose "
                            "another --out")
        if header is not None and header.get("format_version", 1) != FORMAT_VERSION:
            raise UserError(f"{str(self.journal.path)!r} was written by a store of format "
                            f"{header.get('format_version', 1)}; " + OLD_FORMAT_HELP.format(new=FORMAT_VERSION))
        checkpoint = {}
        for meta, _ in records[1:]:
            if meta.get("type") == "checkpoint":
                checkpoint = meta
        self._init_state()
        salvage_from = rebuilt = None
        touched = {int(m["index"]) // self.B for m, _ in records[1:] if m.get("type") == "task"}
        if self.path.exists():
            problem = self._check_file(spec_hash, touched)
            if problem is None:
                self._load_state()
            elif problem.startswith("refuse:"):
                raise UserError(problem[len("refuse:"):])
            elif not records:
                raise UserError(f"{str(self.path)!r} is unreadable ({problem}) and has no journal to rebuild it "
                                "from; move it away or rerun with --new")
            else:
                self.log(f"campaign: {self.path} is damaged ({problem}); salvaging its readable rows into a "
                         "new file and replaying the journal")
                salvage_from = problem
        if salvage_from is not None or not self.path.exists():
            self._create_file(salvage=salvage_from is not None)
            rebuilt = "the damaged part of the" if salvage_from else "the missing"
        self.f = h5py.File(self.path, "r+", locking=False, rdcc_nbytes=CHUNK_CACHE)
        self._datasets = {}
        self.have_configs = set(self.f["configurations"].keys()) if "configurations" in self.f else set()
        self.have_failures = set(self.f["failures"].keys()) if "failures" in self.f else set()
        self.scalar_names = set(self.f["scalars"].keys())
        try:
            self.runs = json.loads(self.f.attrs.get("runs", "[]"))
        except (TypeError, ValueError):
            self.runs = []
        self.run = dict(provenance, start=_now(), end=None, run_id=os.urandom(8).hex())
        replayed = 0
        for meta, arrays in records[1:] if header is not None else ():
            if meta.get("type") == "task":
                self._stage(meta, arrays)
                replayed += 1
            elif meta.get("type") == "run":
                self._merge_run(meta["run"])
            if self.staged_bytes > BUFFER_BYTES:
                self._write_blocks(list(self.staged))
        del records
        lost = int(checkpoint.get("committed", 0)) - self.n_final()
        if rebuilt and lost > 0:
            self.log(f"campaign: at least {lost} finished task(s) were only in {rebuilt} store; they are "
                     "pending again and will be run again")
        if self.journal.damaged:
            n_lost = sum(k for _, _, k in self.journal.damaged)
            n_bytes = sum(n for _, n, _ in self.journal.damaged)
            where = ", ".join(f"{o}" for o, _, _ in self.journal.damaged[:5])
            self.log(f"campaign: {self.journal.path} is damaged: skipped {len(self.journal.damaged)} damaged "
                     f"stretch(es) ({n_bytes} bytes at offset {where}), about {n_lost} record(s) lost; kept "
                     f"{replayed} intact task record(s). The tasks of the lost records are pending again and "
                     "will be run again")
        if self.journal.torn:
            self.log(f"campaign: cut a torn record ({self.journal.torn} bytes) off the end of {self.journal.path}")
        self._merge_run(self.run)
        self._write_root_attrs()
        self.checkpoint()

    def _check_file(self, spec_hash, touched=()):
        """None if the file is a valid store of this spec; 'refuse:...' if it belongs to another.

        ``touched``: the blocks the journal's records go to, the only ones a killed run can
        have been writing; each of their chunks must decompress.
        """
        import h5py

        try:
            with h5py.File(self.path, "r", locking=False) as f:
                problem = format_problem(f.attrs, self.path)
                if problem is not None:
                    return "refuse:" + problem
                if f.attrs.get("spec_hash") != spec_hash:
                    return (f"refuse:{str(self.path)!r} was written by a different spec (name "
                            f"{f.attrs.get('name')!r}, spec hash {f.attrs.get('spec_hash')}; this spec's hash is "
                            f"{spec_hash}); rerun with --new to overwrite it, or choose another --out")
                for name in TASK_FIELDS:
                    if f[f"tasks/{name}"].shape != (self.T,):
                        return f"tasks/{name} has the wrong shape"
                ids = f["tasks/id"]
                for lo in range(0, self.T, 65536):
                    hi = min(lo + 65536, self.T)
                    want = np.array([t.id.encode() for t in self.tasks[lo:hi]], "S32")
                    if not np.array_equal(ids[lo:hi], want):
                        return "its task ids differ from the spec's"
                for h, e in self.edges.items():
                    if f[f"histograms/{h}/counts"].shape != (self.T, len(e) - 1):
                        return f"histograms/{h}/counts has the wrong shape"
                    if not np.array_equal(f[f"histograms/{h}/edges"][:], e):
                        return (f"refuse:the bin edges of histogram {h!r} in {str(self.path)!r} differ from "
                                "the ones this installation would use (the default bins changed?); pin them "
                                "in the spec's 'bins', or rerun with --new")
                for name in f["scalars"]:
                    if f[f"scalars/{name}"].shape != (self.T,):
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
                names += [f"histograms/{h}/counts" for h in self.edges]
                for name in names:
                    ds = f[name]
                    for b in sorted(touched):
                        ds[b * self.B:(b + 1) * self.B]
                f["tasks/status"][:]
        except (OSError, KeyError, ValueError, RuntimeError, TypeError) as exc:
            return f"{type(exc).__name__}: {exc}"
        return None

    def _init_state(self):
        T = self.T
        self.status = np.zeros(T, np.int8)
        self.n_status = [T, 0, 0]  # pending, done, failed
        self.attempts = np.zeros(T, np.int32)
        self.wall = np.full(T, np.nan)
        self.hosts = set()
        self.staged: dict[int, dict[int, tuple]] = {}   # block -> row -> (meta, arrays)
        self.staged_since: dict[int, float] = {}        # block -> when its first staged row came
        self.block_bytes: dict[int, int] = {}           # block -> bytes staged
        self.staged_bytes = 0
        self.in_journal: set[int] = set()               # rows with a record in the journal
        self.last_flush = time.monotonic()

    def n_final(self) -> int:
        return self.n_status[DONE] + self.n_status[FAILED]

    def _load_state(self):
        import h5py

        with h5py.File(self.path, "r", locking=False) as f:
            self.status[:] = f["tasks/status"][:]
            self.attempts[:] = f["tasks/attempts"][:]
            self.wall[:] = f["tasks/wall"][:]
        self.n_status = [int(np.count_nonzero(self.status == k)) for k in (PENDING, DONE, FAILED)]

    def _dataset_kwargs(self, shape, fill):
        chunks = (self.B,) + tuple(shape[1:])
        return dict(shape=shape, chunks=chunks, fillvalue=fill, **COMPRESSION)

    def _create_file(self, salvage=False):
        """A fresh store, created under a temporary name and renamed into place.

        With ``salvage``, the committed rows that can still be read from the damaged
        file at ``self.path`` are copied into it (block by block; a block that cannot be
        read is lost and its tasks are pending again).
        """
        import h5py

        tmp = self.path.with_name(self.path.name + ".tmp")
        if tmp.exists():
            tmp.unlink()
        T = self.T
        with h5py.File(tmp, "w", locking=False) as f:
            g = f.create_group("tasks")
            cols = {"id": "S32", "variant": f"S{VARIANT_LEN}", "N": np.int64, "E": np.float64, "seed": np.int64}
            for name, dt in cols.items():
                g.create_dataset(name, dtype=dt, **self._dataset_kwargs((T,), None))
            for lo in range(0, T, 65536):
                part = self.tasks[lo:lo + 65536]
                hi = lo + len(part)
                g["id"][lo:hi] = np.array([t.id.encode() for t in part], "S32")
                g["variant"][lo:hi] = np.array([_fixed(t.variant, VARIANT_LEN) for t in part], f"S{VARIANT_LEN}")
                g["N"][lo:hi] = np.array([t.N for t in part], np.int64)
                g["E"][lo:hi] = np.array([t.E for t in part], np.float64)
                g["seed"][lo:hi] = np.array([t.seed for t in part], np.int64)
            g.create_dataset("status", shape=(T,), dtype=np.int8)  # contiguous: the commit marker
            for name in ROW_FIELDS:
                g.create_dataset(name, dtype=_dtype(name), **self._dataset_kwargs((T,), _fill(name)))
            f.create_group("scalars")
            hg = f.create_group("histograms")
            for h, e in self.edges.items():
                hg.create_dataset(f"{h}/edges", data=e)
                hg.create_dataset(f"{h}/counts", dtype=np.int64, **self._dataset_kwargs((T, len(e) - 1), 0))
            if self.spec.configurations:
                f.create_group("configurations")
            f.create_group("failures")
            f.attrs["schema"] = SCHEMA
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["spec_hash"] = self.spec.hash
            f.attrs["name"] = self.spec.name
            f.attrs["spec_yaml"] = self.spec.text
            if salvage:
                self._salvage_into(f)
            f.flush()
        _fsync_path(tmp)
        os.replace(tmp, self.path)

    def _salvage_into(self, f):
        """Copy every readable committed row of the damaged store into ``f``."""
        import h5py

        try:
            old = h5py.File(self.path, "r", locking=False)
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
            for B0 in range(0, self.T, self.B):
                lo, hi = B0, min(B0 + self.B, self.T)
                try:
                    st = old["tasks/status"][lo:hi]
                    rows = np.flatnonzero(st != PENDING)
                    if not len(rows):
                        continue
                    data = {f"tasks/{n}": old[f"tasks/{n}"][lo:hi] for n in ROW_FIELDS}
                    for n in scalar_names:
                        data[f"scalars/{n}"] = old[f"scalars/{n}"][lo:hi]
                    for h in self.edges:
                        data[f"histograms/{h}/counts"] = old[f"histograms/{h}/counts"][lo:hi]
                    extra = {}
                    for r in rows:
                        tid = self.tasks[lo + r].id
                        if "configurations" in old and tid in old["configurations"]:
                            g = old[f"configurations/{tid}"]
                            extra[("c", tid)] = {k: g[k][()] for k in ("positions", "radii", "box", "species")}
                        if st[r] == FAILED and "failures" in old and tid in old["failures"]:
                            extra[("f", tid)] = dict(old[f"failures/{tid}"].attrs)
                except (OSError, KeyError, ValueError, RuntimeError, TypeError):
                    continue  # this block is lost: its tasks are pending again
                for name, a in data.items():
                    if name.startswith("scalars/") and name not in f:
                        f["scalars"].create_dataset(name[8:], dtype=np.float64,
                                                    **self._dataset_kwargs((self.T,), np.nan))
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
                self.status[lo:hi] = st
                self.attempts[lo:hi] = data["tasks/attempts"]
                self.wall[lo:hi] = data["tasks/wall"]
        self.n_status = [int(np.count_nonzero(self.status == k)) for k in (PENDING, DONE, FAILED)]

    # ---- recording
    def finished(self, index: int) -> bool:
        return self.status[index] != PENDING

    def record(self, index: int, summary: dict, attempts: int):
        """Record a task's final outcome: done if ``summary['ok']``, else failed."""
        t = self.tasks[index]
        status = DONE if summary["ok"] else FAILED
        err = summary.get("error") or {}
        meta = {"type": "task", "index": index, "id": t.id, "status": status, "attempts": int(attempts),
                "wall": float(summary.get("wall", float("nan"))), "rank": int(summary.get("rank", -1)),
                "host": str(summary.get("host", "")), "message": err.get("message", ""),
                "traceback": err.get("traceback", ""), "run_id": self.run["run_id"]}
        arrays = {}
        if status == DONE:
            sc = summary.get("scalars", {})
            meta["scalar_names"] = ",".join(sc)
            arrays["s"] = np.fromiter(sc.values(), np.float64, len(sc))
            for h in self.edges:
                arrays["h/" + h] = np.asarray(summary["histograms"][h], np.int64)
            cfg = summary.get("configuration")
            if cfg is not None:  # asked for by the spec, or a ladder parent's
                for k in ("positions", "radii", "box", "species"):
                    arrays["c/" + k] = np.asarray(cfg[k])
        self.journal.append(meta, arrays)
        self._stage(meta, arrays)
        self.maybe_flush()

    def _staged_row(self, index):
        return self.staged.get(index // self.B, {}).get(index)

    def configuration(self, index: int):
        """The stored configuration of task ``index`` (dict of arrays), or None."""
        row = self._staged_row(index)
        if row is not None:
            arrays = row[1]
            if "c/positions" in arrays:
                return {k: arrays["c/" + k] for k in ("positions", "radii", "box", "species")}
            return None
        tid = self.tasks[index].id
        if tid in self.have_configs:
            g = self.f[f"configurations/{tid}"]
            return {k: g[k][()] for k in ("positions", "radii", "box", "species")}
        return None

    def read(self, column: str, index: int):
        """One value of a per-task dataset (``tasks/error``, ``scalars/phi``, ...), staged or stored."""
        row = self._staged_row(index)
        if row is not None:
            return self._row_values(row[0], row[1], [column])[column]
        if column not in self.f:
            return np.nan if column.startswith("scalars/") else None
        return self.f[column][index]

    def _stage(self, meta, arrays):
        i = int(meta["index"])
        if not (0 <= i < self.T) or self.tasks[i].id != meta["id"]:
            raise UserError(f"{str(self.journal.path)!r} does not match the spec (task {i})")
        status = int(meta["status"])
        self.n_status[int(self.status[i])] -= 1
        self.n_status[status] += 1
        self.status[i] = status
        self.attempts[i] = meta["attempts"]
        self.wall[i] = meta["wall"]
        if meta.get("host") and int(meta.get("rank", -1)) >= 0:
            self.hosts.add(meta["host"])
        self.in_journal.add(i)
        b = i // self.B
        blk = self.staged.setdefault(b, {})
        if not blk:
            self.staged_since[b] = time.monotonic()
        old = blk.get(i)
        size = _nbytes(arrays) + 512 - (0 if old is None else _nbytes(old[1]) + 512)
        blk[i] = (meta, arrays)
        self.staged_bytes += size
        self.block_bytes[b] = self.block_bytes.get(b, 0) + size

    def _merge_run(self, run):
        for k, r in enumerate(self.runs):
            if r.get("run_id") == run.get("run_id"):
                self.runs[k] = run
                return
        self.runs.append(run)

    # ---- writing
    def _block_complete(self, b):
        lo, hi = b * self.B, min((b + 1) * self.B, self.T)
        return not np.any(self.status[lo:hi] == PENDING)

    def maybe_flush(self):
        now = time.monotonic()
        if (self.staged_bytes > BUFFER_BYTES or self.journal.size > JOURNAL_BYTES
                or (self.staged and now - self.last_flush >= FLUSH_SECONDS)):
            self.flush()

    def flush(self, force=False):
        """Write the staged blocks that are complete (all with ``force``, or when the buffer
        is full, the oldest first), then checkpoint if the journal has grown too long."""
        now = time.monotonic()
        if force:
            blocks = list(self.staged)
        else:
            blocks = [b for b in self.staged if self._block_complete(b) or now - self.staged_since[b] >= HOLD_SECONDS]
            if self.staged_bytes > BUFFER_BYTES:
                rest = sorted((b for b in self.staged if b not in set(blocks)), key=self.staged_since.get)
                size = self.staged_bytes - sum(self.block_bytes[b] for b in blocks)
                for b in rest:
                    if size <= BUFFER_BYTES // 2:
                        break
                    blocks.append(b)
                    size -= self.block_bytes[b]
        if blocks:
            self.journal.sync()  # the journal is durable before the store changes
            self._write_blocks(blocks)
        self.last_flush = time.monotonic()
        if self.journal.size > JOURNAL_BYTES:
            self.checkpoint()

    def _row_values(self, meta, arrays, columns=None):
        """The values a task's record puts into its row, per dataset name."""
        status = int(meta["status"])
        out = {"tasks/attempts": int(meta["attempts"]), "tasks/wall": float(meta["wall"]),
               "tasks/rank": int(meta["rank"]), "tasks/host": _fixed(meta["host"], HOST_LEN),
               "tasks/error": _fixed(meta["message"], ERROR_LEN) if status == FAILED else b""}
        if "scalar_names" in meta:
            names = meta["scalar_names"].split(",") if meta["scalar_names"] else []
            sc = dict(zip(names, arrays["s"].tolist()))
        else:
            sc = meta.get("scalars", {})
        for name, v in sc.items():
            out[f"scalars/{name}"] = float(v)
        for h, e in self.edges.items():
            a = arrays.get("h/" + h)
            out[f"histograms/{h}/counts"] = a if a is not None and a.shape == (len(e) - 1,) else None
        if columns is not None:
            res = {}
            for c in columns:
                if c in out:
                    res[c] = np.zeros(len(self.edges[c.split("/")[1]]) - 1, np.int64) if out[c] is None else out[c]
                elif c.startswith("scalars/"):
                    res[c] = np.nan
                else:
                    res[c] = None
            return res
        return out

    def _dataset(self, name):
        """(dataset, fill value, dtype, row shape), looked up once (h5py lookups are slow)."""
        got = self._datasets.get(name)
        if got is None:
            ds = self.f[name]
            got = self._datasets[name] = (ds, ds.fillvalue, ds.dtype, tuple(ds.shape[1:]))
        return got

    def _write_blocks(self, blocks):
        """Data of the staged rows of ``blocks`` first, flush, then their status, flush."""
        f = self.f
        blocks = sorted(blocks)
        for b in blocks:
            rows = self.staged[b]
            lo, hi = b * self.B, min((b + 1) * self.B, self.T)
            final = np.flatnonzero(self.status[lo:hi] != PENDING) + lo
            kept = [int(i) for i in final if i not in rows]
            # rewriting a chunk that holds committed rows: a write cut by SIGKILL could take them
            # with it, so each of them must have a record in the journal first
            missing = [i for i in kept if i not in self.in_journal]
            if missing:
                self._rejournal(lo, hi, missing)
            idx = np.fromiter(rows, np.int64, len(rows)) - lo
            whole = not kept  # no committed row to keep: no need to read the chunks
            values = [self._row_values(m, a) for m, a in rows.values()]
            keys = set()
            for v in values:
                keys.update(v.keys())
            for name in sorted(k for k in keys if k.startswith("scalars/")):
                if name[8:] not in self.scalar_names:
                    f["scalars"].create_dataset(name[8:], dtype=np.float64, **self._dataset_kwargs((self.T,), np.nan))
                    self.scalar_names.add(name[8:])
            columns = [f"tasks/{n}" for n in ROW_FIELDS] + [f"scalars/{n}" for n in sorted(self.scalar_names)]
            columns += [f"histograms/{h}/counts" for h in self.edges]
            for name in columns:
                ds, fill, dtype, shape = self._dataset(name)
                if whole:
                    block = np.full((hi - lo,) + shape, fill, dtype=dtype)
                else:
                    block = ds[lo:hi]
                col = [v.get(name) for v in values]
                if shape:  # histogram rows
                    zero = np.zeros(shape, dtype)
                    block[idx] = np.stack([zero if x is None else x for x in col])
                else:
                    block[idx] = np.array([fill if x is None else x for x in col], dtype=dtype)
                ds[lo:hi] = block
            for i, (meta, arrays) in sorted(rows.items()):
                tid = self.tasks[i].id
                if "c/positions" in arrays:
                    if tid in self.have_configs:
                        del f[f"configurations/{tid}"]
                    g = f.require_group("configurations").create_group(tid)
                    for k in ("positions", "radii", "box", "species"):
                        g.create_dataset(k, data=arrays["c/" + k])
                    self.have_configs.add(tid)
                if tid in self.have_failures:
                    del f[f"failures/{tid}"]
                    self.have_failures.discard(tid)
                if int(meta["status"]) == FAILED:
                    g = f["failures"].create_group(tid)
                    g.attrs.update(message=meta["message"], traceback=meta["traceback"],
                                   attempts=int(meta["attempts"]), rank=int(meta["rank"]), host=meta["host"])
                    self.have_failures.add(tid)
        f.flush()
        # ... then the commit marker
        status = self._dataset("tasks/status")[0]
        for b in blocks:
            lo, hi = b * self.B, min((b + 1) * self.B, self.T)
            status[lo:hi] = self.status[lo:hi]
            self.staged.pop(b)
            self.staged_bytes -= self.block_bytes.pop(b)
            self.staged_since.pop(b, None)
        f.flush()
        if not self.staged:
            self.staged_bytes = 0

    def _rejournal(self, lo, hi, rows):
        """Append records, rebuilt from the store, for committed ``rows`` of block [lo, hi)."""
        f = self.f
        cols = {n: f[f"tasks/{n}"][lo:hi] for n in ROW_FIELDS}
        scal = {n: f[f"scalars/{n}"][lo:hi] for n in sorted(self.scalar_names)}
        hist = {h: f[f"histograms/{h}/counts"][lo:hi] for h in self.edges}
        for i in rows:
            k = i - lo
            t = self.tasks[i]
            status = int(self.status[i])
            meta = {"type": "task", "index": i, "id": t.id, "status": status,
                    "attempts": int(cols["attempts"][k]), "wall": float(cols["wall"][k]),
                    "rank": int(cols["rank"][k]), "host": cols["host"][k].decode(errors="replace"),
                    "message": cols["error"][k].decode(errors="replace"), "traceback": "", "run_id": None}
            arrays = {}
            if status == DONE:
                meta["scalars"] = {n: float(v[k]) for n, v in scal.items() if not np.isnan(v[k])}
                arrays = {"h/" + h: c[k] for h, c in hist.items()}
            elif t.id in self.have_failures:
                a = f[f"failures/{t.id}"].attrs
                meta["message"], meta["traceback"] = str(a.get("message", "")), str(a.get("traceback", ""))
            if t.id in self.have_configs:
                g = f[f"configurations/{t.id}"]
                for key in ("positions", "radii", "box", "species"):
                    arrays["c/" + key] = g[key][()]
            self.journal.append(meta, arrays)
            self.in_journal.add(i)
        self.journal.sync()

    def checkpoint(self):
        """Everything staged into the store, the store made durable, then the journal cut back
        to its header: from here on the store alone holds every finished task."""
        if self.staged:
            self.journal.sync()
            self._write_blocks(list(self.staged))
        self.f.flush()
        _fsync_path(self.path)
        header = {"type": "header", "schema": SCHEMA, "format_version": FORMAT_VERSION,
                  "spec_hash": self.spec.hash, "T": self.T}
        recs = [(header, None)] + [({"type": "run", "run": r}, None) for r in self.runs]
        recs.append(({"type": "checkpoint", "committed": self.n_final(), "time": _now()}, None))
        self.journal.rewrite(recs)
        self.in_journal = set()
        self.last_flush = time.monotonic()

    def _write_root_attrs(self):
        f = self.f
        f.attrs["schema"] = SCHEMA
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["name"] = self.spec.name
        f.attrs["spec_hash"] = self.spec.hash
        f.attrs["spec_yaml"] = self.spec.text
        run = self.run
        for key in ("package_version", "git_commit"):
            f.attrs[key] = str(run.get(key, "unknown"))
        f.attrs["versions"] = json.dumps(run.get("versions", {}), sort_keys=True)
        f.attrs["runs"] = json.dumps(self.runs, sort_keys=True)
        hosts = sorted({h for r in self.runs for h in r.get("hosts", [])})
        f.attrs["hosts"] = json.dumps(hosts)
        f.attrs["start_time"] = self.runs[0].get("start") or ""
        f.attrs["end_time"] = self.runs[-1].get("end") or ""

    def close(self, **end_info):
        """Write everything, stamp the run's end, checkpoint, release the lock."""
        if self.f is None:
            return
        try:
            self.run.update(end_info, end=_now())
            self.run["hosts"] = sorted(set(self.run.get("hosts", [])) | self.hosts)
            self.journal.append({"type": "run", "run": self.run})
            self._merge_run(self.run)
            self.flush(force=True)
            self._write_root_attrs()
            self.checkpoint()
        finally:
            self.f.close()
            self.f = None
            self.journal.close()

    def abandon(self):
        """Close without stamping the run's end (after a fault); the journal stays the record."""
        try:
            if self.f is not None:
                self.f.close()
        finally:
            self.f = None
            self.journal.close()

    def counts_by_status(self):
        return {"pending": self.n_status[PENDING], "done": self.n_status[DONE], "failed": self.n_status[FAILED]}


def _nbytes(arrays) -> int:
    return sum(a.nbytes for a in arrays.values()) if arrays else 0


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


# --------------------------------------------------------------------------- readers

def open_store(path):
    """Open a campaign store read-only (``locking=False``: fine while a run writes it).

    Raises UserError (exit 2) for a missing file, a file that is not HDF5, or a store
    of another schema or format version (see ``format_problem``).
    """
    import h5py

    try:
        f = h5py.File(path, "r", locking=False)
    except FileNotFoundError:
        raise UserError(f"no such file: {str(path)!r}") from None
    except OSError as exc:
        raise UserError(f"{str(path)!r} is not a readable HDF5 file ({exc})") from None
    try:
        check_format(f.attrs, path)
    except BaseException:
        f.close()
        raise
    return f


def read_summary(path, fields=TASK_FIELDS):
    """The task table's columns ``fields`` (all rows), the root attributes and the failure
    records, read-only. Retries a few times if it catches the file in the middle of a flush.
    Memory grows with the tasks (the error column alone is 512 bytes a task): ``campaign
    status`` reads the table in blocks instead; ask for the columns you need.
    """
    last = None
    for attempt in range(5):
        try:
            with open_store(path) as f:
                out = {k: f[f"tasks/{k}"][:] for k in fields}
                out["attrs"] = {k: f.attrs[k] for k in f.attrs}
                out["failures"] = {}
                if "failures" in f:
                    for tid in f["failures"]:
                        out["failures"][tid] = dict(f[f"failures/{tid}"].attrs)
                return out
        except UserError:
            raise
        except (OSError, KeyError, ValueError) as exc:
            last = exc
            time.sleep(0.2)
    raise UserError(f"cannot read {str(path)!r} as a campaign store: {last}")
