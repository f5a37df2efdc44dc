"""Which default fit range? Candidate rules measured on synthetic data with a known exponent
and a known correction to scaling, then applied to real stores.

    python experiments/fit_rules.py [--reps 200] [--boot 200] [--json FILE] [--pivot 1024 inf]  # synthetic
    python experiments/fit_rules.py --from-json FILE --pivot inf                # its tables again
    python experiments/fit_rules.py --store results/paper-small.h5 [--boot 1000]  # a real store

**Synthetic data.** Per N_G, the grid of a campaign (one energy per decade, 20 packings per cell);
each packing's ``E_G`` lands in ``[E, 1.1 E]``, its typical overlap is
``delta = (alpha E_G / 2)^(1/alpha)``, and

    Delta Z_true = z0 delta^(1/2)                         (jamming scaling)
    Delta Z      = (2 / N) Binomial(m / p, p),  m = N Delta Z_true / 2   (whole excess contacts)
    A_G          = A* + B Delta Z_true^beta_Z (1 + k Delta Z_true^omega) + sd_A(N, E) normal

(``p = 0.55``: the variance of the excess contacts 0.45 times their mean, as measured on
paper-small at N_G = 1024, 1e-9 to 1e-5), so the law against ``Delta Z`` has the exponent
``beta_Z`` and the correction ``k x^omega``, and the law against ``E_G`` the exponent
``beta_E = beta_Z / (2 alpha)`` and the correction exponent ``omega / (2 alpha)``: a correction
set by the distance from jamming, the same for every potential. ``sd_A`` is the packing-to-packing spread of ``A_G`` measured on paper-small
(``SD_A0`` below, or per cell with ``--noise-from STORE``). Scenarios (``SCENARIOS``): no
correction (``k = 0``); a correction like paper-small's (the synthetic data fitted over every
energy give paper-small's ``beta_Z``, and over ``E_G <= 1e-5`` its value there); 1.5 times it;
and a slow one (``omega = 0.5``) that a chi^2 test hardly sees. ``B``, ``z0`` and the noise are
paper-small's at N_G = 1024; the truth ``beta_Z = 1.05`` is a round number near the correction
fits' 0.99-1.07 of paper-small at N_G = 256..1024.

**Rules**, each giving per N_G a set of cells and a fit ``y = a + c x^beta`` (the reducer's
weighted least squares with bootstrap errors over packings) or, for ``corr``, ``y = a + c x^beta
+ e x^(beta + omega)``:

* ``all``: every energy (the reducer's default before, now ``--fit-all``);
* ``overlap D``: the cells whose typical overlap is at most ``D`` (one distance from jamming for
  every alpha; D = 0.01, 0.003, 0.001). The reducer's default is 0.001, chosen from this
  measurement (docs/REDUCED.md, "The fit range");
* ``corr``: every energy, with a correction-to-scaling term (``omega`` free in [0.1, 2], profiled
  like ``beta``);
* ``chi2 P``: the widest range from the lowest energy whose power law passes a chi^2 test at
  level ``P`` (p-value of chi^2 with ``n - 3`` degrees of freedom at least ``P``), at least
  5 cells; no range passing: no fit (counted as a failure). Each fit chooses its own range;
  ``chi2-E P``: the range chosen by the fit against E_G, used by both fits.

For each rule and fit (``beta_E``: A_G against E_G; ``beta_Z``: against Delta Z) and size, over
``--reps`` realisations: the bias (mean estimate minus truth; ``--pivot`` shows the median, which
the few wild fits of short ranges do not move), the spread of the estimates, the median bootstrap
error, the fraction of 1-sigma and 2-sigma intervals that cover the truth
(nominal 68% and 95%), the mean number of cells kept, and the failures (no fit). ``inf`` is the
reducer's linear extrapolation in 1/N_G of the per-size values (the truth does not depend on N).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np
from scipy import stats

from campaign.results import bootstrap, fits
from campaign.results.scaling import typical_overlap
from campaign.results.tables import fmt_err

SIZES = (64, 128, 256, 512, 1024)
SEEDS = 20
#: Per-packing standard deviation of A_G: ``SD_A0 / sqrt(N_G)``, as on paper-small (the RMS over its
#: 13 energies of the per-cell sd times sqrt(N_G) is 0.098, 0.103, 0.101, 0.102, 0.106 for
#: N_G = 64..1024); ``--noise-from STORE`` takes each cell's own sd from a store instead.
SD_A0 = 0.10
SD_A = None


def paper_grid(alpha):
    """One energy per decade from 1e-3 down to the universality campaigns' floors."""
    lowest = {2.0: -15, 2.5: -18, 3.0: -21}[float(alpha)]
    return 10.0 ** np.arange(lowest, -2)


