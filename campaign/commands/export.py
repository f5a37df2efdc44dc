"""campaign export FILE: a store's packings as CSV, Parquet, GSD or extended XYZ."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from campaign.report.export import EXTENSION, FORMATS, export, format_of, require_format

HELP = "export a store's packings: scalars as CSV or Parquet, configurations as GSD or extended XYZ"

EPILOG = """\
Formats (docs/STORE.md, "Export formats"):
  csv, parquet  one row per packing: row, id, variant, N, E, seed, status and every stored
                scalar (A_G, N_G, psi_O, ...), numbers at full precision; parquet needs
                pyarrow (the export extra)
  gsd           one frame per packing (HOOMD-blue's schema, for OVITO, freud, HOOMD):
                box (tilt xy included), positions, diameters, species as types; the
                schema's positions are float32, so each frame also keeps the float64
                positions, radii and box ([Lx, Ly], or [Lx, Ly, xy] for a tilted cell) in its
                log (particles/campaign/position64, particles/campaign/radius64,
                campaign/box64), the variant's cell (campaign/cell) and the packing's
                columns as campaign/<column>; needs gsd (the export extra)
  xyz           extended XYZ text (OVITO, ASE), full float64 precision, one frame per
                packing: Lattice (tilted for a tilted cell), Properties=type:S:1:pos:R:3:
                radius:R:1, pbc, the packing's columns and its cell as key=value in the
                comment line
gsd and xyz write the packings whose configuration the store kept ('store:
{configurations: true}' in the spec); a store without configurations is refused.

Rows: the packings 'campaign reduce' uses (done, jam_status 0, identities_ok 1), in
store order; --all-finished exports every finished packing. 'campaign analyze OUT.gsd
--frame K' (or OUT.xyz) analyses frame K again and gives the store's scalars.

Exit status: 0 written, 2 bad input (missing or foreign file, unknown variant or format,
a missing extra, no configurations for gsd/xyz), 1 internal fault.
"""


def configure(parser):
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("file", metavar="FILE", help="campaign store (HDF5)")
    parser.add_argument("--format", choices=FORMATS, default=None,
                        help="output format (default: from the suffix of --out)")
    parser.add_argument("--out", metavar="PATH",
                        help="output file (default: <FILE stem>.<format> in the current directory); "
                             "replaced if it exists")
    parser.add_argument("--variant", action="append", metavar="NAME",
                        help="export this variant only (repeat for several; default: every variant)")
    parser.add_argument("--all-finished", action="store_true",
                        help="every finished packing, also those the reducer leaves out "
                             "(jam_status != 0 or identities_ok != 1)")


def main(args) -> int:
    fmt = format_of(args.format, args.out)
    require_format(fmt)  # a missing extra is reported before the store is read
    out = Path(args.out) if args.out else Path(Path(args.file).stem + EXTENSION[fmt])
    done = export(args.file, out, fmt, variant=args.variant, good=not args.all_finished)
    what = "packings the reducer uses" if not args.all_finished else "finished packings"
    unit = "frame(s)" if fmt in ("gsd", "xyz") else "row(s)"
    msg = f"wrote {done['out']}: {done['packings']} {unit}, {fmt}, of the {what}"
    if done["without_configuration"]:
        msg += (f"; {done['without_configuration']} selected packing(s) have no stored configuration and are "
                "not in it")
    print(msg, file=sys.stderr)
    return 0
