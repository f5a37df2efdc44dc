"""Reading disk configurations written by other programs (text, .npz, HDF5, GSD, extended XYZ).

The formats are documented in ``docs/CONFIG_FORMAT.md``. Every problem is raised as
``campaign.errors.UserError`` naming the file, the line (text, XYZ), array (npz/HDF5) or
frame (GSD, XYZ) where it applies, what was expected and what came.

``read_configuration(path, fmt="auto", group="/", frame=None) -> Configuration``

A box is the rectangle ``(Lx, Ly)`` or the tilted cell ``(Lx, Ly, xy)`` spanned by ``(Lx, 0)``
and ``(xy Ly, Ly)`` (HOOMD's tilt factor; ``kernels.space``). A tilt of exactly 0 is read as the
rectangle (``Configuration.box`` of shape (2,)); one beyond ``MAX_TILT`` is reduced by a change
of lattice vectors (``b -> b - k a``, the same lattice), with a note.

GSD (the ``gsd`` package, the ``export`` extra) and extended XYZ files may hold several
frames; ``frame`` picks one (negative counts from the end; None: the only one). A frame
written by ``campaign export`` carries the packing's float64 positions, radii and box
(GSD: the log chunks named below; XYZ: full-precision text), which are used, so that the
analysis gives the store's scalars exactly.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from campaign.errors import UserError, require
from campaign.plan.spec import CELLS
from campaign.storage.checksums import check_configuration
from campaign.storage.layout import stored_spec
from kernels.names import MAX_TILT  # a larger tilt is reduced on reading

FORMATS = ("auto", "text", "npz", "hdf5", "gsd", "xyz")
_HDF5_SUFFIXES = (".h5", ".hdf5", ".hdf", ".he5")
_XYZ_SUFFIXES = (".xyz", ".extxyz")
#: formats holding several frames (``--frame``)
FRAME_FORMATS = ("gsd", "xyz")

#: GSD log chunks (``frame.log`` keys) written by ``campaign export`` next to the hoomd schema's
#: float32 data: the float64 positions in the project's convention (``[0, L)``), radii and box
#: sides; and ``campaign/<column>`` for the packing's task columns and scalars.
GSD_POSITIONS64 = "particles/campaign/position64"
GSD_RADII64 = "particles/campaign/radius64"
GSD_BOX64 = "campaign/box64"
GSD_PREFIX = "campaign/"

#: How far outside the box a centre may lie, in box lengths, before the input is
#: taken for a unit or column mix-up (centres are folded back periodically).
OUTSIDE_LIMIT = 1.0


@dataclass(frozen=True)
class Configuration:
    positions: np.ndarray  # (n, 2) float64
    radii: np.ndarray  # (n,) float64
    box: np.ndarray  # (2,) float64 [Lx, Ly], or (3,) [Lx, Ly, xy] for a tilted cell
    species: np.ndarray | None  # (n,) int or None
    source: str
    exponent: float | None = None  # the pair potential's alpha, when the file says (campaign export)
    info: dict | None = None  # a frame's key-value data (GSD log campaign/*, XYZ header keys)
    frame: int | None = None  # the frame read (GSD, XYZ) and how many the file holds
    n_frames: int | None = None
    notes: tuple = ()  # what the reader wants the user to know (e.g. float32 positions)
    cell: str | None = None  # "fixed" or "shear" when the file says (campaign export: the variant's cell)


def tilt(box) -> float:
    """The tilt factor ``xy`` of a box: its third value, 0 for a rectangle ``(Lx, Ly)``."""
    return float(box[2]) if len(box) > 2 else 0.0


def fractional(positions, box) -> np.ndarray:
    """Fractional coordinates ``s`` of ``positions`` (n, 2) in the cell ``box``: ``r = (Lx s_x + xy Ly
    s_y, Ly s_y)``, so ``s_y = y / Ly`` and ``s_x = (x - xy y) / Lx``."""
    p = np.asarray(positions, dtype=np.float64)
    s = np.empty_like(p)
    s[:, 1] = p[:, 1] / box[1]
    s[:, 0] = (p[:, 0] - tilt(box) * p[:, 1]) / box[0]
    return s


def describe_box(box) -> str:
    """``1 x 1``, or ``1.02 x 0.98, tilt xy = 0.013`` for a tilted cell."""
    text = f"{box[0]:g} x {box[1]:g}"
    return text + (f", tilt xy = {box[2]:g}" if len(box) > 2 else "")


def _reduced_tilt(box, notes, where):
    """A (3,) box with ``xy`` 0 as the rectangle (2,); ``|xy| > MAX_TILT`` reduced by whole periods
    ``Lx / Ly`` (``b - k a``: the same lattice), noted."""
    if box.shape != (3,):
        return box
    if box[2] == 0.0:
        return box[:2].copy()
    if abs(box[2]) > MAX_TILT:
        k = round(box[2] * box[1] / box[0])
        xy = box[2] - k * box[0] / box[1]
        notes.append(f"{where}: tilt xy = {box[2]!r} reduced to {xy!r} (lattice vector b - {k} a: the same "
                     "periodic cell)")
        box = np.array([box[0], box[1], xy])
    return box


def detect_format(path: str) -> str:
    low = path.lower()
    if low.endswith(".npz"):
        return "npz"
    if low.endswith(_HDF5_SUFFIXES):
        return "hdf5"
    if low.endswith(".gsd"):
        return "gsd"
    if low.endswith(_XYZ_SUFFIXES):
        return "xyz"
    return "text"


def read_configuration(path, fmt: str = "auto", group: str = "/", frame: int | None = None) -> Configuration:
    path = os.fspath(path)
    if fmt not in FORMATS:
        raise UserError(f"--format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
    if not os.path.exists(path):
        raise UserError(f"{path}: no such file (expected a configuration: text, .npz, HDF5, .gsd or "
                        "extended XYZ)")
    if os.path.isdir(path):
        raise UserError(f"{path}: is a directory (expected a configuration file)")
    kind = detect_format(path) if fmt == "auto" else fmt
    if frame is not None and kind not in FRAME_FORMATS:
        raise UserError(f"--frame {frame}: picks a frame of a .gsd or extended XYZ file; {path} is read as "
                        f"{kind}, which holds one configuration")
    extra = {}
    if kind == "text":
        pos, rad, box, where = _read_text(path)
        species = None
    elif kind == "npz":
        pos, rad, box, species, where = _read_npz(path)
    elif kind == "hdf5":
        pos, rad, box, species, where, extra = _read_hdf5(path, group)
    elif kind == "gsd":
        pos, rad, box, species, where, extra = _read_gsd(path, frame)
    else:
        pos, rad, box, species, where, extra = _read_xyz(path, frame)
    notes = list(extra.pop("notes", ()))
    box = _reduced_tilt(box, notes, path)
    _check_geometry(path, pos, rad, box, where)
    return Configuration(pos, rad, box, species, path, notes=tuple(notes), **extra)


# ----------------------------------------------------------------------------- text


def _number(path, lineno, token, what):
    try:
        value = float(token)
    except ValueError:
        raise UserError(f"{path}, line {lineno}: expected a number for {what}, got {token!r}") from None
    if not math.isfinite(value):
        raise UserError(f"{path}, line {lineno}: expected a finite number for {what}, got {token!r}")
    return value


def _read_text(path):
    try:
        with open(path, encoding="utf-8") as fh:
            lines = fh.readlines()
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file (expected a box line, then 'x y radius' rows; "
                        "use the .npz or .h5 suffix or --format for binary files)") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    box = None
    box_line = None
    rows = []
    row_lines = []
    for lineno, raw in enumerate(lines, start=1):
        text = raw.split("#", 1)[0].strip()
        if not text:
            continue
        tokens = text.replace(",", " ").split()
        if box is None:
            if len(tokens) not in (1, 2, 3):
                raise UserError(
                    f"{path}, line {lineno}: expected the box line 'Lx Ly' (or 'L' for a square box, "
                    f"'Lx Ly xy' for a tilted cell), got {len(tokens)} columns")
            sides = [_number(path, lineno, t, "a box side" if i < 2 else "the tilt xy")
                     for i, t in enumerate(tokens)]
            if len(sides) == 1:
                sides = sides * 2
            if min(sides[:2]) <= 0:
                raise UserError(f"{path}, line {lineno}: expected positive box sides, got {' '.join(tokens[:2])}")
            box = sides
            box_line = lineno
            continue
        if len(tokens) != 3:
            raise UserError(
                f"{path}, line {lineno}: expected 3 columns 'x y radius', got {len(tokens)}")
        x = _number(path, lineno, tokens[0], "x")
        y = _number(path, lineno, tokens[1], "y")
        r = _number(path, lineno, tokens[2], "the radius")
        if r <= 0:
            raise UserError(f"{path}, line {lineno}: expected a positive radius, got {tokens[2]}")
        rows.append((x, y, r))
        row_lines.append(lineno)
    if box is None:
        raise UserError(f"{path}: empty (expected a box line 'Lx Ly', then one 'x y radius' row per disk)")
    arr = np.array(rows, dtype=np.float64).reshape(-1, 3)
    where = [f"line {k}" for k in row_lines]
    return arr[:, :2].copy(), arr[:, 2].copy(), np.array(box, dtype=np.float64), (where, f"line {box_line}")


# ----------------------------------------------------------------------------- npz / HDF5


def _check_arrays(path, pos, rad, box, species, rows=None):
    """Shapes and values of arrays read from npz/HDF5/GSD (rows named "array 'positions', row k",
    or ``rows(k)``)."""
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise UserError(f"{path}: array 'positions': expected shape (n, 2), got {pos.shape}")
    n = pos.shape[0]
    if n == 0:
        raise UserError(f"{path}: array 'positions' is empty; expected at least 2 disks")
    if rad.shape != (n,):
        raise UserError(f"{path}: array 'radii': expected shape ({n},) to match 'positions', got {rad.shape}")
    if box.shape == ():
        box = np.array([float(box), float(box)])
    if box.shape not in ((2,), (3,)):
        raise UserError(f"{path}: array 'box': expected two sides (Lx, Ly) or a tilted cell (Lx, Ly, xy), got "
                        f"shape {box.shape}")
    for name, arr in (("positions", pos), ("radii", rad)):
        bad = np.flatnonzero(~np.all(np.isfinite(arr.reshape(n, -1)), axis=1))
        if bad.size:
            raise UserError(f"{path}: array '{name}', row {bad[0]}: expected finite numbers, got NaN or inf")
    if not np.all(np.isfinite(box)):
        raise UserError(f"{path}: array 'box': expected finite sides, got {box.tolist()}")
    if not np.all(box[:2] > 0):
        raise UserError(f"{path}: array 'box': expected positive sides, got {box.tolist()}")
    bad = np.flatnonzero(rad <= 0)
    if bad.size:
        raise UserError(f"{path}: array 'radii', row {bad[0]}: expected a positive radius, got {rad[bad[0]]}")
    if species is not None:
        species = np.asarray(species)
        if species.shape != (n,) or not np.issubdtype(species.dtype, np.integer):
            raise UserError(f"{path}: array 'species': expected ({n},) integers, got shape {species.shape} "
                            f"dtype {species.dtype}")
    where = [rows(k) if rows else f"array 'positions', row {k}" for k in range(n)]
    return pos, rad, box, species, (where, "array 'box'")


def _read_npz(path):
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's
        raise UserError(f"{path}: not a readable .npz archive ({exc})") from None
    with data:
        missing = [k for k in ("positions", "radii", "box") if k not in data.files]
        if missing:
            raise UserError(f"{path}: expected arrays 'positions', 'radii', 'box'; missing {', '.join(missing)} "
                            f"(found: {', '.join(data.files) or 'none'})")
        try:
            pos = np.asarray(data["positions"])
            rad = np.asarray(data["radii"])
            box = np.asarray(data["box"])
            species = np.asarray(data["species"]) if "species" in data.files else None
        except ValueError as exc:
            raise UserError(f"{path}: cannot read arrays ({exc})") from None
    return _check_arrays(path, *_as_float(path, pos, rad, box), species)


def _as_float(path, pos, rad, box):
    out = []
    for name, arr in (("positions", pos), ("radii", rad), ("box", box)):
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise UserError(f"{path}: array '{name}': expected numbers, got dtype {arr.dtype}")
        out.append(arr.astype(np.float64))
    return out


def _read_hdf5(path, group):
    # imported here: reading text, npz, GSD or XYZ (campaign analyze, draw) needs no HDF5
    from campaign.storage.reader import open_store, read_failure

    with open_store(path, accept="hdf5") as fh:  # any HDF5 file; a store's blocks are checked
        try:
            if group not in fh:
                raise UserError(f"{path}: no group {group!r} (expected datasets positions, radii, box there)")
            g = fh[group]
            missing = [k for k in ("positions", "radii", "box") if k not in g]
            if missing:
                raise UserError(f"{path}: group {group!r}: expected datasets 'positions', 'radii', 'box'; "
                                f"missing {', '.join(missing)}")
            # a campaign store's configuration carries a checksum: StoreDamaged if its bytes changed
            got = check_configuration(g, path, group.strip("/") or "/",
                                      ("positions", "radii", "box", "species"))
        except UserError:
            raise
        except Exception as exc:  # noqa: BLE001 - read_failure says which failures are the file's
            err = read_failure(path, exc, fh, [group.strip("/")], what=f"group {group!r}")
            if err is None:
                raise
            raise err from None
        pos = np.asarray(got["positions"])
        rad = np.asarray(got["radii"])
        box = np.asarray(got["box"])
        species = np.asarray(got["species"]) if "species" in got else None
        cell = _store_cell(fh, group)
    return (*_check_arrays(path, *_as_float(path, pos, rad, box), species), {"cell": cell})


def _store_cell(fh, group):
    """The cell of a campaign store's packing read in place (``/configurations/<task id>``): its
    variant's, from the spec stored in the file; None for any other HDF5 group."""
    parts = [p for p in group.split("/") if p]
    if len(parts) != 2 or parts[0] != "configurations":
        return None
    try:
        spec = stored_spec(fh)
        if spec is None:
            return None
        cells = {v.name: dict(v.protocol).get("cell", "fixed") for v in spec.variants}
        if set(cells.values()) == {"fixed"}:
            return "fixed"
        ids, variants, want = fh["tasks/id"], fh["tasks/variant"], parts[1].encode()
        for lo in range(0, ids.shape[0], 65536):
            hit = np.flatnonzero(ids[lo:lo + 65536] == want)
            if hit.size:
                return cells.get(variants[lo + hit[0]].decode(), None)
    except Exception:  # noqa: BLE001 - a foreign or damaged store: the cell is not known
        return None
    return None


