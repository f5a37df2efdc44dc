"""The space accounting of the campaign store's HDF5 file (docs/STORE.md, "Out of space"): what
a write step may add to the file, the room HDF5's metadata takes on top of that, the
reservation around every write step (and what a failed one leaves), and what finishing the
campaign needs on disk.

Calls go one way: ``campaign.storage.store`` -> here -> ``campaign.storage.faults`` (reserving,
releasing, classifying a failed write) and ``campaign.storage.layout`` (the layout: dtypes,
fill values, a block's columns built from its rows, as the store writes them). The store hands
over what an estimate needs (the blocks its file holds when it opens it, its staged records, its
scalar names, the datasets it has just written); nothing here calls back into it, and nothing of
this object's is set from outside. What a failed step leaves is the handle's
(``GuardedFile.poison``, ``poisoned``): the store reads it there when it closes.

A step rewrites whole chunks (blocks of ``B`` rows of every per-task dataset), compressed;
HDF5 may place a rewritten chunk at the end of the file, so each counts in full: its raw size
times the compression ratio of its column, plus a quarter. The ratios are learnt from the
chunks the store has written (the largest of the last eight, per column), and before there are
any, by compressing the block about to be written (built as the store builds it:
``layout.column_block``) with HDF5's own filters (shuffle, then deflate level 1).
Configurations and failure records are not compressed; new datasets, grown symbol tables and
chunk indices, and a large file's larger structures get fixed room (``slack``). ``tests/storage/test_store.py::test_reservations_cover_every_write_step`` checks that no
step grows the file by more than it reserved.
"""

from __future__ import annotations

import contextlib
import os
import zlib
from pathlib import Path

import numpy as np

from campaign.storage.faults import release, reserve, write_fault
from campaign.storage.layout import FAILED, ROW_FIELDS, SLACK, block_values, column_block, row_dtype


