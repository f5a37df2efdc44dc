"""Errors the command line reports without a traceback.

* ``UserError``: exit status 2, a mistake in what the user gave (spec, file, option).
  ``StoreDamaged`` (a UserError): a store whose bytes no longer match their checksums.
* ``WriteFault``: exit status 3, a file the command writes could not be written any more
  (``OutOfSpace``: a full disk or quota; else a file system gone read-only or failing).
  ``campaign run`` stops with everything it finished kept (the store and its journal
  agree) and a rerun resumes once the cause is fixed (docs/STORE.md, "Out of space").
"""

import errno as _errno
import os

#: errno values that mean "no room": a full file system, an exhausted quota.
SPACE_ERRNOS = frozenset({_errno.ENOSPC, _errno.EDQUOT})


class UserError(Exception):
    """A mistake in what the user gave us (spec, file, option).

    The message is shown as-is, so it must name what was expected, what came,
    and where (file, line, key path) when that is known.
    """


class StoreDamaged(UserError):
    """A campaign store is damaged: a checksum or an HDF5 filter failed, or the file's structure
    cannot be read where a run is not writing it. Exit status 2; the message names the damaged
    part and points at ``campaign verify`` (docs/STORE.md, "Checksums, verify and repair")."""


class MissingExtra(UserError, ImportError):
    """An optional dependency is not installed. A user error on the command line (exit 2),
    and an ImportError for Python callers."""


def require(module: str, extra: str, what: str):
    """Import and return ``module``, or raise MissingExtra naming the extra that brings it:
    ``require("pandas", "frames", "campaign.read_packings")``."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtra(f"{what} needs the {module} package, which is not installed: "
                           f"pip install 'jamming-campaign[{extra}]'") from None

class WriteFault(Exception):
    """Writing ``path`` failed with ``errno`` while ``what`` (exit status 3).

    ``needed``: bytes the failed step wanted (when known); ``free``: bytes the file system
    had free (when known); ``damaged``: the write failed inside HDF5 (past every reservation),
    so the store may need the salvage the next start does. ``message``, when set, is the whole
    paragraph the command line prints (``campaign run`` adds what was kept and how to resume).
    """

    exit_code = 3

    def __init__(self, path, err, what, *, needed=None, free=None):
        self.path, self.errno, self.what = str(path), int(err), what
        self.needed, self.free = needed, free
        self.damaged = False
        self.message = None
        super().__init__(f"{what}: {self.path}: {os.strerror(self.errno)}")

    @property
    def out_of_space(self) -> bool:
        return self.errno in SPACE_ERRNOS

    def __str__(self):
        return self.message or super().__str__()


class OutOfSpace(WriteFault):
    """A write failed (or would fail) for want of space: ENOSPC or EDQUOT."""
