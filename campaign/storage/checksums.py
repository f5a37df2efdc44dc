"""The store's checksums (written by the store, checked by every reader), and the names, limits
and messages the checks of the store share.

What carries a checksum (docs/STORE.md, "Checksums, verify and repair"): every per-task block
dataset and the bin edges (HDF5's ``fletcher32`` filter, checked by HDF5 on every read), every
configuration (attribute ``crc32`` of its arrays' bytes, ``config_crc``, checked by
``check_configuration``), every failure record (``failure_crc``) and the list of the scalars'
names. The writers (``campaign.storage.store``, ``campaign.storage.layout``) and every reader use this module;
finding damage (``campaign verify``'s scan, and ``read_failure``, the error a reader raises when a
read of the store fails) is ``campaign.storage.integrity``, which builds on it, and repairing it
``campaign.storage.repair``.
"""

from __future__ import annotations

import json
import os
import re
import time
import zlib

import numpy as np

from campaign.errors import StoreDamaged
from campaign.version import __version__

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
ROOT_MEMBERS = ("tasks", "scalars", "histograms", "configurations", "failures", "reduced", "checksums", "checkpoints")
ROOT_ATTRS = ("schema", "format_version", "name", "spec_yaml", "spec_hash", "package_version", "git_commit", "versions",
              "runs", "hosts", "start_time", "end_time", "block_checksums")
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


def _crc_value(stored) -> int:
    """A stored CRC-32 attribute's value; ValueError unless it is the one uint32 it was written as (a
    damaged attribute header can change its type and leave the value)."""
    a = np.asarray(stored)
    if a.dtype != np.uint32 or a.size != 1:
        raise ValueError(f"a checksum attribute of type {a.dtype}, shape {a.shape}: not the uint32 written")
    return int(a.reshape(-1)[0])


def _crc_matches(stored, arrays) -> bool:
    try:
        return _crc_value(stored) == config_crc(arrays)
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
        if stored is None and has_sums(g.file):  # a store written with checksums throughout
            return None, "has lost its checksum (crc32): its header is damaged"
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


#: a suspended GPU packing's state (``/checkpoints/<id>``, ``kernels.gpu.batch.Suspended.arrays``)
CHECKPOINT_KEYS = ("positions", "velocities", "reference", "state")
#: its counters, attributes of its group (integers; ``device_seconds`` a float)
CHECKPOINT_ATTRS = ("steps", "force_evaluations", "device_seconds", "launches")


def checkpoint_crc(arrays, attrs) -> int:
    """CRC-32 of a suspended packing: the bytes of its four arrays (float64) in the order of
    ``CHECKPOINT_KEYS``, then the UTF-8 JSON of its counters in the order of ``CHECKPOINT_ATTRS``."""
    crc = 0
    for k in CHECKPOINT_KEYS:
        crc = zlib.crc32(np.ascontiguousarray(arrays[k], np.float64).data, crc)
    counters = [int(attrs[k]) if k != "device_seconds" else float(attrs[k]) for k in CHECKPOINT_ATTRS]
    return zlib.crc32(json.dumps(counters).encode("utf-8"), crc) & 0xFFFFFFFF


def write_checkpoint(parent, tid, arrays, attrs):
    """Create the group ``parent/tid`` of a suspended packing: its four arrays, its counters and
    their checksum (always written: a checkpoint that does not match it is not resumed)."""
    g = parent.create_group(tid)
    for k in CHECKPOINT_KEYS:
        g.create_dataset(k, data=np.ascontiguousarray(arrays[k], np.float64))
    for k in CHECKPOINT_ATTRS:
        g.attrs[k] = float(attrs[k]) if k == "device_seconds" else int(attrs[k])
    g.attrs[CHECKSUM_ATTR] = np.uint32(checkpoint_crc(arrays, attrs))
    return g


