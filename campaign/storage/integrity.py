"""Finding damage in the campaign store: ``campaign verify``'s scan, and the error every reader
raises when a read of the store fails.

What carries a checksum (docs/STORE.md, "Checksums, verify and repair"; written and checked by
``campaign.storage.checksums``): every per-task block dataset (``tasks/*`` but ``status``,
``scalars/*``, ``histograms/*/counts``) and the bin edges (HDF5's ``fletcher32`` filter, one
checksum per chunk, checked by HDF5 itself before every read of it, in any reader), every
configuration (``crc32`` of its arrays' bytes), every failure record (``crc32`` of its message,
traceback and attempts) and the ``scalars`` group's list of its datasets' names (a damaged link
name is then found, and a repair renames the dataset back). ``tasks/status``, the commit marker
(one byte a task, rewritten in place), carries none: it is checked against the row it commits
(``Scan._rows``).

HDF5's own metadata (object headers, chunk indices, heaps) has no checksum in the file format
the store uses; ``Scan`` checks what can be checked of it: the filter pipelines, each chunk's
filter mask and lookup, the names against the layout and the spec, and a walk of the file.

``scan(path)`` reads everything (``campaign verify``) and returns a ``Report``
(``campaign.storage.damage``: what is damaged, which rows a repair drops);
``campaign.storage.repair`` rebuilds the store from it (``campaign verify --repair``), so that
``campaign run`` of the same spec recomputes exactly those rows; ``read_failure`` is the error a
reader raises when a read of the store fails: damage found there is named, and "try again" is
said only when a run writes the file and reading again worked.

A store written without checksums (before they were added, or with ``CAMPAIGN_NO_CHECKSUMS=1``,
the benchmarks' and tests' switch) reads as before; ``scan`` counts what carries none.
"""

from __future__ import annotations

import fnmatch
import json
import os
import time

import numpy as np

from campaign.errors import UserError
from campaign.storage.checksums import (BLOCK_FILTERS, CHECKSUM_ATTR, CONFIG_KEYS, CONFIG_WEIGHT, EDGES_NOTE,
                                        FLETCHER32, IDENTITY, ROOT_ATTRS, ROOT_MEMBERS, SLAB_BYTES,
                                        _text, checkpoint_damage, configuration_problem, failure_problem,
                                        good_scalar_name, is_filter_failure, looks_like_store, reason,
                                        scalar_names_listed)
from campaign.storage.checksums import (BLOCK_MISMATCH, SUMS_GROUP, SUMS_ROWS, has_sums, mismatched_blocks,
                                        sums_name)
from campaign.storage.damage import Damage, Report
from campaign.storage.layout import DONE, FAILED, PENDING, status_counts, stored_spec
from campaign.storage.unprotected import expected_identities, identities, identity_blocks, journal_rows


# --------------------------------------------------------------------------- the scan

class _Found(Exception):
    """Raised inside a scan that stops at the first damage."""


