"""The reducer's linear-response section: moduli, modes, gaps and small forces per cell.

Pure numpy on what ``campaign.results.reduce`` has already read (the usable packings' scalars, the
cells, the summed histograms); the per-packing gap and force histograms are read once more,
through ``Finished.histogram_blocks``, for the bootstrap of the exponents. Nothing here runs
unless the store holds the scalars of the ``moduli`` or ``modes`` observable or the
histograms of ``gaps``. docs/RESPONSE.md describes every output.

Per cell (``cells``): the fraction of packings with ``G < 0`` and with ``c_min < 0`` (binomial
errors), the dimensionless means ``G s^2``, ``B s^2``, ``p s^2`` (``s`` the packing's mean
contact distance), ``G / B``, ``omega_min / sqrt(<k>)``, and the small-gap and small-force
exponents: ``P(h) ~ h^-gamma`` and ``P(f) ~ f^theta`` from straight lines through the
cumulative counts on log axes (``F(h) ~ h^(1 - gamma)``, ``F(f) ~ f^(1 + theta)``), inside the
windows ``GAP_WINDOW`` and ``FORCE_WINDOW``, with bootstrap errors over packings.

Per (variant, N) (``exponents``): the same three exponents from the cells closest to jamming
pooled (typical overlap at most ``POOL_OVERLAP``; the gap window starts at 10 times their
largest typical overlap), bootstrap over their packings.

Per (variant, N) (``fits``): ``G s^2 = c (p s^2)^beta``, ``G s^2 = c Delta_Z^beta`` and
``omega_min / sqrt(<k>) = c Delta_Z^beta``: straight lines in logs through the cell means
(weights from their standard errors, relative), over the cells whose packings carry at least
``MIN_EXCESS`` contacts beyond isostaticity on average (``Delta Z N_G / 2``): below that the
finite-size crossover (Goodrich, Liu and Nagel 2012) bends every curve. Errors from the
weighted fit, scaled by ``sqrt(chi^2/dof)`` when that exceeds 1.

A section of the reducer (``SECTION``, ``campaign.results.sections``), present when the store holds
the linear response.
"""

from __future__ import annotations

import numpy as np

from campaign.results import bootstrap, fits
from campaign.results.sections import Group, Section
from campaign.results.tables import records_csv

#: Gap window of the exponent fit: from 10 typical overlaps (or where the cumulative count of
#: a cell reaches ``MIN_COUNT`` pairs, whichever is larger) up to ``h = 1e-2``.
GAP_WINDOW = (10.0, 1e-2)
#: Force window: from where the cumulative count reaches ``MIN_COUNT`` contacts up to
#: ``f / <f> = 0.1``.
FORCE_WINDOW = 0.1
MIN_COUNT = 20
#: A fit needs the cumulative distribution over at least this many decades.
MIN_DECADES = 1.0
#: Cells whose packings have fewer excess contacts on average are left out of the fits.
MIN_EXCESS = 4.0
#: The exponents pooled per (variant, N) use the cells of typical overlap at most this (the
#: closest to jamming: E_G <= 1e-12 harmonic, <= 1e-16 Hertz on a decade grid).
POOL_OVERLAP = 1e-6

#: What each fit is: (name, y, x) over the dimensionless per-packing columns below.
FITS = (("G_vs_p", "G_s2", "p_s2"), ("G_vs_dZ", "G_s2", "delta_Z"),
        ("omega_min_vs_dZ", "omega_min_scaled", "delta_Z"))


def present(fin) -> bool:
    """Does the store hold any linear-response data?"""
    return any(k in fin.scalars for k in ("G", "omega_min")) or any(
        h in fin.edges for h in ("gap", "force"))


def _columns(fin):
    """Dimensionless per-packing columns (NaN where a packing lacks them)."""
    sc = fin.scalars
    nan = np.full(len(fin), np.nan)
    s2 = sc.get("contact_distance", nan) ** 2
    out = {"G_s2": sc.get("G", nan) * s2, "B_s2": sc.get("B", nan) * s2,
           "p_s2": sc.get("pressure", nan) * s2, "delta_Z": sc.get("delta_Z", nan)}
    with np.errstate(invalid="ignore", divide="ignore"):
        out["G_over_B"] = sc.get("G", nan) / sc.get("B", nan)
        out["omega_min_scaled"] = sc.get("omega_min", nan) / sc.get("omega_scale", nan)
        out["excess"] = sc.get("delta_Z", nan) * sc.get("N_G", nan) / 2.0
    out["G_negative"] = np.where(np.isfinite(sc.get("G", nan)), sc.get("G", nan) < 0, np.nan)
    out["c_min_negative"] = np.where(np.isfinite(sc.get("c_min", nan)), sc.get("c_min", nan) < 0, np.nan)
    return out