# ----------------------------------------------------------------------------- frames


def _pick_frame(path, frame, n):
    """The index of the frame to read among ``n``; ``frame`` None means the only one."""
    if n == 0:
        raise UserError(f"{path}: holds no frames")
    if frame is None:
        if n == 1:
            return 0
        raise UserError(f"{path}: holds {n} frames; choose one with --frame K (0 to {n - 1}, or -1 for "
                        "the last)")
    k = frame + n if frame < 0 else frame
    if not 0 <= k < n:
        raise UserError(f"--frame {frame}: {path} holds {n} frame(s), 0 to {n - 1} (negative K counts from "
                        "the end)")
    return k


def _log_value(value):
    """A GSD log value as a Python value: a one-element array as its number, a char array
    (int8/uint8, HOOMD's and OVITO's strings) or a string chunk as ``str``."""
    if isinstance(value, (str, bytes)):
        return value.decode("utf-8", "replace") if isinstance(value, bytes) else value
    a = np.asarray(value)
    if a.dtype.kind in ("U", "O", "S"):
        flat = a.ravel().tolist()
        text = [x.decode("utf-8", "replace") if isinstance(x, bytes) else str(x) for x in flat]
        return text[0] if len(text) == 1 else text
    if a.dtype in (np.int8, np.uint8) and a.ndim == 1:  # campaign export writes numbers as int64/float64
        return a.astype(np.uint8).tobytes().split(b"\0", 1)[0].decode("utf-8", "replace")
    if a.size == 1:
        return a.reshape(()).item()
    return a


