"""The campaign's HDF5 store and its journal (the layout is documented in docs/STORE.md).

Two files per campaign, written only by the master:

* ``OUT.journal``: append-only, the durable record. One length-prefixed,
  CRC-checked record per finished task (and one per run start/end), each
  written with a single ``write()``. A torn tail (a record cut by SIGKILL or a
  full disk) fails its length or checksum and is cut off on the next start.
* ``OUT`` (HDF5): the materialised view that users read with plain h5py.
  Fixed-size datasets, allocated when the file is created (T rows known from
  the spec), so that recording a task writes raw data only. Writes are batched;
  in every batch the data go first, then ``flush``, then the status column
  (the commit marker), then ``flush`` again.

On every start the journal is replayed into the view (idempotent: a row is a
pure function of its last journal record); if the view is missing or unreadable
it is rebuilt from the spec and the journal (a new file created under a
temporary name and renamed into place). So a master killed at any moment loses
nothing that reached the journal, and the rerun's file equals an uninterrupted
run's.
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
PENDING, DONE, FAILED = 0, 1, 2
HOST_LEN, ERROR_LEN, VARIANT_LEN = 64, 512, 64
TASK_FIELDS = ("id", "variant", "N", "E", "seed", "status", "attempts", "wall", "rank", "host", "error")
FLUSH_SECONDS = 0.5
FLUSH_ROWS = 4096  # at most this many rows between two flushes (else every FLUSH_SECONDS)


# --------------------------------------------------------------------------- journal

_HEAD = struct.Struct("<4sII")  # magic, payload length, crc32(payload)
_MAGIC = b"JCJ1"


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
    return meta, arrays


def read_journal(data: bytes):
    """All whole records of a journal's bytes, and the length of the valid prefix."""
    out, pos = [], 0
    while pos + _HEAD.size <= len(data):
        magic, n, crc = _HEAD.unpack_from(data, pos)
        end = pos + _HEAD.size + n
        if magic != _MAGIC or end > len(data):
            break
        payload = data[pos + _HEAD.size:end]
        if zlib.crc32(payload) != crc:
            break
        try:
            out.append(decode_payload(payload))
        except Exception:  # noqa: BLE001 - a record we cannot decode ends the valid prefix
            break
        pos = end
    return out, pos


class Journal:
    """The append-only journal, locked for the lifetime of a run (one writer per store)."""

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
        self.records, good = read_journal(data)
        self.torn = size - good
        if self.torn:
            os.ftruncate(self.fd, good)
        os.lseek(self.fd, 0, os.SEEK_END)
        self.dirty = False

    def reset(self):
        os.ftruncate(self.fd, 0)
        os.lseek(self.fd, 0, os.SEEK_SET)
        self.records = []

    def append(self, rec: dict, arrays: dict | None = None):
        data = encode_record(rec, arrays)
        n = os.write(self.fd, data)
        while n < len(data):  # a short write (full disk, signal): finish it or fail loudly
            n += os.write(self.fd, data[n:])
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