def _fraction(flags):
    v = flags[np.isfinite(flags)]
    n = v.size
    if n == 0:
        return np.nan, np.nan, 0
    f = float(v.mean())
    # binomial standard error; with no event (or all) the rule of three's 1/(n+1) scale
    err = np.sqrt(f * (1 - f) / n) if 0 < f < 1 else 1.0 / (n + 1)
    return f, float(err), int(n)


def _group_stats(values, cell, C):
    """Count, mean, standard deviation and standard error per cell, NaN ignored."""
    ok = np.isfinite(values)
    c, v = cell[ok], values[ok]
    n = np.bincount(c, minlength=C).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(c, weights=v, minlength=C) / n
        d = v - mean[c]
        std = np.sqrt(np.bincount(c, weights=d * d, minlength=C) / (n - 1))
        return n, mean, std, std / np.sqrt(n)


def _slope(x, F):
    """Least-squares slope of log F against log x."""
    lx, lf = np.log(x), np.log(F)
    lx = lx - lx.mean()
    return float(np.sum(lx * (lf - lf.mean())) / np.sum(lx * lx))


def cumulative_exponent(edges, counts, lo, hi, per_packing=None, n_boot=200, seed=0):
    """Slope of the cumulative count ``F(x) = counts below x`` against ``x`` on log axes at
    the upper bin edges in ``[lo, hi]``; ``lo`` raised to where ``F`` first reaches
    ``MIN_COUNT``. Returns ``(slope, error, lo, hi, n_points, message)``; the error is the
    bootstrap spread over packings (``per_packing``: (n, nb) counts) when given."""
    e = np.asarray(edges, float)[1:]
    F = np.cumsum(counts).astype(float)
    enough = np.flatnonzero(F >= MIN_COUNT)
    if len(enough) == 0 or e[enough[0]] > hi:
        return np.nan, np.nan, lo, hi, 0, f"fewer than {MIN_COUNT} values below {hi:g}"
    lo = max(lo, float(e[enough[0]]))
    sel = (e >= lo * (1 - 1e-12)) & (e <= hi * (1 + 1e-12)) & (F > 0)
    if sel.sum() < 3 or np.log10(hi / lo) < MIN_DECADES:
        return np.nan, np.nan, lo, hi, int(sel.sum()), (
            f"window [{lo:.3g}, {hi:.3g}] spans less than {MIN_DECADES:g} decade(s) with data")
    slope = _slope(e[sel], F[sel])
    err = np.nan
    if per_packing is not None and len(per_packing) > 1 and n_boot > 1:
        cum = np.cumsum(per_packing, axis=1)[:, sel].astype(float)
        # a replica with an empty bin in the window has no slope on log axes: dropped
        reps = [_slope(e[sel], Fb) for Fb in bootstrap.resampled_sums(cum, n_boot, seed) if np.all(Fb > 0)]
        if len(reps) > 1:
            err = float(np.std(reps, ddof=1))
    return slope, err, lo, hi, int(sel.sum()), ""


def _per_packing(fin, name, g):
    """Per-packing counts of histogram ``name``, grouped by cell: ``{cell: (n, nb)}``."""
    out = {}
    if name not in fin.edges:
        return out
    parts = {}
    for pos, block in fin.histogram_blocks(name):
        cells = g.cell[pos]
        for c in np.unique(cells):
            parts.setdefault(int(c), []).append(block[cells == c])
    for c, p in parts.items():
        out[c] = np.concatenate(p)
    return out


def power_fit(x, y, yerr):
    """``y = c x^beta``: weighted straight line in logs (``sigma_log y = yerr / y``); returns
    ``(beta, beta_err, c, c_err_rel, chi2_dof, n)``."""
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(yerr) & (x > 0) & (y > 0) & (yerr > 0)
    n = int(ok.sum())
    if n < 3:
        return np.nan, np.nan, np.nan, np.nan, np.nan, n
    X = np.column_stack([np.ones(n), np.log(x[ok])])
    p, cov, chi2, dof = fits.weighted_linear_fit(X, np.log(y[ok]), yerr[ok] / y[ok])
    scale = np.sqrt(max(1.0, chi2 / dof)) if dof > 0 else 1.0
    return (float(p[1]), float(np.sqrt(cov[1, 1]) * scale), float(np.exp(p[0])),
            float(np.sqrt(cov[0, 0]) * scale), float(chi2 / dof) if dof > 0 else np.nan, n)


