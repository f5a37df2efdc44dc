"""Corrections to scaling in the universality campaign: every system's exponents fitted over
matched windows of the distance to jamming, and the premise Delta Z ~ E_G^(1/(2 alpha)).

    python experiments/universality.py results/universality.h5 results/universality-1024.h5 \
        [--boot 1000] [--json FILE]

For each window of the typical relative overlap ``delta = (alpha E_G / 2)^(1/alpha)`` (``inf``:
every energy, ``campaign reduce --fit-all``; then 0.01, 0.003 and 0.001, the reducer's default)
this runs the reducer with ``campaign reduce --fit-overlap DMAX`` (``Settings.fit_overlap``) and
prints, per system:

* ``beta_E``, ``beta_Z`` per N_G and extrapolated in 1/N_G (the reducer's rows and extrapolation);
* ``x``, the exponent of ``Delta Z = c E_G^x``: a straight line in log-log through the cells of
  the window with at least four excess contacts (``N_G Delta Z / 2 >= 4``: below that a finite
  packing sits on its isostatic plateau), bootstrap errors; the premise of
  ``beta_E = beta_Z / (2 alpha)`` is ``x = 1/(2 alpha)``, and ``beta_E = beta_Z x`` holds whenever
  both power laws do;
* whether the systems share one ``beta_Z``: chi^2 of their extrapolated values about the weighted
  mean, and its p-value.

A window in E_G would not compare like with like: E_G = 1e-5 is delta = 3e-3 for alpha = 2 but
0.03 for alpha = 3.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from scipy import stats

from campaign.results.bootstrap import cell_means as bootstrap_cell_means
from campaign.results import variance
from campaign.results.fits import line_in_inverse_n, spread
from campaign.results.reduce import Settings, reduce_campaign
from campaign.results.scaling import typical_overlap
from campaign.results.tables import fmt_err

WINDOWS = (math.inf, 1e-2, 3e-3, 1e-3)


def loglog_exponent(groups, N, boot):
    """Slope of log <Delta Z> against log <E_G> over the cells (rows (E, Delta Z)) with
    N Delta Z / 2 >= 4, bootstrap error. A cell's weight is ``n_c / s_c^2`` with ``s_c^2`` its mean's
    relative variance from the reducer's model of the spread over the size's cells
    (``variance.pooled_model``: one amplitude and one trend with log10 E; docs/REDUCED.md, "Error bars
    that hold"), not the cell's own few packings' spread; the model is fitted once, from the data
    (40 packings a cell determine its two parameters), and the replicas refit the slope with it."""
    groups = [g for g in groups if g[:, 1].mean() * N / 2 >= 4]
    if len(groups) < 3:
        return None

    def slope(xm, ym, w):
        return np.polyfit(np.log(xm), np.log(ym), 1, w=np.sqrt(w))[0]

    xm = np.array([g[:, 0].mean() for g in groups])
    ym = np.array([g[:, 1].mean() for g in groups])
    n = np.array([len(g) for g in groups], float)
    v = np.array([g[:, 1].var(ddof=1) for g in groups]) / ym ** 2
    u = np.log10(xm) - np.log10(xm).mean()
    s2 = variance.pooled_model(v[None], n, np.zeros(len(groups), int), u, 1)[0]
    w = n / s2
    x = slope(xm, ym, w)
    reps = bootstrap_cell_means(groups, boot, seed=2)
    replicas = np.array([slope(r[:, 0], r[:, 1], w) for r in reps])
    return {"beta": x, "beta_err": spread(replicas), "cells": len(groups), "replicas": replicas}


def extrapolate(per_n, key="beta"):
    """The N_G -> inf value by the reducer's rule (``fits.line_in_inverse_n``: the line and the
    parabola in 1/N_G averaged, from the sizes' replicas; the sizes' cells are independent)."""
    ok = [(n, r) for n, r in sorted(per_n.items()) if r is not None and np.isfinite(r[key + "_err"])]
    if len(ok) < 2:
        return None
    res = line_in_inverse_n([n for n, _ in ok], [r[key] for _, r in ok],
                            np.column_stack([r["replicas"] for _, r in ok]))
    return {key: res.value, key + "_err": res.err, "chi2_dof": res.chi2_dof}


def exponents_x(fin, alpha, dmax, boot):
    """``x`` of ``Delta Z = c E_G^x`` per N_G in the window, and extrapolated."""
    out = {}
    usable, _ = fin.usable()
    E, dZ = fin.scalars["E_G"], fin.scalars["delta_Z"]
    for N in np.unique(fin.N):
        groups = []
        for e in np.unique(fin.E[fin.N == N]):
            if typical_overlap(e, alpha) > dmax * (1 + 1e-9):
                continue
            m = usable & (fin.N == N) & (fin.E == e) & np.isfinite(dZ)
            if m.sum() >= 3:
                groups.append(np.column_stack([E[m], dZ[m]]))
        out[int(N)] = loglog_exponent(groups, int(N), boot)
    out["inf"] = extrapolate(out)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store", nargs="+")
    ap.add_argument("--boot", type=int, default=1000)
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)

    from campaign.results.finished import load_finished

    everything = load_finished(args.store)
    out = {}
    summary, shared = [], []
    for dmax in WINDOWS:
        red = reduce_campaign(args.store, Settings(n_boot=args.boot, fit_overlap=dmax), distributions=False)
        systems = {r["variant"]: r for r in red.systems}
        order = sorted(systems, key=lambda v: (systems[v]["alpha"], v))
        sizes = sorted({r["N_G"] for r in red.rows})
        label = "every energy" if not math.isfinite(dmax) else f"typical overlap <= {dmax:g}"
        option = "--fit-all" if not math.isfinite(dmax) else f"--fit-overlap {dmax:g}"
        print(f"\n## Fits over {label}: `campaign reduce {option}`\n")
        print("| system | alpha | sizes | " + " | ".join(f"beta_Z {n}" for n in sizes) + " | beta_Z inf | "
              "beta_E inf | x inf | beta_Z x | beta_Z/(2 alpha) |")
        print("|" + "---|" * (len(sizes) + 8))
        win = {}
        for v in order:
            r = systems[v]
            var = np.asarray(everything.variant, dtype=str)
            x = exponents_x(everything.subset(var == v), r["alpha"], dmax, min(args.boot, 200))
            rows = {row["N_G"]: row for row in red.rows if row["variant"] == v}
            xi = x["inf"]
            bzx = r["beta_Z"] * xi["beta"] if xi else math.nan
            bzx_err = (math.hypot(r["beta_Z_err"] * xi["beta"], r["beta_Z"] * xi["beta_err"]) if xi else math.nan)
            bz, be = fmt_err(r["beta_Z"], r["beta_Z_err"]), fmt_err(r["beta_E"], r["beta_E_err"])
            # x, beta_Z x and beta_Z/(2 alpha): the last three cells of both tables
            tail = " | ".join([fmt_err(xi["beta"], xi["beta_err"]) if xi else "-", fmt_err(bzx, bzx_err),
                               fmt_err(r["beta_Z_over_2alpha"], r["beta_Z_over_2alpha_err"])])
            print(f"| {v} | {r['alpha']:g} | {r['sizes']} | "
                  + " | ".join(fmt_err(rows[n]["beta_Z"], rows[n]["beta_Z_err"]) if n in rows else "-" for n in sizes)
                  + f" | {bz} | {be} | {tail} |")
            win[v] = {"system": r, "x": x, "rows": rows}
            summary.append(f"| {label if v == order[0] else ''} | {v} | {fmt_err(r['A_G_star_E'], r['A_G_star_E_err'])} | "
                           f"{be} | {bz} | {tail} |")
        val = np.array([systems[v]["beta_Z"] for v in order])
        err = np.array([systems[v]["beta_Z_err"] for v in order])
        ok = np.isfinite(val) & np.isfinite(err) & (err > 0)
        common = None
        if ok.sum() >= 2:
            wts = 1 / err[ok] ** 2
            mean = float(np.sum(wts * val[ok]) / np.sum(wts))
            chi2 = float(np.sum(((val[ok] - mean) / err[ok]) ** 2))
            dof = int(ok.sum()) - 1
            common = {"mean": mean, "err": 1 / math.sqrt(float(np.sum(wts))), "chi2": chi2, "dof": dof,
                      "p": float(stats.chi2.sf(chi2, dof))}
            print(f"\none beta_Z for every system (N_G -> inf): weighted mean "
                  f"{fmt_err(common['mean'], common['err'])}, chi^2 = {chi2:.1f} for {dof} degrees of freedom, "
                  f"p = {common['p']:.2g}")
        out[str(dmax)] = {"systems": win, "common_beta_Z": common}
        if common:
            shared.append(f"| {label} | {fmt_err(common['mean'], common['err'])} | {common['chi2']:.1f} / {common['dof']} | "
                          f"{common['p']:.2g} |")
    print("\n## Every window\n\n| window | system | A_G* | beta_E | beta_Z | x | beta_Z x | beta_Z/(2 alpha) |\n"
          "|---|---|---|---|---|---|---|---|\n" + "\n".join(summary))
    print("\nOne beta_Z for the systems (N_G -> inf; weighted mean, chi^2 about it):\n\n"
          "| window | common beta_Z | chi^2 / dof | p |\n|---|---|---|---|\n" + "\n".join(shared))
    if args.json:
        def clean(x):
            if isinstance(x, dict):
                return {str(k): clean(y) for k, y in x.items() if k != "replicas"}
            if isinstance(x, (list, tuple)):
                return [clean(y) for y in x]
            if isinstance(x, (float, np.floating)):
                return float(x) if np.isfinite(x) else None
            if isinstance(x, np.integer):
                return int(x)
            return x
        Path(args.json).write_text(json.dumps(clean(out), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
