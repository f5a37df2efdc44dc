"""How much a write step of the campaign store may add to its file: the estimate the store
reserves (``campaign.storage.faults.reserve``) before HDF5 writes anything (docs/STORE.md, "Out of space").

A step rewrites whole chunks (blocks of ``B`` rows of every per-task dataset), compressed;
HDF5 may place a rewritten chunk at the end of the file, so each counts in full: its raw size
times the compression ratio of its column, plus a quarter. The ratios are learnt from the
chunks the store has written (the largest of the last eight, per column), and before there are
any, by compressing the block about to be written with HDF5's own filters (shuffle, then
deflate level 1). Configurations and failure records are not compressed; new datasets, grown
symbol tables and chunk indices, and a large file's larger structures get fixed room
(``slack``). ``tests/test_store.py::test_reservations_cover_every_write_step`` checks that no
step grows the file by more than it reserved.
"""

from __future__ import annotations

import os
import zlib

import numpy as np

from campaign.storage.storefile import FAILED, ROW_FIELDS, SLACK, fill_value, row_dtype


class SpaceModel:
    def __init__(self, B: int, T: int, edges: dict):
        self.B, self.T, self.edges = B, T, edges
        self.ratio = {}  # learnt key (a column, or all scalars) -> compressed / raw bytes
        self.seen = {}   # learnt key -> the last few ratios seen in the file

    def columns(self, names):
        """(dataset name, bytes of one row, learnt key) of every per-task column written by block."""
        cols = [(f"tasks/{n}", np.dtype(row_dtype(n)).itemsize, f"tasks/{n}") for n in ROW_FIELDS]
        cols += [(f"scalars/{n}", 8, "scalars") for n in sorted(names)]
        cols += [(f"histograms/{h}/counts", 8 * (len(e) - 1), f"histograms/{h}") for h, e in self.edges.items()]
        return cols

    def blocks_bytes(self, staged, blocks, scalar_names, groups, row_values) -> int:
        """What writing the staged rows of ``blocks`` may add to the file. ``staged``: block ->
        row -> (meta, arrays) records; ``groups``: configuration and failure groups the file
        holds (their name heaps double when they fill); ``row_values(meta, arrays)``: a row's
        values per dataset."""
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
            self.calibrate(staged[blocks[0]], blocks[0], columns, row_values)
        rows = sum(min(self.B, self.T - b * self.B) for b in blocks)
        chunks = sum(rows * width * 1.25 * self.ratio.get(key, 1.0) + 512 * len(blocks) for _, width, key in columns)
        new = 8192 * len(names - set(scalar_names))
        if extra:
            extra += 96 * groups
        return int(chunks + extra + new)

    def calibrate(self, rows, b, columns, row_values):
        """Ratios of the columns not learnt yet, from the values block ``b`` is about to get."""
        lo, hi = b * self.B, min((b + 1) * self.B, self.T)
        idx = np.fromiter(rows, np.int64, len(rows)) - lo
        values = [row_values(m, a) for m, a in rows.values()]
        for name, width, key in columns:
            if key in self.ratio:
                continue
            shape = (len(self.edges[name.split("/")[1]]) - 1,) if name.startswith("histograms/") else ()
            if shape:
                dtype, fill = np.int64, 0
            elif name.startswith("scalars/"):
                dtype, fill = np.float64, np.nan
            else:
                dtype, fill = np.dtype(row_dtype(name[6:])), fill_value(name[6:])
            block = np.full((hi - lo,) + shape, fill, dtype=dtype)
            col = [v.get(name) for v in values]
            if shape:
                block[idx] = np.stack([np.zeros(shape, np.int64) if x is None else x for x in col])
            else:
                block[idx] = np.array([fill if x is None else x for x in col], dtype=dtype)
            raw = block.view(np.uint8).reshape(-1, block.dtype.itemsize).T.tobytes()  # the shuffle filter
            self.ratio[key] = min(1.02, (len(zlib.compress(raw, 1)) + 64) / max(1, len(raw)))

    def learn(self, dataset, blocks, scalar_names):
        """The stored size of the last chunk written in each column (``dataset(name)``: the open
        h5py dataset): the ratios follow the data."""
        b = max(blocks)
        lo, hi = b * self.B, min((b + 1) * self.B, self.T)
        now = {}
        for name, width, key in self.columns(scalar_names):
            try:
                ds = dataset(name)
                info = ds.id.get_chunk_info_by_coord((lo,) + (0,) * (ds.ndim - 1))
            except Exception:  # noqa: BLE001 - an HDF5 without chunk info: keep the calibration
                return
            now[key] = max(now.get(key, 0.0), info.size / max(1, (hi - lo) * width))
        for key, ratio in now.items():
            seen = self.seen.setdefault(key, [])
            seen.append(ratio)
            del seen[:-8]
            self.ratio[key] = max(seen)

    def slack(self, path, n_scalars, written_blocks, new_blocks=0) -> int:
        """Room for HDF5's metadata on top of an estimate: new nodes of the chunk indices (every
        per-task dataset is chunked alike, so their indices grow together: a first node when a
        dataset gets its first chunk, more once it has 64), object headers that grow, and a
        little more for a large file's larger structures."""
        columns = len(ROW_FIELDS) + 1 + n_scalars + len(self.edges)
        try:
            size = os.path.getsize(path)
        except OSError:
            size = 0
        index = 0
        if not written_blocks or written_blocks + new_blocks > 64:
            index = 3072 * columns * (1 + new_blocks // 32)
        return SLACK + index + size // 256