# --------------------------------------------------------------------------- truths
SCENARIOS = {
    # name: beta_Z, and the correction k Delta Z^omega; B and z0 fixed below. "like
    # paper-small": fitted over every energy the synthetic data give paper-small's beta_Z
    # (0.92-0.93 against 0.914-0.918 at N_G = 256..1024) and over E_G <= 1e-5 its 1.01 (0.97-1.02).
    "none": dict(beta_Z=1.05, k=0.0, omega=1.0),
    "like paper-small": dict(beta_Z=1.05, k=-0.2, omega=1.0),
    "1.5x": dict(beta_Z=1.05, k=-0.3, omega=1.0),
    "slow": dict(beta_Z=1.05, k=-0.1, omega=0.5),
}
B_COEFF = 0.22     # Delta A_G = 0.054 at Delta Z = 0.28 (paper-small, N_G = 1024, E_G = 1e-5)
Z0 = 5.0           # Delta Z = 0.28 at E_G = 1e-5 (the same cell)
Z_P = 0.55
A_STAR = 0.446


def sd_a(N, E):
    if SD_A is not None and (N, E) in SD_A:
        return SD_A[(N, E)]
    return SD_A0 / math.sqrt(N)


def simulate(rng, N, Es, alpha, sc, seeds=SEEDS):
    """Per cell (E ascending): an array (seeds, 3) of per-packing (E_G, Delta Z, A_G)."""
    out = []
    for E in Es:
        E_G = E * (1 + 0.1 * rng.random(seeds))
        delta = (alpha * E_G / 2) ** (1 / alpha)
        zt = Z0 * delta**0.5
        m = N * zt / 2                        # excess contacts
        trials = np.maximum(np.ceil(m / Z_P), 1.0)
        dz = 2.0 / N * rng.binomial(trials.astype(np.int64), m / trials)
        dA = B_COEFF * zt ** sc["beta_Z"] * (1 + sc["k"] * zt ** sc["omega"])
        A = A_STAR + dA + sd_a(N, E) * rng.normal(0, 1, seeds)
        out.append(np.column_stack([E_G, dz, A]))
    return out


# --------------------------------------------------------------------------- fits
def _solve3(f1, f2, y, w):
    """Weighted LS of y = a + c f1 + e f2 per row (f1, f2, y: (..., K), w (K,)): (a, c, e, chi2)."""
    one = np.ones_like(f1)
    cols = (one, f1, f2)
    M = np.empty(f1.shape[:-1] + (3, 3))
    v = np.empty(f1.shape[:-1] + (3,))
    for i, ci in enumerate(cols):
        v[..., i] = np.sum(w * ci * y, axis=-1)
        for j, cj in enumerate(cols):
            M[..., i, j] = np.sum(w * ci * cj, axis=-1)
    with np.errstate(all="ignore"):
        try:
            p = np.linalg.solve(M, v[..., None])[..., 0]
        except np.linalg.LinAlgError:
            p = np.full(v.shape, np.nan)
    r = y - p[..., 0:1] - p[..., 1:2] * f1 - p[..., 2:3] * f2
    chi2 = np.sum(w * r * r, axis=-1)
    return p, np.where(np.isfinite(chi2), chi2, np.inf)