class StoreSpace:
    """The space accounting of one store file: ``path``, ``B`` rows a block, ``T`` tasks, the
    histograms' bin ``edges``, the blocks ``written`` (those the file holds chunks of when the
    store opens it; the write steps add theirs)."""

    def __init__(self, path, B: int, T: int, edges: dict, written=()):
        self.path = Path(path)
        self.B, self.T, self.edges = B, T, edges
        self.ratio = {}  # learnt key (a column, or all scalars) -> compressed / raw bytes
        self.seen = {}   # learnt key -> the last few ratios seen in the file
        self.written_blocks = set(written)  # blocks the file holds chunks of
        self.record_bytes = []  # sizes of this run's journal records (what finishing needs)
        self.log = []  # (bytes reserved, bytes the file grew) of the last HDF5 write steps

    # ---- what a write step may add
    def columns(self, names):
        """(dataset name, bytes of one row, learnt key) of every per-task column written by block."""
        cols = [(f"tasks/{n}", np.dtype(row_dtype(n)).itemsize, f"tasks/{n}") for n in ROW_FIELDS]
        cols += [(f"scalars/{n}", 8, "scalars") for n in sorted(names)]
        cols += [(f"histograms/{h}/counts", 8 * (len(e) - 1), f"histograms/{h}") for h, e in self.edges.items()]
        return cols

    def blocks_bytes(self, staged, blocks, scalar_names, groups) -> int:
        """What writing the staged rows of ``blocks`` may add to the file. ``staged``: block ->
        row -> (meta, arrays) records; ``scalar_names``: the scalar datasets the file holds;
        ``groups``: configuration and failure groups the file holds (their name heaps double
        when they fill)."""
        names = set(scalar_names)
        extra = 0
        for b in blocks:
            for meta, arrays in staged[b].values():
                if "scalar_names" in meta:
                    names.update(n for n in meta["scalar_names"].split(",") if n)
                else:
                    names.update(meta.get("scalars", {}))
                if "c/positions" in arrays:
                    extra += sum(a.nbytes for k, a in arrays.items() if k.startswith("c/")) + 3584
                if int(meta["status"]) == FAILED:
                    extra += len(meta.get("message", "")) + len(meta.get("traceback", "")) + 4096
        columns = self.columns(names)
        if any(key not in self.ratio for _, _, key in columns):
            self.calibrate(staged[blocks[0]], blocks[0], columns)
        rows = sum(min(self.B, self.T - b * self.B) for b in blocks)
        chunks = sum(rows * width * 1.25 * self.ratio.get(key, 1.0) + 512 * len(blocks) for _, width, key in columns)
        new = (8192 + 8 * -(-self.T // self.B) + 1024) * len(names - set(scalar_names))  # with its checksums
        if extra:
            extra += 96 * groups
        return int(chunks + extra + new)

    def calibrate(self, rows, b, columns):
        """Ratios of the columns not learnt yet, from the values block ``b`` is about to get
        (``rows``: row -> its (meta, arrays) record), built as the store builds them."""
        lo, hi = b * self.B, min((b + 1) * self.B, self.T)
        idx, values = block_values(rows, lo, self.edges)
        for name, width, key in columns:
            if key in self.ratio:
                continue
            block = column_block(name, hi - lo, idx, values, self.edges)
            raw = block.view(np.uint8).reshape(-1, block.dtype.itemsize).T.tobytes()  # the shuffle filter
            self.ratio[key] = min(1.02, (len(zlib.compress(raw, 1)) + 64) / max(1, len(raw)))

    def learn(self, datasets, blocks, scalar_names):
        """The stored size of the last chunk written in each column (``datasets``: dataset name ->
        the open h5py dataset the step wrote): the ratios follow the data."""
        b = max(blocks)
        lo, hi = b * self.B, min((b + 1) * self.B, self.T)
        now = {}
        for name, width, key in self.columns(scalar_names):
            try:
                ds = datasets[name]
                info = ds.id.get_chunk_info_by_coord((lo,) + (0,) * (ds.ndim - 1))
            except Exception:  # noqa: BLE001 - an HDF5 without chunk info: keep the calibration
                return
            now[key] = max(now.get(key, 0.0), info.size / max(1, (hi - lo) * width))
        for key, ratio in now.items():
            seen = self.seen.setdefault(key, [])
            seen.append(ratio)
            del seen[:-8]
            self.ratio[key] = max(seen)

    @staticmethod
    def attrs_bytes(attrs) -> int:
        """What writing the root attributes ``attrs`` may add to the file."""
        size = sum(len(v) if isinstance(v, str) else 8 for v in attrs.values())
        return 2 * size + 16384

    def slack(self, n_scalars, new_blocks=0) -> int:
        """Room for HDF5's metadata on top of an estimate: new nodes of the chunk indices (every
        per-task dataset is chunked alike, so their indices grow together: a first node when a
        dataset gets its first chunk, more once it has 64), object headers that grow, and a
        little more for a large file's larger structures."""
        columns = len(ROW_FIELDS) + 1 + n_scalars + len(self.edges)
        try:
            size = os.path.getsize(self.path)
        except OSError:
            size = 0
        written = len(self.written_blocks)
        index = 0
        if not written or written + new_blocks > 64:
            index = 3072 * columns * (1 + new_blocks // 32)
        return SLACK + index + size // 256

    # ---- the reservation around a write step
    @contextlib.contextmanager
    def write_step(self, io, nbytes, what, n_scalars, blocks=()):
        """One step that writes the HDF5 file through ``io`` (the store's ``GuardedFile``): the
        space it may need (``nbytes`` plus room for HDF5's own metadata, with ``n_scalars``
        scalar datasets and the chunks of ``blocks`` written) is reserved first, or OutOfSpace
        is raised before anything is written; if anything fails inside, the handle is poisoned
        (``io.poison()``: the store then closes it without writing) and an operating-system
        failure is raised as a WriteFault. Logs (bytes reserved, bytes the file grew) and counts
        ``blocks`` as written."""
        if io.poisoned:
            raise RuntimeError("the store's HDF5 handle failed a write before; it must not be written again")
        fresh = [b for b in blocks if b not in self.written_blocks]
        fd = io.fd
        need = int(nbytes) + self.slack(n_scalars, len(fresh))
        size = os.fstat(fd).st_size
        reserved = reserve(fd, need, self.path, what)
        try:
            yield
        except BaseException as exc:
            io.poison()
            fault = write_fault(exc, self.path, what, needed=need)
            if fault is not None and fault is not exc:
                raise fault from None
            raise
        finally:
            if not io.poisoned:  # a refused write poisons it too (``failed``)
                release(fd, reserved)
        if io.failed is not None:  # HDF5 wrote past the reservation into a full disk: the overlay took it
            fault = write_fault(io.failed, self.path, what, needed=need)
            if fault is None:
                raise RuntimeError(f"writing {self.path} failed: {io.failed}") from io.failed
            fault.damaged = True
            raise fault
        self.log.append((need, os.fstat(fd).st_size - size))
        del self.log[:-64]
        self.written_blocks.update(blocks)

    # ---- what finishing the campaign needs
    def note_record(self, nbytes):
        """A journal record of ``nbytes`` was appended (the first 4096 are kept: a task's share
        of the journal)."""
        if len(self.record_bytes) < 4096:
            self.record_bytes.append(nbytes)

    def needed(self, *, pending, final, staged, scalar_names, groups, journal_cap) -> dict:
        """What finishing the campaign would take on disk: ``{"per_task", "journal_per_task",
        "pending", "total"}`` (bytes; None when unknown), with ``pending`` tasks left and ``final``
        finished, of which ``staged`` (block -> row -> record) still wait to be written; the
        journal grows to at most ``journal_cap`` before a checkpoint cuts it back. A task's share
        of the store is measured on the rows the file holds, else estimated (an upper bound)
        from the rows waiting to be written."""
        out = {"pending": pending, "per_task": None, "journal_per_task": None, "total": None}
        n_staged = sum(len(rows) for rows in staged.values())
        committed = final - n_staged
        try:
            used = os.path.getsize(self.path)
        except OSError:
            used = 0
        if committed > 0 and used:
            out["per_task"] = used / committed
        elif n_staged:
            out["per_task"] = self.blocks_bytes(staged, list(staged), scalar_names, groups) / n_staged
        if self.record_bytes:
            out["journal_per_task"] = sum(self.record_bytes) / len(self.record_bytes)
        if out["per_task"] is not None:
            journal = min(journal_cap, pending * (out["journal_per_task"] or out["per_task"]))
            out["total"] = int(pending * out["per_task"] + journal + self.slack(len(scalar_names)))
        return out
