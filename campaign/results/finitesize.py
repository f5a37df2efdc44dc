"""The N_G -> inf row of the finite-size table (docs/REDUCED.md, "The N_G -> inf row"): per
variant and law, one fit over every size with the exponent shared (``fits.fit_shared_exponent``),
its intercepts extrapolated in 1/N_G (``fits.line_in_inverse_n``, with the rule for sizes off the
line), from the per-size inputs that
``campaign.results.scaling.scaling_fits`` collects; and the notes naming the sizes that entered.
"""

from __future__ import annotations

import numpy as np

from campaign.results import fits
from campaign.results.scaling import FITS

def extrapolate(rows, shared_in, laws, notes, fitted=None) -> dict:
    """The N_G -> inf row per variant (docs/REDUCED.md, "The N_G -> inf row"): for each of the
    four laws the fit over every size with the exponent shared (``laws``: the ``LawFit`` of
    ``campaign.results.scaling``, an intercept and an amplitude per size); its exponent is the
    row's exponent and its intercepts, extrapolated in 1/N_G (``fits.line_in_inverse_n``: the line
    through the intercepts of every bootstrap replica, and the rule for sizes off the line), the
    row's intercept. A size with fewer than three cells in the fit range does not enter; an
    undetermined shared exponent gives no value. ``fitted``, a dict, receives per (variant,
    quantity, abscissa) the sizes, the shared fit and the 1/N_G line (``campaign.precision.allocation``
    plans from them)."""
    extrapolated = {}
    for v in sorted({r["variant"] for r in rows}):
        out = {}
        for quantity, absc, key, bkey in FITS:
            per_n = shared_in.get((v, quantity, absc), {})
            law = laws.get((v, quantity, absc))
            sizes = list(law.sizes) if law is not None else []
            left = {n: d for n, d in per_n.items() if isinstance(d, str)}
            left.update({r["N_G"]: "no cell in the fit range" for r in rows
                         if r["variant"] == v and r["N_G"] not in per_n})
            f = law.shared if law is not None else fits.SharedFit(message="no size with 3 cells in the fit range")
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
                    out[f"{k}_p"] = np.nan
                out[f"{key}_sizes"], out[f"{key}_limited"] = "", ""
                continue
            r = fits.line_in_inverse_n(sizes, f.intercepts, f.intercept_replicas)
            if fitted is not None:
                fitted[(v, quantity, absc)] = (sizes, f, r)
            out[key], out[f"{key}_err"] = r.value, r.err
            out[f"{key}_slope"], out[f"{key}_chi2_dof"], out[f"{key}_n_sizes"] = r.slope, r.chi2_dof, r.n_points
            out[f"{key}_p"] = r.p
            out[f"{key}_sizes"] = " ".join(str(n) for n in r.sizes)
            out[f"{key}_limited"] = _limited(r)
            out[bkey], out[f"{bkey}_err"] = f.exponent, f.exponent_err
            out[f"{bkey}_slope"], out[f"{bkey}_chi2_dof"], out[f"{bkey}_n_sizes"] = 0.0, f.chi2_dof, len(sizes)
            out[f"{bkey}_p"] = fits.chi2_p_value(f.chi2, f.dof)
            if r.left_out:
                notes.append(f"{v}: {key} from N_G = {', '.join(map(str, r.sizes))}: with N_G = "
                             f"{', '.join(map(str, r.left_out))} too, neither the line nor the parabola in 1/N_G passed "
                             f"its chi^2 test (p < {fits.LINE_P:g}), so the smallest size{'s were' if len(r.left_out) > 1 else ' was'} "
                             "left out (a correction beyond 1/N_G is largest there)")
            if r.parabola_weight >= 0.5:
                notes.append(f"{v}: {key}: the sizes curve in 1/N_G: the parabola (a 1/N_G^2 term) carries Akaike "
                             f"weight {r.parabola_weight:.2f} of the average with the line (docs/REDUCED.md, "
                             "\"Sizes off the 1/N_G line\")")
            if r.limited:
                notes.append(f"{v}: {key}: {out[f'{key}_limited']}")
        extrapolated[v] = out
        if not np.isfinite(out["beta_E"]):
            notes.append(f"{v}: no N_G -> inf value of A_G against E_G: {out['beta_E_note']}"
                         + (f" ({out['beta_E_left_out']})" if out["beta_E_left_out"] else ""))
        else:
            notes.append(f"{v}: N_G -> inf from the sizes {out['beta_E_sizes'].replace(' ', ', ')} "
                         "(one exponent shared by the sizes, intercepts extrapolated in 1/N_G)"
                         + (f"; left out: {out['beta_E_left_out']}" if out["beta_E_left_out"] else ""))
    return extrapolated


def _limited(line) -> str:
    """What limits a value whose 1/N_G line still fails with its three largest sizes ("" when none)."""
    if not line.limited:
        return ""
    return (f"limited by its sizes: the 1/N_G line through N_G = {', '.join(map(str, line.sizes))} fails its chi^2 "
            f"test (p = {line.p:.2g}), so the sizes do not lie on a line in 1/N_G at these errors; its error is "
            f"inflated by sqrt(chi^2/dof) = {line.inflation:.2f}, and more seeds will not make it smaller: larger "
            "sizes will")