def _read_gsd(path, frame):
    hoomd = require("gsd.hoomd", "export", f"reading {path} (a GSD file)")
    try:
        traj = hoomd.open(path, "r")
    except Exception as exc:  # noqa: BLE001 - whatever gsd says of a file it cannot read
        raise UserError(f"{path}: not a readable GSD file of the hoomd schema ({exc})") from None
    with traj:
        n_frames = len(traj)
        k = _pick_frame(path, frame, n_frames)
        try:
            fr = traj[k]
        except Exception as exc:  # noqa: BLE001
            raise UserError(f"{path}, frame {k}: cannot read the frame ({exc})") from None
    where = f"{path}, frame {k}"
    dims = int(fr.configuration.dimensions)
    if dims != 2:
        raise UserError(f"{where}: a {dims}-dimensional frame (configuration/dimensions); expected a 2D "
                        "configuration of disks")
    log = dict(fr.log or {})
    notes = []
    box6 = np.asarray(fr.configuration.box, dtype=np.float64).ravel()
    n = int(fr.particles.N)
    if GSD_POSITIONS64 in log and GSD_RADII64 in log:
        pos = np.asarray(log[GSD_POSITIONS64])
        rad = np.asarray(log[GSD_RADII64])
        box = np.asarray(log[GSD_BOX64]) if GSD_BOX64 in log else box6[[0, 1, 3] if box6[3] else [0, 1]]
        if pos.shape[:1] != (n,):
            raise UserError(f"{where}: log chunk {GSD_POSITIONS64!r} has {pos.shape[:1]} rows, the frame "
                            f"{n} particles")
    else:
        if box6.size != 6 or np.any(box6[4:] != 0):
            raise UserError(f"{where}: configuration/box {box6.tolist()} is tilted out of the plane; expected "
                            "a 2D box [Lx, Ly, Lz, xy, 0, 0]")
        p3 = np.asarray(fr.particles.position, dtype=np.float64).reshape(n, -1)
        if p3.shape[1] == 3 and n and np.any(p3[:, 2] != p3[0, 2]):
            raise UserError(f"{where}: particles at different z; expected a 2D configuration")
        box = box6[:2]
        if box6[3] == 0:
            pos = p3[:, :2] + 0.5 * box  # HOOMD's box is centred on the origin: [-L/2, L/2)
        else:  # a tilted box, centred too: r = (Lx s_x + xy Ly s_y, Ly s_y), s in [-1/2, 1/2)
            box = box6[[0, 1, 3]]
            pos = p3[:, :2] + 0.5 * np.array([box[0] + box[2] * box[1], box[1]])
        rad = 0.5 * np.asarray(fr.particles.diameter, dtype=np.float64)
        if np.asarray(fr.particles.position).dtype == np.float32:
            notes.append(f"{where}: positions and diameters are GSD's float32 (the frame has no float64 copy "
                         f"{GSD_POSITIONS64!r}); near jamming float32 rounding can change the contact network")
    species = np.asarray(fr.particles.typeid).astype(np.int64)
    if species.shape != (n,):
        species = None
    pos, rad, box, species, geom = _check_arrays(
        where, *_as_float(where, pos, rad, box), species, rows=lambda i: f"frame {k}, particle {i}")
    info = {key[len(GSD_PREFIX):]: _log_value(v) for key, v in log.items()
            if key.startswith(GSD_PREFIX) and key != GSD_BOX64}
    exponent = info.get("exponent")
    extra = dict(exponent=float(exponent) if isinstance(exponent, (int, float)) else None, info=info,
                 frame=k, n_frames=n_frames, notes=tuple(notes), cell=_cell(info.get("cell")))
    return pos, rad, box, species, geom, extra


