"""Faults of the write path: a full disk or quota, an output that cannot be written.

* ``write_fault(exc, path, what)``: the ``WriteFault`` (``OutOfSpace`` for ENOSPC and
  EDQUOT) that an operating-system error while writing ``path`` amounts to, from an
  ``OSError`` or from the text of an HDF5 error (``... errno = 28 ...``); None for
  anything else (a bug stays a bug).
* ``reserve(fd, nbytes, path, what)``: make sure that the next ``nbytes`` appended to a
  file cannot fail for want of space, before anything is written: ``fallocate`` with
  ``FALLOC_FL_KEEP_SIZE`` past the file's end (a real reservation, charged to quotas,
  invisible in the file's size), or, on a file system that cannot (NFS, some parallel file
  systems), a look at its free space. Raises ``OutOfSpace``. ``release(fd, n)`` hands back
  what the write did not use.
* ``GuardedFile``: the file object the store's HDF5 writes go through (h5py's ``fileobj``
  driver): a refused write is recorded and goes, with every later one, to memory, so that
  HDF5 never sees a failure it does not survive; it keeps what failed through it (``failed``, and
  ``poisoned``: a write step failed, nothing may be written through it any more).
* ``neutralise(h5file)``: the same after the fact, for a file HDF5 writes with its own driver
  (the command line's last resort): after HDF5 failed a write, its metadata cache holds blocks
  that never reached the disk; flushing or closing that handle normally writes a damaged
  file, and the process then dies of a segmentation fault when the library shuts down. So
  its descriptor is pointed at an anonymous in-memory file (``memfd_create``) and then
  closed: whatever HDF5 still writes goes nowhere, and the file on disk keeps what it had.
* ``filesystem(path)``: mount point, type, size and free space of the file system holding it.
* ``check_writable(out)``: ``campaign run``'s preflight, before any worker starts: the
  output's directory can be created and takes new files, and the existing store, journal and
  progress file open for writing; else ``UserError`` (exit 2) naming the path and the reason.
"""

from __future__ import annotations

import ctypes
import errno
import os
import re
import sys
import tempfile
from pathlib import Path

from campaign.errors import SPACE_ERRNOS, OutOfSpace, UserError, WriteFault

#: errno values of a write the file system refused (besides SPACE_ERRNOS).
WRITE_ERRNOS = frozenset({errno.EROFS, errno.EIO, errno.EFBIG, errno.ESTALE, errno.EACCES, errno.EPERM})
_FALLOC_FL_KEEP_SIZE, _FALLOC_FL_PUNCH_HOLE = 0x01, 0x02
_UNSUPPORTED = frozenset({errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL, errno.ENODEV, errno.ENOTTY})
#: Testing hook: "1" makes ``reserve`` neither reserve nor look (as on a file system without
#: fallocate whose free space another writer takes), so that HDF5 itself meets the full disk.
NO_RESERVE_ENV = "CAMPAIGN_NO_RESERVE"


def errno_of(exc) -> int | None:
    """The errno of an OSError, or the one an HDF5 error message names (h5py raises some
    write failures as RuntimeError with ``errno = 28`` in their text)."""
    e = getattr(exc, "errno", None)
    if isinstance(e, int) and e:
        return e
    m = re.search(r"errno = (\d+)", str(exc))
    return int(m.group(1)) if m else None


def write_fault(exc, path, what, *, needed=None, free=None) -> WriteFault | None:
    """The WriteFault ``exc`` amounts to (writing ``path`` while ``what``), or None."""
    if isinstance(exc, WriteFault):
        return exc
    if not isinstance(exc, (OSError, RuntimeError, ValueError, KeyError)):
        return None
    e = errno_of(exc)
    if e in SPACE_ERRNOS:
        return OutOfSpace(path, e, what, needed=needed, free=free)
    if e in WRITE_ERRNOS:
        return WriteFault(path, e, what, needed=needed)
    return None


# --------------------------------------------------------------------------- reserving space

_libc = None


def _fallocate(fd, mode, offset, length):
    global _libc
    if _libc is None:
        _libc = ctypes.CDLL(None, use_errno=True)
        if hasattr(_libc, "fallocate"):
            _libc.fallocate.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]
            _libc.fallocate.restype = ctypes.c_int
    if not hasattr(_libc, "fallocate"):  # not Linux: look at the free space instead
        raise OSError(errno.ENOSYS, "fallocate is not available")
    if _libc.fallocate(fd, mode, offset, length) != 0:
        e = ctypes.get_errno()
        raise OSError(e, os.strerror(e))


def free_bytes(path_or_fd) -> int:
    st = os.fstatvfs(path_or_fd) if isinstance(path_or_fd, int) else os.statvfs(path_or_fd)
    return st.f_bavail * st.f_frsize


