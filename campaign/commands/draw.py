"""campaign draw SOURCE: a picture of one packing (needs the plot extra)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from campaign.errors import UserError
from campaign.report import draw
from campaign.report.plots import _plt

HELP = "draw one packing: disks, contacts, network, grain and void polygons (PNG, SVG or PDF)"

EPILOG = """\
SOURCE is a configuration file (text, .npz, HDF5, .gsd or extended XYZ, as for
'campaign analyze'; --frame K picks a frame of a .gsd or XYZ file) or a campaign store
that keeps configurations ('store: {configurations: true}'); in a store --task ID (or a
unique prefix) or --index ROW picks the packing (default: the first row with a
configuration).

Layers: disks (by species; rattlers yellow), contacts (contact points, red), network
(centre to centre, black), grains (grain polygons, blue), voids (void polygons,
white), fictitious (fictitious contacts, dashed red), forces (the network with line
widths proportional to the pair force). Default: all but forces. Periodic images are
drawn across the box edges (dashed); --region X Y W H shows a window, which may reach
up to one box length beyond the box. A tilted cell (box [Lx, Ly, xy], a shear-stabilised
packing) is drawn as its parallelogram with images by its lattice vectors (Lx, 0) and
(xy Ly, Ly); the window and --region then refer to the parallelogram's bounding box.

Exit status: 0 drawn, 2 bad input (missing or malformed file, no configurations in
the store, unknown task, region outside the box, unknown layer), 1 internal fault.
"""


def configure(parser):
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("source", metavar="SOURCE", help="configuration file or campaign store")
    parser.add_argument("--task", metavar="ID", help="task id (or a unique prefix) in a campaign store")
    parser.add_argument("--index", type=int, metavar="I", help="row of the task table in a campaign store")
    parser.add_argument("--out", metavar="FILE",
                        help="output file, .png, .svg or .pdf (default: <SOURCE stem>.png here)")
    parser.add_argument("--region", type=float, nargs=4, metavar=("X", "Y", "W", "H"),
                        help="draw the window [X, X+W] x [Y, Y+H] (box units) instead of the box")
    parser.add_argument("--layers", nargs="+", metavar="LAYER",
                        help="layers to draw (names, or 'all'; default: all but forces)")
    parser.add_argument("--format", default="auto", choices=("auto", "text", "npz", "hdf5", "gsd", "xyz"),
                        help="configuration format (default: from the suffix)")
    parser.add_argument("--frame", type=int, metavar="K",
                        help="frame of a .gsd or extended XYZ file (0 the first, -1 the last; required "
                             "when the file holds several)")
    parser.add_argument("--group", default="/", help="HDF5 group of a configuration file (default: /)")
    parser.add_argument("--exponent", type=float, default=None,
                        help="alpha of the pair potential, for the forces layer (default: the store's "
                             "spec or the exported frame's, else 2)")


def main(args) -> int:
    layers = draw.check_layers(args.layers) if args.layers else draw.DEFAULT_LAYERS
    if args.exponent is not None and not (math.isfinite(args.exponent) and 2.0 <= args.exponent <= 3.0):
        raise UserError(f"--exponent: expected a number in [2, 3], got {args.exponent}")
    out = Path(args.out) if args.out else None
    if out is not None and out.suffix.lower() not in draw.FORMATS:
        raise UserError(f"--out {args.out}: expected a .png, .svg or .pdf file")
    if out is not None and not out.parent.is_dir():
        raise UserError(f"--out {args.out}: no directory {str(out.parent)!r}")
    plt = _plt()  # fail early when matplotlib is missing
    src = draw.read_source(args.source, task=args.task, index=args.index, fmt=args.format,
                           group=args.group, exponent=args.exponent, frame=args.frame)
    try:
        sc = draw.scene(src.positions, src.radii, src.box, src.species, exponent=src.exponent,
                        region=args.region, layers=layers)
    except ValueError as exc:  # input the reader let through but the network cannot use
        raise UserError(f"{args.source}: {exc}") from None
    out = out or Path(f"{src.stem}.png")
    fig = draw.render(sc, title=draw.title_of(src, sc))
    fig.savefig(out, dpi=110)
    plt.close(fig)
    c = sc.counts
    print(f"wrote {out}: {c['N']} disks ({c['N_R']} rattlers), {c['contacts']} contacts, {c['N_G']} grain "
          f"polygons, {c['N_V']} void polygons, {c['N_F']} fictitious contacts", file=sys.stderr)
    if c["faces_not_drawn"]:
        print(f"note: {c['faces_not_drawn']} face(s) of the network wind around the box and are not drawn "
              f"as voids; 'campaign analyze {args.source}' names the identities this packing fails",
              file=sys.stderr)
    return 0
