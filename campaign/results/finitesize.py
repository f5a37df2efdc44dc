"""The N_G -> inf row of the finite-size table (docs/REDUCED.md, "The N_G -> inf row"): per
variant and law, one fit over every size with the exponent shared (``fits.fit_shared_exponent``),
its intercepts extrapolated in 1/N_G (``fits.fit_inverse_n``), from the per-size inputs that
``campaign.results.scaling.scaling_fits`` collects; and the notes naming the sizes that entered.
"""

from __future__ import annotations

import numpy as np

from campaign.results import fits
from campaign.results.scaling import FITS

def extrapolate(rows, shared_in, notes, fitted=None) -> dict:
    """The N_G -> inf row per variant (docs/REDUCED.md, "The N_G -> inf row"): for each of the
    four laws one fit over every size with the exponent shared (``fits.fit_shared_exponent``: an
    intercept and an amplitude per size); its exponent is the row's exponent and its intercepts,
    extrapolated linearly in 1/N_G, the row's intercept. A size with fewer than three cells in
    the fit range does not enter; an undetermined shared exponent gives no value. ``fitted``, a
    dict, receives per (variant, quantity, abscissa) the sizes, the shared fit and the 1/N_G line
    (``campaign.precision.allocation`` plans from them)."""
    extrapolated = {}
    for v in sorted({r["variant"] for r in rows}):
        out = {}
        for quantity, absc, key, bkey in FITS:
            per_n = shared_in.get((v, quantity, absc), {})
            sizes = sorted(n for n, d in per_n.items() if not isinstance(d, str))
            left = {n: d for n, d in per_n.items() if isinstance(d, str)}
            left.update({r["N_G"]: "no cell in the fit range" for r in rows
                         if r["variant"] == v and r["N_G"] not in per_n})
            d = [per_n[n] for n in sizes]
            boot = all(x[3] is not None for x in d) and len(d) > 0
            f = fits.fit_shared_exponent([x[0] for x in d], [x[1] for x in d], [x[2] for x in d],
                                         boot_xs=[x[3] for x in d] if boot else None,
                                         boot_ys=[x[4] for x in d] if boot else None)
            why = f.undetermined
            if not why and len(sizes) < 2:
                why = ("one size with three cells or more in the fit range; an extrapolation in 1/N_G "
                       "needs two")
            out[f"{bkey}_sizes"] = " ".join(str(n) for n in sizes) if not why else ""
            out[f"{bkey}_left_out"] = "; ".join(f"N_G={n}: {w}" for n, w in sorted(left.items()))
            out[f"{bkey}_note"] = why
            if why:
                for k in (key, bkey):
                    out[k] = out[f"{k}_err"] = out[f"{k}_slope"] = out[f"{k}_chi2_dof"] = np.nan
                    out[f"{k}_n_sizes"] = 0
                continue
            r = fits.fit_inverse_n(sizes, f.intercepts, f.intercept_errs)
            if fitted is not None:
                fitted[(v, quantity, absc)] = (sizes, f, r)
            out[key], out[f"{key}_err"] = r.value, r.err
            out[f"{key}_slope"], out[f"{key}_chi2_dof"], out[f"{key}_n_sizes"] = r.slope, r.chi2_dof, r.n_points
            out[bkey], out[f"{bkey}_err"] = f.exponent, f.exponent_err
            out[f"{bkey}_slope"], out[f"{bkey}_chi2_dof"], out[f"{bkey}_n_sizes"] = 0.0, f.chi2_dof, len(sizes)
            out[f"{bkey}_p"] = fits.chi2_p_value(f.chi2, f.dof)
        extrapolated[v] = out
        if not np.isfinite(out["beta_E"]):
            notes.append(f"{v}: no N_G -> inf value of A_G against E_G: {out['beta_E_note']}"
                         + (f" ({out['beta_E_left_out']})" if out["beta_E_left_out"] else ""))
        else:
            notes.append(f"{v}: N_G -> inf from the sizes {out['beta_E_sizes'].replace(' ', ', ')} "
                         "(one exponent shared by the sizes, intercepts extrapolated in 1/N_G)"
                         + (f"; left out: {out['beta_E_left_out']}" if out["beta_E_left_out"] else ""))
    return extrapolated
