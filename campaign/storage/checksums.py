"""The store's checksums (written by the store, checked by every reader), and the names, limits
and messages the checks of the store share.

What carries a checksum (docs/STORE.md, "Checksums, verify and repair"): every per-task block
dataset and the bin edges (HDF5's ``fletcher32`` filter, checked by HDF5 on every read), every
configuration (attribute ``crc32`` of its arrays' bytes, ``config_crc``, checked by
``check_configuration``), every failure record (``failure_crc``) and the list of the scalars'
names. The writers (``campaign.storage.store``, ``campaign.storage.storefile``) and every reader use this module;
finding damage (``campaign verify``'s scan, and ``read_failure``, the error a reader raises when a
read of the store fails) is ``campaign.storage.integrity``, which builds on it, and repairing it
``campaign.storage.repair``.
"""

from __future__ import annotations

import json
import os
import re
import zlib

import numpy as np

from campaign.errors import StoreDamaged, UserError

CONFIG_KEYS = ("positions", "radii", "box", "species")
CHECKSUM_ATTR = "crc32"
NO_CHECKSUMS_ENV = "CAMPAIGN_NO_CHECKSUMS"
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
JOURNAL_MAGIC = b"JCJ1"
#: Raw (decompressed) bytes read at once while scanning a dataset: a whole number of its chunks.
SLAB_BYTES = 16 << 20
#: Progress weight of one configuration, in bytes of block data (a group costs several HDF5 opens).
CONFIG_WEIGHT = 64 << 10
IDENTITY = ("id", "variant", "N", "E", "seed")
SHUFFLE, DEFLATE, FLETCHER32 = 2, 1, 3  # HDF5's filter ids
ROOT_MEMBERS = ("tasks", "scalars", "histograms", "configurations", "failures", "reduced")
ROOT_ATTRS = ("schema", "format_version", "name", "spec_yaml", "spec_hash", "package_version", "git_commit", "versions",
              "runs", "hosts", "start_time", "end_time")
SCALAR_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def good_scalar_name(name) -> bool:
    """Whether ``name`` (a link name as h5py gives it: bytes when not UTF-8) can be a scalar's."""
    return isinstance(name, str) and SCALAR_NAME.fullmatch(name) is not None
BLOCK_FILTERS = (SHUFFLE, DEFLATE)
#: Exceptions a read of a damaged (or concurrently written) HDF5 file raises through h5py.
READ_ERRORS = (OSError, KeyError, ValueError, RuntimeError, MemoryError)
DOCS = 'docs/STORE.md, "Checksums, verify and repair"'
EDGES_NOTE = ("rewritten from the spec's bins, else the analysis kernels' default bins (the edges `campaign run` "
              "compares them with)")


def checksums_on() -> bool:
    """Whether new datasets and configurations get checksums (``CAMPAIGN_NO_CHECKSUMS=1``: no,
    as stores written before checksums; for benchmarks and tests)."""
    return os.environ.get(NO_CHECKSUMS_ENV, "") in ("", "0")


def config_crc(arrays) -> int:
    """CRC-32 of a configuration: the bytes of positions, radii, box and species, in that order."""
    crc = 0
    for k in CONFIG_KEYS:
        crc = zlib.crc32(np.ascontiguousarray(arrays[k]).data, crc)
    return crc & 0xFFFFFFFF


def write_configuration(parent, tid, arrays):
    """Create the configuration group ``parent/tid``: its four datasets and their checksum."""
    data = {k: np.asarray(arrays[k]) for k in CONFIG_KEYS}
    g = parent.create_group(tid)
    for k in CONFIG_KEYS:
        g.create_dataset(k, data=data[k])
    if checksums_on():
        g.attrs[CHECKSUM_ATTR] = np.uint32(config_crc(data))
    return g


def _crc_matches(stored, arrays) -> bool:
    try:
        return int(np.asarray(stored).reshape(-1)[0]) == config_crc(arrays)
    except (TypeError, ValueError, IndexError):
        return False


def configuration_problem(g, keys=CONFIG_KEYS):
    """``(arrays, problem)``: the arrays ``keys`` of the configuration group ``g`` and None, or what
    is wrong with it (a phrase: it cannot be read, or its bytes do not match its checksum). A
    group written without a checksum is taken as it reads."""
    try:
        out = {k: g[k][()] for k in keys if k in g}
        stored = g.attrs.get(CHECKSUM_ATTR)
        if stored is None and len(g.attrs):  # the layout's only attribute is the checksum
            return None, f"has an attribute {_text(list(g.attrs)[0])!r} the layout has not (a damaged name)"
        if stored is not None and set(out) != set(CONFIG_KEYS):
            out.update({k: g[k][()] for k in CONFIG_KEYS})  # every key enters the checksum
    except Exception as exc:  # noqa: BLE001 - whatever stops us reading it, it is damaged
        return None, f"cannot be read ({reason(exc)})"
    if stored is not None and not _crc_matches(stored, out):
        return None, "does not match its checksum (crc32): its bytes changed after they were written"
    return out, None


