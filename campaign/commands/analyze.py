"""campaign analyze CONFIG: contact-network analysis of one configuration from any program."""

from __future__ import annotations

import json
import math
import sys

HELP = "analyse one configuration (text, .npz, HDF5, GSD or extended XYZ): scalars and identity checks"

EPILOG = """\
CONFIG formats (docs/CONFIG_FORMAT.md): plain text with a box line 'Lx Ly' (or
'Lx Ly xy', a tilted cell) then one 'x y radius' row per disk ('#' starts a comment);
.npz with arrays positions (n, 2), radii (n,), box (2,) or (3,) [Lx, Ly, xy]; HDF5 with
datasets positions, radii, box (in --group); .gsd (HOOMD-blue's schema, tilt xy included;
the gsd package, the export extra) and .xyz/.extxyz (extended XYZ: Lattice, Properties
with pos and radius or diameter), one frame chosen with --frame K. Frames written by
'campaign export' carry the float64 positions, radii and box, and a shear-stabilised
packing's frame its cell, which are used: the analysis gives the store's scalars exactly.
Exit status: 0 analysed (identity failures are reported in the output, not as an
error), 2 unreadable or malformed input, a frame out of range, a missing extra,
1 internal fault.
"""


def configure(parser):
    import argparse

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("config", help="configuration file (text, .npz, HDF5, .gsd or extended XYZ)")
    parser.add_argument("--json", action="store_true",
                        help="print the scalars and identity flags as one JSON object")
    parser.add_argument("--format", default="auto", choices=("auto", "text", "npz", "hdf5", "gsd", "xyz"),
                        help="file format (default: from the suffix; .npz, .h5/.hdf5, .gsd, .xyz/.extxyz "
                             "(extended XYZ), else text)")
    parser.add_argument("--frame", type=int, metavar="K",
                        help="frame of a .gsd or extended XYZ file (0 the first, -1 the last; required "
                             "when the file holds several)")
    parser.add_argument("--group", default="/",
                        help="HDF5 group holding positions, radii, box (default: /), "
                             "e.g. /configurations/<task id> of a campaign store")
    parser.add_argument("--exponent", type=float, default=None,
                        help="alpha of the pair potential (1/alpha)(1 - r/s)^alpha for E_G and "
                             "pressure (default: the frame's, in files written by 'campaign export', "
                             "else 2, harmonic)")
    parser.add_argument("--cell", choices=("fixed", "shear"), default=None,
                        help="the ensemble the packing was made in, for the isostatic count of z_iso and "
                             "delta_Z: fixed (2 N_G - 1 contacts) or shear (a shear-stabilised cell, "
                             "2 N_G + 1); default: the frame's, in files written by 'campaign export', "
                             "else fixed")
    parser.add_argument("--observables", default="scalars",
                        help="comma-separated observable names (the contact network's, and moduli, "
                             "modes, gaps: the linear response), or 'all' (default: scalars); "
                             "histograms are included in the JSON output")


def _clean(value):
    """JSON-safe value: NaN/inf become null, numpy scalars become Python numbers."""
    if isinstance(value, bool):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if hasattr(value, "item"):
        return _clean(value.item())
    return value


def main(args) -> int:
    from campaign.storage.configio import describe_box, read_configuration
    from campaign.errors import UserError
    from kernels.analysis import analyze
    from kernels.observables import OBSERVABLES

    if args.observables.strip() == "all":
        names = list(OBSERVABLES)  # the linear-response ones too
    else:
        names = [s.strip() for s in args.observables.split(",") if s.strip()]
        unknown = [s for s in names if s not in OBSERVABLES]
        if unknown:
            raise UserError(f"--observables: unknown name(s) {', '.join(unknown)}; "
                            f"expected some of {', '.join(OBSERVABLES)} or 'all'")
    if args.exponent is not None and not (math.isfinite(args.exponent) and args.exponent > 1.0):
        raise UserError(f"--exponent: expected a finite number > 1, got {args.exponent}")

    conf = read_configuration(args.config, fmt=args.format, group=args.group, frame=args.frame)
    exponent = args.exponent if args.exponent is not None else (conf.exponent or 2.0)
    if not (math.isfinite(exponent) and exponent > 1.0):
        raise UserError(f"{conf.source}: the file's exponent {exponent} is not a finite number > 1; "
                        "give --exponent")
    for note in conf.notes:
        print(f"note: {note}", file=sys.stderr)
    cell = args.cell or conf.cell or "fixed"
    try:
        result = analyze(conf.positions, conf.radii, conf.box, names, exponent=exponent, species=conf.species,
                         cell=cell)
    except ValueError as exc:  # input the reader let through but the analysis cannot use
        raise UserError(f"{conf.source}: {exc}") from None

    if args.json:
        out = {k: _clean(v) for k, v in result.scalars.items()}
        out["identities"] = dict(result.identities)
        if result.histograms:
            out["histograms"] = {
                name: {"edges": result.bin_edges[name].tolist(), "counts": counts.tolist()}
                for name, counts in result.histograms.items()
            }
        print(json.dumps(out, indent=None, allow_nan=False))
        return 0

    frame = f", frame {conf.frame}" if conf.frame is not None else ""
    shear = ", shear-stabilised cell" if cell != "fixed" else ""
    print(f"{conf.source}{frame}: {result.scalars['N']} disks, box {describe_box(conf.box)}{shear}")
    for key, value in result.scalars.items():
        if isinstance(value, float):
            print(f"  {key:16s} {value:.10g}")
        else:
            print(f"  {key:16s} {value}")
    print("  identities:")
    for key, value in result.identities.items():
        print(f"    {key:24s} {'ok' if value else 'FAILED'}")
    for name, counts in result.histograms.items():
        print(f"  histogram {name}: {int(counts.sum())} counts in {counts.size} bins "
              f"[{result.bin_edges[name][0]:g}, {result.bin_edges[name][-1]:g}]")
    return 0
