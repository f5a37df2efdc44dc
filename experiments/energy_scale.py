"""A_G, Psi_O and Delta Z of large packings against the energy, and the energy scale at
which they match the paper's quoted values (hypothesis (a) of docs/PAPER.md).

    python experiments/energy_scale.py --n 8192 --energies 1e-5 5e-6 2.5e-6 1.25e-6 --seeds 3
    python experiments/energy_scale.py --n 8192 --energies 1e-10 2.5e-11 --seeds 2 --json low.json
    python experiments/energy_scale.py --n 8192 --energies 2.5e-6 2.5e-11 --seeds 40 --factor 4

Each (energy, seed) is one ``kernels.jam`` (default protocol, random start) followed by
``kernels.analyze``; packings run in ``--workers`` processes. Prints one row per energy
(means and standard errors over seeds) with the energy in three normalisations of the
same packings: this project's (pair sum over unordered pairs / all disks), per
non-rattler, and the paper's Eq. (2) read literally (sum over ordered pairs / N_G, twice
the former). Then, for each value the paper quotes at N = 8192, the energy at which this
project's packings reach it (log-linear interpolation between neighbouring energies), and
the factor between the paper's energy label and that energy. ``--factor F`` tests the
hypothesis "the paper's label is F times this project's E_G" where energies label / F were
run: the difference from the paper's value and its z-scores against the combined error (ours,
the paper's three-digit rounding, its own sampling error, ``--paper-error``). ``--json FILE``
writes the per-packing rows too; ``--merge FILE ...`` adds rows measured before.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

#: Values the paper quotes for N = 8192 (text of sections 5 and 6).
PAPER = {"A_G": {1e-5: 0.482, 1e-10: 0.448, 1e-15: 0.446},
         "psi_O": {1e-5: 0.435, 1e-10: 0.373, 1e-15: 0.369}}


def one(args):
    n, energy, seed = args
    import kernels
    t0 = time.perf_counter()
    p = kernels.jam(n, energy, seed)
    a = kernels.analyze(p.positions, p.radii, p.box, ["scalars"])
    s = a.scalars
    e_total = p.energy * n
    return dict(n=n, energy=energy, seed=seed, status=p.status, E_G=p.energy,
                E_G_nonrattler=s["E_G_nonrattler"], E_G_ordered_nonrattler=2.0 * e_total / s["N_G"],
                A_G=s["A_G"], psi_O=s["psi_O"], delta_Z=s["delta_Z"], z_g_mean=s["z_g_mean"],
                phi=p.phi, N_R=s["N_R"], identities_ok=bool(s["identities_ok"]),
                force_evaluations=p.force_evaluations, seconds=time.perf_counter() - t0)


def summarise(rows):
    out = []
    for e in sorted({r["energy"] for r in rows}, reverse=True):
        rs = [r for r in rows if r["energy"] == e and r["status"] == "converged"]
        if not rs:
            continue
        row = {"energy": e, "packings": len(rs)}
        for k in ("E_G", "E_G_nonrattler", "E_G_ordered_nonrattler", "A_G", "psi_O", "delta_Z", "phi", "N_R"):
            v = np.array([r[k] for r in rs], dtype=float)
            row[k] = float(v.mean())
            row[k + "_err"] = float(v.std(ddof=1) / math.sqrt(len(v))) if len(v) > 1 else float("nan")
        out.append(row)
    return out


def match(summary, key, target):
    """Energy (this project's E_G) at which the mean of ``key`` equals ``target``:
    log-linear interpolation between the two bracketing energies, or None."""
    pts = sorted((r["E_G"], r[key]) for r in summary)
    for (e0, v0), (e1, v1) in zip(pts, pts[1:]):
        if (v0 - target) * (v1 - target) <= 0 and v0 != v1:
            t = (target - v0) / (v1 - v0)
            return math.exp(math.log(e0) + t * (math.log(e1) - math.log(e0)))
    return None


def factor_tests(summary, factors, paper_errors):
    """For each factor F and each value the paper quotes at label E, this project's mean at the
    measured energy E / F (when one was run), the difference and its z-scores: the difference
    over sqrt(our standard error^2 + (5e-4 / sqrt 3)^2 (the paper's rounding to three digits,
    uniform) + s^2) for each of the paper's sampling errors s."""
    out = []
    for f in factors:
        for key, vals in PAPER.items():
            for e_paper, v in vals.items():
                cell = [r for r in summary if abs(r["energy"] * f / e_paper - 1.0) < 1e-9]
                if not cell:
                    continue
                r = cell[0]
                d = r[key] - v
                z = [d / math.sqrt(r[key + "_err"] ** 2 + (5e-4 / math.sqrt(3)) ** 2 + s * s) for s in paper_errors]
                out.append(dict(factor=f, quantity=key, paper_energy=e_paper, paper_value=v, energy=r["E_G"],
                                ours=r[key], ours_err=r[key + "_err"], difference=d, z=z))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=8192)
    ap.add_argument("--energies", type=float, nargs="+", default=[1e-5, 5e-6, 2.5e-6, 1.25e-6])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--merge", metavar="FILE", nargs="*", default=[])
    ap.add_argument("--factor", type=float, nargs="*", default=[],
                    help="test 'paper label = factor x this project's E_G' at the measured energies")
    ap.add_argument("--paper-error", type=float, nargs="+", default=[2e-4, 4e-4],
                    help="the paper's own sampling error of a value at N = 8192 (Table 2: 2e-4 to 4e-4)")
    args = ap.parse_args(argv)

    jobs = [(args.n, e, s) for e in args.energies for s in range(args.first_seed, args.first_seed + args.seeds)]
    rows = []
    for f in args.merge:
        rows += json.load(open(f))["packings"]
    with ProcessPoolExecutor(args.workers) as ex:
        for r in ex.map(one, jobs):
            rows.append(r)
            print(f"  N={r['n']} E={r['energy']:.3g} seed={r['seed']}: {r['status']}, A_G={r['A_G']:.4f} "
                  f"psi_O={r['psi_O']:.4f} dZ={r['delta_Z']:.4f} ({r['seconds']:.0f} s)", flush=True)
    summary = summarise(rows)
    print(f"\nN = {args.n}: means over converged packings (standard errors)\n")
    print("| E_G (this project) | per non-rattler | ordered pairs / N_G | packings | A_G | Psi_O | Delta Z | phi | rattlers |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in summary:
        print(f"| {r['E_G']:.3g} | {r['E_G_nonrattler']:.3g} | {r['E_G_ordered_nonrattler']:.3g} | {r['packings']} "
              f"| {r['A_G']:.4f}({r['A_G_err'] * 1e4:.0f}) | {r['psi_O']:.4f}({r['psi_O_err'] * 1e4:.0f}) "
              f"| {r['delta_Z']:.4f} | {r['phi']:.4f} | {r['N_R']:.0f} |")
    matches = []
    print("\nEnergy at which this project's packings reach the paper's N = 8192 values\n")
    print("| quantity | paper's E_G label | paper's value | this project's E_G there | factor label / E_G |")
    print("|---|---|---|---|---|")
    for key, vals in PAPER.items():
        for e_paper, v in vals.items():
            e = match(summary, key, v)
            matches.append(dict(quantity=key, paper_energy=e_paper, paper_value=v, energy=e,
                                factor=(e_paper / e) if e else None))
            print(f"| {key} | {e_paper:g} | {v} | {e:.3g} | {e_paper / e:.2f} |" if e else
                  f"| {key} | {e_paper:g} | {v} | outside the measured range | - |")
    tests = factor_tests(summary, args.factor, args.paper_error)
    if tests:
        print("\nThe paper's values against this project's at the paper's label / factor (z: the difference "
              "over the combined error: ours, the paper's rounding to three digits, its sampling error)\n")
        print("| factor | quantity | paper's label | paper's value | this project's E_G | ours | difference | "
              + " | ".join(f"z (paper error {s:g})" for s in args.paper_error) + " |")
        print("|---|---|---|---|---|---|---|" + "---|" * len(args.paper_error))
        for t in tests:
            print(f"| {t['factor']:g} | {t['quantity']} | {t['paper_energy']:g} | {t['paper_value']} | "
                  f"{t['energy']:.3g} | {t['ours']:.4f}({t['ours_err'] * 1e4:.0f}) | {t['difference']:+.4f} | "
                  + " | ".join(f"{z:+.1f}" for z in t["z"]) + " |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"n": args.n, "packings": rows, "summary": summary, "matches": matches,
                       "factor_tests": tests}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
