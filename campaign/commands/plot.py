"""``campaign plot``: the paper's figures from a campaign file (PNG, needs matplotlib)."""

from __future__ import annotations

import sys
from pathlib import Path

from campaign.commands.reduce import add_fit_range, fit_range
from campaign.errors import UserError
from campaign.report import draw, plots
from campaign.report.writing import default_out_dir
from campaign.results import reduce as R

HELP = "Plot the paper's figures from a campaign file (PNG; needs the plot extra)"


def configure(parser):
    parser.add_argument("files", nargs="+", metavar="FILE", help="campaign HDF5 file(s)")
    parser.add_argument("--out", metavar="DIR",
                        help="output directory (default: <FILE stem>_reduced/figures)")
    parser.add_argument("--boot", type=int, default=200, metavar="B",
                        help="bootstrap resamples for the fit errors shown in the extrapolation "
                             "figure (default 200)")
    parser.add_argument("--min-packings", type=int, default=3, metavar="K",
                        help="cells with fewer finished packings are left out of the fits")
    parser.add_argument("--reference", default="default", metavar="VARIANT",
                        help="the variant the Pareto figure compares the others with (default: default)")
    parser.add_argument("--dpi", type=int, default=90, help="resolution of the PNGs (default 90)")
    add_fit_range(parser)


def main(args) -> int:
    if args.boot < 0 or args.boot == 1:
        raise UserError(f"--boot must be 0 or at least 2, got {args.boot}")
    if args.min_packings < 2:
        raise UserError(f"--min-packings must be at least 2, got {args.min_packings}")
    plots._plt()  # fail early, before the reduction, when matplotlib is missing
    settings = fit_range(args, R.Settings(min_packings=args.min_packings, n_boot=args.boot,
                                          reference=args.reference))
    red = R.reduce_campaign(args.files, settings)
    out = Path(args.out) if args.out else default_out_dir(args.files[0]) / "figures"
    written = plots.make_figures(red, out, dpi=args.dpi)
    gallery = _gallery(args.files, out, args.dpi)
    for n in red.notes:
        print(n, file=sys.stderr)
    print(f"wrote {len(written)} figures to {out}/", file=sys.stderr)
    if gallery is not None:
        print(f"wrote {gallery} (one packing at three energies)", file=sys.stderr)
    return 0


def _gallery(files, out, dpi):
    """packing_gallery.png from the first file that keeps configurations (campaign.report.draw), or None."""
    for f in files:
        if draw.store_packings(f)[2].size:
            return draw.gallery(f, out / "packing_gallery.png", dpi=dpi)
    return None
