"""beta_E and beta_Z of a campaign store under the conventions the paper may have used
(hypotheses (a), (b) and (d) of docs/PAPER.md), side by side.

    python experiments/paper_hypotheses.py results/paper-small.h5 [--boot 200] [--json FILE]

Reads the finished, usable packings of the store (converged jams whose identities hold,
as `campaign reduce` does), groups them into (N_G, E_G) cells of the default variant and
fits ``A_G = A* + c x^beta`` per N_G with the reducer's fitting code
(``campaign.results.fits.fit_power_law``: weighted least squares on the cell means, each cell
weighted by its packings over the spread of the size's variance model, ``campaign.results.variance``,
fitted again in every replica of a bootstrap over packings; the reducer's first stage: the spread of
``A_G`` itself), for these choices of the abscissa ``x`` and of the fit:

* ``E`` -- this project's E_G (sum over unordered pairs / all disks): the reducer's fit over
  every energy (``campaign reduce --fit-all``);
* ``E ordered/N_G`` -- Eq. (2) of the paper read literally: sum over ordered pairs
  divided by the non-rattlers, ``2 E_G N / N_G`` per packing (hypothesis a);
* ``E/N_G`` -- per non-rattler (hypothesis a);
* ``E<=1e-5``, ``E<=1e-6``, ``E>=1e-12`` -- fit ranges (hypothesis d);
* ``unweighted`` -- every cell the same weight (hypothesis d);
* ``log-log, A* fixed`` -- a straight line through ``log(A_G - A*)`` against ``log x``
  with ``A*`` fixed at the mean of the lowest-energy cell (hypothesis d);
* ``dZ`` -- Delta Z = <z_g> - (4 - 2/N_G) over non-rattlers: the reducer's fit over every energy;
* ``dZ, z_iso=4`` -- ``<z_g> - 4`` (hypothesis b; cells with a negative mean are dropped);
* ``dZ, rattlers counted`` -- all contacts over all disks, ``2 C / N - (4 - 2/N)`` (hypothesis b;
  cells with a negative mean are dropped).
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from campaign.results import bootstrap, variance
from campaign.results.fits import fit_power_law
from campaign.results.finished import load_finished


def cells(fin, quantity, abscissa, keep=None):
    """Per (N, E) cell: packings' (x, y) rows; dict N -> list of arrays (n_k, 2)."""
    out = {}
    for N in np.unique(fin.N):
        groups = []
        for E in np.unique(fin.E[fin.N == N]):
            m = (fin.N == N) & (fin.E == E)
            if keep is not None:
                m &= keep(E)
            x = abscissa[m]
            y = quantity[m]
            ok = np.isfinite(x) & np.isfinite(y)
            if ok.sum() >= 3:
                groups.append(np.column_stack([x[ok], y[ok], np.full(ok.sum(), np.log10(E))]))
        out[int(N)] = groups
    return out


def fit(groups, boot, loglog=False, weighted=True):
    if len(groups) < 4:
        return None
    xm = np.array([g[:, 0].mean() for g in groups])
    if np.any(xm < 0):
        keep = xm >= 0
        groups = [g for g, k in zip(groups, keep) if k]
        return fit(groups, boot, loglog, weighted) if len(groups) >= 4 else None
    rng = bootstrap.generator(1)
    moments = [bootstrap.cell_moments(g[:, :2], bootstrap.seed_weights(rng, len(g), boot) if boot else None)
               for g in groups]
    means = np.stack([m for m, _ in moments], 1)            # (1 + boot, cells, 2), row 0 the data's
    n = np.array([len(g) for g in groups], float)
    u = np.array([g[0, 2] for g in groups])
    ye_all = np.sqrt(variance.pooled_model(np.stack([c[:, 1, 1] for _, c in moments], 1), n,
                                           np.zeros(len(n), int), u - u.mean(), 1) / n)
    xm, ym, ye = means[0, :, 0], means[0, :, 1], ye_all[0]
    reps = means[1:] if boot else None
    if not weighted:
        ye, ye_all = np.full_like(ye, ye.mean()), None
    if loglog:
        return _loglog(xm, ym, reps)
    f = fit_power_law(xm, ym, ye, boot_x=None if reps is None else reps[:, :, 0],
                      boot_y=None if reps is None else reps[:, :, 1],
                      boot_err=None if (reps is None or ye_all is None) else ye_all[1:])
    return dict(A_star=f.intercept, A_star_err=f.intercept_err, beta=f.exponent, beta_err=f.exponent_err,
                chi2_dof=f.chi2_dof, cells=len(groups))