def checkpoint_problem(g):
    """``(arrays, counters, problem)``: a suspended packing's group read back and None, or what is
    wrong with it (it cannot be read, or does not match its checksum): such a task starts over."""
    try:
        arrays = {k: np.asarray(g[k][()], np.float64) for k in CHECKPOINT_KEYS}
        attrs = {k: g.attrs[k] for k in CHECKPOINT_ATTRS}
        stored = _crc_value(g.attrs[CHECKSUM_ATTR])
        counters = {k: float(v) if k == "device_seconds" else int(v) for k, v in attrs.items()}
    except Exception as exc:  # noqa: BLE001 - whatever stops us reading it, it is damaged
        return None, None, f"cannot be read ({reason(exc)})"
    if stored != checkpoint_crc(arrays, counters):
        return None, None, "does not match its checksum (crc32): its bytes changed after they were written"
    return arrays, counters, None


def checkpoint_damage(f, rows_of=None):
    """``(name, problem)`` of every damaged part of a store's ``/checkpoints`` (``campaign verify``):
    a checkpoint that cannot be read or does not match its checksum, one named after no task
    (``rows_of(names)``: their task rows, -1 for none; None: names not checked), an index that
    cannot be listed."""
    try:
        names = list(f["checkpoints"].keys()) if "checkpoints" in f else []
    except Exception as exc:  # noqa: BLE001
        return [("checkpoints", f"its index cannot be read ({reason(exc)})")]
    rows = rows_of(names) if rows_of is not None and names else None
    out = []
    for k, key in enumerate(names):
        name = f"checkpoints/{_text(key)}"
        if rows is not None and rows[k] < 0:
            out.append((name, "is named after no task of this store (its name is damaged)"))
            continue
        try:
            g = f["checkpoints"][key]
        except Exception:  # noqa: BLE001 - checkpoint_problem says it cannot be read
            g = None
        problem = checkpoint_problem(g)[2]
        if problem is not None:
            out.append((name, problem))
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


#: the group of a precision campaign's round decisions (docs/STORE.md, "Rounds"), one dataset each
ROUNDS_GROUP = "precision"


def round_name(k: int) -> str:
    return f"round{int(k):04d}"


def write_round(group, k: int, text: str):
    """One round's decision (its JSON text, UTF-8 bytes) as ``group/roundKKKK`` with its checksum."""
    name = round_name(k)
    if name in group:
        del group[name]
    data = np.frombuffer(text.encode(), np.uint8)
    ds = group.create_dataset(name, data=data)
    ds.attrs[CHECKSUM_ATTR] = np.uint32(zlib.crc32(data.tobytes()) & 0xFFFFFFFF)
    return ds


def read_rounds(f) -> tuple[dict, list]:
    """The decisions a store (an open HDF5 file) holds in its ``precision`` group, ``({round: record},
    [problems])``; none in a store without the group (a fixed grid). A record that cannot be read, is
    not JSON or fails its checksum is left out and named (its round is decided again from the
    packings, which decide it the same way)."""
    out, problems = {}, []
    try:
        if ROUNDS_GROUP not in f:
            return out, problems
        group = f[ROUNDS_GROUP]
        names = sorted(group.keys())
    except Exception as exc:  # noqa: BLE001 - a damaged index: every decision is made again
        return {}, [f"its index cannot be read ({reason(exc)})"]
    for name in names:
        try:
            k = int(str(name)[5:]) if str(name).startswith("round") else None
            if k is None or round_name(k) != name:
                raise ValueError("not a round's name")
            ds = group[name]
            data = np.asarray(ds[()], np.uint8)
            if _crc_value(ds.attrs[CHECKSUM_ATTR]) != zlib.crc32(data.tobytes()) & 0xFFFFFFFF:
                raise ValueError("it does not match its checksum (crc32)")
            record = json.loads(data.tobytes().decode())
            if not isinstance(record, dict) or record.get("round") != k:
                raise ValueError("it is not a round's decision")
            out[k] = record
        except Exception as exc:  # noqa: BLE001 - this decision is made again
            problems.append(f"{name}: {reason(exc)}")
    return out, problems


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
        ok = text is not None and _crc_value(stored) == zlib.crc32(text.encode()) & 0xFFFFFFFF
        names = json.loads(text) if ok else None
    except (TypeError, ValueError, IndexError):
        ok = False
    if not ok or not isinstance(names, list):
        raise ValueError("the list of its scalars' names does not match its checksum")
    return set(names)


