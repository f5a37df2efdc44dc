"""campaign verify FILE [--repair]: read a whole campaign store against its checksums."""

from __future__ import annotations

import argparse
import json
import sys
import time

from campaign.errors import UserError
from campaign.storage.checksums import PROTECTED_SINCE, checksums_on

HELP = "check every block and configuration of a store against its checksums; --repair drops the damaged rows"

EPILOG = """\
Reads every chunk of the store's per-task datasets (HDF5 checks each against its fletcher32
checksum), every configuration (against its crc32 attribute), the failure records, the bin
edges and the root attributes, and checks each task's status byte against its row. Read-only;
refused while a run writes the file.

Exit status: 0 the store is sound (or, with --repair, has been repaired); 1 damage found (each
damaged part named with the tasks it holds), or damage --repair could not mend; 2 not a
campaign store (missing, not HDF5, another program's file or store format), or a run is writing it.

--repair writes the store anew (beside it, renamed into place when complete; it needs room for a
second copy) without the rows that cannot be trusted: their tasks become pending and `campaign
run` of the same spec recomputes them, giving the file an undamaged run would have. The task
identities and bin edges are rewritten from the spec. It cannot recover a file whose superblock
or root group is gone, nor a store whose stored spec is damaged (docs/STORE.md, "Checksums,
verify and repair").

A store written before the block checksums (0.2.7 and older) is checked for what can stand in for
them (each block's task identities against the spec, the journal's records against their rows), and
--repair writes it anew with them, damaged rows dropped; damage older than that which no check
sees cannot be found (docs/STORE.md, "Stores written before the block checksums").
"""


def configure(parser):
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("file", metavar="FILE", help="campaign store (HDF5) written by 'campaign run'")
    parser.add_argument("--repair", action="store_true",
                        help="drop the damaged rows (their tasks become pending, for 'campaign run' to recompute); "
                             "a store without block checksums gets them")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress line")


class _Progress:
    """A progress line on stderr: rewritten in place on a terminal, else a line every 30 s."""

    def __init__(self, enabled):
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.t0 = time.monotonic()
        self.last = 0.0
        self.shown = False

    def __call__(self, fraction, what):
        if not self.enabled:
            return
        now = time.monotonic()
        if self.tty:
            sys.stderr.write(f"\rverify: {100 * fraction:5.1f}%  {what[:60]:<60}")
            sys.stderr.flush()
            self.shown = True
        elif now - self.t0 > 30 and now - self.last >= 30:
            self.last = now
            print(f"verify: {100 * fraction:.0f}% after {now - self.t0:.0f} s ({what})", file=sys.stderr, flush=True)

    def end(self):
        if self.shown:
            sys.stderr.write("\r" + " " * 80 + "\r")
            sys.stderr.flush()


def main(args) -> int:
    # imported when the command runs: the scan, the reader and the repair bring h5py, which
    # `campaign --help` (every command's module imported to build the parser) need not load
    from campaign.storage.integrity import scan
    from campaign.storage.reader import run_is_writing
    from campaign.storage.repair import repair

    if run_is_writing(args.file):
        raise UserError(f"a run is writing {args.file}: verify reads a store no run is writing (its chunks and "
                        "status change under a reader); run it once the run has ended or been stopped")
    progress = _Progress(not args.quiet and not args.json)
    try:
        report = scan(args.file, progress=progress)
    finally:
        progress.end()
    out = report.to_json()
    if args.repair and (not report.ok or (report.unprotected and checksums_on())):
        fixable = report.fatal is None and not report.unrepairable()
        if fixable:
            out["repaired"] = repair(report)
            out["repaired"]["block_checksums_added"] = report.unprotected and checksums_on()
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        _print(report, out, args.file)
    if report.ok or "repaired" in out:
        return 0
    return 1


def _size(n) -> str:
    for unit, k in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= k:
            return f"{n / k:.3g} {unit}"
    return f"{n} bytes"