def fit_corrected_batch(x, y, yerr, betas=np.linspace(0.02, 4.0, 100), omegas=np.geomspace(0.1, 2.0, 14)):
    """``y = a + c x^beta + e x^(beta + omega)`` per row by profiling chi^2 over a (beta, omega)
    grid, then refining beta around the best grid point. Returns (a, beta, omega, chi2)."""
    x = np.atleast_2d(x)
    y = np.atleast_2d(y)
    w = 1.0 / np.asarray(yerr, float) ** 2
    pos = x > 0
    lx = np.where(pos, np.log(np.where(pos, x, 1.0)), -np.inf)
    lref = (np.where(pos, lx, 0.0).sum(-1) / np.maximum(pos.sum(-1), 1))[:, None]
    lu = lx - lref
    best = np.full(x.shape[0], np.inf)
    out = np.full((x.shape[0], 3), np.nan)
    rows = np.arange(x.shape[0])
    for om in omegas:  # every beta of the grid at once: arrays (G, B, K)
        f1 = np.exp(betas[:, None, None] * lu[None])
        f2 = f1 * np.exp(om * lu)[None]
        p, chi2 = _solve3(f1, f2, y[None], w)
        k = np.argmin(chi2, axis=0)
        c = chi2[k, rows]
        better = c < best
        best = np.where(better, c, best)
        out[better] = np.column_stack([p[k, rows, 0][better], betas[k][better], np.full(better.sum(), om)])
    # refine beta (omega fixed at its grid value) on a fine local grid
    step = betas[1] - betas[0]
    fine = np.linspace(-step, step, 41)
    b = out[:, 1][None, :] + fine[:, None]                      # (F, B)
    with np.errstate(invalid="ignore"):  # rows without any finite fit stay NaN
        f1 = np.exp(b[..., None] * lu[None])
        f2 = f1 * np.exp(out[:, 2][None, :, None] * lu[None])
        p, chi2 = _solve3(f1, f2, y[None], w)
    k = np.argmin(chi2, axis=0)
    c = chi2[k, rows]
    better = c < best
    best = np.where(better, c, best)
    out[better, 0] = p[k, rows, 0][better]
    out[better, 1] = b[k, rows][better]
    return out[:, 0], out[:, 1], out[:, 2], best


def cell_arrays(cells, col_x, col_y=2):
    x = np.array([c[:, col_x].mean() for c in cells])
    y = np.array([c[:, col_y].mean() for c in cells])
    ye = np.array([c[:, col_y].std(ddof=1) / math.sqrt(len(c)) for c in cells])
    return x, y, ye


def plain_fit(cells, col_x, boot, seed):
    """The reducer's fit over these cells: dict or None."""
    if len(cells) < 4:
        return None
    x, y, ye = cell_arrays(cells, col_x)
    if np.count_nonzero(x > 0) < 3 or np.any(ye <= 0):
        return None
    bx = by = None
    if boot:
        reps = bootstrap.cell_means(cells, boot, seed=seed)
        bx, by = reps[:, :, col_x], reps[:, :, 2]
    f = fits.fit_power_law(x, y, ye, boot_x=bx, boot_y=by)
    if not f.ok:
        return None
    return dict(beta=f.exponent, beta_err=f.exponent_err, a=f.intercept, a_err=f.intercept_err,
                chi2=f.chi2, dof=f.dof, cells=len(cells))


def corr_fit(cells, col_x, boot, seed):
    if len(cells) < 6:
        return None
    x, y, ye = cell_arrays(cells, col_x)
    if np.count_nonzero(x > 0) < 5 or np.any(ye <= 0):
        return None
    a, b, om, chi2 = (v[0] for v in fit_corrected_batch(x[None], y[None], ye))
    res = dict(beta=b, a=a, omega=om, chi2=chi2, dof=len(cells) - 5, cells=len(cells),
               beta_err=math.nan, a_err=math.nan)
    if boot:
        reps = bootstrap.cell_means(cells, boot, seed=seed)
        ba, bb, _, _ = fit_corrected_batch(reps[:, :, col_x], reps[:, :, 2], ye)
        res["beta_err"] = float(np.std(bb, ddof=1))
        res["a_err"] = float(np.std(ba, ddof=1))
    return res


def chi2_range(cells, col_x, level, kmin):
    """The number of lowest-energy cells of the widest range whose power law passes the chi^2
    test at ``level`` (at least ``kmin`` cells), or 0 when none passes."""
    x, y, ye = cell_arrays(cells, col_x)
    for n in range(len(cells), kmin - 1, -1):
        if np.count_nonzero(x[:n] > 0) < 3 or np.any(ye[:n] <= 0):
            continue
        f = fits.fit_power_law(x[:n], y[:n], ye[:n])
        if f.ok and stats.chi2.sf(f.chi2, f.dof) >= level:
            return n
    return 0