def failure_problem(attrs, required=False):
    """What is wrong with a failure record's attributes (a phrase), or None; ``required``: it must
    carry its checksum (a store written with checksums throughout, ``has_sums``)."""
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
    if stored is None and required:
        return "has lost its checksum (crc32): its header is damaged"
    if stored is not None:
        try:
            ok = _crc_value(stored) == crc
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


def _text(v):
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.ndarray) and v.shape == () and v.dtype.kind in "SO":
        return _text(v[()])
    return v if isinstance(v, str) else None


def check_identities(path, spec, variant, N, E, lo=0):
    """StoreDamaged unless every row (from row ``lo``) of the store ``path`` is a task of its own
    ``spec`` (``campaign.storage.layout.stored_spec``, verified: its variant, N and E; nothing is
    checked without): a block of the task table read from another place (a damaged chunk index, in a
    store without block checksums) can read as rows of no task, and must not become a cell of a table."""
    if spec is None:
        return
    variant = np.array([_text(x) if isinstance(x, bytes) else str(x) for x in np.asarray(variant).ravel()])
    N, E = np.asarray(N), np.asarray(E)
    bad = ~np.isin(variant, [v.name for v in spec.variants])
    for v in spec.variants:
        bad |= (variant == v.name) & ~(np.isin(N, list(spec.N)) & np.isin(E, list(v.E)))
    if bad.any():
        i = np.flatnonzero(bad)
        raise StoreDamaged(damaged_message(
            path, "tasks", f"rows {lo + int(i[0])}-{lo + int(i[-1])} hold {len(i)} row(s) of no task of its own spec "
            f"(the first: variant {str(variant[i[0]])!r}, N = {N[i[0]]}, E = {E[i[0]]!r}): its task table is damaged"))


# --------------------------------------------------------------------------- block checksums
#
# Fletcher32 guards the bytes of each chunk, not which chunk a row is read from: a damaged chunk
# index can list a chunk off its place (a block reads another block's rows) or lose it (the block
# reads as its fill value), and a damaged object header can make HDF5 decode a chunk differently,
# all without an error. Every block of rows of every per-task dataset (``tasks/*`` with the status
# column, ``scalars/*``, ``histograms/*/counts``) and every histogram's bin edges therefore also
# has a checksum of its values as written (the logical values, not the stored bytes): the dataset
# ``checksums/<name with "/" as ".">`` (uint64, one a block, contiguous, attribute ``rows``: the
# rows of a block), written with the block and checked by every reader on the blocks it reads
# (``CheckedFile``): a block read from the wrong place then fails like a block with wrong bytes.

SUMS_GROUP = "checksums"
SUMS_ROWS = "rows"
#: Datasets under these groups are per-task block datasets (or bin edges), each with its sums.
SUMMED = ("/tasks/", "/scalars/", "/histograms/")
_MASK = (1 << 64) - 1
_LENGTH = 0x9E3779B97F4A7C15  # the block's byte length enters the sum: an all-zero block sums to nonzero
_W = np.zeros(0, np.uint64)


def sums_name(name) -> str:
    """The name of the block checksums of the dataset ``name`` (``scalars/A_G`` -> ``checksums/scalars.A_G``)."""
    return f"{SUMS_GROUP}/" + str(name).strip("/").replace("/", ".")


def _weights(n):
    """The first ``n`` weights of the block sum: splitmix64 of 1, 2, 3, ..., made odd."""
    global _W
    if len(_W) < n:
        m = max(n, 2 * len(_W), 1 << 12)
        with np.errstate(over="ignore"):
            x = np.arange(1, m + 1, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15)
            x ^= x >> np.uint64(30)
            x *= np.uint64(0xBF58476D1CE4E5B9)
            x ^= x >> np.uint64(27)
            x *= np.uint64(0x94D049BB133111EB)
            x ^= x >> np.uint64(31)
        _W = x | np.uint64(1)
    return _W[:n]