def reduce_response(fin, g, s, dists, exponents, notes):
    """The response records: ``{"cells": [...], "fits": [...]}`` (see the module docstring).
    ``g``: the reducer's cell grid (``campaign.results.cells.Grid``); ``s``: its Settings
    (bootstrap size and seed); ``dists``: its summed histograms; ``exponents``: variant -> alpha."""
    cols = _columns(fin)
    C = g.C
    stats = {}
    for k in ("G_s2", "B_s2", "p_s2", "delta_Z", "G_over_B", "omega_min_scaled", "excess"):
        n, mean, std, sem = _group_stats(cols[k], g.cell, C)
        stats[k] = (n, mean, sem)
    gaps = _per_packing(fin, "gap", g)
    forces = {h: _per_packing(fin, h, g) for h in ("force", "force_extended")}
    n_boot = max(2, min(s.n_boot, 400))
    records = []
    for i in range(C):
        rows = g.packings(i)
        v, N, E = str(g.cv[i]), int(g.cN[i]), float(g.cE[i])
        rec = {"variant": v, "N": N, "E": E, "n_packings": int(len(rows))}
        for k, (n, mean, sem) in stats.items():
            rec[f"mean_{k}"], rec[f"sem_{k}"] = float(mean[i]), float(sem[i])
        for flag in ("G_negative", "c_min_negative"):
            f, err, n = _fraction(cols[flag][rows])
            rec[f"frac_{flag}"], rec[f"frac_{flag}_err"] = f, err
        rec["n_moduli"] = n  # packings with elastic constants (moduli_ok)
        alpha = exponents.get(v, 2.0)
        delta = (alpha * E / 2.0) ** (1.0 / alpha)  # the typical overlap (campaign.results.scaling)
        for name, key, lo, hi, conv in (("gap", "gamma", GAP_WINDOW[0] * delta, GAP_WINDOW[1], lambda b: 1 - b),
                                        ("force", "theta", 0.0, FORCE_WINDOW, lambda b: b - 1),
                                        ("force_extended", "theta_ext", 0.0, FORCE_WINDOW, lambda b: b - 1)):
            d = dists.get(name)
            if d is None:
                continue
            per = (gaps if name == "gap" else forces[name]).get(i)
            lo = max(lo, float(d["edges"][1]))  # never the first bin [0, e1)
            b, be, flo, fhi, npts, msg = cumulative_exponent(d["edges"], d["counts"][i], lo, hi, per,
                                                             n_boot=n_boot, seed=[s.boot_seed, i])
            rec[key], rec[f"{key}_err"] = conv(b), be
            rec[f"{key}_lo"], rec[f"{key}_hi"], rec[f"{key}_points"] = flo, fhi, npts
            rec[f"{key}_message"] = msg
        records.append(rec)
    fit_records = []
    alphas = {str(v): float(a) for v, a in exponents.items()}
    if not records:
        return {"cells": records, "fits": fit_records, "exponents": [], "alpha": alphas}
    for v in sorted(set(str(x) for x in g.cv)):
        for N in sorted({int(n) for n, vv in zip(g.cN, g.cv) if str(vv) == v}):
            idx = [i for i in range(C) if str(g.cv[i]) == v and int(g.cN[i]) == N and g.n_done[i] >= s.min_packings]
            idx = np.array(idx, int)
            for name, ykey, xkey in FITS:
                rec = {"variant": v, "N_G": N, "fit": name, "y": ykey, "x": xkey}
                if len(idx) == 0 or not np.isfinite(stats[ykey][1][idx]).any():
                    rec.update(exponent=np.nan, exponent_err=np.nan, prefactor=np.nan,
                               prefactor_err_rel=np.nan, chi2_dof=np.nan, n_cells=0, E_min=np.nan,
                               E_max=np.nan, message="no data")
                    fit_records.append(rec)
                    continue
                exc = stats["excess"][1][idx]
                use = idx[np.isfinite(exc) & (exc >= MIN_EXCESS)]
                x, y, ye = stats[xkey][1][use], stats[ykey][1][use], stats[ykey][2][use]
                beta, berr, c, cerr, chi, n = power_fit(x, y, ye)
                ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
                rec.update(exponent=beta, exponent_err=berr, prefactor=c, prefactor_err_rel=cerr,
                           chi2_dof=chi, n_cells=n,
                           E_min=float(g.cE[use][ok].min()) if ok.any() else np.nan,
                           E_max=float(g.cE[use][ok].max()) if ok.any() else np.nan,
                           message="" if n >= 3 else (
                               f"needs 3 cells with positive means and at least {MIN_EXCESS:g} excess "
                               f"contacts per packing, has {n}"))
                fit_records.append(rec)
    pooled = []
    for v in sorted(set(str(x) for x in g.cv)):
        alpha = exponents.get(v, 2.0)
        for N in sorted({int(n) for n, vv in zip(g.cN, g.cv) if str(vv) == v}):
            near = [i for i in range(C) if str(g.cv[i]) == v and int(g.cN[i]) == N
                    and (alpha * g.cE[i] / 2.0) ** (1.0 / alpha) <= POOL_OVERLAP * (1 + 1e-9)]
            rec = {"variant": v, "N_G": N, "n_cells": len(near),
                   "E_max": float(max(g.cE[near])) if near else np.nan,
                   "n_packings": int(sum(len(g.packings(i)) for i in near))}
            dmax = max(((alpha * g.cE[i] / 2.0) ** (1.0 / alpha) for i in near), default=np.nan)
            for name, key, lo, hi, conv, per in (
                    ("gap", "gamma", GAP_WINDOW[0] * dmax, GAP_WINDOW[1], lambda b: 1 - b, gaps),
                    ("force", "theta", 0.0, FORCE_WINDOW, lambda b: b - 1, forces.get("force", {})),
                    ("force_extended", "theta_ext", 0.0, FORCE_WINDOW, lambda b: b - 1,
                     forces.get("force_extended", {}))):
                d = dists.get(name)
                if d is None or not near:
                    rec.update({key: np.nan, f"{key}_err": np.nan, f"{key}_lo": np.nan, f"{key}_hi": np.nan,
                                f"{key}_points": 0, f"{key}_message": "no data"})
                    continue
                counts = d["counts"][near].sum(axis=0)
                blocks = [per[i] for i in near if i in per]
                allp = np.concatenate(blocks) if blocks else None
                lo = max(lo, float(d["edges"][1]))
                b, be, flo, fhi, npts, msg = cumulative_exponent(d["edges"], counts, lo, hi, allp, n_boot=n_boot,
                                                                 seed=[s.boot_seed, 7, N])
                rec.update({key: conv(b), f"{key}_err": be, f"{key}_lo": flo, f"{key}_hi": fhi,
                            f"{key}_points": npts, f"{key}_message": msg})
            pooled.append(rec)
    dense = fin.scalars.get("modes_dense")
    if dense is not None and np.any(dense == 0):
        sizes = sorted({int(n) for n in g.cN[g.cell[dense == 0]]})
        notes.append(f"response: {int(np.sum(dense == 0))} packing(s) above the dense limit of the modes "
                     f"(N_G = {', '.join(map(str, sizes))}): lowest modes only, no density of states")
    skipped = [r for r in fit_records if r["n_cells"] < 3 and r["message"] != "no data"]
    if skipped:
        notes.append(f"response: {len(skipped)} power-law fit(s) without enough cells (at least 3 with "
                     f"{MIN_EXCESS:g} excess contacts per packing)")
    return {"cells": records, "fits": fit_records, "exponents": pooled, "alpha": alphas}