def _cell(value):
    """The cell a file names (``campaign/cell``, ``cell=``), if it is one of ``CELLS``."""
    return value if isinstance(value, str) and value in CELLS else None


# ----------------------------------------------------------------------------- extended XYZ

#: column names (lower case) of the extended XYZ ``Properties`` that the reader understands
_XYZ_POS = ("pos", "positions")
_XYZ_RADIUS = ("radius", "radii")
_XYZ_DIAMETER = ("diameter", "diameters")
_XYZ_TYPE = ("type", "species", "element", "atom_types")


def parse_xyz_header(text, where="header", quoted=None):
    """The key=value pairs of an extended XYZ comment line, as strings (quotes removed; a key
    without a value is ``True``). Values may be bare, "double quoted" (with \" inside), or in
    {braces} or [brackets]. ``quoted``: a set that receives the keys whose value was quoted."""
    out = {}
    i, n = 0, len(text)
    while True:
        while i < n and text[i].isspace():
            i += 1
        if i >= n:
            return out
        start = i
        while i < n and not text[i].isspace() and text[i] != "=":
            i += 1
        key = text[start:i]
        if not key:
            raise UserError(f"{where}: expected a key before '=' at column {i + 1}")
        j = i
        while j < n and text[j].isspace():
            j += 1
        if j >= n or text[j] != "=":
            out[key] = True
            continue
        i = j + 1
        while i < n and text[i].isspace():
            i += 1
        if i < n and text[i] == '"':
            i += 1
            chars = []
            while i < n and text[i] != '"':
                if text[i] == "\\" and i + 1 < n:
                    i += 1
                chars.append(text[i])
                i += 1
            if i >= n:
                raise UserError(f"{where}: the value of {key!r} opens a quote that is never closed")
            value = "".join(chars)
            i += 1
            if quoted is not None:
                quoted.add(key)
        elif i < n and text[i] in "{[":
            close = "}" if text[i] == "{" else "]"
            end = text.find(close, i)
            if end < 0:
                raise UserError(f"{where}: the value of {key!r} opens {text[i]!r} that is never closed")
            value = text[i + 1:end]
            i = end + 1
        else:
            start = i
            while i < n and not text[i].isspace():
                i += 1
            value = text[start:i]
        out[key] = value
    return out


