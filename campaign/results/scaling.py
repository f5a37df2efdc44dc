"""The scaling fits per size: for every (variant, N_G) the four power laws of ``FITS`` over the
cells of the fit range, with bootstrap errors over packings; and the fit range in words
(``fit_rule_name``, ``fit_rule_text``; docs/REDUCED.md, "The fit range"), in numbers in
``campaign.plan.targets`` (``DEFAULT_FIT_OVERLAP``, ``typical_overlap``, ``in_fit_range``). The
fitting maths is ``campaign.results.fits``, its replicas ``campaign.results.bootstrap``; the N_G -> inf
row built on these fits, ``campaign.results.finitesize``.
``s`` is the reducer's ``Settings`` (``campaign.results.reduce``, which imports this module).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from campaign.errors import UserError
# The four laws fitted per (variant, N) with their table keys, the row's keys and the fit range
# (docs/REDUCED.md, "The fit range"): defined with the spec, whose precision targets name them.
from campaign.plan.targets import DEFAULT_FIT_OVERLAP, FITS, TABLE_KEYS, in_fit_range, typical_overlap  # noqa: F401
from campaign.results import bootstrap, fits, variance
from campaign.results.cells import Grid


def _window(s) -> list:
    lo, hi = s.fit_energies
    out = [f"E_G in [{lo:g}, {hi:g}]"] if (lo > 0 or math.isfinite(hi)) else []
    if math.isfinite(s.fit_overlap):
        out.append(f"typical overlap <= {s.fit_overlap:g}")
    return out


def is_default_range(s) -> bool:
    return (s.fit_overlap == DEFAULT_FIT_OVERLAP and tuple(s.fit_energies) == (0.0, math.inf))


def fit_rule_name(s) -> str:
    """The fit range in a few words, for a CSV column, a figure title or a table's footnote:
    ``typical overlap <= 0.001 (default)``, ``every energy``, ``E_G in [0, 1e-05]``,
    ``typical overlap <= 0.01``, or both of the last two."""
    window = ", ".join(_window(s)) or "every energy"
    return window + (" (default)" if is_default_range(s) else "")


def fit_rule_text(s) -> str:
    """One sentence saying which cells the scaling fits use."""
    window = " and ".join(_window(s))
    if is_default_range(s):
        return (f"Fits over the cells of typical overlap (alpha E_G / 2)^(1/alpha) <= {s.fit_overlap:g} (the "
                f"default range: one distance from jamming for every potential, E_G <= {s.fit_overlap ** 2:.2g} "
                "at alpha = 2; --fit-all fits every energy)")
    return "Fits over every energy" if not window else f"Fits over the cells with {window}"


def with_fit_rule(records, s) -> list:
    """``records`` of values drawn from the scaling fits, each with the fit range they come from
    (``fit_rule``, the last key)."""
    for rec in records:
        rec["fit_rule"] = fit_rule_name(s)
    return records


def _min_positive(x):
    x = x[x > 0]
    return float(x.min()) if len(x) else np.nan


#: the per-packing scalars the scaling fits read: the abscissae, then the quantities
COLUMNS = ("E_G", "delta_Z", "A_G", "psi_O")


@dataclass
class LawFit:
    """One variant's law over its sizes (docs/REDUCED.md, "Error bars that hold"): the sizes in the
    shared fit, the shared fit (its intercepts' replicas drawn together), each size's own fit, and per
    size the cells' means, the model's errors (the weights) and the cells of the grid."""

    sizes: list
    shared: fits.SharedFit
    per_size: dict                # N_G -> fits.PowerLawFit
    inputs: dict                  # N_G -> (x, y, yerr, cells)
    trend: float = np.nan         # the spread's change with energy (variance.trend)
    homogeneity: dict = field(default_factory=dict)  # N_G -> Bartlett's p over its cells


def _law(moments, cells_by_size, qi, xi, n_done, logE, bounds_fit, per_size):
    """The fits of one variant's law: ``moments`` cell -> (means, cov) (1 + B rows), ``cells_by_size``
    N_G -> its cells with a usable mean (at least 3 with a positive abscissa: those enter). Returns a
    ``LawFit``; the weights are the variance model's (``campaign.results.variance``) in the data and
    in every replica, first from the spread of ``y``, then of ``y`` less the abscissa's scatter
    carried through the law's slope at the first fit."""
    sizes = sorted(cells_by_size)
    G, K = len(sizes), max(len(c) for c in cells_by_size.values())
    R1 = next(iter(moments.values()))[0].shape[0]
    X, Y = np.ones((R1, G, K)), np.zeros((R1, G, K))
    VY, CXY, VX = (np.zeros((R1, G, K)) for _ in range(3))
    n, u, valid = np.zeros((G, K)), np.zeros((G, K)), np.zeros((G, K), bool)
    for gi, N in enumerate(sizes):
        for k, c in enumerate(cells_by_size[N]):
            means, cov = moments[c]
            X[:, gi, k], Y[:, gi, k] = np.maximum(means[:, xi], 0.0), means[:, qi]
            VY[:, gi, k], CXY[:, gi, k], VX[:, gi, k] = cov[:, qi, qi], cov[:, qi, xi], cov[:, xi, xi]
            n[gi, k], u[gi, k], valid[gi, k] = n_done[c], logE[c], True
    u = np.where(valid, u - u[valid].mean(), 0.0)
    size_of = np.nonzero(valid)[0]

    # a cell's packings cannot agree better than their values' last bit: a spread floored there keeps
    # the weights of a size whose packings are alike finite (1/0 would overflow the fits' sums)
    floor = (np.finfo(float).eps * np.abs(Y[:, valid])) ** 2

    def errors(v):
        err = np.full(v.shape, np.inf)
        err[:, valid] = np.sqrt(variance.pooled_model(np.maximum(v[:, valid], floor), n[valid], size_of, u[valid], G)
                                / n[valid])
        return err

    a, c, beta, _ = fits.fit_shared_exponent_batch(X, Y, errors(VY), bounds_fit)
    with np.errstate(all="ignore"):
        slope = c[:, :, None] * beta[:, None, None] * X ** (beta[:, None, None] - 1.0)
    slope = np.where(np.isfinite(slope) & (X > 0), slope, 0.0)
    VR = VY - 2.0 * slope * CXY + slope ** 2 * VX
    err = errors(VR)
    xs = [X[0, gi, valid[gi]] for gi in range(G)]
    ys = [Y[0, gi, valid[gi]] for gi in range(G)]
    es = [err[0, gi, valid[gi]] for gi in range(G)]
    boot = R1 > 2
    shared = fits.fit_shared_exponent(
        xs, ys, es, bounds=bounds_fit,
        boot_xs=[X[1:, gi, valid[gi]] for gi in range(G)] if boot else None,
        boot_ys=[Y[1:, gi, valid[gi]] for gi in range(G)] if boot else None,
        boot_errs=[err[1:, gi, valid[gi]] for gi in range(G)] if boot else None)
    own = {}
    for gi, N in enumerate(sizes):
        if per_size:
            kk = valid[gi]
            own[N] = fits.fit_power_law(xs[gi], ys[gi], es[gi], bounds=bounds_fit,
                                        boot_x=X[1:, gi, kk] if boot else None, boot_y=Y[1:, gi, kk] if boot else None,
                                        boot_err=err[1:, gi, kk] if boot else None)
    inputs = {N: (xs[gi], ys[gi], es[gi], np.asarray(cells_by_size[N], int)) for gi, N in enumerate(sizes)}
    vr = np.maximum(VR[:1], 0.0)
    law = LawFit(sizes, shared, own, inputs,
                 trend=variance.trend(vr[:, valid], n[valid], size_of, u[valid], G) if G else np.nan)
    for gi, N in enumerate(sizes):
        law.homogeneity[N] = variance.homogeneity(vr[0, gi, valid[gi]], n[gi, valid[gi]])
    return law


def scaling_fits(fin, g: Grid, s, cells, notes, exponents=None, per_size=True, chains=()):
    """The power-law fits of A_G and Psi_O against E_G and Delta Z per (variant, N), with
    bootstrap errors; returns (fit records, normalised residuals per cell, table rows, the
    inputs of the shared-exponent fits: (variant, quantity, abscissa) -> per N the cell means, the
    model's errors, None, None and the cells of ``g``, or why the size did not enter; and the laws:
    (variant, quantity, abscissa) -> ``LawFit``, whose shared fits ``campaign.results.finitesize``
    extrapolates; and the replica weights of the fit range's cells, ``bootstrap.replica_weights``,
    which the jamming point resamples too). ``exponents``: variant -> alpha, for ``s.fit_overlap``; ``chains``: the variants
    whose packings of one seed share a history (resampled by whole seeds). ``per_size=False``: the
    per-size fits left empty (the ``N_G -> inf`` row needs none)."""
    C, cv, cN, cE, n_done = g.C, g.cv, g.cN, g.cE, g.n_done
    fit_records, residuals, rows, shared_in, laws = [], [], [], {}, {}
    cols = list(COLUMNS)
    have = all(c in fin.scalars for c in cols)
    if not have:
        notes.append("the file lacks one of the scalars " + ", ".join(cols) + ": no scaling fits")
    groups = sorted({(v, int(n)) for v, n in zip(cv, cN)})
    plan = {}
    for gi, (v, n) in enumerate(groups):
        in_group = np.flatnonzero((cv == v) & (cN == n))
        row = {"variant": v, "N_G": n, "n_packings": int(n_done[in_group].sum()),
               "n_cells": 0}
        lo, hi = s.fit_energies
        alpha = (exponents or {}).get(v, 2.0)
        if gi == 0 and not in_fit_range(cE[in_group], alpha, math.inf, s.fit_energies).all():
            notes.append(f"scaling fits use the cells with E_G in [{lo:g}, {hi:g}] only")
        in_range = in_fit_range(cE[in_group], alpha, s.fit_overlap, s.fit_energies)
        if math.isfinite(s.fit_overlap) and n == min(int(x) for x in cN[cv == v]):
            e_max = 2.0 / alpha * s.fit_overlap ** alpha
            notes.append(f"{v}: scaling fits use the cells with typical overlap <= {s.fit_overlap:g} "
                         f"(E_G <= {e_max:.3g} at alpha = {alpha:g})")
        in_group = in_group[in_range]
        short = len(in_group) < fits.MIN_CELLS
        why = (f"the fit range ({fit_rule_name(s)}) holds {len(in_group)} energies of the grid, fewer than "
               f"the {fits.MIN_CELLS} a power law with an intercept needs (three parameters and one "
               "degree of freedom)")
        if short and s.strict_range:
            raise UserError(f"{v} N={n}: {why}; widen the range")
        if short and have:
            notes.append(f"{v} N={n}: no fits: {why}; --fit-all or --fit-energies fit a wider range")
        small = in_group[n_done[in_group] < s.min_packings]
        usable = in_group[n_done[in_group] >= s.min_packings]
        if len(small) and have:
            notes.append(f"{v} N={n}: {len(small)} cell(s) with fewer than {s.min_packings} "
                         "finished packings left out of the fits (E = "
                         + ", ".join(f"{cE[i]:.3g} ({n_done[i]})" for i in small) + ")")
        row["n_cells"] = int(len(usable))
        row["fit_E_min"] = float(cE[usable].min()) if len(usable) else np.nan
        row["fit_E_max"] = float(cE[usable].max()) if len(usable) else np.nan
        plan[(v, n)] = (row, usable, short, why)
    # the cells' means and spreads, in the data and in every replica of the one resampling
    moments, W = {}, {}
    if have:
        data = np.column_stack([np.asarray(fin.scalars[c], float) for c in cols])
        every = [i for (_, usable, _, _) in plan.values() for i in usable]
        W = (bootstrap.replica_weights(g, fin.seed, every, set(chains), s.n_boot, s.boot_seed)
             if s.n_boot > 1 else {})
        for i in every:
            p = g.packings(i)
            keep = np.all(np.isfinite(data[p]), axis=1)
            if keep.sum() >= 2:
                moments[i] = bootstrap.cell_moments(data[p][keep], W[i][:, keep] if i in W else None)
    logE = np.log10(np.where(cE > 0, cE, np.nan))
    results = {}
    for v in sorted({v for v, _ in groups}):
        for quantity, absc, key, bkey in FITS:
            qi, xi = cols.index(quantity), cols.index(absc)
            entering = {}
            for (vv, n), (row, usable, short, why) in plan.items():
                if vv != v or not have or not len(usable):
                    continue
                ok = [i for i in usable if i in moments and np.isfinite(moments[i][0][0, xi])
                      and moments[i][0][0, xi] >= 0 and np.isfinite(moments[i][0][0, qi])]
                n_pos = sum(1 for i in ok if moments[i][0][0, xi] > 0)
                if n_pos < 3:  # the size's cells, or why it cannot enter the shared fit
                    shared_in.setdefault((v, quantity, absc), {})[n] = (
                        f"{n_pos} cell(s) with a positive mean {absc} in the fit range (3 needed)")
                else:
                    entering[n] = ok
                results[(v, n, quantity, absc)] = (ok, n_pos)
            if entering:
                law = _law(moments, entering, qi, xi, n_done, logE, fits.BETA_BOUNDS, per_size)
                laws[(v, quantity, absc)] = law
                for n, (x, y, ye, cl) in law.inputs.items():
                    shared_in.setdefault((v, quantity, absc), {})[n] = (x, y, ye, None, None, cl)
    for v, n in groups:
        row, usable, short, why = plan[(v, n)]
        not_determined = []
        for quantity, absc, key, bkey in FITS:
            res = np.full(C, np.nan)
            rec = {"variant": v, "N_G": n, "quantity": quantity, "abscissa": absc}
            ok, n_pos = results.get((v, n, quantity, absc), ([], 0))
            law = laws.get((v, quantity, absc))
            if not have:
                f = fits.PowerLawFit(message="scalars missing")
                ok_cells = np.zeros(0, int)
            elif short:
                f = fits.PowerLawFit(n_points=len(usable), message=why)
                ok_cells = np.zeros(0, int)
            else:
                ok_cells = np.asarray(ok, int)
                if n_pos < 3:  # the exponent needs three positive abscissae
                    f = fits.PowerLawFit(n_points=len(ok), message=(
                        f"needs at least 3 cells with a positive mean {absc}, has {n_pos}"))
                elif per_size:
                    f = law.per_size[n]
                else:
                    f = fits.PowerLawFit(n_points=len(ok), ok=True, message="not fitted (the N_G -> inf row only)")
                if len(ok) < len(usable):
                    f.message = (f.message + "; " if f.message else "") + (
                        f"{len(usable) - len(ok)} cell(s) with a negative mean {absc} or fewer than 2 "
                        f"packings with every scalar left out")
                if f.residuals.size == len(ok_cells):
                    res[ok_cells] = f.residuals
            undetermined = f.undetermined if (f.ok and not short) else ""
            if not f.ok and not short:
                notes.append(f"{v} N={n}: no fit of {quantity} against {absc}: {f.message}")
            elif undetermined:
                not_determined.append(f"{quantity} against {absc} ({undetermined})")
            rec.update(intercept=f.intercept, intercept_err=f.intercept_err, coeff=f.coeff,
                       coeff_err=f.coeff_err, exponent=f.exponent, exponent_err=f.exponent_err,
                       chi2=f.chi2, dof=f.dof, chi2_dof=f.chi2_dof, n_points=f.n_points,
                       n_boot=f.n_boot, ok=f.ok, message=f.message, undetermined=undetermined,
                       boot_at_bound=f.boot_at_bound,
                       p_value=fits.chi2_p_value(f.chi2, f.dof),
                       spread_p=law.homogeneity.get(n, np.nan) if law is not None else np.nan,
                       E_min=float(cE[ok_cells].min()) if len(ok_cells) else np.nan,
                       E_max=float(cE[ok_cells].max()) if len(ok_cells) else np.nan,
                       x_min=_min_positive(xs := cells.get(f"mean_{absc}", np.zeros(C))[ok_cells]),
                       x_max=float(xs.max()) if len(xs) else np.nan)
            fit_records.append(rec)
            residuals.append(res)
            row[key], row[f"{key}_err"] = f.intercept, f.intercept_err
            row[bkey], row[f"{bkey}_err"] = f.exponent, f.exponent_err
            row[f"{bkey}_undetermined"] = undetermined
            row[f"chi2_dof_{quantity}_{absc}"] = f.chi2_dof
        if not_determined:
            notes.append(f"{v} N={n}: exponents not determined, marked * in the table: "
                         + "; ".join(not_determined))
        row["fit_p"] = next(r["p_value"] for r in fit_records[-len(FITS):]
                            if r["quantity"] == "A_G" and r["abscissa"] == "E_G")
        rows.append(row)
    return fit_records, np.array(residuals).reshape(len(fit_records), C), rows, shared_in, laws, W
