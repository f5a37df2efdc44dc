"""The write-ahead journal beside a campaign store (``OUT.h5.journal``).

A sequence of records, each a 12-byte header (magic, payload length, CRC-32 of the payload)
and a payload: JSON metadata, then the raw bytes of the record's arrays. The master appends
one record per finished task with a single ``write()`` before the task touches the HDF5
file; a checkpoint (``campaign.storage.store``) cuts the journal back once the store holds
everything. Reading keeps every intact record: a record failing its length or checksum is
skipped up to the next intact record header, and a torn tail is cut off.

The journal is also the run's lock: ``Journal`` holds an exclusive ``flock`` on it for
the lifetime of the run (one writer per store).

Writing never leaves half a record behind when the file system refuses it: an append that
fails (a full disk, a quota, an I/O error) is cut back to the previous record's end and
raised as ``campaign.errors.WriteFault`` (``OutOfSpace`` for ENOSPC and EDQUOT).
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import struct
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from campaign.errors import UserError
from campaign.storage.faults import write_fault
from campaign.storage.layout import DONE, FAILED, FORMAT_VERSION, OLD_FORMAT_HELP, SCHEMA, ForeignStore

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


def task_record(index, tid, summary, attempts, edges, run_id):
    """The journal record ``(meta, arrays)`` of the final outcome of task ``tid`` (row ``index``), from
    its worker's ``summary`` (docs/CONTRACTS.md): done if ``summary['ok']``, else failed; ``row_values``
    (``campaign.storage.layout``) reads it back."""
    status = DONE if summary["ok"] else FAILED
    err = summary.get("error") or {}
    meta = {"type": "task", "index": index, "id": tid, "status": status, "attempts": int(attempts),
            "wall": float(summary.get("wall", float("nan"))), "rank": int(summary.get("rank", -1)),
            "host": str(summary.get("host", "")), "message": err.get("message", ""),
            "traceback": err.get("traceback", ""), "run_id": run_id}
    arrays = {}
    if status == DONE:
        sc = summary.get("scalars", {})
        meta["scalar_names"] = ",".join(sc)
        arrays["s"] = np.fromiter(sc.values(), np.float64, len(sc))
        for h in edges:
            arrays["h/" + h] = np.asarray(summary["histograms"][h], np.int64)
        cfg = summary.get("configuration")
        if cfg is not None:  # asked for by the spec, or a ladder parent's
            for k in ("positions", "radii", "box", "species"):
                arrays["c/" + k] = np.asarray(cfg[k])
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


def task_indices(path) -> set:
    """The task indices the journal at ``path`` has records of, read without locking it or
    checking checksums (``campaign status``, while a run may be writing it): record headers
    and metadata only, up to the first record that does not parse."""
    out = set()
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return out
    try:
        size, pos = os.fstat(fd).st_size, 0
        while pos + _HEAD.size + 4 <= size:
            magic, n, _ = _HEAD.unpack(os.pread(fd, _HEAD.size, pos))
            if magic != _MAGIC or pos + _HEAD.size + n > size:
                break
            (m,) = struct.unpack("<I", os.pread(fd, 4, pos + _HEAD.size))
            try:
                meta = json.loads(os.pread(fd, m, pos + _HEAD.size + 4))
            except ValueError:
                break
            if meta.get("type") == "task":
                out.add(int(meta["index"]))
            pos += _HEAD.size + n
    except (OSError, struct.error, KeyError, TypeError, ValueError):
        pass
    finally:
        os.close(fd)
    return out


def header_spec_hash(path):
    """The spec hash in the header of the journal at ``path``, or None (read without locking it)."""
    try:
        with open(path, "rb") as fh:
            records, _, _ = scan_journal(fh.read(1 << 20))
        head = records[0][0] if records else {}
        return head.get("spec_hash") if head.get("type") == "header" else None
    except (OSError, ValueError, IndexError, AttributeError):
        return None


@dataclass
class Replay:
    """What a run's start takes from its journal (``Journal.replay``): the records that follow the
    header (``task``, ``suspended``, ``round``, ``run``, ``checkpoint``), in order, to be replayed into
    the store; whether there was a journal at all (a header); and what reading it found damaged."""

    path: Path
    found: bool = False
    records: list = field(default_factory=list)  # (meta, arrays) after the header
    damaged: list = field(default_factory=list)  # (offset, length, records lost) of each damaged stretch
    torn: int = 0  # bytes of a torn last record, cut off

    @property
    def committed(self) -> int:
        """The finished tasks the store held at the journal's last checkpoint."""
        last = {}
        for meta, _ in self.records:
            if meta.get("type") == "checkpoint":
                last = meta
        return int(last.get("committed", 0))

    def rows(self) -> set:
        """The task rows its records go to: the only ones a killed run can have been writing (their
        blocks' rows and checksums may be out of step until the replay rewrites them)."""
        return {int(m["index"]) for m, _ in self.records if m.get("type") == "task"}

    def notes(self) -> list:
        """What reading it found, as the lines a run prints: damaged stretches skipped (their tasks run
        again), a torn record cut off."""
        out = []
        if self.damaged:
            kept = sum(1 for m, _ in self.records if m.get("type") == "task")
            n_lost = sum(k for _, _, k in self.damaged)
            n_bytes = sum(n for _, n, _ in self.damaged)
            where = ", ".join(f"{o}" for o, _, _ in self.damaged[:5])
            out.append(f"campaign: {self.path} is damaged: skipped {len(self.damaged)} damaged stretch(es) ({n_bytes} "
                       f"bytes at offset {where}), about {n_lost} record(s) lost; kept {kept} intact task record(s). "
                       "The tasks of the lost records are pending again and will be run again")
        if self.torn:
            out.append(f"campaign: cut a torn record ({self.torn} bytes) off the end of {self.path}")
        return out