def _xyz_scalar(key, value, quoted=()):
    """A header value as int, float or str (``id`` and quoted text stay strings)."""
    if value is True or key == "id" or key in quoted:
        return value
    for cast in (int, float):
        try:
            return cast(value)
        except ValueError:
            pass
    return value


def _xyz_bool(token):
    low = token.lower()
    if low in ("t", "true", "1"):
        return True
    if low in ("f", "false", "0"):
        return False
    return None


def _xyz_columns(where, header):
    """(column layout, total columns): name -> (first column, count, type) from ``Properties``."""
    props = next((v for k, v in header.items() if k.lower() == "properties"), None)
    if props is None or props is True:
        raise UserError(f"{where}: no Properties=... in the comment line; expected an extended XYZ header "
                        "with pos and a radius (or diameter) column, e.g. "
                        "Properties=type:S:1:pos:R:3:radius:R:1")
    parts = props.split(":")
    if len(parts) % 3:
        raise UserError(f"{where}: Properties={props}: expected name:type:columns triples")
    cols, at = {}, 0
    for name, typ, count in zip(parts[0::3], parts[1::3], parts[2::3]):
        if typ.upper() not in ("S", "R", "I", "L"):
            raise UserError(f"{where}: Properties: column {name!r} has type {typ!r}; expected S, R, I or L")
        try:
            m = int(count)
        except ValueError:
            m = 0
        if m < 1:
            raise UserError(f"{where}: Properties: column {name!r} has {count!r} columns; expected a "
                            "positive integer")
        cols[name.lower()] = (at, m, typ.upper())
        at += m
    return cols, at


