"""The part of ``campaign verify``'s scan that reads a store's per-task block datasets, on which the
whole scan (``campaign.storage.integrity.Scan``) builds: what a scan records (``BlockScan.add``: every
damage into its ``Report``, ``campaign.storage.damage``), the status column, and every chunk of
``tasks/*``, ``scalars/*``, ``histograms/*/counts`` and the bin edges read (in slabs of
``SLAB_BYTES``, a damaged chunk then found alone), with what HDF5 checks of them by itself (each
chunk's fletcher32) and what it does not: each dataset's filter pipeline, each chunk-index entry
(its filter mask, its place on the chunk grid, that a read finds it), each block against its block
checksums (``campaign.storage.checksums``: which rows a read gives back).

In a store written before the block checksums (0.2.7 and older), where nothing records which rows
a block held (docs/STORE.md, "Stores written before the block checksums"), each block of the task
table's identities is checked against the spec's tasks of its rows, in their order (``identities``,
the spec's, also name a damaged id block's tasks in any store).
"""

from __future__ import annotations

import fnmatch
import time

import h5py
import numpy as np

from campaign.plan.tasks import expand
from campaign.storage.checksums import (BLOCK_FILTERS, BLOCK_MISMATCH, EDGES_NOTE, FLETCHER32, IDENTITY,
                                        PROTECTION_ATTR, SLAB_BYTES, SUMS_ROWS, _text, has_sums, is_filter_failure,
                                        mismatched_blocks, reason, sums_name)
from campaign.storage.damage import Damage, Report
from campaign.storage.layout import BLOCK_ROWS, PENDING, VARIANT_LEN, fixed, status_counts


class _Found(Exception):
    """Raised inside a scan that stops at the first damage."""