class Scan:
    """One reading of a store, recording every damage it meets into ``self.report``.

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

    # ---- the walk
    def run(self, patterns=None):
        """Read every part of the store (``patterns``: only the datasets they name, for readers)."""
        f, r = self.f, self.report
        t0 = time.monotonic()
        full = patterns is None
        if full:
            self._root()
        self._status()
        if full:
            self._layout()
            self.expected = expected_identities(self)
        names = self._block_names(patterns)
        if not full:
            names = [n for n in names if _matches(n, patterns)]
        self.total_units = sum(self._units(n) for n in names) + 1
        if full:
            try:
                n_conf = len(f["configurations"]) if "configurations" in f else 0
            except Exception:  # noqa: BLE001 - reported when the group is walked
                n_conf = 0
            self.total_units += n_conf * CONFIG_WEIGHT
        for name in names:
            self._dataset(name)
        if r.spec is not None and any(d.name == "tasks/id" for d in r.damage):  # the damaged rows' ids: the spec's
            ids = (self.expected or identities(r.spec))["id"]
            self.ids = ids if len(ids) == r.T else self.ids
        if full:
            self._edges()
            self._configurations()
            self._failures()
            for name, how in checkpoint_damage(f, self._rows_of if self.ids is not None else None):
                self.add(Damage(name, how, repair="remove", note="left out: its task starts over"))  # stop and go
            self._rows()
            journal_rows(self)
            self._reduced()
            self._walk()
        else:
            if any(p.startswith("histograms") for p in patterns):
                self._edges(patterns)
            if any(p == "configurations" or p.startswith("configurations/") for p in patterns):
                self._configurations(patterns)
            if any(p == "failures" or p.startswith("failures/") for p in patterns):
                self._failures(patterns)
        r.checked["seconds"] = round(time.monotonic() - t0, 3)
        if self.progress is not None:
            self.progress(1.0, "done")
        r.damage.sort(key=lambda d: (d.span[0] if d.span else -1, d.name))
        for d in r.damage:
            d.labels = self._labels(d.rows[:5])

    # ---- root attributes and the spec
    def _root(self):
        from campaign.storage.layout import FORMAT_VERSION, SCHEMA, format_problem

        f, r = self.f, self.report
        attrs, unreadable = {}, []
        try:
            keys = list(f.attrs.keys())
        except Exception as exc:  # noqa: BLE001
            keys = []
            unreadable.append(Damage("/", f"its attributes cannot be read ({reason(exc)})", repair="none"))
        for k in keys:
            try:
                attrs[k] = f.attrs[k]
            except Exception as exc:  # noqa: BLE001
                unreadable.append(Damage(f"/@{k}", f"cannot be read ({reason(exc)})",
                                         repair="none" if k in ("spec_yaml", "spec_hash") else "remove"))
        r.name = _text(attrs.get("name")) or ""
        schema = _text(attrs.get("schema"))
        for k in attrs:
            if k not in ROOT_ATTRS:
                unreadable.append(Damage(f"/@{_text(k) or k}", "is not an attribute of the layout (a damaged name?)",
                                         repair="remove", note="left out"))
        try:
            has_tasks = isinstance(f.get("tasks/status"), __import__("h5py").Dataset)
        except Exception:  # noqa: BLE001
            has_tasks = False
        if schema != SCHEMA and not unreadable and not (has_tasks and "spec_yaml" in attrs):
            raise UserError(format_problem(attrs, self.path) or f"{self.path}: not a campaign store")
        for d in unreadable:
            self.add(d)
        if schema != SCHEMA:
            if "schema" in attrs:
                self.add(Damage("/@schema", f"is {schema!r}, not {SCHEMA!r}", repair="rewrite"))
        else:
            try:
                version = int(attrs.get("format_version", 1))
            except (TypeError, ValueError):
                version = -1
            if 1 <= version < FORMAT_VERSION + 8 and version != FORMAT_VERSION:
                raise UserError(format_problem(attrs, self.path))
            if version != FORMAT_VERSION:  # no format this program knows of: a damaged number
                self.add(Damage("/@format_version", f"is {attrs.get('format_version')!r}, no store format",
                                repair="rewrite"))
        for k in ("runs", "hosts", "versions"):
            if k in attrs:
                try:
                    json.loads(_text(attrs[k]) or "")
                except ValueError:
                    self.add(Damage(f"/@{k}", "is not the JSON it was written as (provenance only)", repair="remove",
                                    note="left out; the next run writes it again"))
        text, stored_hash = _text(attrs.get("spec_yaml")), _text(attrs.get("spec_hash"))
        if text is None:
            if "spec_yaml" in attrs:
                self.add(Damage("/@spec_yaml", "is not text", repair="none"))
            return
        try:
            spec = stored_spec(attrs, strict=True)
        except UserError as exc:
            self.add(Damage("/@spec_yaml", f"no longer reads as the spec that wrote the store ({reason(exc)})",
                            repair="none"))
            return
        if spec.hash != stored_hash:
            from campaign.storage.journal import header_spec_hash

            witness = header_spec_hash(str(self.path) + ".journal")
            if witness == spec.hash:  # the journal's header agrees with spec_yaml: spec_hash is the damaged one
                self.add(Damage("/@spec_hash", f"is {stored_hash!r}, but the stored spec and the journal's header "
                                               f"say {spec.hash!r}", repair="rewrite"))
            else:
                self.add(Damage("/@spec_hash", f"is {stored_hash!r}, but the stored spec (spec_yaml) hashes to "
                                               f"{spec.hash!r}: one of the two root attributes is damaged",
                                repair="none"))
                return
        if spec.name != r.name:
            self.add(Damage("/@name", f"is {r.name!r}, not the spec's name {spec.name!r}", repair="rewrite"))
        r.spec = spec

    # ---- the layout's groups and names
    def _layout(self):
        """The groups and names the layout has: a damaged link name shows as a member missing and a
        stray one."""
        from campaign.storage.layout import TASK_FIELDS

        f, r = self.f, self.report
        spec = r.spec
        every = self.finished_in(0, r.T)
        try:
            members = list(f.keys())
        except Exception as exc:  # noqa: BLE001
            self.add(Damage("/", f"its members cannot be listed ({reason(exc)})", rows=every, span=(0, r.T)))
            return
        for m in members:
            if m not in ROOT_MEMBERS:
                self.add(Damage(f"/{m}", "is not part of the layout (a damaged name?)", repair="remove",
                                note="left out"))
        required = {"tasks": every, "scalars": every, "histograms": every, "failures":
                    np.flatnonzero(r.status == FAILED) if r.status is not None else every}
        if spec is not None and spec.configurations:
            required["configurations"] = np.flatnonzero(r.status == DONE) if r.status is not None else every
        for g, rows in required.items():
            if g not in members:
                self.add(Damage(g, "is missing (its link in the root group is damaged?)", rows=rows.astype(np.int64)))
        checks = [("tasks", set(TASK_FIELDS), None)]
        if spec is not None:
            checks.append(("histograms", set(spec.histograms), every))
        for g, want, lost in checks:
            try:
                have = set(f[g].keys()) if g in members else set(want)
            except Exception as exc:  # noqa: BLE001
                self.add(Damage(g, f"its members cannot be listed ({reason(exc)})", rows=every, span=(0, r.T)))
                continue
            for m in sorted(have - want):
                self.add(Damage(f"{g}/{m}", "is not part of the layout (a damaged name?)", repair="remove",
                                note="left out"))
            if lost is not None:
                for m in sorted(want - have):
                    self.add(Damage(f"{g}/{m}", "is missing (a damaged name?)", rows=lost))
        if SUMS_GROUP in members:
            self._stray_sums(f)
        try:
            names = list(f["scalars"].keys()) if "scalars" in members else []
            listed = scalar_names_listed(f["scalars"]) if "scalars" in members else None
        except ValueError as exc:
            self.add(Damage("scalars", f"{exc}", repair="rewrite", note="the list is written anew"))
            listed = None
        except Exception:  # noqa: BLE001 - reported with the block datasets
            names, listed = [], None
        extra = [n for n in names if listed is not None and n not in listed]
        missing = sorted(listed - {n for n in names if isinstance(n, str)}) if listed is not None else []
        if missing:  # a listed dataset is gone: a damaged name (an unlisted extra one alone is a dataset
            # added by a version of the program that keeps no list)
            if len(extra) == 1 and len(missing) == 1:
                r.renames[extra[0]] = missing[0]
                self.add(Damage(f"scalars/{_text(extra[0])}", f"is {missing[0]!r} under a damaged name",
                                repair="rewrite", note=f"renamed back to {missing[0]!r}; nothing is lost"))
            else:
                self.add(Damage("scalars", f"lists {', '.join(map(repr, missing[:3]))}, which it does not hold (a "
                                           "damaged name)", rows=every))
            return
        for n in names:
            if not good_scalar_name(n):
                self.add(Damage(f"scalars/{_text(n)}", "has a name no scalar has (a damaged name: the scalar it was is "
                                                "missing)", rows=every, repair="drop", note="left out; every "
                                                "finished task is recomputed"))

    def _stray_sums(self, f):
        """Block checksums of no dataset of the store (a damaged name: its dataset's are then missing)."""
        try:
            want = {sums_name(f"tasks/{n}") for n in f["tasks"].keys()}
            want.update(sums_name(f"scalars/{n}") for n in f["scalars"].keys())
            for h in f["histograms"].keys():
                want.update(sums_name(f"histograms/{h}/{k}") for k in ("counts", "edges"))
            have = list(f[SUMS_GROUP].keys())
        except Exception:  # noqa: BLE001 - reported with the datasets
            return
        for m in have:
            if f"{SUMS_GROUP}/{m}" not in want:
                self.add(Damage(f"{SUMS_GROUP}/{_text(m) or m}", "are the checksums of no dataset of the store (a "
                                "damaged name?)", repair="remove", note="left out"))

    # ---- the commit marker
    def _status(self):
        import h5py

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
            from campaign.storage.layout import BLOCK_ROWS

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
        import h5py

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
        identity_blocks(self, col, lo, data)
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

    # ---- configurations and failure records
    def _rows_of(self, names):
        """Task rows of task ids ``names`` (-1 where none)."""
        if self.ids is None or not len(names):
            return np.full(len(names), -1, np.int64)
        if self.id_order is None:
            self.id_order = np.argsort(self.ids, kind="stable")
        keys = np.array([(n if isinstance(n, bytes) else n.encode("utf-8", "replace"))[:32] for n in names], "S32")
        pos = np.searchsorted(self.ids, keys, sorter=self.id_order)
        pos = np.minimum(pos, len(self.ids) - 1)
        rows = self.id_order[pos]
        return np.where(self.ids[rows] == keys, rows, -1).astype(np.int64)

    def _configurations(self, patterns=None):
        import h5py

        f, r = self.f, self.report
        try:
            if "configurations" not in f:
                names = []
            else:
                g = f["configurations"]
                names = list(g.keys())
        except Exception as exc:  # noqa: BLE001
            self.add(Damage("configurations", f"its index cannot be read ({reason(exc)}): no configuration can "
                                              "be trusted", rows=self.finished_in(0, r.T)))
            return
        if patterns is not None:
            names = [n for n in names if _matches(f"configurations/{n}", patterns)]
        rows = self._rows_of(names)
        N = self._column("tasks/N") if self.ids is not None else None
        for key, row in zip(names, rows.tolist()):
            tid = _text(key)
            name = f"configurations/{tid}"
            self.tick(CONFIG_WEIGHT, "configurations")
            if row < 0 and self.ids is not None:
                self.add(Damage(name, "is named after no task of this store (its name is damaged)", repair="remove",
                                note="left out"))
                continue
            held = (np.array([row], np.int64) if row >= 0 and (r.status is None or r.status[row] != PENDING)
                    else np.zeros(0, np.int64))
            try:
                c = g[key]
                if not isinstance(c, h5py.Group):
                    raise ValueError(f"not a group but {type(c).__name__}")
                has_sum = CHECKSUM_ATTR in c.attrs
            except Exception as exc:  # noqa: BLE001
                self.config_rows.add(row)  # damaged, not missing
                self.add(Damage(name, f"cannot be read ({reason(exc)})", rows=held))
                continue
            arrays, problem = configuration_problem(c)
            if problem is None:
                problem = _config_shape_problem(arrays, N[row] if N is not None and row >= 0 else None)
            if problem is not None:
                self.config_rows.add(row)  # damaged, not missing
                self.add(Damage(name, problem, rows=held))
                continue
            r.checked["configurations"] += 1
            if not has_sum:
                r.unchecked["configurations"] += 1
            self.config_rows.add(row)

    def _failures(self, patterns=None):
        import h5py

        f, r = self.f, self.report
        try:
            names = list(f["failures"].keys()) if "failures" in f else []
        except Exception as exc:  # noqa: BLE001
            self.add(Damage("failures", f"its index cannot be read ({reason(exc)})",
                            rows=np.flatnonzero(r.status == FAILED) if r.status is not None else np.zeros(0, np.int64)))
            return
        rows = self._rows_of(names)
        for key, row in zip(names, rows.tolist()):
            tid = _text(key)
            name = f"failures/{tid}"
            if not _matches(name, patterns):
                continue
            if row < 0:
                if self.ids is not None:
                    self.add(Damage(name, "is named after no task of this store (its name is damaged)",
                                    repair="remove", note="left out"))
                continue
            held = np.array([row], np.int64) if r.status is None or r.status[row] != PENDING else np.zeros(0, np.int64)
            self.failure_ids.add(row)
            try:
                obj = f["failures"][key]
                if not isinstance(obj, h5py.Group):
                    raise ValueError(f"not a group but {type(obj).__name__}")
                a = dict(obj.attrs)
            except Exception as exc:  # noqa: BLE001
                self.add(Damage(name, f"cannot be read ({reason(exc)})", rows=held))
                continue
            problem = failure_problem(a, self.summed)
            if problem is not None:
                self.add(Damage(name, problem, rows=held))
                continue
            if CHECKSUM_ATTR not in a:
                r.unchecked["failures"] += 1
            r.checked["failures"] += 1

    def _rows(self):
        """The commit marker against the rows it commits (it carries no checksum of its own)."""
        from campaign.storage.journal import task_indices

        r = self.report
        st = r.status
        if st is None or self.attempts is None:
            return
        lost = {d.span for d in r.damage if d.span is not None}
        unknown = np.zeros(r.T, bool)  # rows whose columns could not be read: reported already
        for lo, hi in lost:
            unknown[lo:hi] = True
        journal = np.zeros(r.T, bool)
        idx = [i for i in task_indices(str(self.path) + ".journal") if 0 <= i < r.T]
        journal[idx] = True
        failed_rec = np.zeros(r.T, bool)
        failed_rec[list(self.failure_ids)] = True
        problems = [
            (~np.isin(st, (PENDING, DONE, FAILED)), "is not 0, 1 or 2"),
            (np.isin(st, (DONE, FAILED)) & (self.attempts < 1), "says finished, but its row holds no finished task"),
            ((st == PENDING) & (self.attempts >= 1) & ~journal,
             "says pending, but its row holds a finished task and the journal has no record of it (a flipped "
             "byte, or a run killed between the two writes whose journal was lost since)"),
            ((st == DONE) & self.error_set, "says done, but its row holds a failure message"),
            ((st == DONE) & failed_rec, "says done, but the task has a failure record"),
            ((st == FAILED) & ~failed_rec & ~journal, "says failed, but the task has no failure record"),
        ]
        spec = r.spec
        if spec is not None and spec.configurations:
            have = np.zeros(r.T, bool)
            have[[i for i in self.config_rows if i >= 0]] = True
            problems.append(((st == DONE) & ~have & ~journal,
                             "says done, but the configuration the spec keeps is missing"))
        flagged = np.zeros(r.T, bool)
        for mask, _ in problems:
            flagged |= mask & ~unknown
        for a, b in self.status_bad:  # a status block that differs from its checksum, with no row found wrong
            if not flagged[a:b].any():
                self.add(Damage("tasks/status", f"rows {a}-{b - 1} {BLOCK_MISMATCH}", rows=self.finished_in(a, b),
                                span=(a, b)))
        for mask, how in problems:
            rows = np.flatnonzero(mask & ~unknown).astype(np.int64)
            if len(rows):
                values = sorted({int(v) for v in st[rows[:50]]})
                self.add(Damage("tasks/status", f"{how} at {len(rows)} row(s) (value(s) {values}): the commit "
                                                "marker or its row is damaged", rows=rows))

    def _reduced(self):
        import h5py

        f = self.f
        try:
            if "reduced" not in f:
                return
            items = []
            f["reduced"].visititems(lambda n, o: items.append(n) if isinstance(o, h5py.Dataset) else None)
            for n in items:
                f[f"reduced/{n}"][()]
        except Exception as exc:  # noqa: BLE001
            self.add(Damage("reduced", f"cannot be read ({reason(exc)})", repair="remove",
                            note="left out (derived from the rows: `campaign reduce --in-place` writes it again)"))

    def _walk(self):
        """Every object of the file, as HDF5 walks them (its heaps and indices): damage there reads
        fine name by name but breaks the walk, and a write into a damaged heap could spread it."""
        try:
            self.f.visit(lambda name: None)
        except Exception as exc:  # noqa: BLE001
            self.add(Damage("/", f"walking its objects fails ({reason(exc)}): a heap or index of HDF5's is "
                                 "damaged", repair="rewrite", note="written anew; no task is lost by it"))

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


def _config_shape_problem(a, n):
    pos, rad, box, sp = (np.asarray(a.get(k)) if k in a else None for k in CONFIG_KEYS)
    if pos is None or rad is None or box is None:
        return "lacks positions, radii or box"
    m = rad.shape[0] if rad.ndim == 1 else -1
    if pos.shape != (m, 2) or box.shape not in ((2,), (3,)) or (sp is not None and sp.shape != (m,)):
        return f"has arrays of inconsistent shapes (positions {pos.shape}, radii {rad.shape}, box {box.shape})"
    if n is not None and m != int(n):
        return f"holds {m} disks, but its task has N = {int(n)}"
    return None


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


def scan(path, progress=None) -> Report:
    """Read every part of the store ``path`` (``campaign verify``). Raises UserError for a file that
    is not a campaign store (missing, a directory, not HDF5 and no journal, another schema or store
    format); a store that cannot be opened at all comes back with ``fatal`` set."""
    import h5py

    path = str(path)
    if not os.path.exists(path):
        raise UserError(f"{path}: no such file (expected a campaign store)")
    if os.path.isdir(path):
        raise UserError(f"{path}: is a directory (expected a campaign store)")
    try:
        f = h5py.File(path, "r", locking=False)
    except Exception as exc:  # noqa: BLE001
        if looks_like_store(path):
            r = Report(path)
            r.fatal = (f"it cannot be opened as HDF5 ({reason(exc)}): its superblock or root group is damaged, or "
                       "the file was cut short")
            return r
        raise UserError(f"{path}: not a readable HDF5 file ({reason(exc)}); expected a campaign store") from None
    with f:
        s = Scan(f, path, progress=progress)
        try:
            s.run()
        except UserError:
            raise
        except Exception as exc:  # noqa: BLE001 - a structure so damaged that the walk itself fails
            s.report.fatal = f"walking it failed ({reason(exc)})"
        return s.report