def apply_rule(rule, cells, Es, alpha, col_x, boot, seed):
    """Cells sorted by energy; returns the fit dict (with ``E_hi``) or None."""
    kind = rule[0]
    if kind == "all":
        sel = cells
    elif kind == "overlap":
        keep = typical_overlap(Es, alpha) <= rule[1] * (1 + 1e-9)   # the reducer's --fit-overlap
        sel = [c for c, k in zip(cells, keep) if k]
    elif kind == "corr":
        r = corr_fit(cells, col_x, boot, seed)
        if r is not None:
            r["E_hi"] = float(Es[-1])
        return r
    elif kind == "chi2":
        n = chi2_range(cells, col_x, rule[1], rule[2])
        sel = cells[:n]
    elif kind == "chi2-E":  # the range of the fit against E_G, for both fits
        n = chi2_range(cells, 0, rule[1], rule[2])
        sel = cells[:n]
    else:
        raise ValueError(rule)
    r = plain_fit(sel, col_x, boot, seed)
    if r is not None:
        r["E_hi"] = float(Es[len(sel) - 1])
    return r


RULES = {
    "all": ("all",),
    "overlap 0.01": ("overlap", 0.01),
    "overlap 0.003": ("overlap", 0.003),
    "overlap 0.001": ("overlap", 0.001),
    "corr": ("corr",),
    "chi2 0.05": ("chi2", 0.05, 5),
    "chi2 0.01": ("chi2", 0.01, 5),
    "chi2-E 0.05": ("chi2-E", 0.05, 5),
}
FITS = {"beta_E": 0, "beta_Z": 1}   # column of the abscissa: E_G, Delta Z


def truth_of(sc, alpha):
    return {"beta_E": sc["beta_Z"] / (2 * alpha), "beta_Z": sc["beta_Z"], "A_star": A_STAR}


# --------------------------------------------------------------------------- measurement
def measure(scenarios, rules, alphas, reps, boot, sizes, seed0=1):
    """{(scenario, alpha, rule, fit, N): list of (estimate, error) or None}."""
    out = {}
    for sname in scenarios:
        sc = SCENARIOS[sname]
        for alpha in alphas:
            Es = paper_grid(alpha)
            for rep in range(reps):
                rng = np.random.default_rng([seed0, rep, int(alpha * 10), list(SCENARIOS).index(sname)])
                data = {N: simulate(rng, N, Es, alpha, sc) for N in sizes}
                for rname in rules:
                    for fname, col in FITS.items():
                        per_n = {}
                        for N in sizes:
                            r = apply_rule(RULES[rname], data[N], Es, alpha, col, boot, [rep, N])
                            per_n[N] = r
                            out.setdefault((sname, alpha, rname, fname, N), []).append(r)
                        ok = [(N, r) for N, r in per_n.items() if r is not None and np.isfinite(r["beta_err"])]
                        ex = None
                        if len(ok) >= 2:
                            e = fits.fit_inverse_n([N for N, _ in ok], [r["beta"] for _, r in ok],
                                                   [r["beta_err"] for _, r in ok])
                            ex = dict(beta=e.value, beta_err=e.err, cells=np.nan, E_hi=np.nan)
                        out.setdefault((sname, alpha, rname, fname, "inf"), []).append(ex)
    return out


def summarise(results, scenarios_alpha_truth):
    rows = []
    for key, rs in results.items():
        sname, alpha, rname, fname, N = key
        truth = scenarios_alpha_truth[(sname, alpha)][fname]
        good = [r for r in rs if r is not None and np.isfinite(r["beta"]) and np.isfinite(r["beta_err"])]
        n = len(rs)
        row = dict(scenario=sname, alpha=alpha, rule=rname, fit=fname, N=N, truth=truth, reps=n,
                   fails=n - len(good))
        if good:
            b = np.array([r["beta"] for r in good])
            e = np.array([r["beta_err"] for r in good])
            row.update(bias=float(b.mean() - truth), median_bias=float(np.median(b) - truth),
                       sd=float(b.std(ddof=1)) if len(b) > 1 else math.nan,
                       err=float(np.median(e)), cov1=float(np.mean(np.abs(b - truth) <= e)),
                       cov2=float(np.mean(np.abs(b - truth) <= 2 * e)),
                       cells=float(np.nanmean([r["cells"] for r in good])),
                       E_hi=float(np.nanmedian([r["E_hi"] for r in good])))
        rows.append(row)
    return rows


