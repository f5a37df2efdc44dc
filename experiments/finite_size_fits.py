"""Which fits enter the finite-size table, over which cells? Candidate estimators measured on
synthetic campaigns that have the finite-size plateau, then applied to real stores.

    python experiments/finite_size_fits.py [--reps 100] [--boot 200] [--grid hidden paper] [--json F]
    python experiments/finite_size_fits.py --store results/a.h5 [--halves]   # a real store

**Synthetic campaigns.** The harmonic system (alpha = 2). Per packing ``E_G`` lands in
``[E, 1.1 E]``, its typical overlap is ``delta = E_G^(1/2)`` and

    Delta Z_inf = z0 delta^(1/2)                                  (thermodynamic limit)
    Delta Z     = Delta Z_inf (1 - exp(-(N Delta Z_inf / x0)^2))  (the finite-size plateau)
    N Delta Z / 2 excess contacts drawn as whole numbers (variance 0.45 of the mean)
    A_G         = A*_inf + b / N + B Delta Z^beta_Z (1 + k Delta Z) + sd_A / sqrt(N) normal

so the law against ``Delta Z`` holds at every size (its amplitude does not depend on N, as
measured: ``(A_G - A_G(plateau)) / Delta Z`` = 0.195, 0.193, 0.199, 0.199 at N_G = 64..512,
E_G = 1e-6), while the law against ``E_G`` bends into a plateau below the crossover
``N_G Delta Z ~ x0`` (Goodrich, Liu & Nagel, PRL 109, 095704: ``p N^2 ~ 1``). The constants are
measured, not fitted to exponents: ``z0 = 5`` (``Delta Z`` at 1e-6 and 1e-5, N_G = 512), ``x0 =
4.3`` (the suppression of ``N_G Delta Z`` at 1e-8: 0.69 at N_G = 64 and 3.4 at 128 against 2.4
and 4.9 from ``z0``), ``b = -0.4`` (the plateaus 0.440 ... 0.446 at N_G = 64 ... 512), ``B =
0.22``, ``sd_A = 0.10``, from the cells (``cells.csv`` of ``campaign reduce``) of a 32-seed
campaign of the ``hidden`` grid (docs/REDUCED.md, "The N_G -> inf row").
Truth: ``beta_Z = 1.05``, ``beta_E = beta_Z / 4``, ``A*_inf = 0.446``; ``k = 0`` (no correction)
or ``k = -0.2`` (like paper-small, experiments/fit_rules.py).

**Grids.** ``hidden``: N_G 64, 128, 256, 512, E_G 1e-14, 1e-12, 1e-10, 1e-8, 1e-6, 1e-5, 1e-4,
1e-3, 16 seeds; ``paper``: N_G 64 ... 1024, E_G 1e-15 ... 1e-3 (one per decade), 20 seeds;
``four``: N_G 64 ... 512, E_G 1e-9, 1e-7, 1e-5, 1e-3, 16 seeds.

**Estimators** (``ESTIMATORS``), all on the cells of typical overlap <= 0.001 (the upper bound
of docs/REDUCED.md) and, with ``t``, of ``N_G Delta Z >= t`` (the cell's mean):

* ``per-size``: one fit per size, extrapolated linearly in 1/N_G over the sizes whose fit is
  determined (``fits.PowerLawFit.undetermined``; fewer than 2 sizes: no value);
* ``shared``: one fit per campaign, the exponent shared by the sizes with 3 cells or more, an
  intercept and an amplitude per size (``fits.fit_shared_exponent``); the exponent is the
  answer (no value when undetermined), the intercepts are extrapolated in 1/N_G.

Printed per grid, scenario, estimator and quantity: the failures (no value), the median bias in
units of the median error, the 1-sigma / 2-sigma coverage (nominal 0.68 / 0.95) and the median
error.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from campaign.results import bootstrap, fits

Z0, X0, Z_P = 5.0, 4.3, 0.55
A_INF, B_N, B_COEFF, SD_A0 = 0.446, -0.4, 0.22, 0.10
BETA_Z = 1.05
TRUTH = {"beta_E": BETA_Z / 4, "beta_Z": BETA_Z, "A_star_E": A_INF, "A_star_Z": A_INF}
OVERLAP_MAX = 0.001

GRIDS = {
    "hidden": dict(sizes=(64, 128, 256, 512), energies=(1e-14, 1e-12, 1e-10, 1e-8, 1e-6, 1e-5, 1e-4, 1e-3),
                   seeds=16),
    "paper": dict(sizes=(64, 128, 256, 512, 1024), energies=tuple(10.0 ** np.arange(-15, -2)), seeds=20),
    "four": dict(sizes=(64, 128, 256, 512), energies=(1e-9, 1e-7, 1e-5, 1e-3), seeds=16),
}
SCENARIOS = {"none": 0.0, "like paper-small": -0.2}
ESTIMATORS = {
    "per-size": ("per-size", 0.0), "per-size t=1": ("per-size", 1.0), "per-size t=3": ("per-size", 3.0),
    "per-size t=10": ("per-size", 10.0),
    "shared": ("shared", 0.0), "shared t=1": ("shared", 1.0), "shared t=3": ("shared", 3.0),
    "shared t=10": ("shared", 10.0),
}


def simulate(rng, N, energies, k, seeds):
    """Per cell: an array (seeds, 3) of per-packing (E_G, Delta Z, A_G)."""
    out = []
    for E in energies:
        E_G = E * (1 + 0.1 * rng.random(seeds))
        z_inf = Z0 * E_G ** 0.25
        z = z_inf * (1 - np.exp(-(N * z_inf / X0) ** 2))
        m = N * z / 2
        trials = np.maximum(np.ceil(m / Z_P), 1.0)
        dz = 2.0 / N * rng.binomial(trials.astype(np.int64), m / trials)
        A = A_INF + B_N / N + B_COEFF * z ** BETA_Z * (1 + k * z) + SD_A0 / math.sqrt(N) * rng.normal(0, 1, seeds)
        out.append(np.column_stack([E_G, dz, A]))
    return out


def select(cells, energies, N, t):
    """The cells of the default window: typical overlap <= 0.001 and N_G <Delta Z> >= t."""
    keep = []
    for E, c in zip(energies, cells):
        if math.sqrt(E) <= OVERLAP_MAX * (1 + 1e-9) and N * c[:, 1].mean() >= t:
            keep.append(c)
    return keep


def means(cells, col):
    x = np.array([c[:, col].mean() for c in cells])
    y = np.array([c[:, 2].mean() for c in cells])
    ye = np.array([c[:, 2].std(ddof=1) / math.sqrt(len(c)) for c in cells])
    return x, y, ye


def per_size(data, col, boot, seed):
    """{N: (beta, err, a, a_err) or None}, then the 1/N extrapolation of the determined ones."""
    got = {}
    for N, cells in data.items():
        if len(cells) < fits.MIN_CELLS:
            got[N] = None
            continue
        x, y, ye = means(cells, col)
        if np.count_nonzero(x > 0) < 3 or np.any(ye <= 0):
            got[N] = None
            continue
        reps = bootstrap.cell_means(cells, boot, seed=[seed, N])
        f = fits.fit_power_law(x, y, ye, boot_x=reps[:, :, col], boot_y=reps[:, :, 2])
        got[N] = None if f.undetermined else (f.exponent, f.exponent_err, f.intercept, f.intercept_err)
    ok = [(N, r) for N, r in got.items() if r is not None]
    if len(ok) < 2:
        return None
    b = fits.fit_inverse_n([N for N, _ in ok], [r[0] for _, r in ok], [r[1] for _, r in ok])
    a = fits.fit_inverse_n([N for N, _ in ok], [r[2] for _, r in ok], [r[3] for _, r in ok])
    return b.value, b.err, a.value, a.err


def shared(data, col, boot, seed):
    groups = []
    for N, cells in data.items():
        x, y, ye = means(cells, col) if cells else (np.zeros(0),) * 3
        if np.count_nonzero(x > 0) >= 3 and np.all(ye > 0):
            groups.append((N, cells, x, y, ye))
    if not groups:
        return None
    reps = [bootstrap.cell_means(c, boot, seed=[seed, N]) for N, c, *_ in groups]
    f = fits.fit_shared_exponent([g[2] for g in groups], [g[3] for g in groups], [g[4] for g in groups],
                                 boot_xs=[r[:, :, col] for r in reps], boot_ys=[r[:, :, 2] for r in reps])
    if f.undetermined:
        return None
    Ns = [g[0] for g in groups]
    if len(Ns) >= 2:
        a = fits.fit_inverse_n(Ns, f.intercepts, f.intercept_errs)
        a_val, a_err = a.value, a.err
    else:
        a_val = a_err = math.nan
    return f.exponent, f.exponent_err, a_val, a_err


def measure(grid, scenario, estimators, reps, boot, seed0=7):
    g = GRIDS[grid]
    k = SCENARIOS[scenario]
    res = {(e, q): [] for e in estimators for q in ("beta_E", "beta_Z", "A_star_E", "A_star_Z")}
    for rep in range(reps):
        rng = np.random.default_rng([seed0, rep, list(GRIDS).index(grid), list(SCENARIOS).index(scenario)])
        data = {N: simulate(rng, N, g["energies"], k, g["seeds"]) for N in g["sizes"]}
        for name in estimators:
            kind, t = ESTIMATORS[name]
            sel = {N: select(c, g["energies"], N, t) for N, c in data.items()}
            for col, (qb, qa) in ((0, ("beta_E", "A_star_E")), (1, ("beta_Z", "A_star_Z"))):
                r = (per_size if kind == "per-size" else shared)(sel, col, boot, rep)
                res[(name, qb)].append(None if r is None else r[:2])
                res[(name, qa)].append(None if r is None or not np.isfinite(r[2]) else r[2:])
    return res


def summarise(res, reps):
    rows = []
    for (name, q), vals in res.items():
        good = [v for v in vals if v is not None and np.isfinite(v[0]) and np.isfinite(v[1]) and v[1] > 0]
        row = dict(estimator=name, quantity=q, truth=TRUTH[q], fails=reps - len(good))
        if good:
            b = np.array([v[0] for v in good])
            e = np.array([v[1] for v in good])
            row.update(median=float(np.median(b)), median_bias=float(np.median(b) - TRUTH[q]),
                       err=float(np.median(e)), cov1=float(np.mean(np.abs(b - TRUTH[q]) <= e)),
                       cov2=float(np.mean(np.abs(b - TRUTH[q]) <= 2 * e)))
        rows.append(row)
    return rows


def print_rows(rows, title):
    print(f"\n### {title}\n")
    print("| estimator | quantity (truth) | no value | median | median bias / error | cover 1 / 2 sigma | median error |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        if "median" not in r:
            print(f"| {r['estimator']} | {r['quantity']} ({r['truth']:.4g}) | {r['fails']} | - | - | - | - |")
            continue
        print(f"| {r['estimator']} | {r['quantity']} ({r['truth']:.4g}) | {r['fails']} | {r['median']:.4f} | "
              f"{r['median_bias'] / r['err']:+.1f} | {r['cov1']:.2f} / {r['cov2']:.2f} | {r['err']:.4f} |")


def store_data(paths, halves):
    """{label: {N: [cells]}} of a store's default variant: every seed, or two disjoint halves."""
    from campaign.results.finished import load_finished

    fin = load_finished(paths)
    ok, _ = fin.usable()
    fin = fin.subset(ok & (np.asarray(fin.variant, dtype=str) == "default"))
    cols = np.column_stack([fin.scalars["E_G"], fin.scalars["delta_Z"], fin.scalars["A_G"]])
    parts = {"all seeds": np.ones(len(fin), bool)}
    if halves:
        cut = np.median(np.unique(fin.seed))
        parts = {"seeds below the median": fin.seed < cut, "seeds above": fin.seed >= cut}
    out = {}
    for label, m in parts.items():
        data = {}
        for N in np.unique(fin.N[m]):
            Es = np.unique(fin.E[m & (fin.N == N)])
            data[int(N)] = (Es, [cols[m & (fin.N == N) & (fin.E == E)] for E in Es])
        out[label] = data
    return out


