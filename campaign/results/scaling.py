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

import numpy as np

from campaign.errors import UserError
# The four laws fitted per (variant, N) with their table keys, the row's keys and the fit range
# (docs/REDUCED.md, "The fit range"): defined with the spec, whose precision targets name them.
from campaign.plan.targets import DEFAULT_FIT_OVERLAP, FITS, TABLE_KEYS, in_fit_range, typical_overlap  # noqa: F401
from campaign.results import bootstrap, fits
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


def scaling_fits(fin, g: Grid, s, cells, notes, exponents=None, per_size=True, chains=()):
    """The power-law fits of A_G and Psi_O against E_G and Delta Z per (variant, N), with
    bootstrap errors; returns (fit records, normalised residuals per cell, table rows, the
    inputs of the shared-exponent fits of ``campaign.results.finitesize``: (variant, quantity,
    abscissa) -> per N the cell means, their errors and bootstrap replicas). ``exponents``:
    variant -> alpha, for ``s.fit_overlap``. ``per_size=False``: only those inputs (the
    ``N_G -> inf`` row needs nothing else), the per-size fits left empty."""
    C, cv, cN, cE, n_done = g.C, g.cv, g.cN, g.cE, g.n_done
    fit_records, residuals, rows, shared_in = [], [], [], {}
    cols = ["E_G", "delta_Z", "A_G", "psi_O"]
    have = all(c in fin.scalars for c in cols)
    if not have:
        notes.append("the file lacks one of the scalars " + ", ".join(cols) + ": no scaling fits")
    groups = sorted({(v, int(n)) for v, n in zip(cv, cN)})
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
        boot = None
        if have and len(usable) >= 3 and s.n_boot > 1:
            data = [np.column_stack([fin.scalars[c][g.packings(i)] for c in cols]) for i in usable]
            keep = [np.all(np.isfinite(d), axis=1) for d in data]
            data = [d[k] for d, k in zip(data, keep)]
            if all(len(d) >= 2 for d in data) and v in chains:
                seeds = [fin.seed[g.packings(i)][k] for i, k in zip(usable, keep)]
                boot = bootstrap.seed_means(data, seeds, s.n_boot, seed=[s.boot_seed, gi])
            elif all(len(d) >= 2 for d in data):
                boot = bootstrap.cell_means(data, s.n_boot, seed=[s.boot_seed, gi])
        not_determined = []
        for quantity, absc, key, bkey in FITS:
            res = np.full(C, np.nan)
            rec = {"variant": v, "N_G": n, "quantity": quantity, "abscissa": absc}
            # this size's cells, computed afresh for every quantity: nothing of an earlier size or
            # quantity may carry over (a size without a usable cell has none)
            ok, n_pos, bx, by = np.zeros(len(usable), bool), 0, None, None
            if have:
                x = cells[f"mean_{absc}"][usable]
                y = cells[f"mean_{quantity}"][usable]
                ye = cells[f"sem_{quantity}"][usable]
                # x = 0 is a legitimate abscissa (an isostatic cell: Delta Z = 0 exactly)
                with np.errstate(invalid="ignore"):
                    ok = np.isfinite(x) & (x >= 0) & np.isfinite(y) & np.isfinite(ye) & (ye > 0)
                n_pos = int(np.count_nonzero(x[ok] > 0))
                if boot is not None:
                    bx = boot[:, ok, cols.index(absc)]
                    by = boot[:, ok, cols.index(quantity)]
            if have and len(usable):
                if n_pos < 3:  # the size's cells, or why it cannot enter the shared fit
                    entry = f"{n_pos} cell(s) with a positive mean {absc} in the fit range (3 needed)"
                elif bx is None and s.n_boot > 1:
                    entry = "a cell with fewer than 2 usable packings (no bootstrap)"
                else:
                    entry = (x[ok], y[ok], ye[ok], bx, by, usable[ok])  # the last: its cells (of g)
                shared_in.setdefault((v, quantity, absc), {})[n] = entry
            if not have:
                f = fits.PowerLawFit(message="scalars missing")
                ok_cells = np.zeros(0, int)
            elif short:
                f = fits.PowerLawFit(n_points=len(usable), message=why)
                ok_cells = np.zeros(0, int)
            else:
                ok_cells = usable[ok]
                if n_pos < 3:  # the exponent needs three positive abscissae
                    f = fits.PowerLawFit(n_points=int(ok.sum()), message=(
                        f"needs at least 3 cells with a positive mean {absc}, has {n_pos}"))
                elif per_size:
                    f = fits.fit_power_law(x[ok], y[ok], ye[ok], boot_x=bx, boot_y=by)
                else:
                    f = fits.PowerLawFit(n_points=int(ok.sum()), ok=True, message="not fitted (the N_G -> inf row only)")
                if (~ok).any():
                    f.message = (f.message + "; " if f.message else "") + (
                        f"{int((~ok).sum())} cell(s) with a negative mean {absc} or without "
                        f"a spread of {quantity} left out")
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
    return fit_records, np.array(residuals).reshape(len(fit_records), C), rows, shared_in