class BlockScan:
    """One reading of a store (the open h5py file ``f`` at ``path``), recording every damage it meets
    into ``self.report``: what it records, and its reading of the block datasets.

    ``progress(fraction, what)`` is called now and then; with ``stop_first`` the scan raises
    ``_Found`` at the first damage (the readers' search)."""

    def __init__(self, f, path, progress=None, stop_first=False):
        self.f, self.path = f, path
        self.progress = progress
        self.stop_first = stop_first
        self.report = Report(path)
        self.done_units = 0
        self.total_units = 1
        self.last_progress = 0.0
        self.ids = None           # (T,) S32 task ids, as read (None while unknown)
        self.id_order = None
        self.attempts = None
        self.error_set = None     # (T,) bool: the error column holds text
        self.failure_ids = set()  # rows with a failure record (readable or not)
        self.config_rows = set()  # rows with a configuration group (sound or not)
        self.summed = has_sums(f)  # the store keeps block checksums
        self.status_bad = []      # blocks of the status column that do not match their checksums
        self.expected = None      # without block checksums: the spec's task identities, column by column

    # ---- recording
    def add(self, d: Damage):
        self.report.damage.append(d)
        if self.stop_first:
            raise _Found()

    def finished_in(self, lo, hi):
        st = self.report.status
        if st is None or len(st) < hi:
            return np.arange(lo, hi, dtype=np.int64)
        return np.flatnonzero(st[lo:hi] != PENDING).astype(np.int64) + lo

    def tick(self, units, what):
        self.done_units += units
        if self.progress is None:
            return
        now = time.monotonic()
        if now - self.last_progress >= 0.5:
            self.last_progress = now
            self.progress(min(1.0, self.done_units / max(1, self.total_units)), what)

    # ---- the commit marker
    def _status(self):
        f, r = self.f, self.report
        try:
            ds = f["tasks/status"]
            if not isinstance(ds, h5py.Dataset) or ds.ndim != 1 or ds.dtype != np.int8:
                raise ValueError(f"shape {ds.shape}, type {ds.dtype}: not one int8 a task")
            if r.spec is not None and ds.shape[0] != r.spec.n_tasks:
                raise ValueError(f"{ds.shape[0]} rows, but the spec has {r.spec.n_tasks} tasks")
            st = ds[:]
        except Exception as exc:  # noqa: BLE001
            T = r.spec.n_tasks if r.spec is not None else 0
            r.T = T
            self.add(Damage("tasks/status", f"cannot be read ({reason(exc)}): no task can be trusted",
                            rows=np.arange(T, dtype=np.int64), span=(0, T) if T else None))
            return
        r.T = len(st)
        r.status = st
        B = self._status_rows(f, len(st))
        sums = self._sums("tasks/status", len(st), B) if B else None
        if sums is not None:
            self.status_bad = mismatched_blocks(sums, st, 0, B, len(st))
            if self.status_bad and self.stop_first:  # a reader's search: name it now (verify: see _rows)
                a, b = self.status_bad[0]
                self.add(Damage("tasks/status", f"rows {a}-{b - 1} {BLOCK_MISMATCH}", rows=self.finished_in(a, b),
                                span=(a, b)))
        self.attempts = np.zeros(r.T, np.int32)
        self.error_set = np.zeros(r.T, bool)
        r.counts = status_counts(st)
        try:
            r.B = int(f["tasks/attempts"].chunks[0])
        except Exception:  # noqa: BLE001
            r.B = max(1, min(BLOCK_ROWS, r.T))

    def _status_rows(self, f, T):
        """The rows of a block of the status column's checksums (those of the other columns' chunks)."""
        try:
            return int(np.asarray(f[sums_name("tasks/status")].attrs[SUMS_ROWS]).reshape(-1)[0])
        except Exception:  # noqa: BLE001 - reported by _sums
            try:
                return int(f["tasks/attempts"].chunks[0])
            except Exception:  # noqa: BLE001
                return 0

    # ---- block datasets
    def _block_names(self, patterns=None):
        f = self.f
        names = []
        for n in IDENTITY + ("attempts", "wall", "rank", "host", "error"):
            names.append(f"tasks/{n}")
        for group, sub in (("scalars", None), ("histograms", "counts")):
            if patterns is not None and not any(p == group or p.startswith((group + "/", "*")) for p in patterns):
                continue
            try:
                if group not in f:
                    continue
                keys = sorted(f[group].keys(), key=str)
            except Exception as exc:  # noqa: BLE001
                self.add(Damage(group, f"its index cannot be read ({reason(exc)}): every finished task's "
                                       f"{group} are lost", rows=self.finished_in(0, self.report.T)))
                continue
            if group == "scalars":
                keys = [k for k in keys if isinstance(k, str) and "/" not in k]  # damaged names: see _layout
            names += [f"{group}/{k}" + (f"/{sub}" if sub else "") for k in keys]
        return names

    def _exists(self, name):
        try:
            return name in self.f
        except Exception:  # noqa: BLE001
            return True

    def _units(self, name):
        try:
            ds = self.f[name]
            return int(np.prod(ds.shape, dtype=np.float64) * ds.dtype.itemsize)
        except Exception:  # noqa: BLE001
            return 0

    def _expected(self, name):
        """(row shape, dtype kind) a block dataset must have."""
        if name.startswith("histograms/"):
            return "2d", "i"
        if name.startswith("scalars/"):
            return (), "f"
        col = name[6:]
        return (), {"id": "S", "variant": "S", "host": "S", "error": "S", "N": "i", "seed": "i", "attempts": "i",
                    "rank": "i", "E": "f", "wall": "f"}[col]

    def _dataset(self, name):
        f, r = self.f, self.report
        T = r.T
        identity = name[6:] in IDENTITY if name.startswith("tasks/") else False
        repair = "rewrite" if identity else "drop"
        try:
            ds = f[name]
            if not isinstance(ds, h5py.Dataset):
                raise ValueError("not a dataset")
            shape, kind = self._expected(name)
            if ds.shape[0] != T or ds.dtype.kind != kind or (shape == () and ds.ndim != 1) or (
                    shape == "2d" and (ds.ndim != 2 or not 0 < ds.shape[1] < 1 << 24)):
                raise ValueError(f"shape {ds.shape}, type {ds.dtype}: not the layout's")
            chunk = int(ds.chunks[0]) if ds.chunks else T
            has_sum = bool(ds.fletcher32)
            pipeline = _filters(ds)
            if pipeline not in (BLOCK_FILTERS, BLOCK_FILTERS + (FLETCHER32,)):
                raise ValueError(f"its filter pipeline {pipeline} is not the layout's {BLOCK_FILTERS + (FLETCHER32,)} "
                                 "(shuffle, deflate, fletcher32): its header is damaged, and HDF5 would read "
                                 "its chunks wrongly without noticing")
        except KeyError as exc:
            missing = name.startswith("tasks/") and not self._exists(name)
            self.add(Damage(name, "is missing" if missing else f"cannot be opened ({reason(exc)})",
                            rows=np.zeros(0, np.int64) if identity else self.finished_in(0, T),
                            span=None if identity else (0, T), repair=repair))
            return
        except Exception as exc:  # noqa: BLE001
            self.add(Damage(name, f"cannot be read ({reason(exc)})", rows=np.zeros(0, np.int64) if identity
                            else self.finished_in(0, T), span=None if identity else (0, T), repair=repair))
            return
        r.checked["datasets"] += 1
        if not has_sum:
            r.unchecked["datasets"].append(name)
        rowbytes = max(1, ds.dtype.itemsize * (ds.shape[1] if ds.ndim == 2 else 1))
        sums = self._sums(name, T, chunk)
        skip = self._chunk_index(name, ds, chunk, rowbytes, repair)
        step = max(chunk, (SLAB_BYTES // rowbytes) // chunk * chunk)
        col = name[6:] if name.startswith("tasks/") else None
        for lo in range(0, T, step):
            hi = min(lo + step, T)
            if skip and any(lo < b and a < hi for a, b in skip):  # read chunk by chunk, past the bad ones
                self._by_chunks(name, ds, col, lo, hi, chunk, repair, skip, sums=sums)
                self.tick((hi - lo) * rowbytes, name)
                continue
            try:
                data = ds[lo:hi]
                self._values(col, lo, hi, data)
                r.checked["chunks"] += -(-(hi - lo) // chunk)
            except _Found:
                raise
            except Exception:  # noqa: BLE001 - find the damaged chunks of this slab
                self._by_chunks(name, ds, col, lo, hi, chunk, repair, sums=sums)
            else:
                self._check_sums(name, sums, lo, data, chunk, repair)
            self.tick((hi - lo) * rowbytes, name)
        r.checked["bytes"] += _stored_size(ds)

    def _by_chunks(self, name, ds, col, lo, hi, chunk, repair, skip=(), sums=None):
        """Read rows [lo, hi) of ``ds`` chunk by chunk, past the chunks in ``skip``: a chunk that
        cannot be read is damage (``_bad_chunk``), the others are checked as usual."""
        for a in range(lo, hi, chunk):
            b = min(a + chunk, hi)
            if (a, b) in skip:
                continue
            try:
                data = ds[a:b]
            except Exception as exc:  # noqa: BLE001
                self._bad_chunk(name, ds, a, b, exc, repair)
                continue
            self.report.checked["chunks"] += 1
            self._values(col, a, b, data)
            self._check_sums(name, sums, a, data, chunk, repair)

    # ---- block checksums (campaign.storage.checksums: which rows a read gives back)
    def _sums(self, name, T, B):
        """The block checksums of the dataset ``name`` (T rows, blocks of B), or None when the store
        keeps none; missing or malformed ones are damage (a damaged name or header: a repair
        writes them anew from the rows, which their own checksums still guard)."""
        if not self.summed:
            return None
        key = sums_name(name)
        try:
            ds = self.f[key]
            rows = int(np.asarray(ds.attrs[SUMS_ROWS]).reshape(-1)[0])
            if rows != B or ds.shape != (-(-T // B),) or ds.dtype != np.uint64:
                raise ValueError(f"not one uint64 a block of {B} rows (shape {ds.shape}, type {ds.dtype}, "
                                 f"{rows} rows a block)")
            return ds[()]
        except Exception as exc:  # noqa: BLE001
            how = ("has no block checksums (" + key + " is missing: a damaged name?)" if isinstance(exc, KeyError)
                   else f"has block checksums that cannot be read ({reason(exc)})")
            self.add(Damage(name, how, repair="rewrite", note="its checksums are written anew; no task is lost"))
            return None

    def _check_sums(self, name, sums, lo, data, B, repair):
        """Blocks of rows ``data`` (from row ``lo``) that differ from the checksums of the rows written
        there: read from the wrong place (a damaged chunk index), as never written, or decoded
        otherwise (a damaged header), though each chunk's own bytes are sound."""
        if sums is None:
            return
        k = lo // B
        for a, b in mismatched_blocks(sums[k:k + -(-len(data) // B)], data, lo, B, lo + len(data)):
            rows = np.zeros(0, np.int64) if repair == "rewrite" else self.finished_in(a, b)
            note = "the task identities it held are rewritten from the spec" if repair == "rewrite" else ""
            self.add(Damage(name, f"rows {a}-{b - 1} {BLOCK_MISMATCH}", rows=rows, span=(a, b), repair=repair,
                            note=note))

    def _chunk_index(self, name, ds, chunk, rowbytes, repair):
        """Every chunk the index lists must have had every filter applied (a set bit of its filter
        mask makes HDF5 skip that filter on read, checksum included), lie on the chunk grid and
        have a plausible size. Returns the (first, last + 1) rows of the chunks found wrong."""
        infos = []
        try:
            ds.id.chunk_iter(infos.append)
        except AttributeError:  # an HDF5 without chunk iteration: the reads alone check the chunks
            return set()
        except Exception as exc:  # noqa: BLE001
            self.add(Damage(name, f"its chunk index cannot be walked ({reason(exc)})",
                            rows=np.zeros(0, np.int64) if repair == "rewrite" else self.finished_in(0, self.report.T),
                            span=(0, self.report.T), repair=repair))
            return {(a, min(a + chunk, self.report.T)) for a in range(0, self.report.T, chunk)}
        bad = set()
        limit = chunk * rowbytes + chunk * rowbytes // 100 + 1024  # deflate's worst case, and more
        for info in infos:
            a = int(info.chunk_offset[0])
            b = min(a + chunk, self.report.T)
            if a % chunk or not 0 <= a < self.report.T or any(int(x) != 0 for x in info.chunk_offset[1:]):
                self.add(Damage(name, f"its chunk index lists a chunk at row {a}, off the chunk grid (the index is "
                                      "damaged)", rows=self.finished_in(0, self.report.T) if repair == "drop" else
                                np.zeros(0, np.int64), span=(0, self.report.T), repair=repair))
                continue
            problem = None
            if info.filter_mask:
                problem = (f"its chunk index says filters were skipped for it (filter mask {info.filter_mask}): HDF5 "
                           "would read it without unpacking or checking it")
            elif not 0 < info.size <= limit:
                problem = f"its chunk index gives it {info.size} bytes, impossible for {b - a} rows"
            else:  # a read looks the chunk up by its key: it must find this very chunk
                try:
                    mask, raw = ds.id.read_direct_chunk(tuple(int(x) for x in info.chunk_offset))
                    if mask or len(raw) != info.size:
                        problem = ("its chunk index is inconsistent: a read finds another chunk than the index "
                                   "lists")
                except Exception as exc:  # noqa: BLE001
                    problem = (f"its chunk index is inconsistent: a read does not find the chunk the index lists "
                               f"({reason(exc)}), and HDF5 would return the rows as never written")
            if problem is not None:
                rows = np.zeros(0, np.int64) if repair == "rewrite" else self.finished_in(a, b)
                where = f" (the chunk at byte {info.byte_offset} of the file, {info.size} bytes)"
                note = "the task identities it held are rewritten from the spec" if repair == "rewrite" else ""
                self.add(Damage(name, f"rows {a}-{b - 1}{where}: {problem}", rows=rows, span=(a, b), repair=repair,
                                note=note))
                bad.add((a, b))
        st = self.report.status
        if st is not None and (name.startswith(("tasks/", "histograms/"))):  # written for every block
            have = {int(i.chunk_offset[0]) for i in infos}
            for a in range(0, self.report.T, chunk):
                b = min(a + chunk, self.report.T)
                if a in have or (a, b) in bad:
                    continue
                rows = np.flatnonzero(st[a:b] != PENDING).astype(np.int64) + a
                if len(rows) or repair == "rewrite":
                    self.add(Damage(name, f"rows {a}-{b - 1} have no chunk in its index, though the block holds "
                                          "finished tasks (the index is damaged: HDF5 returns the rows as never "
                                          "written)", rows=np.zeros(0, np.int64) if repair == "rewrite" else rows,
                                    span=(a, b), repair=repair))
                    bad.add((a, b))
        return bad

    def _bad_chunk(self, name, ds, a, b, exc, repair):
        where = ""
        try:
            info = ds.id.get_chunk_info_by_coord((a,) + (0,) * (ds.ndim - 1))
            if info.byte_offset is not None:
                where = f" (the chunk at byte {info.byte_offset} of the file, {info.size} bytes)"
        except Exception:  # noqa: BLE001 - the location is a courtesy
            pass
        what = "fails its checksum" if is_filter_failure(exc) else "cannot be read"
        rows = np.zeros(0, np.int64) if repair == "rewrite" else self.finished_in(a, b)
        how = f"rows {a}-{b - 1}{where} {what} ({reason(exc)})"
        note = "the task identities it held are rewritten from the spec" if repair == "rewrite" else ""
        self.add(Damage(name, how, rows=rows, span=(a, b), repair=repair, note=note))

    def _values(self, col, lo, hi, data):
        """What the task table's columns say about their rows (checked in ``_rows``)."""
        self._identity_blocks(col, lo, data)
        if col == "attempts" and self.attempts is not None:
            self.attempts[lo:hi] = data
        elif col == "error" and self.error_set is not None:
            self.error_set[lo:hi] = np.char.str_len(np.asarray(data)) > 0
        elif col == "id":
            if self.ids is None:
                self.ids = np.zeros(self.report.T, "S32")
            self.ids[lo:hi] = data

    def _edges(self, patterns=None):
        f, r = self.f, self.report
        try:
            names = sorted(f["histograms"].keys()) if "histograms" in f else []
        except Exception:  # noqa: BLE001 - reported with the counts
            names = []
        for h in names:
            name = f"histograms/{h}/edges"
            if not _matches(name, patterns):
                continue
            try:
                ds = f[name]
                if _filters(ds) not in ((), (FLETCHER32,)):
                    raise ValueError(f"its filter pipeline {_filters(ds)} is not the layout's (none, or fletcher32)")
                e = ds[()]
                width = f[f"histograms/{h}/counts"].shape[1]
                sums = self._sums(name, len(e), max(1, len(e)))
                if sums is not None and mismatched_blocks(sums, e, 0, max(1, len(e)), len(e)):
                    raise ValueError(BLOCK_MISMATCH)
                if not ds.fletcher32:
                    r.unchecked["datasets"].append(name)
                r.checked["datasets"] += 1
            except KeyError:
                self.add(Damage(name, "is missing", repair="rewrite", note=EDGES_NOTE))
                continue
            except Exception as exc:  # noqa: BLE001
                self.add(Damage(name, f"cannot be read ({reason(exc)})", repair="rewrite", note=EDGES_NOTE))
                continue
            e = np.asarray(e)
            if (e.ndim != 1 or e.dtype.kind != "f" or len(e) != width + 1 or not np.all(np.isfinite(e))
                    or not np.all(np.diff(e) > 0)):
                self.add(Damage(name, "is not a list of increasing bin edges for its counts", repair="rewrite",
                                note=EDGES_NOTE))
                continue
            r.edges[h] = e

    # ---- naming the tasks
    def _column(self, name):
        try:
            return self.f[name][:]
        except Exception:  # noqa: BLE001
            return None

    def _labels(self, rows):
        if not len(rows):
            return []
        out = []
        cols = {}
        for k in IDENTITY:
            try:
                cols[k] = self.f[f"tasks/{k}"][np.sort(np.asarray(rows))]
            except Exception:  # noqa: BLE001
                cols[k] = None
        order = {int(x): i for i, x in enumerate(np.sort(np.asarray(rows)))}
        for row in rows.tolist():
            i = order[int(row)]
            try:
                out.append(f"{_text(cols['id'][i])} ({_text(cols['variant'][i])} N={int(cols['N'][i])} "
                           f"E={float(cols['E'][i]):g} seed {int(cols['seed'][i])})")
            except Exception:  # noqa: BLE001
                out.append(f"row {row}")
        return out

    # ---- a store without block checksums (0.2.7 and older): the task identities against the spec's
    def _expected_identities(self):
        """``identities`` of the scanned store's spec when the store has no block checksums (what its
        task table is checked against, ``_identity_blocks``), else None; and the report's ``unprotected``
        and ``protection`` (the store's ``block_checksums`` attribute: how it came to have them)."""
        r = self.report
        r.unprotected = not self.summed
        try:
            r.protection = _text(self.f.attrs.get(PROTECTION_ATTR)) or ""
        except Exception:  # noqa: BLE001 - unreadable root attributes: reported by the scan
            r.protection = ""
        return identities(r.spec) if not self.summed and r.spec is not None and r.spec.n_tasks == r.T else None

    def _identity_blocks(self, col, lo, data):
        """Whether each block of rows ``data`` (from row ``lo``) of the identity column ``col`` was read from
        its own place: its values, in their rows' order, are those the spec gives its rows
        (``self.expected``, from ``_expected_identities``; nothing to check without)."""
        if self.expected is None or col not in self.expected:
            return
        want, B = self.expected[col], max(1, self.report.B)
        data = np.asarray(data)
        for a in range(lo, lo + len(data), B):
            b = min(a + B, lo + len(data))
            if not np.array_equal(data[a - lo:b - lo], want[a:b]):
                self.add(Damage(f"tasks/{col}", f"rows {a}-{b - 1} are not the spec's {col} of those rows, in their "
                                "order: the block was read from another place (its chunk index is damaged)",
                                span=(a, b), repair="rewrite",
                                note="the task identities it held are rewritten from the spec"))


def identities(spec) -> dict:
    """The task table's identity columns (id, variant, N, E, seed) as the spec gives them, stored types."""
    tasks = expand(spec)
    return {"id": np.array([t.id.encode() for t in tasks], "S32"),
            "variant": np.array([fixed(t.variant, VARIANT_LEN) for t in tasks], f"S{VARIANT_LEN}"),
            "N": np.array([t.N for t in tasks], np.int64), "E": np.array([t.E for t in tasks], np.float64),
            "seed": np.array([t.seed for t in tasks], np.int64)}


def _filters(ds) -> tuple:
    pl = ds.id.get_create_plist()
    return tuple(int(pl.get_filter(i)[0]) for i in range(pl.get_nfilters()))


def _stored_size(ds) -> int:
    try:
        return int(ds.id.get_storage_size())
    except Exception:  # noqa: BLE001
        return 0


def _matches(name, patterns) -> bool:
    if patterns is None:
        return True
    return any(name == p or name.startswith(p.rstrip("/") + "/") or fnmatch.fnmatchcase(name, p) for p in patterns)
