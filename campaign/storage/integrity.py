"""``campaign verify``'s scan: every part of a campaign store read and checked (``scan``), what it
finds recorded in a ``Report`` (``campaign.storage.damage``: what is damaged, which rows a repair
drops; ``campaign.storage.repair`` rebuilds the store from it, so that ``campaign run`` of
the same spec recomputes exactly those rows); and the readers' search for the first damage among
the datasets a failed read was after (``first_damage``, for ``campaign.storage.reader.read_failure``).

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
the store uses; the scan checks what can be checked of it: the filter pipelines, each chunk's
filter mask and lookup (``campaign.storage.blockscan``, the reading of the block datasets), the
names against the layout and the spec, and a walk of the file. In a store written before the block
checksums it also checks each finished task the journal still holds against its row.

A store written without checksums (before they were added, or with ``CAMPAIGN_NO_CHECKSUMS=1``,
the benchmarks' and tests' switch) reads as before; ``scan`` counts what carries none.
"""

from __future__ import annotations

import json
import os
import time

import h5py
import numpy as np

from campaign.errors import UserError
from campaign.storage.blockscan import BlockScan, _Found, _matches, identities
from campaign.storage.checksums import (BLOCK_MISMATCH, CHECKSUM_ATTR, CONFIG_KEYS, CONFIG_WEIGHT, ROOT_ATTRS,
                                        ROOT_MEMBERS, SUMS_GROUP, _text, checkpoint_damage, configuration_problem,
                                        failure_problem, good_scalar_name, looks_like_store, reason,
                                        scalar_names_listed, sums_name)
from campaign.storage.damage import Damage, Report
from campaign.storage.journal import header_spec_hash, scan_journal, task_indices
from campaign.storage.layout import (DONE, FAILED, FORMAT_VERSION, PENDING, SCHEMA, TASK_FIELDS, format_problem,
                                     row_values, stored_spec)


class Scan(BlockScan):
    """One reading of a whole store (``BlockScan``: what it records, and its reading of the block
    datasets): the root attributes and the spec, the layout's names, the configurations, failure
    records and suspended packings, the commit marker against its rows, the journal's records
    against theirs, ``/reduced``, and a walk of every object."""

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
            self.expected = self._expected_identities()
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
            self._journal_rows()
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
            has_tasks = isinstance(f.get("tasks/status"), h5py.Dataset)
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

    # ---- the commit marker against its rows
    def _rows(self):
        """The commit marker against the rows it commits (it carries no checksum of its own)."""
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

    # ---- a store without block checksums (0.2.7 and older): the journal's records against their rows
    def _journal_rows(self):
        """Every finished task the journal has a record of (a run killed before its checkpoint) against the
        row the store holds for it, where both say done. A row that differs was read from another place, or
        changed since it was written: a repair drops it, and the next run replays the record."""
        r = self.report
        if self.summed:  # the block checksums say it all
            return
        try:
            with open(str(self.path) + ".journal", "rb") as fh:
                records, _, _ = scan_journal(fh.read())
        except OSError:
            return
        head = records[0][0] if records else {}
        if r.spec is None or r.status is None or head.get("type") != "header" or head.get("spec_hash") != r.spec.hash:
            return
        last = {int(m["index"]): (m, a) for m, a in records[1:] if m.get("type") == "task" and "index" in m}
        rows = sorted(i for i, (m, _) in last.items() if 0 <= i < r.T and r.status[i] == DONE
                      and int(m.get("status", -1)) == DONE)
        if not rows:
            return
        try:
            names = ["tasks/attempts"] + [f"scalars/{n}" for n in self.f["scalars"].keys() if good_scalar_name(n)]
        except Exception:  # noqa: BLE001 - reported with the block datasets
            return
        names += [f"histograms/{h}/counts" for h in r.edges]
        B = max(1, r.B)
        lost = {d.span for d in r.damage if d.span is not None}
        for name in names:
            bad = []
            for block in sorted({i // B for i in rows}):
                a, b = block * B, min(block * B + B, r.T)
                if any(lo < b and a < hi for lo, hi in lost):
                    continue  # its rows are dropped already
                try:
                    data = self.f[name][a:b]
                except Exception:  # noqa: BLE001 - reported with the block datasets
                    continue
                for i in (i for i in rows if a <= i < b):
                    want = row_values(*last[i], r.edges, [name])[name]
                    got = data[i - a]
                    same = (np.array_equal(got, want) if name.startswith("histograms/") else
                            got == want or (name.startswith("scalars/") and np.isnan(got) and np.isnan(want)))
                    if not same:
                        bad.append(i)
            if bad:
                self.add(Damage(name, f"differs from the journal's record of the task at {len(bad)} row(s): read from "
                                      "another place, or changed since it was written", rows=np.asarray(bad, np.int64),
                                note="dropped; the next run replays the journal's record"))


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


def scan(path, progress=None) -> Report:
    """Read every part of the store ``path`` (``campaign verify``). Raises UserError for a file that
    is not a campaign store (missing, a directory, not HDF5 and no journal, another schema or store
    format); a store that cannot be opened at all comes back with ``fatal`` set."""
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


def first_damage(f, path, patterns):
    """The first damage among the datasets ``patterns`` name in the open store ``f`` at ``path``, its
    first tasks named, or None: a reader's search after a failed read
    (``campaign.storage.reader.read_failure``)."""
    s = Scan(f, str(path), stop_first=True)
    try:
        s.run(patterns=patterns)
    except _Found:
        pass
    if not s.report.damage:
        return None
    d = s.report.damage[0]
    d.labels = s._labels(d.rows[:5])
    return d
