"""The two ensembles of campaigns/shear.yaml side by side: stability, residual stresses, the cell's
shape, and the finite-size table.

    python experiments/shear.py results/shear.h5 [--boot 200] [--json FILE]

Prints, per ensemble (variant ``default``: the fixed box; ``shear``: tilt and aspect ratio
relaxed) and N_G, over every energy of the store:

* the fraction of packings with ``G <= 0`` (a failed moduli computation counts as not ``G > 0``),
  ``c66 <= 0`` (simple shear) and ``c11 + c22 - 2 c12 <= 0`` (pure shear), with binomial errors;
* the largest ``|sigma_xy| / p`` and ``|sigma_xx - sigma_yy| / (2 p)``, recomputed from the stored
  float64 configurations over every contact (``kernels.network.contact_bonds``,
  ``kernels.potential.stress_from_bonds``), and the smallest isostatic excess
  ``N_C/2 - (2 N_G - 1 + free)`` (free = 0 fixed, 2 shear);
* the spread of the cell's shape: the standard deviations of the tilt ``gamma`` and of the
  pure-shear strain ``eps = ln(Lx / sqrt(A)) ``;

The finite-size table of each ensemble and the paired differences: ``campaign reduce STORE``.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

import campaign
from campaign.report.frames import Packings
from kernels.network import contact_bonds
from kernels.potential import stress_from_bonds


def _frac(bad):
    n, k = len(bad), int(np.sum(bad))
    return k / n, (np.sqrt(k * (n - k) / n) if 0 < k < n else 1.0) / n


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store")
    ap.add_argument("--exponent", type=float, default=2.0, help="the store's potential exponent (default 2)")
    ap.add_argument("--json")
    args = ap.parse_args(argv)

    df = campaign.read_packings(args.store)
    out = {"ensembles": []}
    print("| ensemble | N_G | packings | G <= 0 | c66 <= 0 | pure <= 0 | max sxy/p | max (sxx-syy)/2p | min excess | std gamma | std eps |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    with Packings(args.store) as pk:
        for (v, N), g in df.groupby(["variant", "N"]):
            sxy, sn, eps = [], [], []
            for tid in g.id:
                c = pk.configuration(tid)
                box = np.asarray(c["box"], float)
                bi, bj, dx, dy = contact_bonds(c["positions"], c["radii"], box)
                s = np.array(stress_from_bonds(np.asarray(c["radii"]), bi, bj, dx, dy, args.exponent))
                p = (s[0] + s[1]) / 2
                sxy.append(abs(s[2]) / p)
                sn.append(abs(s[0] - s[1]) / 2 / p)
                eps.append(np.log(box[0] / np.sqrt(box[0] * box[1])))
            free = 2 if v != "default" else 0
            excess = g.N_C / 2 - (2 * g.N_G - 1 + free)
            row = dict(variant=v, N=int(N), packings=len(g), G=_frac(~(g.G > 0)), c66=_frac(~(g.c66 > 0)),
                       pure=_frac(~(g.c11 + g.c22 - 2 * g.c12 > 0)), max_sxy=float(np.max(sxy)),
                       max_sn=float(np.max(sn)), min_excess=int(excess.min()),
                       std_gamma=float(np.std(g.gamma)), std_eps=float(np.std(eps)))
            out["ensembles"].append(row)
            f = lambda x: f"{x[0]:.3f}({x[1]:.3f})"  # noqa: E731
            print(f"| {v} | {N} | {len(g)} | {f(row['G'])} | {f(row['c66'])} | {f(row['pure'])} | "
                  f"{row['max_sxy']:.1e} | {row['max_sn']:.1e} | {row['min_excess']} | {row['std_gamma']:.4f} | "
                  f"{row['std_eps']:.4f} |", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