def check_configuration(g, path, name, keys=CONFIG_KEYS):
    """The arrays ``keys`` of the configuration group ``g`` (``name`` in the store ``path``), checked
    against its checksum; StoreDamaged naming it when it cannot be read or does not match."""
    out, problem = configuration_problem(g, keys)
    if problem is not None:
        raise StoreDamaged(damaged_message(path, name, problem))
    return out


FAILURE_KEYS = ("message", "traceback", "attempts", "rank", "host")


def failure_crc(a) -> int:
    """CRC-32 of a failure record: the UTF-8 JSON of [message, traceback, attempts] (rank and host, which
    differ from run to run, are the task table's, checksummed there)."""
    items = [str(_text(a["message"])), str(_text(a["traceback"])), int(a["attempts"])]
    return zlib.crc32(json.dumps(items).encode("utf-8")) & 0xFFFFFFFF


def write_failure(parent, tid, attrs):
    """Create the failure record ``parent/tid``: its attributes and their checksum."""
    g = parent.create_group(tid)
    g.attrs.update({k: attrs[k] for k in FAILURE_KEYS})
    if checksums_on():
        g.attrs[CHECKSUM_ATTR] = np.uint32(failure_crc(attrs))
    return g


def write_scalar_names(group, names):
    """The ``scalars`` group's list of its datasets (attribute ``names``, JSON, and its ``crc32``): a
    damaged link name then shows as a name the list does not hold, and a repair renames it back."""
    if not checksums_on():
        return
    text = json.dumps(sorted(names))
    group.attrs["names"] = text
    group.attrs[CHECKSUM_ATTR] = np.uint32(zlib.crc32(text.encode()) & 0xFFFFFFFF)


def scalar_names_listed(group):
    """The names the ``scalars`` group lists, None when it lists none (a store before checksums);
    ValueError when the list fails its checksum."""
    text, stored = _text(group.attrs.get("names")), group.attrs.get(CHECKSUM_ATTR)
    if text is None and stored is None:
        return None
    try:
        ok = text is not None and int(np.asarray(stored).reshape(-1)[0]) == zlib.crc32(text.encode()) & 0xFFFFFFFF
        names = json.loads(text) if ok else None
    except (TypeError, ValueError, IndexError):
        ok = False
    if not ok or not isinstance(names, list):
        raise ValueError("the list of its scalars' names does not match its checksum")
    return set(names)


def failure_problem(attrs):
    """What is wrong with a failure record's attributes (a phrase), or None."""
    try:
        unknown = sorted(str(_text(k) or k) for k in attrs if k not in FAILURE_KEYS + (CHECKSUM_ATTR,))
        if unknown:
            return f"has an attribute {unknown[0]!r} the layout has not (a damaged name)"
        for k in ("message", "traceback", "host"):
            if _text(attrs.get(k)) is None:
                return f"has no text attribute {k!r}"
        int(attrs["rank"])
        crc = failure_crc(attrs)
    except (KeyError, TypeError, ValueError) as exc:
        return f"lacks an attribute or holds a wrong one ({reason(exc)})"
    stored = attrs.get(CHECKSUM_ATTR)
    if stored is not None:
        try:
            ok = int(np.asarray(stored).reshape(-1)[0]) == crc
        except (TypeError, ValueError, IndexError):
            ok = False
        if not ok:
            return "does not match its checksum (crc32): its text changed after it was written"
    return None


# --------------------------------------------------------------------------- what readers say

def reason(exc) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text if len(text) < 300 else text[:300] + "..."


def is_filter_failure(exc) -> bool:
    """A read that failed a checksum or a decompression (HDF5 reports both as a filter failure)."""
    text = str(exc).lower()
    return any(w in text for w in ("filter returned failure", "fletcher32", "checksum", "data error", "inflate"))


def damaged_message(path, what, how, held="") -> str:
    return (f"{path} is damaged: {what} {how}{held}. `campaign verify {path}` reads the whole store and names "
            f"every damaged part and the tasks it holds; `campaign verify {path} --repair` then marks those "
            f"tasks pending, for `campaign run` of the same spec to recompute them ({DOCS})")


def run_is_writing(path) -> bool:
    """Whether a live run writes the store (its progress file, judged as ``campaign status`` does)."""
    try:
        from campaign.storage.progress import read_sidecar, writer_state

        return writer_state(read_sidecar(path))["state"] == "running"
    except Exception:  # noqa: BLE001 - no progress file, or an unreadable one: no run known
        return False


def looks_like_store(path) -> bool:
    """Whether ``path`` is an HDF5 file by its signature (at 0, 512, 1024, ...: where HDF5 looks for
    it), or has a campaign journal beside it."""
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            offset = 0
            while offset + len(HDF5_SIGNATURE) <= size:
                fh.seek(offset)
                if fh.read(len(HDF5_SIGNATURE)) == HDF5_SIGNATURE:
                    return True
                offset = 512 if offset == 0 else 2 * offset
        with open(str(path) + ".journal", "rb") as fh:
            return fh.read(4) == JOURNAL_MAGIC
    except OSError:
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


def _text(v):
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.ndarray) and v.shape == () and v.dtype.kind in "SO":
        return _text(v[()])
    return v if isinstance(v, str) else None
