"""``campaign verify --repair``: the store rebuilt without what a scan found damaged
(``campaign.storage.integrity.scan``, its ``Report``: ``campaign.storage.damage``), under the
lock a run holds, so that ``campaign run`` of the same spec recomputes exactly the rows dropped
(docs/STORE.md, "Checksums, verify and repair"). The copying of the rows kept is
``campaign.storage.salvage``'s, which a run's start uses too.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from pathlib import Path

import numpy as np

from campaign.errors import UserError
from campaign.plan.spec import histogram_edges
from campaign.plan.tasks import expand
from campaign.storage.damage import Report
from campaign.storage.layout import status_counts
from campaign.storage.salvage import salvage


@contextlib.contextmanager
def run_lock(path):
    """Hold the lock a run holds (an exclusive ``flock`` on ``<path>.journal``, created if missing):
    no run can start meanwhile; UserError if one is writing."""
    jpath = Path(str(path) + ".journal")
    created = not jpath.exists()
    try:
        fd = os.open(jpath, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise UserError(f"cannot open {str(jpath)!r} (the journal of {str(path)!r}) to lock it: "
                        f"{exc.strerror}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise UserError(f"another run is writing {str(path)!r} (its journal {str(jpath)!r} is locked); "
                                "wait for it to finish or stop it first") from None
            # a file system without flock: carry on, unprotected (as a run does)
        yield
    finally:
        os.close(fd)
        if created:
            try:
                if jpath.stat().st_size == 0:
                    jpath.unlink()
            except OSError:
                pass


def repair(report: Report) -> dict:
    """Rebuild the store of ``report`` (a ``scan`` that found damage) without what cannot be trusted.

    Every readable, sound row is copied into a new file (created beside it, renamed into place
    when complete, the space reserved first: a full disk leaves the store as it was): the rows
    of damaged parts are dropped (their tasks pending, so that ``campaign run`` of the same spec
    recomputes them), the task identities and the bin edges are written from the spec, and
    whatever is not a task's (damaged provenance, stray groups, ``/reduced``) is left out.
    Returns ``{"pending_again", "rows_before", "rows_after"}``. Raises UserError when it cannot be
    done (the file cannot be opened, its spec attributes are damaged, a run is writing it)."""
    if report.fatal is not None:
        raise UserError(f"{report.path}: cannot be repaired: {report.fatal}")
    bad = report.unrepairable()
    if bad:
        raise UserError(f"{report.path}: cannot be repaired: {bad[0].name} {bad[0].how}")
    spec = report.spec
    tasks = expand(spec)
    edges = dict(report.edges)
    missing = [h for h in spec.histograms if h not in edges]
    if missing:
        edges.update(histogram_edges(missing, {h: list(e) for h, e in spec.bins}))
    edges = {h: np.asarray(edges[h], np.float64) for h in sorted(spec.histograms)}
    B = report.B or 1
    drop = set(report.drop_rows().tolist())
    before = report.counts
    with run_lock(report.path):
        state = salvage(report.path, spec, tasks, edges, B, drop=drop, renames=report.renames, checked=True)
    after = status_counts(state.status)
    return {"pending_again": before["done"] + before["failed"] - after["done"] - after["failed"],
            "rows_before": before, "rows_after": after}
