"""Reading a campaign store from outside its run (``campaign status``, ``validate``, ``slurm``,
``draw``): open it read-only and checked (``open_store``), retry a read caught in the middle of a
run's flush (``read_retrying``), the task table's columns (``read_summary``). The reducer has its own
reader, ``campaign.results.finished``.
"""

from __future__ import annotations

import time

from campaign.errors import StoreDamaged, UserError
from campaign.storage.layout import TASK_FIELDS, check_format

def open_store(path):
    """Open a campaign store read-only (``locking=False``: fine while a run writes it).

    Raises UserError (exit 2) for a missing file, a file that is not HDF5, or a store
    of another schema or format version (see ``format_problem``).
    """
    import h5py

    from campaign.storage.checksums import open_checked

    try:
        f = open_checked(path)
    except FileNotFoundError:
        raise UserError(f"no such file: {str(path)!r}") from None
    except OSError as exc:
        from campaign.storage.checksums import open_failure

        raise open_failure(path, exc, f"{str(path)!r} is not a readable HDF5 file ({exc})") from None
    try:
        check_format({k: f.attrs[k] for k in f.attrs}, path)
    except UserError:
        f.close()
        raise
    except Exception as exc:  # noqa: BLE001 - its root attributes cannot be read
        f.close()
        from campaign.storage.readerror import read_failure

        err = read_failure(path, exc, None, (), what="its root attributes")
        if err is None:
            raise
        raise err from None
    except BaseException:
        f.close()
        raise
    return f


def read_retrying(path, read, patterns=("tasks", "failures")):
    """``read(f)`` on the store opened read-only, retried a few times while a run writes it (the
    read may catch the file in the middle of a flush); a failure that is the file's becomes the
    readers' error (``campaign.storage.readerror.read_failure``: damaged, naming ``patterns``' datasets)."""
    last = None
    for _ in range(5):
        try:
            with open_store(path) as f:
                return read(f)
        except UserError:
            raise
        except Exception as exc:  # noqa: BLE001 - read_failure says which failures are the file's
            from campaign.storage.checksums import run_is_writing
            from campaign.storage.readerror import read_failure

            err = read_failure(path, exc, None, list(patterns))
            if err is None:
                raise
            last = err
            if not run_is_writing(path) or isinstance(err, StoreDamaged):
                break
            time.sleep(0.2)
    raise last


def read_summary(path, fields=TASK_FIELDS):
    """The task table's columns ``fields`` (all rows), the root attributes and the failure
    records, read-only. Retries a few times if it catches the file in the middle of a flush.
    Memory grows with the tasks (the error column alone is 512 bytes a task): ``campaign
    status`` reads the table in blocks instead; ask for the columns you need.
    """
    def read(f):
        out = {k: f[f"tasks/{k}"][:] for k in fields}
        out["attrs"] = {k: f.attrs[k] for k in f.attrs}
        out["failures"] = {}
        if "failures" in f:
            for tid in f["failures"]:
                out["failures"][tid] = dict(f[f"failures/{tid}"].attrs)
        return out

    return read_retrying(path, read)