class Store:
    """The master's view of one campaign file. Not thread-safe; one per process."""

    def __init__(self, path, spec, tasks, edges: dict, *, new=False, provenance=None, log=None):
        import h5py  # noqa: F401 - fail early and clearly if missing

        self.path = Path(path)
        self.spec, self.tasks = spec, tasks
        self.T = len(tasks)
        self.edges = {k: np.asarray(v, np.float64) for k, v in sorted(edges.items())}
        self.log = log or (lambda msg: print(msg, file=sys.stderr))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.journal = Journal(Path(str(self.path) + ".journal"))
        try:
            self._open(new, provenance or {})
        except BaseException:
            self.journal.close()
            raise

    # ---- opening, refusing, rebuilding, replaying
    def _open(self, new, provenance):
        import h5py

        spec_hash = self.spec.hash
        records = self.journal.records
        if new:
            self.journal.reset()
            records = []
            if self.path.exists():
                self.path.unlink()
        header = records[0][0] if records else None
        if header is not None and (header.get("type") != "header" or header.get("spec_hash") != spec_hash):
            raise UserError(f"{str(self.journal.path)!r} belongs to a different spec (or a different "
                            f"program); rerun with --new to start {str(self.path)!r} afresh, or choose "
                            "another --out")
        valid = False
        if self.path.exists():
            problem = self._check_file(spec_hash)
            if problem is None:
                valid = True
            elif problem.startswith("refuse:"):
                raise UserError(problem[len("refuse:"):])
            elif not records:
                raise UserError(f"{str(self.path)!r} is unreadable ({problem}) and has no journal to rebuild it "
                                "from; move it away or rerun with --new")
            else:
                self.log(f"campaign: {self.path} is unreadable ({problem}); rebuilding it from its journal")
        self._init_mirror()
        if valid:
            self._load_mirror()
        else:
            self._create_file()
        self.f = h5py.File(self.path, "r+", locking=False)
        self.have_configs = set(self.f["configurations"].keys()) if "configurations" in self.f else set()
        self.have_failures = set(self.f["failures"].keys()) if "failures" in self.f else set()
        self.runs = []
        if header is None:
            # a new journal: its header, then whatever the view already holds (journal lost or new)
            self.journal.append({"type": "header", "schema": SCHEMA, "spec_hash": spec_hash, "T": self.T})
            try:
                self.runs = json.loads(self.f.attrs.get("runs", "[]"))
            except (TypeError, ValueError):
                self.runs = []
            for run in self.runs:
                self.journal.append({"type": "run", "run": run})
            for i in np.flatnonzero(self.status != PENDING):
                self._journal_row(int(i))
        else:
            for meta, arrays in records[1:]:
                if meta.get("type") == "task":
                    self._apply(meta, arrays)
                elif meta.get("type") == "run":
                    self._merge_run(meta["run"])
                if len(self.pending_configs) >= 64:
                    self.flush(force=True)
        if self.journal.torn:
            self.log(f"campaign: cut a torn record ({self.journal.torn} bytes) off the end of {self.journal.path}")
        self.run = dict(provenance, start=_now(), end=None, run_id=os.urandom(8).hex())
        self._merge_run(self.run)
        self.journal.append({"type": "run", "run": self.run})
        self._write_root_attrs()
        self.flush(force=True)

    def _check_file(self, spec_hash):
        """None if the file is a valid view of this spec; 'refuse:...' if it belongs to another."""
        import h5py

        try:
            with h5py.File(self.path, "r", locking=False) as f:
                if f.attrs.get("schema") != SCHEMA:
                    return (f"refuse:{str(self.path)!r} is not a campaign store of this program (schema "
                            f"{f.attrs.get('schema')!r}); rerun with --new to overwrite it, or choose another --out")
                if f.attrs.get("spec_hash") != spec_hash:
                    return (f"refuse:{str(self.path)!r} was written by a different spec (name "
                            f"{f.attrs.get('name')!r}, spec hash {f.attrs.get('spec_hash')}; this spec's hash is "
                            f"{spec_hash}); rerun with --new to overwrite it, or choose another --out")
                for name in TASK_FIELDS:
                    if f[f"tasks/{name}"].shape != (self.T,):
                        return f"tasks/{name} has the wrong shape"
                ids = f["tasks/id"][:]
                if list(ids) != [t.id.encode() for t in self.tasks]:
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
                f["tasks/status"][:]
        except (OSError, KeyError, ValueError, RuntimeError) as exc:
            return f"{type(exc).__name__}: {exc}"
        return None

    def _init_mirror(self):
        T = self.T
        self.status = np.zeros(T, np.int8)
        self.n_status = [T, 0, 0]  # pending, done, failed
        self.attempts = np.zeros(T, np.int32)
        self.wall = np.full(T, np.nan)
        self.rank = np.full(T, -1, np.int32)
        self.host = np.zeros(T, f"S{HOST_LEN}")
        self.error = np.zeros(T, f"S{ERROR_LEN}")
        self.scalars: dict[str, np.ndarray] = {}
        self.counts = {h: np.zeros((T, len(e) - 1), np.int64) for h, e in self.edges.items()}
        self.dirty: set[int] = set()
        self.new_scalars: set[str] = set()
        self.pending_configs: dict[int, dict] = {}
        self.pending_failures: dict[int, dict] = {}
        self.last_flush = time.monotonic()

    def _load_mirror(self):
        import h5py

        with h5py.File(self.path, "r", locking=False) as f:
            for name in ("status", "attempts", "wall", "rank", "host", "error"):
                getattr(self, name)[:] = f[f"tasks/{name}"][:]
            self.n_status = [int(np.sum(self.status == k)) for k in (PENDING, DONE, FAILED)]
            for name in f["scalars"]:
                self.scalars[name] = f[f"scalars/{name}"][:]
            for h in self.edges:
                self.counts[h][:] = f[f"histograms/{h}/counts"][:]

    def _create_file(self):
        """A fresh, empty view, created under a temporary name and renamed into place."""
        import h5py

        tmp = self.path.with_name(self.path.name + ".tmp")
        if tmp.exists():
            tmp.unlink()
        T = self.T
        with h5py.File(tmp, "w", locking=False) as f:
            g = f.create_group("tasks")
            g.create_dataset("id", data=np.array([t.id.encode() for t in self.tasks], "S32").reshape(T))
            g.create_dataset("variant", data=np.array([_fixed(t.variant, VARIANT_LEN) for t in self.tasks],
                                                      f"S{VARIANT_LEN}").reshape(T))
            g.create_dataset("N", data=np.array([t.N for t in self.tasks], np.int64).reshape(T))
            g.create_dataset("E", data=np.array([t.E for t in self.tasks], np.float64).reshape(T))
            g.create_dataset("seed", data=np.array([t.seed for t in self.tasks], np.int64).reshape(T))
            for name in ("status", "attempts", "wall", "rank", "host", "error"):
                g.create_dataset(name, data=getattr(self, name))
            f.create_group("scalars")
            hg = f.create_group("histograms")
            for h, e in self.edges.items():
                hg.create_dataset(f"{h}/edges", data=e)
                hg.create_dataset(f"{h}/counts", data=self.counts[h])
            if self.spec.configurations:
                f.create_group("configurations")
            f.create_group("failures")
            f.attrs["schema"] = SCHEMA
            f.attrs["spec_hash"] = self.spec.hash
            f.attrs["name"] = self.spec.name
            f.attrs["spec_yaml"] = self.spec.text
        os.replace(tmp, self.path)

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
                "traceback": err.get("traceback", "")}
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
        self._apply(meta, arrays)
        self.maybe_flush()

    def configuration(self, index: int):
        """The stored configuration of task ``index`` (dict of arrays), or None."""
        if index in self.pending_configs:
            return dict(self.pending_configs[index])
        tid = self.tasks[index].id
        if tid in self.have_configs:
            g = self.f[f"configurations/{tid}"]
            return {k: g[k][()] for k in ("positions", "radii", "box", "species")}
        return None

    def _journal_row(self, i):
        """Re-journal a row the view holds (when the journal was lost)."""
        t = self.tasks[i]
        status = int(self.status[i])
        scalars = {k: float(v[i]) for k, v in self.scalars.items() if status == DONE and not np.isnan(v[i])}
        arrays = {"h/" + h: self.counts[h][i] for h in self.edges} if status == DONE else {}
        if t.id in self.have_configs:
            g = self.f[f"configurations/{t.id}"]
            for k in ("positions", "radii", "box", "species"):
                arrays["c/" + k] = g[k][()]
        fail = {}
        if t.id in self.have_failures:
            fail = dict(self.f[f"failures/{t.id}"].attrs)
        self.journal.append({"type": "task", "index": i, "id": t.id, "status": status,
                             "attempts": int(self.attempts[i]), "wall": float(self.wall[i]),
                             "rank": int(self.rank[i]), "host": self.host[i].decode(errors="replace"),
                             "message": str(fail.get("message", self.error[i].decode(errors="replace"))),
                             "traceback": str(fail.get("traceback", "")), "scalars": scalars}, arrays)

    def _apply(self, meta, arrays):
        i = int(meta["index"])
        if not (0 <= i < self.T) or self.tasks[i].id != meta["id"]:
            raise UserError(f"{str(self.journal.path)!r} does not match the spec (task {i})")
        status = int(meta["status"])
        self.n_status[int(self.status[i])] -= 1
        self.n_status[status] += 1
        self.status[i] = status
        self.attempts[i] = meta["attempts"]
        self.wall[i] = meta["wall"]
        self.rank[i] = meta["rank"]
        self.host[i] = _fixed(meta["host"], HOST_LEN)
        self.error[i] = _fixed(meta["message"], ERROR_LEN) if status == FAILED else b""
        if "scalar_names" in meta:
            names = meta["scalar_names"].split(",") if meta["scalar_names"] else []
            sc = dict(zip(names, arrays["s"].tolist()))
        else:
            sc = meta.get("scalars", {})
        for name in sc:
            if name not in self.scalars:
                self.scalars[name] = np.full(self.T, np.nan)
                self.new_scalars.add(name)
        for name, col in self.scalars.items():
            col[i] = float(sc.get(name, np.nan))
        for h, c in self.counts.items():
            key = "h/" + h
            if key in arrays and arrays[key].shape == c.shape[1:]:
                c[i] = arrays[key]
            else:
                c[i] = 0
        if "c/positions" in arrays:
            self.pending_configs[i] = {k: arrays["c/" + k] for k in ("positions", "radii", "box", "species")}
        if status == FAILED:
            self.pending_failures[i] = {"message": meta["message"], "traceback": meta["traceback"],
                                        "attempts": int(meta["attempts"]), "rank": int(meta["rank"]),
                                        "host": meta["host"]}
        else:
            self.pending_failures[i] = None  # a former failure, now done: drop its record
        self.dirty.add(i)

    def _merge_run(self, run):
        for k, r in enumerate(self.runs):
            if r.get("run_id") == run.get("run_id"):
                self.runs[k] = run
                return
        self.runs.append(run)

    # ---- flushing
    def maybe_flush(self):
        if len(self.dirty) >= FLUSH_ROWS or time.monotonic() - self.last_flush >= FLUSH_SECONDS:
            self.flush(force=True)

    def flush(self, force=False):
        if not force and not self.dirty:
            return
        self.journal.sync()
        f = self.f
        idx = np.array(sorted(self.dirty), dtype=np.int64)
        runs = _runs(idx)
        for name in sorted(self.new_scalars):
            if name not in f["scalars"]:
                f["scalars"].create_dataset(name, data=self.scalars[name])
        self.new_scalars.clear()
        # data first ...
        for name in ("attempts", "wall", "rank", "host", "error"):
            _write_rows(f[f"tasks/{name}"], getattr(self, name), runs)
        for name, col in self.scalars.items():
            _write_rows(f[f"scalars/{name}"], col, runs)
        for h, c in self.counts.items():
            _write_rows(f[f"histograms/{h}/counts"], c, runs, one_d=False)
        for i, cfg in sorted(self.pending_configs.items()):
            tid = self.tasks[i].id
            if tid in self.have_configs:
                del f[f"configurations/{tid}"]
            g = f.require_group("configurations").create_group(tid)
            for k, a in cfg.items():
                g.create_dataset(k, data=a)
            self.have_configs.add(tid)
        self.pending_configs.clear()
        for i, fail in sorted(self.pending_failures.items()):
            tid = self.tasks[i].id
            if tid in self.have_failures:
                del f[f"failures/{tid}"]
                self.have_failures.discard(tid)
            if fail is not None:
                g = f["failures"].create_group(tid)
                for k, v in fail.items():
                    g.attrs[k] = v
                self.have_failures.add(tid)
        self.pending_failures.clear()
        f.flush()
        # ... then the commit marker
        _write_rows(f["tasks/status"], self.status, runs)
        f.flush()
        self.dirty.clear()
        self.last_flush = time.monotonic()

    def _write_root_attrs(self):
        f = self.f
        f.attrs["schema"] = SCHEMA
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
        """Flush, stamp the run's end in the journal and the attributes, release the lock."""
        if self.f is None:
            return
        try:
            self.run.update(end_info, end=_now())
            self.run["hosts"] = sorted(set(self.run.get("hosts", [])) |
                                       {h.decode() for h in np.unique(self.host[self.rank >= 0]) if h})
            self.journal.append({"type": "run", "run": self.run})
            self._merge_run(self.run)
            self.flush(force=True)
            self._write_root_attrs()
            self.f.flush()
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


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def _runs(idx):
    if len(idx) == 0:
        return []
    breaks = np.flatnonzero(np.diff(idx) != 1) + 1
    return [(int(r[0]), int(r[-1]) + 1) for r in np.split(idx, breaks)]


