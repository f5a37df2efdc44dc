"""Reading disk configurations written by other programs (text, .npz, HDF5).

The formats are documented in ``docs/CONFIG_FORMAT.md``. Every problem is raised as
``campaign.errors.UserError`` naming the file, the line (text) or array (npz/HDF5)
where it applies, what was expected and what came.

``read_configuration(path, fmt="auto", group="/") -> Configuration``
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from campaign.errors import UserError

FORMATS = ("auto", "text", "npz", "hdf5")
_HDF5_SUFFIXES = (".h5", ".hdf5", ".hdf", ".he5")

#: How far outside the box a centre may lie, in box lengths, before the input is
#: taken for a unit or column mix-up (centres are folded back periodically).
OUTSIDE_LIMIT = 1.0


@dataclass(frozen=True)
class Configuration:
    positions: np.ndarray  # (n, 2) float64
    radii: np.ndarray  # (n,) float64
    box: np.ndarray  # (2,) float64
    species: np.ndarray | None  # (n,) int or None
    source: str


def detect_format(path: str) -> str:
    low = path.lower()
    if low.endswith(".npz"):
        return "npz"
    if low.endswith(_HDF5_SUFFIXES):
        return "hdf5"
    return "text"


def read_configuration(path, fmt: str = "auto", group: str = "/") -> Configuration:
    path = os.fspath(path)
    if fmt not in FORMATS:
        raise UserError(f"--format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
    if not os.path.exists(path):
        raise UserError(f"{path}: no such file (expected a configuration: text, .npz or HDF5)")
    if os.path.isdir(path):
        raise UserError(f"{path}: is a directory (expected a configuration file)")
    kind = detect_format(path) if fmt == "auto" else fmt
    if kind == "text":
        pos, rad, box, where = _read_text(path)
        species = None
    elif kind == "npz":
        pos, rad, box, species, where = _read_npz(path)
    else:
        pos, rad, box, species, where = _read_hdf5(path, group)
    _check_geometry(path, pos, rad, box, where)
    return Configuration(pos, rad, box, species, path)


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
            if len(tokens) not in (1, 2):
                raise UserError(
                    f"{path}, line {lineno}: expected the box line 'Lx Ly' (or 'L' for a square box), "
                    f"got {len(tokens)} columns")
            sides = [_number(path, lineno, t, "a box side") for t in tokens]
            if len(sides) == 1:
                sides = sides * 2
            if min(sides) <= 0:
                raise UserError(f"{path}, line {lineno}: expected positive box sides, got {' '.join(tokens)}")
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


def _check_arrays(path, pos, rad, box, species):
    """Shapes and values of arrays read from npz/HDF5 (rows named 'positions[k]')."""
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise UserError(f"{path}: array 'positions': expected shape (n, 2), got {pos.shape}")
    n = pos.shape[0]
    if n == 0:
        raise UserError(f"{path}: array 'positions' is empty; expected at least 2 disks")
    if rad.shape != (n,):
        raise UserError(f"{path}: array 'radii': expected shape ({n},) to match 'positions', got {rad.shape}")
    if box.shape == ():
        box = np.array([float(box), float(box)])
    if box.shape != (2,):
        raise UserError(f"{path}: array 'box': expected two sides (Lx, Ly), got shape {box.shape}")
    for name, arr in (("positions", pos), ("radii", rad)):
        bad = np.flatnonzero(~np.all(np.isfinite(arr.reshape(n, -1)), axis=1))
        if bad.size:
            raise UserError(f"{path}: array '{name}', row {bad[0]}: expected finite numbers, got NaN or inf")
    if not np.all(np.isfinite(box)):
        raise UserError(f"{path}: array 'box': expected finite sides, got {box.tolist()}")
    if not np.all(box > 0):
        raise UserError(f"{path}: array 'box': expected positive sides, got {box.tolist()}")
    bad = np.flatnonzero(rad <= 0)
    if bad.size:
        raise UserError(f"{path}: array 'radii', row {bad[0]}: expected a positive radius, got {rad[bad[0]]}")
    if species is not None:
        species = np.asarray(species)
        if species.shape != (n,) or not np.issubdtype(species.dtype, np.integer):
            raise UserError(f"{path}: array 'species': expected ({n},) integers, got shape {species.shape} "
                            f"dtype {species.dtype}")
    where = [f"array 'positions', row {k}" for k in range(n)]
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
    try:
        import h5py
    except ImportError:  # pragma: no cover - h5py is a dependency
        raise UserError(f"{path}: reading HDF5 needs h5py") from None
    try:
        fh = h5py.File(path, "r", locking=False)
    except OSError as exc:
        raise UserError(f"{path}: not a readable HDF5 file ({exc})") from None
    with fh:
        if group not in fh:
            raise UserError(f"{path}: no group {group!r} (expected datasets positions, radii, box there)")
        g = fh[group]
        missing = [k for k in ("positions", "radii", "box") if k not in g]
        if missing:
            raise UserError(f"{path}: group {group!r}: expected datasets 'positions', 'radii', 'box'; "
                            f"missing {', '.join(missing)}")
        pos = np.asarray(g["positions"][()])
        rad = np.asarray(g["radii"][()])
        box = np.asarray(g["box"][()])
        species = np.asarray(g["species"][()]) if "species" in g else None
    return _check_arrays(path, *_as_float(path, pos, rad, box), species)


# ----------------------------------------------------------------------------- geometry


def _check_geometry(path, pos, rad, box, where):
    rows, box_where = where
    n = pos.shape[0]
    if n < 2:
        raise UserError(f"{path}: expected at least 2 disks, got {n}")
    with np.errstate(over="ignore"):  # a box near the float64 limit: the bounds go to inf, harmlessly
        lo = -OUTSIDE_LIMIT * box
        hi = (1.0 + OUTSIDE_LIMIT) * box
    outside = np.flatnonzero(np.any((pos < lo) | (pos >= hi), axis=1))
    if outside.size:
        k = outside[0]
        raise UserError(
            f"{path}, {rows[k]}: position ({pos[k, 0]:g}, {pos[k, 1]:g}) is far outside the box "
            f"[0, {box[0]:g}) x [0, {box[1]:g}) (expected centres within one box length of it; "
            f"{outside.size} such row(s))")
    if 4.0 * rad.max() >= box.min():
        k = int(np.argmax(rad))
        raise UserError(
            f"{path}, {rows[k]}: radius {rad[k]:g} is too large for the box ({box_where}: "
            f"{box[0]:g} x {box[1]:g}); expected every diameter below half the smaller box side")