def _xyz_box(where, header):
    """The box of a ``Lattice``: ``(Lx, Ly)``, or ``(Lx, Ly, xy)`` when its second vector is tilted
    (``xy Ly, Ly, 0``); the comment line's ``gamma`` (``campaign export``'s float64 tilt) is that
    ``xy`` when it agrees with the lattice to rounding."""
    lat = next((v for k, v in header.items() if k.lower() == "lattice"), None)
    if lat is None or lat is True:
        raise UserError(f"{where}: no Lattice=\"...\" in the comment line; expected the periodic box "
                        "Lattice=\"Lx 0 0 0 Ly 0 0 0 Lz\"")
    try:
        v = [float(x) for x in lat.replace(",", " ").split()]
    except ValueError:
        v = []
    if len(v) != 9 or not all(math.isfinite(x) for x in v):
        raise UserError(f"{where}: Lattice=\"{lat}\": expected 9 finite numbers (three cell vectors)")
    a, b = v[0:3], v[3:6]
    if a[1] != 0 or a[2] != 0 or b[2] != 0:
        raise UserError(f"{where}: Lattice=\"{lat}\": expected its first vector along x and its second in the "
                        "x-y plane (\"Lx 0 0 0 Ly 0 0 0 Lz\", or \"Lx 0 0 xy*Ly Ly 0 0 0 Lz\" for a tilted cell)")
    if a[0] <= 0 or b[1] <= 0:
        raise UserError(f"{where}: Lattice=\"{lat}\": expected positive box sides, got {a[0]!r} and {b[1]!r}")
    pbc = next((v for k, v in header.items() if k.lower() == "pbc"), None)
    if isinstance(pbc, str):
        flags = [_xyz_bool(t) for t in pbc.split()]
        if len(flags) < 2 or None in flags:
            raise UserError(f"{where}: pbc=\"{pbc}\": expected T or F for each direction")
        if not (flags[0] and flags[1]):
            raise UserError(f"{where}: pbc=\"{pbc}\": the box is not periodic in x and y; the analysis "
                            "needs a periodic box")
    if b[0] == 0:
        return np.array([a[0], b[1]], dtype=np.float64)
    xy = b[0] / b[1]
    exact = _xyz_scalar("gamma", header.get("gamma", ""))
    if isinstance(exact, float) and math.isfinite(exact) and abs(exact * b[1] - b[0]) <= 1e-12 * max(a[0], b[1]):
        xy = exact
    return np.array([a[0], b[1], xy], dtype=np.float64)