def _sum_rows(m):
    """The sums of the rows of ``m`` ((k, L) uint8, one block a row): the block's bytes as little-endian
    64-bit words (zero-padded), each times its weight, plus the length times a constant, modulo 2^64."""
    k, L = m.shape
    if L % 8:
        buf = np.zeros((k, L + 8 - L % 8), np.uint8)
        buf[:, :L] = m
        m = buf
    words = np.ascontiguousarray(m).view("<u8")
    with np.errstate(over="ignore"):
        s = words @ _weights(words.shape[1])
        return s.astype(np.uint64) + np.uint64((L * _LENGTH) & _MASK)


def block_sums(a, B) -> np.ndarray:
    """The checksums (uint64) of the blocks of ``B`` rows of ``a`` (rows first; the first block
    starts at row 0 of ``a``, the last may be shorter): a weighted sum of the values' little-endian
    bytes, which any change of a value, or of where it sits in the block, changes (not a CRC:
    fletcher32 guards the stored bytes; this one says whether the rows read are the rows written,
    at a few per cent of the cost of reading them)."""
    a = np.asarray(a)
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    a = np.ascontiguousarray(a)
    n = a.shape[0] if a.ndim else 1
    if n == 0:
        return np.zeros(0, np.uint64)
    raw = a.reshape(n, -1).view(np.uint8).reshape(n, -1) if a.nbytes else np.zeros((n, 0), np.uint8)
    full = n // B
    parts = []
    if full:
        parts.append(_sum_rows(raw[:full * B].reshape(full, -1)))
    if n % B:
        parts.append(_sum_rows(raw[full * B:].reshape(1, -1)))
    return np.concatenate(parts) if len(parts) > 1 else parts[0]