def print_table(rows, sizes_shown=(64, 1024, "inf"), file=sys.stdout):
    hdr = ("scenario", "alpha", "fit", "rule", "N_G", "cells", "median E_hi", "fails", "bias",
           "sd", "error", "bias/error", "cover 1 sigma", "cover 2 sigma")
    print("| " + " | ".join(hdr) + " |", file=file)
    print("|" + "---|" * len(hdr), file=file)
    for r in rows:
        if r["N"] not in sizes_shown:
            continue
        if "bias" not in r:
            vals = ["-"] * 8
        else:
            vals = [f"{r['cells']:.1f}" if np.isfinite(r["cells"]) else "-",
                    f"{r['E_hi']:.0e}" if np.isfinite(r["E_hi"]) else "-", f"{r['fails']}",
                    f"{r['bias']:+.3f}", f"{r['sd']:.3f}", f"{r['err']:.3f}",
                    f"{r['bias'] / r['err']:+.1f}" if r["err"] > 0 else "-",
                    f"{r['cov1']:.2f}", f"{r['cov2']:.2f}"]
            vals = vals[:2] + vals[2:]
        print(f"| {r['scenario']} | {r['alpha']:g} | {r['fit']} ({r['truth']:.3f}) | {r['rule']} | {r['N']} | "
              + " | ".join(vals) + " |", file=file)


def print_pivot(rows, size="inf", file=sys.stdout):
    """One line per (alpha, fit, rule), one column group per scenario: the median bias in units of
    the median bootstrap error (robust to the few wild fits of short ranges) and the 1-sigma /
    2-sigma coverage, at one size (``inf``: extrapolated); the median error beside."""
    scen = list(dict.fromkeys(r["scenario"] for r in rows))
    by = {(r["scenario"], r["alpha"], r["fit"], r["rule"]): r for r in rows if str(r["N"]) == str(size)}
    print(f"N_G = {size}: median bias / median error, coverage of the 1-sigma / 2-sigma intervals "
          "(nominal 0.68 / 0.95)\n",
          file=file)
    print("| alpha | fit | rule | median error | " + " | ".join(scen) + " | failures |", file=file)
    print("|" + "---|" * (len(scen) + 5), file=file)
    for alpha in dict.fromkeys(r["alpha"] for r in rows):
        for fit in FITS:
            for rule in dict.fromkeys(r["rule"] for r in rows):
                got = [by.get((sc, alpha, fit, rule)) for sc in scen]
                if not any(got):
                    continue
                errs = [g["err"] for g in got if g and "err" in g]
                cells = []
                for g in got:
                    if not g or "bias" not in g:
                        cells.append("-")
                    else:
                        cells.append(f"{g['median_bias'] / g['err']:+.1f}, {g['cov1']:.2f} / {g['cov2']:.2f}")
                fails = sum(g["fails"] for g in got if g)
                print(f"| {alpha:g} | {fit} | {rule} | {np.median(errs):.3f} | " + " | ".join(cells)
                      + f" | {fails} |", file=file)


# --------------------------------------------------------------------------- real stores
def store_cells(paths):
    """{(variant, N): (Es, cells)} of a store's usable packings (3 or more per cell)."""
    from campaign.results.finished import load_finished, variant_systems

    fin = load_finished(paths)
    ok, _ = fin.usable()
    fin = fin.subset(ok)
    systems = variant_systems(fin.attrs, variants=sorted(set(fin.variant)))
    out = {}
    var = np.asarray(fin.variant, dtype=str)
    for v in sorted(set(var)):
        for N in np.unique(fin.N[var == v]):
            Es, cells = [], []
            for E in np.unique(fin.E[(var == v) & (fin.N == N)]):
                m = (var == v) & (fin.N == N) & (fin.E == E)
                d = np.column_stack([fin.scalars["E_G"][m], fin.scalars["delta_Z"][m], fin.scalars["A_G"][m]])
                d = d[np.all(np.isfinite(d), axis=1)]
                if len(d) >= 3:
                    Es.append(E)
                    cells.append(d)
            out[(v, int(N))] = (np.array(Es), cells, systems[v]["exponent"])
    return out