def _xyz_count(path, lineno, line):
    tokens = line.split()
    if len(tokens) == 1:
        try:
            n = int(tokens[0])
        except ValueError:
            n = -1
        if n >= 0:
            return n
    hint = " (a plain text configuration 'Lx Ly' then 'x y radius' rows? use --format text)" if lineno == 1 else ""
    raise UserError(f"{path}, line {lineno}: expected the number of particles of an extended XYZ frame, got "
                    f"{line.strip()[:80]!r}{hint}")


def _xyz_frames(fh, path):
    """Yield ``(first line number, n, comment line, reader)`` per frame; ``reader()`` returns the
    frame's n particle lines (call it, or the lines are skipped)."""
    lineno = 0
    while True:
        line = fh.readline()
        lineno += 1
        if not line:
            return
        if not line.strip():
            rest = fh.read()
            if rest.strip():
                raise UserError(f"{path}, line {lineno}: a blank line where a frame's particle count was "
                                "expected")
            return
        start = lineno
        n = _xyz_count(path, lineno, line)
        comment = fh.readline()
        lineno += 1
        if not comment:
            raise UserError(f"{path}, line {lineno}: the file ends before the comment line of the frame "
                            f"at line {start}")
        lines = []
        for _ in range(n):
            text = fh.readline()
            lineno += 1
            if not text:
                raise UserError(f"{path}, line {lineno}: the file ends inside the frame at line {start} "
                                f"({len(lines)} of {n} particle lines)")
            lines.append(text)
        yield start, n, comment.rstrip("\r\n"), lines


def _open_text(path):
    try:
        return open(path, encoding="utf-8")
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None


def _read_xyz(path, frame):
    try:
        if frame is not None and frame >= 0:  # read up to the frame asked for
            seen = 0
            with _open_text(path) as fh:
                for j, fr in enumerate(_xyz_frames(fh, path)):
                    seen = j + 1
                    if j == frame:
                        return _parse_xyz_frame(path, frame, None, *fr)
            _pick_frame(path, frame, seen)  # out of range: says how many frames there are
        first, total = None, 0  # the only frame, or one counted from the end: count them all
        with _open_text(path) as fh:
            for fr in _xyz_frames(fh, path):
                first = first or fr
                total += 1
        k = _pick_frame(path, frame, total)
        chosen = first
        if k:
            with _open_text(path) as fh:
                for j, fr in enumerate(_xyz_frames(fh, path)):
                    if j == k:
                        chosen = fr
                        break
        return _parse_xyz_frame(path, k, total, *chosen)
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file (expected extended XYZ; use --format for other "
                        "formats)") from None