def reserve(fd, nbytes, path, what) -> int:
    """Reserve ``nbytes`` past the end of the open file ``fd`` (``path``), or check that the
    file system has them free. Returns the bytes reserved (0 when only checked); raises
    OutOfSpace when they are not there, before anything is written."""
    nbytes = int(nbytes)
    if nbytes <= 0 or os.environ.get(NO_RESERVE_ENV) == "1":
        return 0
    end = os.fstat(fd).st_size
    try:
        _fallocate(fd, _FALLOC_FL_KEEP_SIZE, end, nbytes)
        return nbytes
    except OSError as exc:
        if exc.errno in SPACE_ERRNOS:
            raise OutOfSpace(path, exc.errno, what, needed=nbytes, free=free_bytes(fd)) from None
        if exc.errno not in _UNSUPPORTED:
            fault = write_fault(exc, path, what, needed=nbytes)
            if fault is not None:
                raise fault from None
            raise
    free = free_bytes(fd)  # cannot reserve here: look instead
    if free < nbytes:
        raise OutOfSpace(path, errno.ENOSPC, what, needed=nbytes, free=free)
    return 0


def release(fd, nbytes):
    """Hand back the part of a reservation past the file's end that writing did not use."""
    if not nbytes:
        return
    try:
        end = os.fstat(fd).st_size
        _fallocate(fd, _FALLOC_FL_PUNCH_HOLE | _FALLOC_FL_KEEP_SIZE, end, int(nbytes))
    except OSError:
        try:
            os.ftruncate(fd, os.fstat(fd).st_size)  # drops blocks past the end on most file systems
        except OSError:
            pass


# --------------------------------------------------------------------------- HDF5 handles

class GuardedFile:
    """The file HDF5 writes a store through (h5py's ``fileobj`` driver), so that HDF5 never
    sees a write fail.

    HDF5 does not survive a failed write: its metadata cache then holds blocks that never
    reached the disk, later writes fail inside object deallocation where nobody sees them,
    and the process dies of a segmentation fault (reproduced with ENOSPC on a tmpfs). So a
    write the file system refuses is recorded in ``failed`` and, like every write after it,
    goes to an in-memory overlay instead: HDF5 carries on, reads back what it wrote, and the
    file on disk keeps what it had at that moment. The store checks ``failed`` after each
    write step and stops. ``discard()`` sends every later write to the overlay (closing a
    handle that must not write any more).

    What failed is kept here, for whoever holds the handle: ``failed`` (a write the file system
    refused) and ``poisoned``: a write step through this handle failed (``poison()``, by
    ``campaign.storage.space``'s ``write_step``), so HDF5's cache may hold blocks that never
    reached the disk and nothing may be written through it any more; the store then closes it
    with ``discard()`` first.
    """

    def __init__(self, path, create=False):
        self.path = str(path)
        flags = os.O_RDWR | (os.O_CREAT | os.O_TRUNC if create else 0)
        self.fd = os.open(self.path, flags, 0o644)
        self.pos = 0
        self.failed = None       # the OSError of the first refused write
        self._poisoned = False   # a write step through this handle failed (poison())
        self._overlay = None     # memfd holding what was written after it
        self._ranges = []        # (start, end) of the overlay's written ranges, sorted, disjoint

    # the file-object protocol h5py's fileobj driver uses
    def seek(self, offset, whence=0):
        if whence == 0:
            self.pos = int(offset)
        elif whence == 1:
            self.pos += int(offset)
        else:
            end = os.fstat(self.fd).st_size
            if self._ranges:
                end = max(end, self._ranges[-1][1])
            self.pos = end + int(offset)
        return self.pos

    def tell(self):
        return self.pos

    def read(self, n=-1):
        n = int(n)
        data = os.pread(self.fd, n, self.pos) if n > 0 else b""
        if len(data) < n:  # past the end: zeros, as HDF5's own POSIX driver reads them
            data += b"\0" * (n - len(data))
        if self._ranges:
            data = self._patch(bytearray(data), self.pos)
        self.pos += n
        return bytes(data)

    def readinto(self, buf):
        data = self.read(len(buf))
        buf[:len(data)] = data
        return len(data)

    def write(self, data):
        view = memoryview(data).cast("B")
        if self.failed is None and self._overlay is None:
            done = 0
            try:
                while done < len(view):
                    done += os.pwrite(self.fd, view[done:], self.pos + done)
            except OSError as exc:
                self.failed = exc
                self._to_overlay(view[done:], self.pos + done)
        else:
            self._to_overlay(view, self.pos)
        self.pos += len(view)
        return len(view)

    def truncate(self, size=None):
        size = self.pos if size is None else int(size)
        if self.failed is None and self._overlay is None:
            try:
                os.ftruncate(self.fd, size)
            except OSError as exc:
                self.failed = exc
        return size

    def flush(self):
        pass

    def fileno(self):
        return self.fd

    def close(self):
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
        if self._overlay is not None:
            os.close(self._overlay)
            self._overlay = None

    @property
    def closed(self):
        return self.fd is None

    def readable(self):
        return True

    def writable(self):
        return True

    def seekable(self):
        return True

    # what failed
    def poison(self):
        """A write step through this handle failed: nothing may be written through it any more."""
        self._poisoned = True

    @property
    def poisoned(self) -> bool:
        """Whether a write step through this handle failed, or the file system refused a write."""
        return self._poisoned or self.failed is not None

    # the overlay
    def discard(self):
        """From now on nothing reaches the file: every write goes to the overlay."""
        if self._overlay is None:
            self._overlay = _scratch_fd()

    def _to_overlay(self, view, at):
        self.discard()
        done = 0
        while done < len(view):
            done += os.pwrite(self._overlay, view[done:], at + done)
        start, end = at, at + len(view)
        kept = []
        for a, b in self._ranges:
            if b < start or a > end:
                kept.append((a, b))
            else:
                start, end = min(a, start), max(b, end)
        kept.append((start, end))
        self._ranges = sorted(kept)

    def _patch(self, data, at):
        end = at + len(data)
        for a, b in self._ranges:
            lo, hi = max(a, at), min(b, end)
            if lo < hi:
                data[lo - at:hi - at] = os.pread(self._overlay, hi - lo, lo)
        return data