def _print(report, out, path):
    c = report.checked
    print(f"{path}: campaign {report.name or '?'}, {report.T} tasks ({report.counts['done']} done, "
          f"{report.counts['failed']} failed, {report.counts['pending']} pending)")
    if report.fatal is not None:
        print(f"  DAMAGED: {report.fatal}. Nothing in it can be read: a repair cannot recover it. If its journal "
              "holds records, `campaign run SPEC --out FILE` with the campaign's spec salvages what it can; "
              "otherwise run the spec into a new file (`--new`): packings are pure functions of the spec")
        return
    print(f"  read {c['datasets']} datasets ({c['chunks']} chunks, {_size(c['bytes'])} stored), "
          f"{c['configurations']} configurations and {c['failures']} failure records in {c['seconds']:.1f} s")
    bare_ds, bare_conf = report.unchecked["datasets"], report.unchecked["configurations"]
    if report.unprotected:
        print(f"  UNPROTECTED: no block checksums (written before {PROTECTED_SINCE}): a chunk listed off its place in "
              "HDF5's chunk index reads as other rows without an error. Checked instead: each block's task "
              "identities against the spec, every chunk's own checksum and index entry, the journal's records")
    elif report.protection.startswith("added"):
        print(f"  block checksums {report.protection}")
    if not bare_ds and not bare_conf:
        print("  every chunk and configuration carries its own checksum" if report.unprotected else
              "  every dataset and configuration carries a checksum")
    else:
        parts = []
        if bare_ds:
            parts.append(f"{len(bare_ds)} of its {c['datasets']} datasets")
        if bare_conf:
            parts.append(f"{bare_conf} of its {c['configurations']} configurations")
        print(f"  {' and '.join(parts)} carry no checksums (written before checksums were added): they were "
              "checked only as far as HDF5 checks them without (a compressed chunk's deflate stream has its own "
              "Adler-32; an uncompressed configuration nothing)")
    if report.ok and "repaired" not in out:
        print("  OK: no damage found")
        if report.unprotected:
            print(f"  `campaign verify {path} --repair` writes it anew with block checksums (it needs room for a "
                  "second copy)")
        return
    if report.ok:  # a sound store without block checksums, written anew with them
        _protected(out["repaired"], path)
        return
    lost = report.lost_rows()
    print(f"  DAMAGED: {len(report.damage)} part(s); {len(lost)} finished task(s) cannot be trusted")
    for d in report.damage:
        note = f" [a repair: {d.note}]" if d.note else ""
        print(f"    {d.name} {d.how}{d.held_text(limit=5)}{note}")
    if "repaired" in out:
        rep = out["repaired"]
        after = rep["rows_after"]
        print(f"  REPAIRED: wrote {path} anew without the damaged rows: {rep['pending_again']} task(s) are pending "
              f"again ({after['done']} done, {after['failed']} failed, {after['pending']} pending now). "
              f"`campaign run SPEC --out {path}` with the campaign's spec recomputes them (the spec is the file's "
              "'spec_yaml' attribute); the tasks are deterministic, so the store then equals an undamaged run's")
        if rep["block_checksums_added"]:
            _protected(rep, path)
        return
    bad = report.unrepairable()
    if bad:
        print(f"  a repair cannot mend {bad[0].name} ({bad[0].how}). `campaign run SPEC --out {path}` with the "
              "campaign's own spec rewrites a damaged spec_yaml when spec_hash is intact; otherwise run the spec "
              "into a new file (--new): packings are pure functions of the spec")
    else:
        print(f"  `campaign verify {path} --repair` drops the rows that cannot be trusted (their tasks become "
              f"pending), then `campaign run SPEC --out {path}` recomputes them")


def _protected(rep, path):
    """What writing an unprotected store anew with block checksums did, and what it could not do."""
    print(f"  PROTECTED: wrote {path} anew with block checksums ({rep['rows_after']['done']} done, "
          f"{rep['rows_after']['failed']} failed, {rep['rows_after']['pending']} pending); from now on every reader "
          "checks each block it reads. Damage done before this, which the checks above could not see (a chunk of "
          "scalars or histograms listed off its place whose rows read as plausible values), cannot be found: the "
          "new checksums are of the rows as they read now. If in doubt, rerun the spec into a new file "
          "(`campaign run SPEC --out NEW.h5`: packings are pure functions of the spec) and compare")