def _parse_xyz_frame(path, k, n_frames, start, n, comment, lines):
    where = f"{path}, line {start + 1}"
    quoted = set()
    header = parse_xyz_header(comment, where, quoted)
    box = _xyz_box(where, header)
    cols, width = _xyz_columns(where, header)
    pos_col = next((cols[c] for c in _XYZ_POS if c in cols), None)
    if pos_col is None or pos_col[2] != "R" or pos_col[1] not in (2, 3):
        raise UserError(f"{where}: Properties needs a position column pos:R:3 (or pos:R:2)")
    scale, rad_col = 1.0, next((cols[c] for c in _XYZ_RADIUS if c in cols), None)
    if rad_col is None:
        scale, rad_col = 0.5, next((cols[c] for c in _XYZ_DIAMETER if c in cols), None)
    if rad_col is None or rad_col[2] != "R" or rad_col[1] != 1:
        raise UserError(f"{where}: Properties has no radius:R:1 (or diameter:R:1) column; the analysis needs "
                        "each disk's size")
    type_col = next((cols[c] for c in _XYZ_TYPE if c in cols and cols[c][1] == 1), None)
    pos = np.empty((n, pos_col[1]), dtype=np.float64)
    rad = np.empty(n, dtype=np.float64)
    labels = []
    for i, raw in enumerate(lines):
        lineno = start + 2 + i
        tokens = raw.split()
        if len(tokens) != width:
            raise UserError(f"{path}, line {lineno}: expected {width} columns (Properties of line {start + 1}), "
                            f"got {len(tokens)}")
        a, m, _ = pos_col
        for c in range(m):
            pos[i, c] = _number(path, lineno, tokens[a + c], "xyz"[c])
        rad[i] = _number(path, lineno, tokens[rad_col[0]], "the radius" if scale == 1.0 else "the diameter")
        if type_col is not None:
            labels.append(tokens[type_col[0]])
    rad *= scale
    bad = np.flatnonzero(rad <= 0)
    if bad.size:
        raise UserError(f"{path}, line {start + 2 + bad[0]}: expected a positive radius, got {rad[bad[0]]!r}")
    if pos.shape[1] == 3 and n and np.any(pos[:, 2] != pos[0, 2]):
        raise UserError(f"{where}: particles at different z; expected a 2D configuration")
    species = None
    if type_col is not None:
        if type_col[2] == "I":
            try:
                species = np.array([int(x) for x in labels], dtype=np.int64)
            except ValueError:
                k_bad = next(i for i, x in enumerate(labels) if not x.lstrip("+-").isdigit())
                raise UserError(f"{path}, line {start + 2 + k_bad}: expected an integer type, got "
                                f"{labels[k_bad]!r}") from None
        else:
            codes = {}
            species = np.array([codes.setdefault(x, len(codes)) for x in labels], dtype=np.int64)
    info = {key: _xyz_scalar(key, v, quoted) for key, v in header.items()
            if key.lower() not in ("lattice", "properties", "pbc")}
    rows = [f"line {start + 2 + i}" for i in range(n)]
    exponent = info.get("exponent")
    extra = dict(exponent=float(exponent) if isinstance(exponent, (int, float)) and not isinstance(exponent, bool)
                 else None, info=info, frame=k, n_frames=n_frames, cell=_cell(info.get("cell")))
    return np.ascontiguousarray(pos[:, :2]), rad, box, species, (rows, f"line {start + 1}"), extra


# ----------------------------------------------------------------------------- geometry


def _check_geometry(path, pos, rad, box, where):
    rows, box_where = where
    n = pos.shape[0]
    if n < 2:
        raise UserError(f"{path}: expected at least 2 disks, got {n}")
    if box.shape == (2,):
        with np.errstate(over="ignore"):  # a box near the float64 limit: the bounds go to inf, harmlessly
            lo = -OUTSIDE_LIMIT * box
            hi = (1.0 + OUTSIDE_LIMIT) * box
        outside = np.flatnonzero(np.any((pos < lo) | (pos >= hi), axis=1))
        cell = f"the box [0, {box[0]:g}) x [0, {box[1]:g})"
    else:  # the same bound on the fractional coordinates of the tilted cell
        with np.errstate(over="ignore", invalid="ignore"):
            s = fractional(pos, box)
        outside = np.flatnonzero(np.any((s < -OUTSIDE_LIMIT) | (s >= 1.0 + OUTSIDE_LIMIT) | ~np.isfinite(s), axis=1))
        cell = f"the tilted cell ({box[0]:g} x {box[1]:g}, xy = {box[2]:g})"
    if outside.size:
        k = outside[0]
        raise UserError(
            f"{path}, {rows[k]}: position ({pos[k, 0]:g}, {pos[k, 1]:g}) is far outside {cell} (expected "
            f"centres within one box length of it; {outside.size} such row(s))")
    if 4.0 * rad.max() >= box[:2].min():
        k = int(np.argmax(rad))
        raise UserError(
            f"{path}, {rows[k]}: radius {rad[k]:g} is too large for the box ({box_where}: "
            f"{box[0]:g} x {box[1]:g}); expected every diameter below half the smaller box side")
