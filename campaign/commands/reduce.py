"""``campaign reduce``: distributions, scaling fits and the finite-size table of a campaign file."""

from __future__ import annotations

import fcntl
import json
import os
import sys
from pathlib import Path

from campaign.errors import UserError
from campaign.report import writing
from campaign.results import reduce as R

HELP = "Reduce a campaign file: distributions, scaling fits, the finite-size table"


def configure(parser):
    parser.add_argument("files", nargs="+", metavar="FILE",
                        help="campaign HDF5 file(s); several files are reduced together "
                             "(a packing done in more than one counts once)")
    parser.add_argument("-o", "--out", metavar="DIR",
                        help="output directory (default: <FILE stem>_reduced next to FILE)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object (rows, extrapolated) on stdout; "
                             "the table and notes go to stderr")
    parser.add_argument("--boot", type=int, default=1000, metavar="B",
                        help="bootstrap resamples for the fit errors (default 1000)")
    parser.add_argument("--seed", type=int, default=None, metavar="S",
                        help="bootstrap seed (default: a fixed seed)")
    parser.add_argument("--min-packings", type=int, default=3, metavar="K",
                        help="cells with fewer finished packings are left out of the fits "
                             "(default 3)")
    add_fit_range(parser)
    parser.add_argument("--reference", default="default", metavar="VARIANT",
                        help="the variant every other one is compared with: cost ratio and deviations "
                             "(default: default, the spec's base protocol)")
    parser.add_argument("--in-place", action="store_true",
                        help="also write the /reduced group into FILE itself (refused while "
                             "tasks are pending or while a run holds the file)")


def add_fit_range(parser):
    """The fit-range options ``reduce`` and ``plot`` share (docs/REDUCED.md, "The fit range")."""
    g = parser.add_argument_group(
        "fit range", "by default the scaling laws are fitted to the cells of typical relative overlap "
        "(alpha E_G / 2)^(1/alpha) <= 0.001, one distance from jamming for every potential (E_G <= 1e-6 "
        "at alpha = 2); these options replace that range")
    g.add_argument("--fit-all", action="store_true",
                   help="fit every energy (the reducer's default before the overlap window)")
    g.add_argument("--fit-energies", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                   help="fit the cells with E_G in [LO, HI]")
    g.add_argument("--fit-overlap", type=float, default=None, metavar="DMAX",
                   help="fit the cells whose typical relative overlap (alpha E_G / 2)^(1/alpha) is at "
                        "most DMAX, alpha each variant's exponent (default 0.001; with --fit-energies "
                        "both apply; docs/UNIVERSALITY.md)")


def fit_range(args, settings):
    """Check the fit-range options and set them on ``settings``. A range given on the command line
    replaces the default one, and is refused where it holds fewer energies than a fit needs."""
    if args.fit_all and (args.fit_energies is not None or args.fit_overlap is not None):
        raise UserError("--fit-all fits every energy; it does not go with --fit-energies or --fit-overlap")
    explicit = args.fit_all or args.fit_energies is not None or args.fit_overlap is not None
    if explicit:
        settings.fit_overlap = float("inf")
        settings.strict_range = True
    if args.fit_energies is not None:
        lo, hi = args.fit_energies
        if not (lo >= 0 and hi > lo and lo < float("inf")):
            raise UserError(f"--fit-energies expects 0 <= LO < HI, got {lo:g} {hi:g}")
        settings.fit_energies = (lo, hi)
    if args.fit_overlap is not None:
        if not args.fit_overlap > 0:
            raise UserError(f"--fit-overlap expects a relative overlap > 0, got {args.fit_overlap:g}")
        settings.fit_overlap = args.fit_overlap
    return settings


def main(args) -> int:
    if args.boot < 0 or args.boot == 1:
        raise UserError(f"--boot must be 0 (no errors) or at least 2, got {args.boot}")
    if args.min_packings < 2:
        raise UserError(f"--min-packings must be at least 2 (a standard error needs two "
                        f"packings), got {args.min_packings}")
    if args.in_place and len(args.files) != 1:
        raise UserError("--in-place needs exactly one FILE")
    settings = fit_range(args, R.Settings(min_packings=args.min_packings, n_boot=args.boot,
                                          reference=args.reference))
    if args.seed is not None:
        settings.boot_seed = args.seed
    red = R.reduce_campaign(args.files, settings)
    out = Path(args.out) if args.out else writing.default_out_dir(args.files[0])
    written = writing.write_outputs(red, out)
    text = sys.stderr if args.json else sys.stdout
    m = red.meta
    print(f"{m['name'] or Path(args.files[0]).name}: {m['done']} of {m['total']} packings used"
          + (f", {m['excluded']} finished but left out (see the notes)" if m["excluded"] else "")
          + (f", {m['pending']} pending" if m["pending"] else "")
          + (f", {m['failed']} failed" if m["failed"] else "")
          + f"; {len(red.rows)} (variant, N_G) rows; bootstrap {m['n_boot']}", file=text)
    print("", file=text)
    print(writing.table_markdown(red), file=text)
    for sec in R.in_order("console"):  # the sections' tables (campaign.results.sections)
        said = sec.console(red.sections[sec.name])
        if said:
            print(said, file=text)
    for n in red.notes:
        print(n, file=sys.stderr)
    if args.in_place:
        _write_in_place(red, args.files[0])
        written.append(Path(args.files[0]))
    print(f"wrote {out}/ ({', '.join(p.name for p in written)})", file=sys.stderr)
    if args.json:
        json.dump(red.to_json(), sys.stdout)
        sys.stdout.write("\n")
    return 0


def _write_in_place(red, path):
    """Write /reduced into the campaign file, as its one writer.

    A run holds an exclusive lock on ``<FILE>.journal`` while it writes FILE; taking
    the same lock (without waiting) keeps a run from starting meanwhile and refuses
    while one is going on.
    """
    if red.meta["pending"]:
        raise UserError(f"{path}: {red.meta['pending']} tasks are still pending (a run may be "
                        "writing the file); not writing into it. The reduced group is in the "
                        "output directory's reduced.h5")
    journal = Path(str(path) + ".journal")
    fd = None
    try:
        if journal.exists():
            fd = os.open(journal, os.O_RDONLY)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                raise UserError(f"{path}: a run is writing it ({journal} is locked); the reduced "
                                "group is in the output directory's reduced.h5") from None
        try:
            writing.write_reduced(red, path, mode="r+")
        except OSError as exc:  # read-only, locked by HDF5, ...
            raise UserError(f"{path}: could not open for writing ({exc}); the reduced group is "
                            "in the output directory's reduced.h5") from None
    finally:
        if fd is not None:
            os.close(fd)