def real_store(paths, estimators, boot, halves):
    print("| seeds | estimator | beta_E | beta_Z | A*(E_G=0) | A*(Delta Z=0) |")
    print("|---|---|---|---|---|---|")
    from campaign.results.tables import fmt_err

    for label, data in store_data(paths, halves).items():
        for name in estimators:
            kind, t = ESTIMATORS[name]
            sel = {N: select(c, Es, N, t) for N, (Es, c) in data.items()}
            got = []
            for col in (0, 1):
                r = (per_size if kind == "per-size" else shared)(sel, col, boot, 0)
                got.append(("--", "--") if r is None else (fmt_err(r[0], r[1]), fmt_err(r[2], r[3])))
            print(f"| {label} | {name} | {got[0][0]} | {got[1][0]} | {got[0][1]} | {got[1][1]} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--boot", type=int, default=200)
    ap.add_argument("--grid", nargs="+", default=["hidden", "paper"], choices=list(GRIDS))
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS))
    ap.add_argument("--estimators", nargs="+", default=list(ESTIMATORS), choices=list(ESTIMATORS))
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--store", nargs="+", metavar="FILE", help="apply the estimators to these stores instead")
    ap.add_argument("--halves", action="store_true", help="with --store: two disjoint halves of the seeds")
    args = ap.parse_args(argv)
    if args.store:
        real_store(args.store, args.estimators, args.boot, args.halves)
        return 0
    t0 = time.time()
    out = {}
    for grid in args.grid:
        for sc in args.scenarios:
            rows = summarise(measure(grid, sc, args.estimators, args.reps, args.boot), args.reps)
            print_rows(rows, f"grid {grid}, correction {sc}, {args.reps} campaigns, bootstrap {args.boot}")
            out[f"{grid}/{sc}"] = rows
            sys.stdout.flush()
    print(f"\n{time.time() - t0:.0f} s", file=sys.stderr)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
