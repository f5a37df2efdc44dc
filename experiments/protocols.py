"""Does the contact network follow the jamming density across protocols? (docs/PROTOCOLS.md)

Reads a reduction's summary.json (``campaign reduce data/protocols.h5 data/protocols-more.h5
--out DIR`` writes DIR/summary.json) and fits each N_G -> inf network quantity against phi_J over
the variants, a straight line weighted by the errors of both (effective variance, iterated):
its slope, the slope's error and z, and the line's chi^2 (do the protocols lie on one line?).

    python experiments/protocols.py results/protocols24/summary.json [--json out.json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from scipy.special import chdtrc

QUANTITIES = ("A_G_star_E", "A_G_star_Z", "psi_O_star", "beta_E", "beta_Z", "rattler_fraction")


def line_with_x_errors(x, ex, y, ey, iterations=20):
    """y = a + b (x - mean x), weights 1 / (ey^2 + b^2 ex^2) iterated to convergence (the effective
    variance method): (b, b_err, chi2, dof)."""
    b = 0.0
    for _ in range(iterations):
        w = 1.0 / (ey**2 + b**2 * ex**2)
        xm = np.sum(w * x) / w.sum()
        X = np.column_stack([np.ones_like(x), x - xm])
        cov = np.linalg.inv(X.T @ (w[:, None] * X))
        p = cov @ X.T @ (w * y)
        b = p[1]
    chi2 = float(np.sum(w * (y - X @ p) ** 2))
    return float(b), float(np.sqrt(cov[1, 1])), chi2, len(x) - 2


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("summary", help="summary.json of campaign reduce")
    ap.add_argument("--json", help="write the records here")
    args = ap.parse_args(argv)
    prot = json.load(open(args.summary))["protocols"]
    vals = prot["values"]
    nan = float("nan")
    x = np.array([r["phi_J"] if r["phi_J"] is not None else nan for r in vals])
    ex = np.array([r["phi_J_err"] if r["phi_J_err"] is not None else nan for r in vals])
    print(f"{len(vals)} variants: {', '.join(r['variant'] for r in vals)}")
    print("| quantity | slope d q / d phi_J | z | chi2 / dof | p (one line) |\n|---|---|---|---|---|")
    out = []
    for q in QUANTITIES:
        y = np.array([r[q] if r[q] is not None else nan for r in vals])
        ey = np.array([r[f"{q}_err"] if r[f"{q}_err"] is not None else nan for r in vals])
        ok = np.isfinite(x) & np.isfinite(ex) & np.isfinite(y) & np.isfinite(ey) & (ey > 0)
        b, eb, chi2, dof = line_with_x_errors(x[ok], ex[ok], y[ok], ey[ok])
        p = float(chdtrc(dof, chi2)) if dof > 0 else nan
        out.append({"quantity": q, "slope": b, "slope_err": eb, "z": b / eb, "chi2": chi2, "dof": dof, "p": p})
        print(f"| {q} | {b:+.3g} ± {eb:.2g} | {b / eb:+.1f} | {chi2:.3g} / {dof} | {p:.2g} |")
    if args.json:
        json.dump(out, open(args.json, "w"), indent=1)


if __name__ == "__main__":
    main()
