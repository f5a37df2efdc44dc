"""A damaged store's readable rows salvaged into a new file: the store's start when it cannot read
its file (the journal is replayed on top), and ``campaign verify --repair``
(``campaign.storage.repair``, which says what to drop) (docs/STORE.md, "Kill and resume" and
"Checksums, verify and repair").

The new file is made by ``campaign.storage.layout.create_file`` (under a temporary name, the
space reserved first, renamed into place when complete): a full disk leaves the damaged store as
it was. Calls go one way: ``campaign.storage.store`` and ``campaign.storage.repair`` -> here ->
``campaign.storage.layout`` (the layout) and ``campaign.storage.checksums``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np

from campaign.storage.checksums import (PROTECTION_ATTR, ROUNDS_GROUP, SUMS_GROUP, SUMS_ROWS, check_rows,
                                        checkpoint_problem, read_rounds, write_round,
                                        checksums_on, configuration_problem, create_fill_sums, failure_problem,
                                        good_scalar_name, has_sums, protection_text, sums_name, write_checkpoint,
                                        write_configuration, write_failure, write_scalar_names, write_sums)
from campaign.storage.layout import (DONE, FAILED, PENDING, ROW_FIELDS, State, create_file, dataset_kwargs,
                                    fill_value)


def salvage(path, spec, tasks, edges, B, *, drop=(), renames=None, checked=False) -> State:
    """Rebuild the damaged store at ``path`` as a fresh one holding every committed row that can
    still be read from it, copied block by block; returns the new store's ``State`` (the kept rows'
    values, every other task pending). Lost (their tasks pending again): a block that
    cannot be read, a row in ``drop``, a row whose commit marker contradicts it, and one whose
    configuration or failure record cannot be read or fails its checksum (or, failed, has none); a block that differs
    from its block checksums too, unless ``checked`` (``campaign verify --repair``: its scan found
    those, and ``drop`` holds their rows). ``renames`` maps scalar datasets found under a damaged
    name to their name.

    The space it needs (the new layout and the damaged file's size) is reserved first; a full disk
    (OutOfSpace) or any other fault removes the temporary file and leaves ``path`` as it was."""
    path = Path(path)
    try:
        extra = os.stat(path).st_size
    except OSError:
        extra = 0
    state = State.fresh(len(tasks))
    create_file(path, spec, tasks, edges, B, extra=extra, what="salvaging the damaged store into a new file",
                fill=lambda f: _salvage_into(f, path, tasks, edges, B, state, drop, renames or {}, checked))
    return state


def _salvage_into(f, old_path, tasks, edges, B, state, drop=(), renames=None, checked=False):
    """Copy every readable committed row of the damaged store ``old_path`` into ``f``, and their
    values into the new store's ``state`` (every task pending in it to begin with).

    Dropped (pending again, every column at its fill value): the rows of a block that cannot be
    read, the rows in ``drop``, a row whose status is not 0, 1 or 2 or says finished where its
    row holds no finished task (``attempts`` 0), and a finished row whose configuration or failure
    record cannot be read or fails its checksum, and a failed row without its failure record. Root
    attributes that read are carried over."""
    T = len(tasks)
    drop = set(int(i) for i in drop)
    try:
        old = h5py.File(old_path, "r", locking=False)
    except (OSError, ValueError, RuntimeError):
        return
    with old:
        if checksums_on() and _unprotected(old):  # a store without block checksums, now with them
            f.attrs[PROTECTION_ATTR] = protection_text(upgraded=True)
        try:
            for key in old.attrs.keys():
                if key in f.attrs:
                    continue
                try:
                    value = old.attrs[key]
                    if key in ("runs", "hosts", "versions"):
                        json.loads(value)
                    f.attrs[key] = value
                except (OSError, KeyError, ValueError, RuntimeError, TypeError):
                    continue  # a damaged provenance attribute: left out (the next run writes it again)
        except (OSError, KeyError, ValueError, RuntimeError):
            pass
        renames = renames or {}
        try:  # old name -> name (a damaged name is renamed back when known, else left out)
            scalar_names = {n: renames.get(n, n) for n in old["scalars"].keys()
                            if n in renames or good_scalar_name(n)}
        except (OSError, KeyError, ValueError, RuntimeError):
            scalar_names = {}
        fills = {f"tasks/{n}": fill_value(n) for n in ROW_FIELDS}
        fills.update({f"scalars/{n}": np.nan for n in scalar_names.values()})
        fills.update({f"histograms/{h}/counts": 0 for h in edges})
        for lo in range(0, T, B):
            hi = min(lo + B, T)
            try:
                st = np.array(old["tasks/status"][lo:hi])
                if not checked:
                    _check_old(old, "tasks/status", lo, st, B)
                rows = np.flatnonzero(st != PENDING)
                if not len(rows):
                    continue
                data = {f"tasks/{n}": old[f"tasks/{n}"][lo:hi] for n in ROW_FIELDS}
                for n, new in scalar_names.items():
                    data[f"scalars/{new}"] = old["scalars"][n][lo:hi]
                for h in edges:
                    data[f"histograms/{h}/counts"] = old[f"histograms/{h}/counts"][lo:hi]
                for name, a in data.items():  # a block read from the wrong place is lost like a damaged one
                    if not checked:
                        _check_old(old, name, lo, a, B)
            except (OSError, KeyError, ValueError, RuntimeError, TypeError, MemoryError):
                continue  # this block is lost: its tasks are pending again
            bad = {int(r) for r in rows if lo + int(r) in drop or st[r] not in (DONE, FAILED)
                   or data["tasks/attempts"][r] < 1}
            bad.update(int(r) for r in np.flatnonzero(st == PENDING))  # nothing of a pending row is kept
            extra = {}
            for r in rows:
                if int(r) in bad:
                    continue
                tid = tasks[lo + r].id
                try:
                    if "configurations" in old and tid in old["configurations"]:
                        conf, problem = configuration_problem(old[f"configurations/{tid}"])
                        if problem is not None:
                            raise ValueError(problem)
                        extra[("c", tid)] = conf
                    if st[r] == FAILED:  # its record gone (a torn index of the group): pending again
                        rec = dict(old[f"failures/{tid}"].attrs)
                        problem = failure_problem(rec, has_sums(old))
                        if problem is not None:
                            raise ValueError(problem)
                        extra[("f", tid)] = rec
                except (OSError, KeyError, ValueError, RuntimeError, TypeError):
                    bad.add(int(r))  # this task is pending again
                    extra.pop(("c", tid), None)
            for r in bad:
                st[r] = PENDING
                extra.pop(("c", tasks[lo + r].id), None)
                extra.pop(("f", tasks[lo + r].id), None)
                for name, a in data.items():
                    a[r] = fills[name]
            for name, a in data.items():
                if name.startswith("scalars/") and name not in f:
                    f["scalars"].create_dataset(name[8:], dtype=np.float64, **dataset_kwargs(B, (T,), np.nan))
                    create_fill_sums(f, name, T, B, (), np.float64, np.nan)
                    write_scalar_names(f["scalars"], f["scalars"].keys())
                f[name][lo:hi] = a
                write_sums(f.get(sums_name(name)), lo, a, B)
            for (kind, tid), v in extra.items():
                if kind == "c":
                    write_configuration(f.require_group("configurations"), tid, v)
                else:
                    write_failure(f["failures"], tid, v)
            f["tasks/status"][lo:hi] = st
            write_sums(f.get(sums_name("tasks/status")), lo, st, B)
            state.status[lo:hi] = st
            state.attempts[lo:hi] = data["tasks/attempts"]
            state.wall[lo:hi] = data["tasks/wall"]
        _carry_checkpoints(f, old, tasks, state.status)
        _carry_rounds(f, old)


def _carry_rounds(f, old):
    """A precision campaign's round decisions that read and match their checksum (the others are
    made again from the packings by the next run)."""
    got, _ = read_rounds(old)
    if got:
        g = f.require_group(ROUNDS_GROUP)
        for k, record in sorted(got.items()):
            write_round(g, k, json.dumps(record, sort_keys=True, separators=(",", ":"), allow_nan=False))


def _carry_checkpoints(f, old, tasks, status):
    """The suspended packings (``/checkpoints``) of tasks still pending that read and match their
    checksum; the others' tasks start over."""
    try:
        names = list(old["checkpoints"].keys()) if "checkpoints" in old else []
    except (OSError, KeyError, ValueError, RuntimeError):
        return
    if not names:
        return
    row = {t.id: t.index for t in tasks}
    for tid in names:
        i = row.get(tid if isinstance(tid, str) else str(tid))
        if i is None or status[i] != PENDING:
            continue
        try:
            g = old[f"checkpoints/{tid}"]
        except (OSError, KeyError, ValueError, RuntimeError):
            continue
        arrays, counters, problem = checkpoint_problem(g)
        if problem is None:
            write_checkpoint(f.require_group("checkpoints"), tid, arrays, counters)



def _unprotected(old) -> bool:
    """Whether the store ``old`` was written without block checksums (0.2.7 and older): its root
    attributes read, and neither they nor its groups say it has them (a store too damaged to tell is
    not taken for one)."""
    try:
        return old.attrs.get("schema") is not None and PROTECTION_ATTR not in old.attrs and SUMS_GROUP not in old
    except Exception:  # noqa: BLE001 - unreadable attributes
        return False


def _check_old(old, name, lo, data, B):
    """Raise BlockMismatch when rows of the damaged store ``old`` being salvaged differ from their block
    checksums (a store without them, or without those of ``name``, is taken as it reads)."""
    if not has_sums(old):
        return
    ds = old.get(sums_name(name))
    if ds is None or int(ds.attrs.get(SUMS_ROWS, -1)) != B:
        return
    check_rows(ds, name, lo, data, B)
