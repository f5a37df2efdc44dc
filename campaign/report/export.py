"""``campaign export``: a store's packings as CSV, Parquet, GSD or extended XYZ.

``export(path, out, fmt, variant=None, good=True) -> dict`` writes ``out`` and returns what it
wrote. The rows are those of ``campaign.read_packings`` (``campaign.report.frames.Packings``, read in
blocks, histograms never read), in store order:

* ``csv``, ``parquet``: one row per packing, columns ``row``, ``id``, ``variant``, ``N``, ``E``,
  ``seed``, ``status`` and every stored scalar, numbers at full precision.
* ``gsd`` (the hoomd schema of the ``gsd`` package), ``xyz`` (extended XYZ): one frame per
  packing that kept its configuration: box, positions, diameters (radii), species as particle
  types, and the packing's columns with the frame. GSD holds positions as float32, too coarse
  near jamming, so every frame also carries the float64 positions, radii and box sides in its
  log (``campaign.storage.configio.GSD_POSITIONS64`` ...); extended XYZ is text at full precision.
  A tilted cell (a stored box ``[Lx, Ly, xy]``, ``cell: shear``) is HOOMD's tilted box
  ``[Lx, Ly, 1, xy, 0, 0]`` and the extended XYZ ``Lattice="Lx 0 0 xy*Ly Ly 0 0 0 1"``; the float64
  box ``campaign/box64`` is the stored box as it is (``[Lx, Ly]`` or ``[Lx, Ly, xy]``), and every
  frame names its variant's cell (``campaign/cell``, ``cell="fixed"`` or ``"shear"``) for
  ``campaign analyze``.

The layout of each format is documented in docs/STORE.md ("Export formats"). The file is
written under a temporary name beside ``out`` and renamed into place when complete.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from campaign.storage.configio import GSD_BOX64, GSD_POSITIONS64, GSD_PREFIX, GSD_RADII64, fractional, tilt
from campaign.errors import UserError, require
from campaign.storage.layout import stored_spec

FORMATS = ("csv", "parquet", "gsd", "xyz")
SUFFIXES = {".csv": "csv", ".parquet": "parquet", ".pq": "parquet", ".gsd": "gsd", ".xyz": "xyz",
            ".extxyz": "xyz"}
EXTENSION = {"csv": ".csv", "parquet": ".parquet", "gsd": ".gsd", "xyz": ".xyz"}
#: the needs of each format: (module, what it is for)
NEEDS = {"parquet": "pyarrow", "gsd": "gsd.hoomd"}
KEEP_CONFIGURATIONS = (
    "a spec keeps them with 'store: {configurations: true}'; add it to the spec and run it into a new "
    "file (campaign run SPEC --out NEW.h5: packings are pure functions of the spec, so the same packings "
    "come out; the spec is in the store's 'spec_yaml' attribute)")
#: the extended XYZ column layout written for every frame
XYZ_PROPERTIES = "type:S:1:pos:R:3:radius:R:1"


def format_of(fmt, out) -> str:
    """The format asked for (``--format``), else the one ``out``'s suffix names."""
    suffix_fmt = SUFFIXES.get(Path(out).suffix.lower()) if out else None
    if fmt is None:
        if suffix_fmt is None:
            raise UserError("give --format (csv, parquet, gsd or xyz), or an --out file whose suffix says it "
                            f"({', '.join(sorted(SUFFIXES))})")
        return suffix_fmt
    if fmt not in FORMATS:
        raise UserError(f"--format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
    if suffix_fmt is not None and suffix_fmt != fmt:
        raise UserError(f"--out {out}: its suffix says {suffix_fmt}, but --format is {fmt}; give a file name "
                        f"ending in {EXTENSION[fmt]}")
    return fmt


def require_format(fmt):
    """Import what the format needs (MissingExtra, exit 2, naming the extra, if it is missing)."""
    if fmt in NEEDS:
        return require(NEEDS[fmt], "export", f"--format {fmt}")
    return None


def export(path, out, fmt, *, variant=None, good=True) -> dict:
    """Write the selected packings of the store ``path`` to ``out`` in ``fmt`` (see the module
    docstring). Returns ``{"format", "out", "packings", "without_configuration"}``."""
    from campaign.report.frames import Packings

    if fmt not in FORMATS:
        raise UserError(f"--format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
    module = require_format(fmt)
    out = Path(out)
    if out.is_dir():
        raise UserError(f"--out {out}: is a directory; expected a file name")
    if not out.parent.is_dir():
        raise UserError(f"--out {out}: no directory {str(out.parent)!r}")
    if out.exists() and os.path.exists(path) and os.path.samefile(out, path):
        raise UserError(f"--out {out}: is the campaign store itself; give another file name")
    with Packings(path, variant, good) as pk:
        if fmt in ("gsd", "xyz") and pk.n_configurations == 0:
            raise UserError(f"{pk.path}: the store holds no configurations, so there is nothing to write as "
                            f"{fmt}; {KEEP_CONFIGURATIONS}. --format csv or parquet exports the scalars")
        tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
        try:
            writer = {"csv": _write_csv, "parquet": _write_parquet, "gsd": _write_gsd, "xyz": _write_xyz}[fmt]
            counts = writer(pk, tmp, module)
            if fmt in ("gsd", "xyz") and counts["packings"] == 0:
                raise UserError(f"{pk.path}: none of the {counts['without_configuration']} selected packing(s) "
                                f"kept its configuration; {KEEP_CONFIGURATIONS}")
            os.replace(tmp, out)
        finally:
            if tmp.exists():
                tmp.unlink()
    return {"format": fmt, "out": str(out), **counts}


# ----------------------------------------------------------------------------- tables


def _write_csv(pk, tmp, _module):
    import csv

    names = [n for n, _ in pk.columns]
    count = 0
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(names)
        for b in pk.blocks():
            # Python floats are written as repr(): the shortest text that reads back bit for bit
            w.writerows(zip(*(b[n].tolist() for n in names)))
            count += len(b["row"])
    return {"packings": count, "without_configuration": 0}


def _provenance(pk) -> dict:
    return {"source": pk.path, "name": str(pk.attrs.get("name", "")),
            "spec_hash": str(pk.attrs.get("spec_hash", "")), "good": pk.good,
            "rows": "the packings the reducer uses" if pk.good else "every finished packing"}


def _write_parquet(pk, tmp, pa):
    import json

    import pyarrow.parquet as pq

    fields = [(n, pa.string() if dt == np.dtype(object) else pa.from_numpy_dtype(dt)) for n, dt in pk.columns]
    schema = pa.schema(fields, metadata={"campaign": json.dumps(_provenance(pk))})
    count = 0
    with pq.ParquetWriter(tmp, schema) as w:
        for b in pk.blocks():
            w.write_table(pa.Table.from_arrays([pa.array(b[n], type=t) for n, t in fields], schema=schema))
            count += len(b["row"])
    return {"packings": count, "without_configuration": 0}


# ----------------------------------------------------------------------------- frames


def variant_types(attrs) -> dict:
    """``{variant: (species names, exponent, cell)}`` from the spec stored in the file (``cell``:
    the protocol's, "fixed" or "shear"); a spec this version cannot read gives the paper's system
    (A, B; exponent 2) in a fixed cell."""
    from campaign.plan.spec import System

    def describe(system, protocol=()):
        names = ("A",) if system.sizes is not None else tuple(s.name for s in system.species)
        return names, float(system.exponent), dict(protocol).get("cell", "fixed")

    spec = stored_spec(attrs)
    out = {} if spec is None else {v.name: describe(v.system, v.protocol) for v in spec.variants}
    out.setdefault("default", describe(System()))
    return out


def _types(names, species):
    """Type names covering every species index (names the spec lacks are T<k>)."""
    top = int(species.max()) + 1 if species.size else 0
    return list(names) + [f"T{k}" for k in range(len(names), top)]


def _frames(pk):
    """``(k, columns of the packing, configuration, type names, exponent, cell)`` per frame, and
    the count of selected packings without a configuration (the last item yielded: an int)."""
    systems = variant_types(pk.attrs)
    names = [n for n, _ in pk.columns]
    k = missing = 0
    for b in pk.blocks():
        for i in range(len(b["row"])):
            cols = {n: b[n][i] for n in names}
            conf = pk.configuration(cols["id"])
            if conf is None:
                missing += 1
                continue
            types, alpha, cell = systems.get(str(cols["variant"]), systems["default"])
            yield k, cols, conf, _types(types, conf["species"]), alpha, cell
            k += 1
    yield missing


def hoomd_positions(positions, box) -> np.ndarray:
    """(n, 3) float32 positions in HOOMD's convention: the box centred on the origin, every
    coordinate in [-L/2, L/2) after rounding to float32, z = 0. A tilted cell ``[Lx, Ly, xy]``:
    ``r = (Lx s_x + xy Ly s_y, Ly s_y)`` with fractional coordinates ``s`` in [-1/2, 1/2), as HOOMD
    computes them from the float32 values of the positions and of the box it reads."""
    L = np.asarray(box, dtype=np.float64)
    if L.shape == (3,):
        return _hoomd_tilted(positions, L)
    p = np.asarray(positions, dtype=np.float64)
    p = p - L * np.floor(p / L) - 0.5 * L
    p32 = p.astype(np.float32)
    half = (0.5 * L).astype(np.float32)
    L32 = L.astype(np.float32)
    p32 = np.where(p32 >= half, p32 - L32, p32)
    p32 = np.where(p32 < -half, p32 + L32, p32)
    out = np.zeros((len(p), 3), dtype=np.float32)
    out[:, :2] = p32
    return out


def _hoomd_tilted(positions, box):
    Lx, Ly, xy = box
    s = fractional(positions, box) - 0.5  # the cell centred on the origin: r - (a + b) / 2
    s -= np.floor(s + 0.5)  # [-1/2, 1/2)
    p32 = np.stack([Lx * s[:, 0] + xy * Ly * s[:, 1], Ly * s[:, 1]], axis=1).astype(np.float32)
    # what HOOMD reads: the float32 box; a coordinate rounded onto an edge goes to its image
    b32 = np.asarray(box, np.float32)
    shift_y, shift_x = np.array([b32[2] * b32[1], b32[1]], np.float32), np.array([b32[0], 0.0], np.float32)
    for _ in range(4):
        f = fractional(p32.astype(np.float64), b32.astype(np.float64))
        up, down = f[:, 1] >= 0.5, f[:, 1] < -0.5
        if not (up.any() or down.any()):
            right, left = f[:, 0] >= 0.5, f[:, 0] < -0.5
            if not (right.any() or left.any()):
                break
            p32[right] -= shift_x
            p32[left] += shift_x
        p32[up] -= shift_y
        p32[down] += shift_y
    out = np.zeros((len(p32), 3), dtype=np.float32)
    out[:, :2] = p32
    return out


def _gsd_log_value(name, value):
    if isinstance(value, str):  # HOOMD's and OVITO's strings: a 1-D char (int8) array
        return np.frombuffer(value.encode("utf-8"), dtype=np.int8).copy()
    if isinstance(value, (np.integer, int)) and not isinstance(value, bool):
        return np.array([value], dtype=np.int64)  # (1,) int8 would read as a character in OVITO
    return np.array([value], dtype=np.float64)


def _write_gsd(pk, tmp, hoomd):
    count = missing = 0
    with hoomd.open(str(tmp), "w") as traj:
        for item in _frames(pk):
            if isinstance(item, int):
                missing = item
                break
            k, cols, conf, types, alpha, cell = item
            pos, rad, box = conf["positions"], conf["radii"], conf["box"]
            fr = hoomd.Frame()
            fr.configuration.step = k
            fr.configuration.dimensions = 2
            fr.configuration.box = [float(box[0]), float(box[1]), 1.0, tilt(box), 0.0, 0.0]
            fr.particles.N = len(rad)
            fr.particles.types = types
            fr.particles.typeid = conf["species"].astype(np.uint32)
            fr.particles.diameter = (2.0 * rad).astype(np.float32)
            fr.particles.position = hoomd_positions(pos, box)
            log = {GSD_POSITIONS64: np.asarray(pos, np.float64), GSD_RADII64: np.asarray(rad, np.float64),
                   GSD_BOX64: np.asarray(box, np.float64), f"{GSD_PREFIX}exponent": np.array([alpha])}
            for name, value in cols.items():
                log[f"{GSD_PREFIX}{name}"] = _gsd_log_value(name, value)
            log[f"{GSD_PREFIX}cell"] = _gsd_log_value("cell", cell)  # in every frame, as every log chunk
            fr.log = log
            traj.append(fr)
            count += 1
    return {"packings": count, "without_configuration": missing}


_UNSAFE = re.compile(r'[\s"\\]')


def _xyz_value(value) -> str:
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (np.integer, int)):
        return str(int(value))
    return repr(float(value))


def xyz_frame(cols, conf, types, exponent, cell="fixed") -> str:
    """One extended XYZ frame (see docs/STORE.md, "Export formats"). A tilted cell's second lattice
    vector is ``(xy Ly, Ly, 0)``, and ``gamma`` carries its float64 ``xy``."""
    pos, rad, box, sp = conf["positions"], conf["radii"], conf["box"], conf["species"]
    Lx, Ly = (repr(float(x)) for x in box[:2])
    bx = repr(tilt(box) * float(box[1])) if len(box) > 2 else "0.0"
    head = [f'Lattice="{Lx} 0.0 0.0 {bx} {Ly} 0.0 0.0 0.0 1.0"', f"Properties={XYZ_PROPERTIES}", 'pbc="T T F"']
    head += [f"{name}={_xyz_value(value)}" for name, value in cols.items()]
    if len(box) > 2 and "gamma" not in cols:
        head.append(f"gamma={_xyz_value(tilt(box))}")
    head.append(f"exponent={_xyz_value(float(exponent))}")
    head.append(f"cell={_xyz_value(cell)}")
    names = [_UNSAFE.sub("_", t) or "_" for t in types]
    lines = [str(len(rad)), " ".join(head)]
    lines += [f"{names[s]} {x!r} {y!r} 0.0 {r!r}"
              for s, (x, y), r in zip(sp.tolist(), np.asarray(pos, np.float64).tolist(),
                                      np.asarray(rad, np.float64).tolist())]
    return "\n".join(lines) + "\n"


def _write_xyz(pk, tmp, _module):
    count = missing = 0
    with open(tmp, "w", encoding="utf-8") as fh:
        for item in _frames(pk):
            if isinstance(item, int):
                missing = item
                break
            k, cols, conf, types, alpha, cell = item
            fh.write(xyz_frame(cols, conf, types, alpha, cell))
            count += 1
    return {"packings": count, "without_configuration": missing}