def fill_sums(T, B, row_shape, dtype, fill) -> np.ndarray:
    """The checksums of the ``ceil(T / B)`` blocks of a dataset never written (every row at ``fill``)."""
    dtype = np.dtype(dtype)
    n = -(-T // B)
    block = np.zeros((min(B, T),) + tuple(row_shape), dtype) if fill is None else \
        np.full((min(B, T),) + tuple(row_shape), fill, dtype)
    out = np.full(n, block_sums(block, B)[0], np.uint64)
    if T % B and n:
        out[-1] = block_sums(block[:T % B], B)[0]
    return out


def create_sums(f, name, B, sums):
    """Create the block checksums ``sums`` of the dataset ``name`` of the open store ``f`` (nothing
    when checksums are off); returns the dataset."""
    if not checksums_on():
        return None
    g = f.require_group(SUMS_GROUP)
    key = sums_name(name)[len(SUMS_GROUP) + 1:]
    if key in g:
        del g[key]
    ds = g.create_dataset(key, data=np.asarray(sums, np.uint64))
    ds.attrs[SUMS_ROWS] = np.int64(B)
    return ds


def create_fill_sums(f, name, T, B, row_shape, dtype, fill):
    """The block checksums of a new dataset ``name`` of T rows at ``fill`` (``create_sums``)."""
    if not checksums_on():
        return None
    return create_sums(f, name, B, fill_sums(T, B, row_shape, dtype, fill))


#: The root attribute of a store that keeps block checksums (since 0.3.0): how it came to have them
#: (``protection_text``). A store with neither it nor ``/checksums`` was written without them (0.2.7
#: and older): unprotected. With the attribute and without the group, the group's link is damaged.
PROTECTION_ATTR = "block_checksums"
#: The version that added block checksums: stores written before it have none.
PROTECTED_SINCE = "0.3.0"


def protection_text(upgraded=False) -> str:
    """The value of a store's ``block_checksums`` attribute: written with every block since the store
    was created, or added (``upgraded``) when a store without them was written anew."""
    if not upgraded:
        return "written with every block since the store was created"
    return (f"added {time.strftime('%Y-%m-%dT%H:%M:%S%z')} by jamming-campaign {__version__}, which wrote the store "
            "anew from a store without them: damage done before that and not found by the checks of "
            "`campaign verify` then cannot be found")


def has_sums(f) -> bool:
    """Whether the store ``f`` keeps block checksums: its ``checksums`` group, or the root attribute
    that says it has one (so that a damaged link to the group is not taken for a store without)."""
    try:
        return SUMS_GROUP in f or PROTECTION_ATTR in f.attrs
    except Exception:  # noqa: BLE001 - a damaged root group: the readers' other checks say so
        return False


def unprotected_note(path) -> str:
    """The one line a reader prints about a store without block checksums (0.2.7 and older)."""
    return (f"note: {path} has no block checksums (written before {PROTECTED_SINCE}): damage to HDF5's chunk "
            f"index would change what is read without an error. `campaign verify {path} --repair` checks what "
            "can be checked and adds them")


#: Stores a checked open found without block checksums, in this process (``unprotected_seen``).
_UNPROTECTED: list = []


def unprotected_seen() -> list:
    """``(path, schema, format_version)`` of the files without block checksums that readers opened
    since the last call (each once), for the command line's note on those of the current format
    (``campaign.cli``; a file of another format is refused by its reader)."""
    out = list(dict.fromkeys(_UNPROTECTED))
    _UNPROTECTED.clear()
    return out


def write_sums(sums_ds, lo, data, B):
    """Write the checksums of ``data`` (rows ``lo``, ``lo + 1``, ...; ``lo`` a multiple of ``B``) into
    the block checksums dataset ``sums_ds`` (None: a store without them)."""
    if sums_ds is None or not len(data):
        return
    s = block_sums(data, B)
    b0 = lo // B
    sums_ds[b0:b0 + len(s)] = s


class BlockMismatch(ValueError):
    """Rows read from the store do not match the checksum of the rows written there."""

    def __init__(self, name, lo, hi, how=None):
        self.name, self.lo, self.hi = name, lo, hi
        super().__init__(f"{name} rows {lo}-{hi - 1} " + (how or BLOCK_MISMATCH))


BLOCK_MISMATCH = ("do not match their checksum: the rows read are not the rows written (a chunk index, "
                  "a header or the checksums are damaged)")


def mismatched_blocks(stored, data, lo, B, T):
    """``[(a, b), ...]``: the blocks of rows [a, b) among the rows ``data`` (from row ``lo``, a multiple of
    ``B``) whose checksums differ from ``stored`` (the stored checksums of those blocks)."""
    got = block_sums(data, B)
    stored = np.asarray(stored).reshape(-1)
    bad = []
    for k in range(len(got)):
        if k >= len(stored) or stored[k] != got[k]:
            a = lo + k * B
            bad.append((a, min(a + B, T, lo + len(data))))
    return bad


def check_rows(sums_ds, name, lo, data, B):
    """Raise BlockMismatch when the rows ``data`` (from row ``lo``, a multiple of ``B``) of the dataset
    ``name`` differ from the block checksums ``sums_ds``."""
    nb = -(-len(data) // B)
    stored = sums_ds[lo // B: lo // B + nb]
    bad = mismatched_blocks(stored, data, lo, B, lo + len(data))
    if bad:
        raise BlockMismatch(name, *bad[0])


def _block_rows(sums_ds, T):
    B = int(np.asarray(sums_ds.attrs[SUMS_ROWS]).reshape(-1)[0])
    if not 0 < B or sums_ds.shape != (-(-T // B),) or sums_ds.dtype != np.uint64:
        raise ValueError(f"its block checksums ({sums_ds.name}) are not one uint64 a block of {B} rows")
    return B


def _import_h5py():
    # imported when a store is opened, not with this module: the command line (its note on stores
    # without block checksums) and the reading of text or GSD configurations need no HDF5
    import h5py

    return h5py


def _check_scalar_names(g):
    """The ``scalars`` group holds exactly the names it lists (a damaged link name renames a column)."""
    try:
        listed = scalar_names_listed(g)
        names = set(h5py_keys(g))
    except ValueError as exc:
        raise StoreDamaged(damaged_message(g.file.filename, "scalars", f"is damaged: {exc}")) from None
    if listed is not None and names != listed:
        odd = sorted(map(str, names ^ listed))
        raise StoreDamaged(damaged_message(g.file.filename, "scalars", f"holds names it does not list, or lists "
                                           f"names it does not hold ({', '.join(odd[:3])}: a damaged name)"))


def h5py_keys(g):
    return list(_import_h5py().Group.keys(g))


def _make_classes():
    h5py = _import_h5py()

    class _Checked:
        def _get(self, name, lapl=None):
            return _checked(super()._get(name, lapl))

    class Group(_Checked, h5py.Group):
        """A group of a checked store: its datasets check their block checksums."""

    class File(_Checked, h5py.File):
        """A campaign store opened by a reader: every per-task dataset it gives checks the rows it
        reads against their block checksums (BlockMismatch), and the ``scalars`` group its names
        against their list (StoreDamaged). A store without block checksums reads as before."""

    class Dataset(h5py.Dataset):
        """A per-task dataset of a checked store: a read covers whole blocks, checked, then sliced."""

        def __getitem__(self, args, new_dtype=None):
            sums = self._sums()
            if sums is None or new_dtype is not None:
                return super().__getitem__(args) if new_dtype is None else super().__getitem__(args, new_dtype)
            T = self.shape[0] if self.shape else 0
            args = args if isinstance(args, tuple) else (args,)
            sel, rest = (args[0], args[1:]) if args else (Ellipsis, ())
            B = _block_rows(sums, T)
            if sel is Ellipsis:
                lo, hi, local = 0, T, args
            elif isinstance(sel, slice) and (sel.step or 1) > 0:
                start, stop, step = sel.indices(T)
                if stop <= start:
                    return super().__getitem__(args)
                lo, hi = start, stop
                local = None
            elif isinstance(sel, (int, np.integer)):
                i = int(sel) + (T if int(sel) < 0 else 0)
                if not 0 <= i < T:
                    return super().__getitem__(args)
                lo, hi, local = i, i + 1, None
            else:
                lo, hi, local = 0, T, args
            a, b = lo // B * B, min(T, -(-hi // B) * B)
            if T == 0:
                return super().__getitem__(args)
            data = super().__getitem__(slice(a, b))
            check_rows(sums, self.name.lstrip("/"), a, data, B)
            if local is not None:
                return data[local]
            if isinstance(sel, slice):
                return data[(slice(start - a, stop - a, step),) + rest]
            return data[(i - a,) + rest]

        def _sums(self):
            f = self.file
            if not has_sums(f):
                return None
            name = sums_name(self.name)
            if name not in f:
                raise BlockMismatch(self.name.lstrip("/"), 0, self.shape[0] if self.shape else 1,
                                    f"have no block checksums ({name} is missing: a damaged name?)")
            return f[name]

    return Group, File, Dataset


_CLASSES = None


def _classes():
    global _CLASSES
    if _CLASSES is None:
        _CLASSES = _make_classes()
    return _CLASSES


def _checked(obj):
    """``obj`` (an h5py object of a checked store) as a checked one."""
    h5py = _import_h5py()
    group, _, dataset = _classes()
    if type(obj) is h5py.Group:
        g = group(obj.id)
        if g.name == "/scalars":
            _check_scalar_names(g)
        return g
    if type(obj) is h5py.Dataset and obj.name.startswith(SUMMED):
        return dataset(obj.id, readonly=True)
    return obj


def open_checked(path, **kwargs):
    """Open the store ``path`` read-only (``locking=False``) for a reader, as a checked ``File``
    (``_make_classes``): its per-task datasets check the blocks they read against their checksums."""
    kwargs.setdefault("locking", False)
    f = _classes()[1](path, "r", **kwargs)
    if not has_sums(f):
        try:  # the command line names it (``unprotected_seen``) if it is a store of the current format
            _UNPROTECTED.append((str(path), _text(f.attrs.get("schema")), int(f.attrs.get("format_version", 1))))
        except Exception:  # noqa: BLE001 - unreadable attributes: its reader says what is wrong
            pass
    return f