class Journal:
    """The write-ahead journal, locked for the lifetime of a run (one writer per store)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.fd = None
        self.store = str(self.path)[:-len(".journal")] if str(self.path).endswith(".journal") else str(self.path)
        try:
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            fault = write_fault(exc, self.path, "creating the journal")
            if fault is not None and fault.out_of_space:
                raise fault from None
            raise UserError(f"cannot open {str(self.path)!r} (the journal of {self.store!r}) for writing: "
                            f"{exc.strerror}; choose another --out, or make its directory writable") from None
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                os.close(self.fd)
                self.fd = None
                raise UserError(f"another run is writing {self.store!r} (its journal {str(self.path)!r} is locked); "
                                "wait for it to finish or stop it first") from None
            # a file system without flock (some Lustre mounts): carry on, unprotected
            print(f"campaign: warning: cannot lock {self.path} ({exc.strerror}); make sure no other run "
                  "writes this file at the same time", file=sys.stderr)
        size = os.fstat(self.fd).st_size
        data = os.pread(self.fd, size, 0) if size else b""
        self.records, good, self.damaged = scan_journal(data)
        del data
        self.torn = size - good
        if self.torn:
            os.ftruncate(self.fd, good)  # needs no space
        self.size = good
        os.lseek(self.fd, 0, os.SEEK_END)
        self.dirty = False

    def clear(self):
        """Start afresh (``campaign run --new``): nothing of what the journal held is kept or reported."""
        self.rewrite([])
        self.damaged, self.torn = [], 0

    def replay(self, spec_hash) -> Replay:
        """What the journal holds for a run of the spec ``spec_hash`` to replay (``Replay``), handed over
        once (the journal keeps no copy). ForeignStore when its header is another spec's or program's,
        or of another store format."""
        records, self.records = self.records, []
        replay = Replay(self.path, found=bool(records), records=records[1:], damaged=self.damaged, torn=self.torn)
        if not records:
            return replay
        header = records[0][0]
        if header.get("type") != "header" or header.get("spec_hash") != spec_hash:
            raise ForeignStore(f"{str(self.path)!r} belongs to a different spec (or a different program); rerun "
                               f"with --new to start {self.store!r} afresh, or choose another --out")
        if header.get("format_version", 1) != FORMAT_VERSION:
            raise ForeignStore(f"{str(self.path)!r} was written by a store of format "
                               f"{header.get('format_version', 1)}; " + OLD_FORMAT_HELP.format(new=FORMAT_VERSION))
        return replay

    def cut_back(self, spec_hash, T, runs, committed, when):
        """Cut the journal back to what a store that holds every finished task needs of it: its header
        (the spec ``spec_hash`` of ``T`` tasks), the ``runs`` so far and a checkpoint record (``committed``
        tasks in the store, at ``when``)."""
        header = {"type": "header", "schema": SCHEMA, "format_version": FORMAT_VERSION, "spec_hash": spec_hash,
                  "T": T}
        recs = [(header, None)] + [({"type": "run", "run": r}, None) for r in runs]
        recs.append(({"type": "checkpoint", "committed": committed, "time": when}, None))
        self.rewrite(recs)

    def rewrite(self, records):
        """Replace the journal's content by ``records`` ((meta, arrays) pairs), durably.

        Called only when everything else the journal held is safely in the store: a kill
        (or a full disk) between the truncation and the write leaves an empty or torn
        journal, which the next start recreates from the store.
        """
        data = b"".join(encode_record(m, a) for m, a in records)
        os.ftruncate(self.fd, 0)
        os.lseek(self.fd, 0, os.SEEK_SET)
        self.size = 0
        self.records = []
        self._write(data, "rewriting the journal at a checkpoint")
        self.dirty = True
        self.sync()

    def _write(self, data, what):
        """Append ``data`` whole, or cut it back off and raise the WriteFault."""
        start = self.size
        try:
            n = os.write(self.fd, data)
            while n < len(data):  # a short write (full disk, signal): finish it or fail
                n += os.write(self.fd, data[n:])
        except OSError as exc:
            try:  # no half record left behind (truncating needs no space)
                os.ftruncate(self.fd, start)
                os.lseek(self.fd, start, os.SEEK_SET)
            except OSError:
                pass  # a torn tail is cut at the next start anyway
            fault = write_fault(exc, self.path, what, needed=len(data))
            if fault is None:
                raise
            raise fault from None
        self.size += len(data)

    def append(self, rec: dict, arrays: dict | None = None):
        self._write(encode_record(rec, arrays), "appending a finished task to the journal")
        self.dirty = True

    def sync(self):
        if self.dirty:
            try:
                os.fsync(self.fd)
            except OSError as exc:
                fault = write_fault(exc, self.path, "making the journal durable (fsync)")
                if fault is None:
                    raise
                raise fault from None
        self.dirty = False

    def close(self):
        if self.fd is not None:
            try:
                if self.dirty:
                    self.sync()
            finally:
                os.close(self.fd)  # releases the lock
                self.fd = None
