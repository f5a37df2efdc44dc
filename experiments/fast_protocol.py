"""The fast protocol for energy scans (`start: ladder` with `endgame: auto`) against independent
FIRE packings, and the ladder alone, paired packing by packing.

    python experiments/fast_protocol.py REFERENCE.h5:VARIANT OTHER.h5:VARIANT [...] [--boot 2000]

The first argument is the reference (e.g. ``fast.h5:default``, independent FIRE packings), each
further one a protocol made from the same random starts (the same campaign seed and system: the
task seeds leave the protocol out), e.g. ``fast.h5:fast`` and ``ladder.h5:default``. For each
protocol and N_G, over the energies E_G <= 1e-12 (where ``endgame: auto`` may take Newton) and
above, this prints the mean paired difference of ``A_G``, ``delta_Z``, ``psi_O``, the contacts
beyond isostatic ``N_C/2 - (2 N_G - 1)`` and ``E_G/E``, with bootstrap errors that resample whole
seeds (a ladder's packings of one seed share their history), and the ratio of summed force
evaluations. The finite-size table of each store: ``campaign reduce``.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

import campaign

QUANTITIES = ("A_G", "delta_Z", "psi_O", "excess", "E_rel")


def _load(arg):
    path, _, variant = arg.rpartition(":")
    df = campaign.read_packings(path)
    df = df[df.variant == variant].copy()
    if df.empty:
        raise SystemExit(f"{arg}: no finished packings of variant {variant!r}")
    df["excess"] = df.N_C / 2 - (2 * df.N_G - 1)
    df["E_rel"] = df.E_G / df.E - 1
    return df.set_index(["N", "E", "seed"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reference")
    ap.add_argument("others", nargs="+")
    ap.add_argument("--boot", type=int, default=2000)
    args = ap.parse_args(argv)
    ref = _load(args.reference)
    rng = np.random.default_rng(0)
    print("| protocol | N_G | energies | pairs | cost (FE) | " + " | ".join(f"d{q}" for q in QUANTITIES) + " |")
    print("|---|---|---|---|---|" + "---|" * len(QUANTITIES))
    for arg in args.others:
        oth = _load(arg)
        j = ref.merge(oth, left_index=True, right_index=True, how="inner", suffixes=("", "_o"))
        for N in sorted(set(j.index.get_level_values("N"))):
            for label, sel in (("<= 1e-12", lambda e: e <= 1e-12), ("> 1e-12", lambda e: e > 1e-12), ("all", lambda e: e > 0)):
                jj = j[(j.index.get_level_values("N") == N) & sel(j.index.get_level_values("E"))]
                seeds = np.array(sorted(set(jj.index.get_level_values("seed"))))
                d = {q: (jj[q + "_o"] - jj[q]).groupby(level="seed").sum() for q in QUANTITIES}
                cnt = jj.groupby(level="seed").size()
                cells = []
                for q in QUANTITIES:
                    est = d[q].sum() / cnt.sum()
                    b = []
                    for _ in range(args.boot):
                        s = rng.choice(seeds, len(seeds))
                        b.append(d[q].loc[s].sum() / cnt.loc[s].sum())
                    cells.append(f"{est:+.2e} ± {np.std(b):.1e}")
                fe = jj["force_evaluations_o"].sum() / jj["force_evaluations"].sum()
                print(f"| {arg} | {N} | {label} | {len(jj)} | {fe:.3f} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