def _scratch_fd():
    """An anonymous file in memory (memfd) for writes that must go nowhere; elsewhere than Linux,
    an unlinked temporary file."""
    if hasattr(os, "memfd_create"):
        return os.memfd_create("campaign-discarded-hdf5-writes")
    with tempfile.TemporaryFile() as fh:
        return os.dup(fh.fileno())


def neutralise(h5file):
    """Close an h5py File whose last write failed without writing anything more to its
    file (see the module's docstring). Never raises."""
    try:
        fid = h5file.id if hasattr(h5file, "id") else h5file
        fd = fid.get_vfd_handle()
        sink = _scratch_fd()
        try:
            os.dup2(sink, int(fd))
        finally:
            os.close(sink)
    except Exception:  # noqa: BLE001 - closed already, or another driver: nothing to redirect
        pass
    try:
        h5file.close()
    except Exception:  # noqa: BLE001 - its writes went nowhere; errors about them do not matter
        pass


def neutralise_open_files(near=None):
    """Neutralise every HDF5 file this process has open for writing (on the file system
    of ``near``, when given): the command line's last resort after a write fault."""
    h5py = sys.modules.get("h5py")
    if h5py is None:
        return
    dev = None
    if near is not None:
        try:
            dev = os.stat(Path(near) if Path(near).exists() else Path(near).parent).st_dev
        except OSError:
            dev = None
    try:
        ids = h5py.h5f.get_obj_ids(types=h5py.h5f.OBJ_FILE)
    except Exception:  # noqa: BLE001
        return
    for fid in ids:
        try:
            if not fid.get_intent() & h5py.h5f.ACC_RDWR:
                continue
            name = fid.name.decode(errors="replace") if isinstance(fid.name, bytes) else str(fid.name)
            if dev is not None and os.stat(name).st_dev != dev:
                continue
        except Exception:  # noqa: BLE001
            pass
        neutralise(h5py.File(fid))


# --------------------------------------------------------------------------- describing

def fmt_bytes(n) -> str:
    n = int(n)
    for unit, k in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= k:
            return f"{n / k:.3g} {unit}"
    return f"{n} bytes"


def _unescape(s):
    return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), s)


def filesystem(path) -> dict:
    """``{"mount", "type", "size", "free"}`` of the file system holding ``path`` (its nearest
    existing ancestor); "?" and None for what cannot be found."""
    p = Path(os.path.abspath(path))
    while not p.exists() and p != p.parent:
        p = p.parent
    real = os.path.realpath(p)
    mount, fstype = "?", "?"
    try:
        best = -1
        with open("/proc/self/mountinfo") as fh:
            for line in fh:
                parts = line.split()
                if "-" not in parts:
                    continue
                mp = _unescape(parts[4])
                if (real == mp or real.startswith(mp.rstrip("/") + "/")) and len(mp) > best:
                    best, mount, fstype = len(mp), mp, parts[parts.index("-") + 1]
    except OSError:
        pass
    out = {"mount": mount, "type": fstype, "size": None, "free": None}
    try:
        st = os.statvfs(real)
        out.update(size=st.f_blocks * st.f_frsize, free=st.f_bavail * st.f_frsize)
    except OSError:
        pass
    return out