def _loglog(xm, ym, reps):
    """log(y - A*) = log c + beta log x, A* fixed at the mean of the cell of smallest x
    (the lowest energy standing in for the jamming point), fitted on the other cells."""
    def one(x, y):
        o = np.argsort(x)
        a_star = y[o[0]]
        d = y - a_star
        ok = (d > 0) & (x > 0)
        b, _ = np.polyfit(np.log(x[ok]), np.log(d[ok]), 1)
        return a_star, b
    a, b = one(xm, ym)
    if reps is not None:
        bs = [one(r[:, 0], r[:, 1]) for r in reps]
        ae, be = np.std([v[0] for v in bs], ddof=1), np.std([v[1] for v in bs], ddof=1)
    else:
        ae = be = float("nan")
    return dict(A_star=a, A_star_err=ae, beta=b, beta_err=be, chi2_dof=float("nan"), cells=len(xm))


def fmt(r, key="beta"):
    if r is None:
        return "-"
    v, e = r[key], r[key + "_err"]
    if not np.isfinite(e) or e <= 0:
        return f"{v:.3f}"
    d = max(0, -int(math.floor(math.log10(e))) + 1)
    return f"{v:.{d}f}({round(e * 10 ** d):d})"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store", nargs="+")
    ap.add_argument("--boot", type=int, default=200)
    ap.add_argument("--variant", default="default")
    ap.add_argument("--max-n", type=int, default=1024)
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)

    fin = load_finished(args.store)
    usable, _ = fin.usable()
    var = np.array([v.decode() if isinstance(v, bytes) else str(v) for v in fin.variant])
    fin = fin.subset(usable & (var == args.variant) & (fin.N <= args.max_n))
    s = fin.scalars
    A = s["A_G"]
    E = s["E_G"]
    n_all = s["N"]
    n_g = s["N_G"]
    E_ord = 2.0 * E * n_all / n_g
    E_nr = E * n_all / n_g
    dZ = s["delta_Z"]
    dZ4 = s["z_g_mean"] - 4.0
    contacts_total = s["contacts_total"] if "contacts_total" in s else s["N_C"] / 2
    dZall = 2.0 * contacts_total / n_all - (4.0 - 2.0 / n_all)

    rows = {
        "E": (E, None, {}),
        "E ordered/N_G": (E_ord, None, {}),
        "E/N_G": (E_nr, None, {}),
        "E<=1e-5": (E, lambda e: e <= 1.01e-5, {}),
        "E<=1e-6": (E, lambda e: e <= 1.01e-6, {}),
        "E>=1e-12": (E, lambda e: e >= 0.99e-12, {}),
        "E unweighted": (E, None, {"weighted": False}),
        "E log-log, A* fixed": (E, None, {"loglog": True}),
        "dZ": (dZ, None, {}),
        "dZ, z_iso=4": (dZ4, None, {}),
        "dZ, rattlers counted": (dZall, None, {}),
        "dZ, E<=1e-5": (dZ, lambda e: e <= 1.01e-5, {}),
        "dZ log-log, A* fixed": (dZ, None, {"loglog": True}),
    }
    sizes = [int(N) for N in np.unique(fin.N)]
    results = {}
    for name, (x, keep, kw) in rows.items():
        per = cells(fin, A, x, keep)
        results[name] = {N: fit(per[N], args.boot, **kw) for N in sizes}
        print(f"  {name}: done", file=sys.stderr, flush=True)
    print(f"{len(fin.N)} packings ({args.variant}), fits of A_G = A* + c x^beta per N_G\n")
    print("| abscissa / fit | " + " | ".join(f"beta N_G={N}" for N in sizes) + " | "
          + " | ".join(f"A* N_G={N}" for N in sizes) + " |")
    print("|---|" + "---|" * (2 * len(sizes)))
    for name, per in results.items():
        print(f"| {name} | " + " | ".join(fmt(per[N]) for N in sizes) + " | "
              + " | ".join(fmt(per[N], "A_star") for N in sizes) + " |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"packings": int(len(fin.N)), "results": {k: {str(N): v for N, v in per.items()}
                                                                 for k, per in results.items()}}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
