"""The error a reader raises when it cannot read a campaign store: ``read_failure`` names the
damaged part (searching the datasets the reader was after with ``campaign verify``'s scan,
``locate``), or says that a run writing the file was caught in the middle of a flush."""

from __future__ import annotations

from campaign.errors import StoreDamaged, UserError
from campaign.storage.checksums import READ_ERRORS, damaged_message, is_filter_failure, reason, run_is_writing


def read_failure(path, exc, f=None, patterns=("tasks", "scalars"), what="the store"):
    """The error a reader raises when reading ``what`` of the store ``path`` failed with ``exc``
    (``f``: its open h5py file, if any), or None when ``exc`` is not about reading the file (a bug:
    let its traceback show).

    The datasets ``patterns`` name (fnmatch patterns of dataset or group names: ``"tasks"``,
    ``"scalars/*"``, ``"histograms/z_v/counts"``, ``"configurations/<id>"``) are read again, chunk
    by chunk: damage found there is named (StoreDamaged). Otherwise a checksum or filter failure
    is still damage; any other failure is a read caught in the middle of a flush when a run
    writes the file ("try again"), and damage when none does."""
    if isinstance(exc, UserError):
        return exc
    found = None
    try:
        found = locate(path, f, patterns)
    except Exception:  # noqa: BLE001 - the search is a courtesy; the failure itself is reported below
        found = None
    if found is not None:
        return StoreDamaged(damaged_message(path, found.name, found.how, found.held_text()))
    if not isinstance(exc, READ_ERRORS) and not is_filter_failure(exc):
        return None  # not the file's: a bug, with its traceback
    writing = run_is_writing(path)
    if writing and not is_filter_failure(exc):
        return UserError(f"{path}: could not read {what} ({reason(exc)}); a run is writing the file: try again "
                         "in a moment")
    if writing:
        return UserError(f"{path}: reading {what} failed a checksum or filter ({reason(exc)}), but reading it "
                         "again worked: a run is writing the file and the read met a chunk being rewritten; "
                         "try again in a moment")
    how = (f"failed a checksum or filter while reading {what} ({reason(exc)})" if is_filter_failure(exc)
           else f"could not be read ({reason(exc)}) while reading {what}, and no run is writing it")
    return StoreDamaged(damaged_message(path, "the file", how))


def locate(path, f=None, patterns=("tasks", "scalars")):
    """The first damage among the datasets ``patterns`` name (see ``read_failure``), or None."""
    import h5py

    own = None
    if f is None or not f.id.valid:
        own = f = h5py.File(path, "r", locking=False)
    try:
        from campaign.storage.integrity import Scan, _Found

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
    finally:
        if own is not None:
            own.close()