def noise_table(paths):
    """Per-packing standard deviation of A_G per (N, E) of a store's default variant."""
    table = {}
    for (v, N), (Es, cells, _) in store_cells(paths).items():
        if v == "default":
            for E, c in zip(Es, cells):
                table[(N, float(E))] = float(c[:, 2].std(ddof=1))
    return table


def real_store(paths, rules, boot):
    data = store_cells(paths)
    variants = sorted({v for v, _ in data})
    out = []
    for v in variants:
        keys = sorted(k for k in data if k[0] == v)
        print(f"\n### {v}\n")
        print("| fit | rule | " + " | ".join(f"N_G={N}" for _, N in keys) + " | N_G -> inf |")
        print("|" + "---|" * (len(keys) + 3))
        for fname, col in FITS.items():
            for rname in rules:
                per = []
                for k in keys:
                    Es, cells, alpha = data[k]
                    r = apply_rule(RULES[rname], cells, Es, alpha, col, boot, [0, k[1]])
                    per.append(r)
                ok = [(k[1], r) for k, r in zip(keys, per) if r is not None and np.isfinite(r["beta_err"])]
                ex = (fits.fit_inverse_n([n for n, _ in ok], [r["beta"] for _, r in ok],
                                         [r["beta_err"] for _, r in ok]) if len(ok) >= 2 else None)

                def cell(r):
                    if r is None:
                        return "--"
                    chi = r["chi2"] / r["dof"] if r["dof"] > 0 else math.nan
                    return f"{fmt_err(r['beta'], r['beta_err'])} [<= {r['E_hi']:.0e}, {chi:.1f}]"

                print(f"| {fname} | {rname} | " + " | ".join(cell(r) for r in per) + " | "
                      + (fmt_err(ex.value, ex.err) if ex else "--") + " |")
                out.append(dict(variant=v, fit=fname, rule=rname,
                                per_N={int(k[1]): r for k, r in zip(keys, per)},
                                inf=None if ex is None else (ex.value, ex.err)))
    return out


def main(argv=None):
    global SD_A
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", nargs="+", metavar="FILE", help="apply the rules to these stores instead")
    ap.add_argument("--noise-from", nargs="+", metavar="FILE",
                    help="take the per-cell spread of A_G from this store (default: the built-in table)")
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--boot", type=int, default=200)
    ap.add_argument("--rules", nargs="+", default=list(RULES), choices=list(RULES))
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS))
    ap.add_argument("--alphas", nargs="+", type=float, default=[2.0])
    ap.add_argument("--sizes", nargs="+", type=int, default=list(SIZES))
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--from-json", metavar="FILE", help="print the tables of an earlier --json instead")
    ap.add_argument("--pivot", nargs="+", default=None, metavar="N",
                    help="print one compact table per size (e.g. 1024 inf) instead of the long one")
    args = ap.parse_args(argv)
    if args.from_json:
        with open(args.from_json) as fh:
            rows = json.load(fh)
        for size in args.pivot or []:
            print_pivot(rows, size)
            print()
        if not args.pivot:
            print_table(rows)
        return 0
    if args.store:
        out = real_store(args.store, args.rules, args.boot)
        if args.json:
            with open(args.json, "w") as fh:
                json.dump(out, fh, default=float, indent=1)
        return 0
    if args.noise_from:
        SD_A = noise_table(args.noise_from)
    t0 = time.time()
    res = measure(args.scenarios, args.rules, args.alphas, args.reps, args.boot, tuple(args.sizes))
    truths = {(s, a): truth_of(SCENARIOS[s], a) for s in args.scenarios for a in args.alphas}
    rows = summarise(res, truths)
    for size in args.pivot or []:
        print_pivot(rows, size)
        print()
    if not args.pivot:
        print_table(rows)
    print(f"\n{args.reps} realisations, bootstrap {args.boot}, {time.time() - t0:.0f} s", file=sys.stderr)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, default=float, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