def _write_rows(ds, mirror, runs, one_d=True):
    if not runs:
        return
    if one_d and len(runs) > 16:  # many scattered rows: one bounding slice is cheaper
        lo, hi = runs[0][0], runs[-1][1]
        ds[lo:hi] = mirror[lo:hi]
        return
    for lo, hi in runs:
        ds[lo:hi] = mirror[lo:hi]


# --------------------------------------------------------------------------- readers

def read_summary(path):
    """What ``campaign status`` shows: the task table and root attributes, read-only.

    Works while a run is writing (``locking=False``); retries a few times if it
    catches the file in the middle of a flush.
    """
    import h5py

    last = None
    for attempt in range(5):
        try:
            with h5py.File(path, "r", locking=False) as f:
                if f.attrs.get("schema") != SCHEMA:
                    raise UserError(f"{str(path)!r} is not a campaign store (no schema {SCHEMA!r})")
                out = {k: f[f"tasks/{k}"][:] for k in TASK_FIELDS}
                out["attrs"] = {k: f.attrs[k] for k in f.attrs}
                out["failures"] = {}
                if "failures" in f:
                    for tid in f["failures"]:
                        out["failures"][tid] = dict(f[f"failures/{tid}"].attrs)
                return out
        except UserError:
            raise
        except FileNotFoundError:
            raise UserError(f"no such file: {str(path)!r}") from None
        except (OSError, KeyError, ValueError) as exc:
            last = exc
            time.sleep(0.2)
    raise UserError(f"cannot read {str(path)!r} as a campaign store: {last}")
