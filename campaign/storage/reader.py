"""Reading a campaign store from outside its run: the one way every reader opens it (``open_store``:
read-only, its blocks checked against their checksums, its format checked), a read retried while a
run's flush is caught in the middle (``read_retrying``), the task table's columns
(``read_summary``), and the error a reader raises when a read fails (``read_failure``: the damage
named, found with ``campaign verify``'s scan, ``locate``; "try again" only while a run writes the
file and reading again worked).

The commands (``status``, ``validate``, ``slurm``, ``draw``), the reducer
(``campaign.results.finished``), the frames and exports (``campaign.report.frames``) and the reading
of a configuration from an HDF5 file (``campaign.storage.configio``) all open through here.
``campaign verify``'s own scan (``campaign.storage.integrity``) opens the file plainly: it checks
everything itself.
"""

from __future__ import annotations

import os
import time

import h5py

from campaign.errors import StoreDamaged, UserError
from campaign.storage.checksums import (READ_ERRORS, damaged_message, is_filter_failure, looks_like_store,
                                        open_checked, reason, DOCS)
from campaign.storage.integrity import first_damage
from campaign.storage.layout import TASK_FIELDS, check_format
from campaign.storage.progress import read_sidecar, writer_state

#: What ``open_store`` accepts: a campaign store of this format; also a file of the store's layout that
#: does not say which (no ``schema`` attribute: written by another program, docs/CONTRACTS.md); any
#: HDF5 file (a configuration group of any program's file).
ACCEPT = ("store", "layout", "hdf5")


def open_store(path, *, accept="store"):
    """Open ``path`` read-only (``locking=False``: fine while a run writes it) as a reader does:
    every block of rows read from its per-task datasets is checked against its block checksums
    (``campaign.storage.checksums.open_checked``).

    UserError (exit 2) for a missing file, a directory, a file that is not HDF5 (StoreDamaged when it
    looks like one: ``open_failure``) and, by ``accept`` (``ACCEPT``), a file of another schema or store
    format (``campaign.storage.layout.ForeignStore``: ``"store"`` always checks it, ``"layout"`` when
    the file has a ``schema`` attribute, ``"hdf5"`` never)."""
    if accept not in ACCEPT:
        raise ValueError(f"accept: expected one of {ACCEPT}, got {accept!r}")
    path = os.fspath(path)
    if not os.path.exists(path):
        raise UserError(f"{path}: no such file (expected a campaign store)")
    if os.path.isdir(path):
        raise UserError(f"{path}: is a directory (expected a campaign store)")
    try:
        f = open_checked(path)
    except OSError as exc:
        raise open_failure(path, exc, f"{path}: not a readable HDF5 file ({exc})") from None
    try:
        if accept == "store" or (accept == "layout" and "schema" in f.attrs):
            check_format({k: f.attrs[k] for k in f.attrs}, path)
    except UserError:
        f.close()
        raise
    except Exception as exc:  # noqa: BLE001 - its root attributes cannot be read
        f.close()
        err = read_failure(path, exc, None, (), what="its root attributes")
        if err is None:
            raise
        raise err from None
    except BaseException:
        f.close()
        raise
    return f


def read_retrying(path, read, patterns=("tasks", "failures"), tries=10, wait=0.3):
    """``read(f)`` on the store opened read-only (``open_store``), retried while a run writes it: the
    read may catch the file in the middle of a flush, between a block of rows and its checksum, so
    that even damage found then (StoreDamaged) is read again, ``tries`` times ``wait`` seconds apart,
    before it is believed. A failure that is the file's becomes the readers' error (``read_failure``:
    damaged, naming ``patterns``' datasets); with no run writing, the first one is final."""
    last = None
    for k in range(tries):
        if k:
            time.sleep(wait)
        try:
            with open_store(path) as f:
                return read(f)
        except StoreDamaged as exc:
            last = exc
        except UserError:
            raise
        except Exception as exc:  # noqa: BLE001 - read_failure says which failures are the file's
            err = read_failure(path, exc, None, list(patterns))
            if err is None:
                raise
            last = err
        if not run_is_writing(path):
            break
    raise last


def read_summary(path, fields=TASK_FIELDS, configurations=False):
    """The task table's columns ``fields`` (all rows), the root attributes and the failure records
    (with ``configurations``, also the ids of the tasks whose configuration the store keeps), read-only.
    Retries a few times if it catches the file in the middle of a flush. Memory grows with the tasks
    (the error column alone is 512 bytes a task): ``campaign status`` reads the table in blocks
    instead; ask for the columns you need."""
    def read(f):
        out = {k: f[f"tasks/{k}"][:] for k in fields}
        out["attrs"] = {k: f.attrs[k] for k in f.attrs}
        out["failures"] = {}
        if "failures" in f:
            for tid in f["failures"]:
                out["failures"][tid] = dict(f[f"failures/{tid}"].attrs)
        if configurations:
            out["configurations"] = set(f["configurations"].keys()) if "configurations" in f else set()
        return out

    return read_retrying(path, read, ("tasks", "failures") + (("configurations",) if configurations else ()))


def run_is_writing(path) -> bool:
    """Whether a live run writes the store (its progress file, judged as ``campaign status`` does)."""
    try:
        return writer_state(read_sidecar(path))["state"] == "running"
    except Exception:  # noqa: BLE001 - no progress file, or an unreadable one: no run known
        return False


def open_failure(path, exc, otherwise: str) -> UserError:
    """The error for a file h5py cannot open: damaged when it looks like an HDF5 file (or has a
    campaign journal), else ``otherwise`` (not an HDF5 file)."""
    if looks_like_store(path):
        return StoreDamaged(
            f"{path} is damaged: it cannot be opened as HDF5 ({reason(exc)}), though it is an HDF5 file (or has "
            f"a campaign journal beside it): its superblock or root group is damaged, or the file was cut short. "
            f"`campaign verify {path}` says what can be recovered ({DOCS})")
    return UserError(otherwise)


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
    own = None
    if f is None or not f.id.valid:
        own = f = h5py.File(path, "r", locking=False)
    try:
        return first_damage(f, path, patterns)
    finally:
        if own is not None:
            own.close()