def describe_filesystem(path) -> str:
    fs = filesystem(path)
    what = f"the file system {fs['mount']} ({fs['type']}"
    if fs["size"] is not None:
        what += f", {fmt_bytes(fs['size'])}, {fmt_bytes(fs['free'])} free"
    return what + ")"


# --------------------------------------------------------------------------- preflight

def check_writable(out, *, new=False):
    """Can ``campaign run`` write the store ``out``, its journal and its progress file?

    Creates the directory if needed, then creates and removes an empty probe file in it (a
    real attempt: permissions, read-only mounts, ACLs and root-squashed NFS all answer it),
    and opens the existing store, journal and progress file for writing. UserError (exit 2)
    naming the path and the reason otherwise; OutOfSpace if not even an empty file fits.
    """
    out = Path(out)
    if out.is_dir():
        raise UserError(f"the output {str(out)!r} is a directory; give the store's file name, such as "
                        f"{str(out / 'campaign.h5')!r}")
    parent = out.parent if str(out.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the output directory {str(parent)!r} for {str(out)!r}: "
                        f"{exc.strerror or exc}; choose another --out, or create it first") from None
    probe = parent / f".{out.name}.probe-{os.getpid()}"
    try:
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        os.close(fd)
    except OSError as exc:
        if exc.errno in SPACE_ERRNOS:
            raise OutOfSpace(probe, exc.errno, "creating a file in the output directory",
                             free=_free_or_none(parent)) from None
        raise UserError(f"cannot write in the output directory {str(parent)!r}: {exc.strerror or exc} "
                        f"(a run creates {out.name}, {out.name}.journal and {out.name}.progress.json there); "
                        "choose another --out, or make the directory writable") from None
    finally:
        try:
            os.unlink(probe)
        except OSError:
            pass
    names = ([] if new else [out]) + [Path(str(out) + ".journal")]
    for p in names:
        if not (p.exists() or p.is_symlink()):
            continue
        try:
            fd = os.open(p, os.O_RDWR)
            os.close(fd)
        except OSError as exc:
            raise UserError(f"{str(p)!r} exists but cannot be opened for writing: {exc.strerror or exc}; "
                            "choose another --out, or make it writable") from None


def _free_or_none(path):
    try:
        return free_bytes(str(path))
    except OSError:
        return None


# --------------------------------------------------------------------------- the stop message

def stop_paragraph(fault, out, *, counts=None, total=None, need=None, resume=None) -> str:
    """The one paragraph ``campaign run`` ends with after a WriteFault: the file, the file
    system, the space wanted, what was kept, what finishing needs, and how to resume."""
    fs = filesystem(fault.path)
    where = f"{fs['mount']} ({fs['type']}"
    if fs["size"] is not None:
        where += f", {fmt_bytes(fs['size'])}, {fmt_bytes(fs['free'])} free"
    where += ")"
    reason = os.strerror(fault.errno)
    if fault.out_of_space:
        text = f"out of space: {fault.what} failed: {fault.path}: {reason}, on the file system {where}"
        if fault.needed:
            text += f"; that step needed {fmt_bytes(fault.needed)}"
        text += "."
    else:
        text = f"cannot write: {fault.what} failed: {fault.path}: {reason}, on the file system {where}."
    if getattr(fault, "damaged", False):
        text += (f" HDF5 met the failure in the middle of writing {out}, which may be left damaged; nothing "
                 "finished is lost: the journal holds every task the store may have lost, and the next run "
                 "salvages the store's readable rows into a new file (room for a second copy of it is needed).")
    if counts is None:
        text += " No task was started; nothing finished was lost."
    else:
        kept = counts["done"] + counts["failed"]
        text += (f" The run stopped and kept everything it had finished: {kept} of {total} tasks are in {out} "
                 f"and its journal, which agree; {counts['pending']} are left.")
        if need and need.get("total") and counts["pending"]:
            text += (f" Finishing them needs about {fmt_bytes(need['total'])} more on {fs['mount']} (about "
                     f"{fmt_bytes(need['per_task'])} a task in the store")
            if need.get("journal_per_task"):
                text += f", and {fmt_bytes(need['journal_per_task'])} a task in the journal until a checkpoint"
            text += ")."
    if fault.out_of_space:
        text += f" Free space on {fs['mount']} (or raise the quota), then rerun the same command to resume"
    else:
        text += " Once the file system takes writes again, rerun the same command to resume"
    return text + (f": {resume}" if resume else ".")