def compute(table, s, distributions) -> dict:
    """The reducer's step: ``reduce_response`` on its usable packings, cells and summed histograms."""
    return reduce_response(table.fin, table.grid, s, distributions,
                           {v: d["exponent"] for v, d in table.systems.items()}, table.notes)


#: The tables of the response's files and groups of /reduced, each written when it has records.
PARTS = ("cells", "fits", "exponents")


def _reduced(resp) -> dict:
    if not resp:
        return {}
    return {"response": Group(), **{f"response/{k}": Group(resp[k]) for k in PARTS if resp.get(k)}}


#: The linear response as a section of the reducer (campaign.results.sections), when the store holds
#: it: response_cells.csv, response_fits.csv, response_exponents.csv, /reduced/response, summary.json's
#: "response".
SECTION = Section(
    name="response", compute=compute, present=lambda table: present(table.fin), empty=dict,
    files=lambda resp: {f"response_{k}.csv": records_csv(resp.get(k, [])) for k in PARTS} if resp else {},
    reduced=_reduced,
    json=lambda resp: {"response": resp} if resp else {})


__all__ = ["reduce_response", "present", "cumulative_exponent", "power_fit", "GAP_WINDOW",
           "FORCE_WINDOW", "MIN_EXCESS", "MIN_COUNT", "SECTION"]
