"""Speed against accuracy: every variant of a campaign compared with a reference variant.

All variants of one campaign share the grid and, for each (N, E, seed), the initial
random positions, so they are compared **packing by packing**: a pair is the same
(N, E, seed) finished in both the variant and the reference. For each variant:

* cost: the median force evaluations and seconds per packing, and the cost ratio
  ``sum(variant) / sum(reference)`` over the pairs (what a campaign pays);
* deviation of each quantity in ``QUANTITIES``: the mean over pairs of
  ``q(variant) - q(reference)``; ``bias_rel`` is that deviation in units of the
  packing-to-packing spread of ``q`` in the reference (the pooled within-cell
  standard deviation), i.e. how it compares with the noise of one packing;
  ``worst_cell_z``: the largest ``|mean difference| / standard error`` of any single
  (N, E) cell, to see whether the deviation is concentrated somewhere;
* packings that did not converge or whose identities failed (``n_excluded``) count in
  the costs, since a campaign pays for them, but no quantity of theirs is compared;
* ``dev_E_rel``: the mean paired difference of ``E_G / E - 1``, where in its window
  each packing landed (a wider window, or another search rule, moves it, and with it
  every observable); not part of ``score``;
* the finite-size table entries (``TABLE_KEYS``): the variant's value minus the
  reference's, with the two errors added in quadrature.

Errors come from a bootstrap over (N, seed) chains: resampling whole chains keeps
the correlations of the ladder protocol (whose packings at different energies share a
history) and is equally valid for independent packings. ``on_front``: no other
variant is at once cheaper (cost ratio in force evaluations, deterministic) and more
accurate (``score``: the largest ``|bias_rel|`` over the quantities).

A section of the reducer (``SECTION``, ``campaign.results.sections``): the variants of the reference's
physical system; those of other systems are compared in ``campaign.results.systems``.
"""

from __future__ import annotations

import numpy as np

from campaign.results import bootstrap
from campaign.results.scaling import with_fit_rule
from campaign.results.sections import Group, Section
from campaign.results.tables import records_csv

#: per-packing quantities compared with the reference
QUANTITIES = ("A_G", "delta_Z", "psi_O", "iso_excess")
#: finite-size table entries compared with the reference
TABLE_KEYS = ("A_G_star_E", "beta_E", "A_G_star_Z", "beta_Z", "psi_O_star")


def _per_packing(fin):
    """The compared quantities and costs as columns over the finished packings."""
    s = fin.scalars
    nan = np.full(len(fin), np.nan)
    cols = {q: s.get(q, nan) for q in QUANTITIES if q != "iso_excess"}
    if "N_C" in s and "N_G" in s:
        # contacts (N_C counts each twice) beyond the isostatic count: 2 N_G - 1 in a fixed cell,
        # 2 N_G + 1 in a shear-stabilised one, z_iso N_G / 2 (an integer) where z_iso is stored
        iso = 2.0 * s["N_G"] - 1.0
        if "z_iso" in s:
            with np.errstate(invalid="ignore"):
                z = np.rint(s["z_iso"] * s["N_G"] / 2.0)
            iso = np.where(np.isfinite(z), z, iso)
        cols["iso_excess"] = s["N_C"] / 2.0 - iso
    else:
        cols["iso_excess"] = nan
    e_rel = s["E_G"] / np.asarray(fin.E, float) - 1.0 if "E_G" in s else nan
    return cols, e_rel, s.get("force_evaluations", nan), s.get("jam_seconds", nan)


def compare(fin, extrapolated, reference="default", n_boot=1000, seed=20240917, usable=None):
    """Records, one per variant (the reference first), and notes. See the module docstring.

    ``usable`` (n,) bool: the packings whose quantities may be compared (the reducer
    passes ``Finished.usable()``: converged, identities held); the others still count
    in the costs, since a campaign pays for them, and in ``n_excluded``."""
    notes = []
    usable = np.ones(len(fin), bool) if usable is None else np.asarray(usable, bool)
    variants = sorted({str(v) for v in fin.variant})
    if len(variants) < 2:
        return [], notes
    if reference not in variants:
        notes.append(f"no variant comparison: the reference variant {reference!r} has no finished packing "
                     f"(variants: {', '.join(variants)})")
        return [], notes
    cols, e_rel, fe, secs = _per_packing(fin)
    # quantities of unusable packings are not compared (NaN drops them from every mean)
    cols = {q: np.where(usable, x, np.nan) for q, x in cols.items()}
    e_rel = np.where(usable, e_rel, np.nan)
    var = np.asarray(fin.variant, dtype=str)
    key = list(zip(fin.N.tolist(), fin.E.tolist(), fin.seed.tolist()))
    ref_rows = {k: i for i, k in enumerate(key) if var[i] == reference}
    # the reference's packing-to-packing spread per quantity: pooled within-cell variance
    spread = {}
    ref_idx = np.flatnonzero(var == reference)
    cell_of = {}
    for i in ref_idx:
        cell_of.setdefault((fin.N[i], fin.E[i]), []).append(i)
    for q, x in cols.items():
        ss, dof = 0.0, 0
        for rows in cell_of.values():
            v = x[rows]
            v = v[np.isfinite(v)]
            if v.size >= 2:
                ss += float(np.sum((v - v.mean()) ** 2))
                dof += v.size - 1
        spread[q] = np.sqrt(ss / dof) if dof else np.nan
    rng = bootstrap.generator([seed, 7])
    out = []
    for v in [reference] + [x for x in variants if x != reference]:
        rows = np.flatnonzero(var == v)
        pairs = [(i, ref_rows[key[i]]) for i in rows if key[i] in ref_rows]
        rec = {"variant": v, "reference": reference, "n_packings": int(len(rows)),
               "n_excluded": int(np.count_nonzero(~usable[rows])), "n_pairs": len(pairs),
               "fe_median": float(np.nanmedian(fe[rows])) if len(rows) else np.nan,
               "seconds_median": float(np.nanmedian(secs[rows])) if len(rows) and np.isfinite(secs[rows]).any()
               else np.nan}
        if not pairs:
            notes.append(f"variant {v!r}: no packing shared with the reference {reference!r}: not compared")
            out.append(rec)
            continue
        a = np.array([p[0] for p in pairs])
        b = np.array([p[1] for p in pairs])
        # clusters for the bootstrap: (N, seed) chains
        chain = {}
        stat = bootstrap.clusters(np.array([chain.setdefault((fin.N[i], fin.seed[i]), len(chain)) for i in a]),
                                  n_boot, rng)
        for name, c in (("fe", fe), ("seconds", secs)):
            ca, cb = c[a], c[b]
            if np.all(np.isfinite(ca)) and np.all(np.isfinite(cb)) and cb.sum() > 0:
                rec[f"cost_ratio_{name}"], rec[f"cost_ratio_{name}_err"] = stat(
                    lambda s, ca=ca, cb=cb: float(ca[s].sum() / cb[s].sum()))
            else:
                rec[f"cost_ratio_{name}"], rec[f"cost_ratio_{name}_err"] = np.nan, np.nan
        score = 0.0
        for q, x in cols.items():
            d = x[a] - x[b]
            ok = np.isfinite(d)
            if not ok.any():
                rec[f"dev_{q}"] = rec[f"dev_{q}_err"] = rec[f"bias_rel_{q}"] = rec[f"worst_cell_z_{q}"] = np.nan
                continue
            rec[f"dev_{q}"], rec[f"dev_{q}_err"] = stat(lambda s, d=d, ok=ok: float(np.mean(d[s][ok[s]]))
                                                        if ok[s].any() else np.nan)
            rec[f"bias_rel_{q}"] = rec[f"dev_{q}"] / spread[q] if spread[q] > 0 else np.nan
            if np.isfinite(rec[f"bias_rel_{q}"]):
                score = max(score, abs(rec[f"bias_rel_{q}"]))
            worst = 0.0
            for (N, E) in sorted({(fin.N[i], fin.E[i]) for i in a}):
                m = (fin.N[a] == N) & (fin.E[a] == E) & ok
                if m.sum() >= 3:
                    sem = np.std(d[m], ddof=1) / np.sqrt(m.sum())
                    mean = np.mean(d[m])
                    z = abs(mean) / sem if sem > 0 else (0.0 if mean == 0 else np.inf)
                    worst = max(worst, z)
            rec[f"worst_cell_z_{q}"] = worst
        rec["score"] = score
        d = e_rel[a] - e_rel[b]
        ok = np.isfinite(d)
        rec["dev_E_rel"], rec["dev_E_rel_err"] = stat(lambda s, d=d, ok=ok: float(np.mean(d[s][ok[s]]))
                                                      if ok[s].any() else np.nan)
        ex_v, ex_r = extrapolated.get(v, {}), extrapolated.get(reference, {})
        for k in TABLE_KEYS:
            x, xr = ex_v.get(k, np.nan), ex_r.get(k, np.nan)
            rec[f"dev_{k}"] = x - xr
            rec[f"dev_{k}_err"] = float(np.hypot(ex_v.get(f"{k}_err", np.nan), ex_r.get(f"{k}_err", np.nan)))
        out.append(rec)
    for r in out:
        c, sc = r.get("cost_ratio_fe", np.nan), r.get("score", np.nan)
        r["on_front"] = bool(np.isfinite(c) and np.isfinite(sc) and not any(
            (o is not r and o.get("cost_ratio_fe", np.inf) <= c and o.get("score", np.inf) <= sc
             and (o.get("cost_ratio_fe") < c or o.get("score") < sc)) for o in out))
    return out, notes


def _fmt(x, e=None, digits=3):
    if x is None or not np.isfinite(x):
        return "--"
    if e is None or not np.isfinite(e):
        return f"{x:.{digits}g}"
    return f"{x:+.{digits}g} ± {e:.2g}"


def table_markdown(records) -> str:
    """The per-variant comparison as a markdown table (empty without records)."""
    if not records:
        return ""
    head = ("variant", "packings", "FE/packing", "cost (FE)", "cost (s)", "d(E_G/E)", "dA_G", "dDelta_Z", "dPsi_O", "d(iso excess)",
            "max bias/spread", "dA_G*(E=0)", "dbeta_E", "front")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in records:
        lines.append("| " + " | ".join([
            r["variant"] + (" (ref)" if r["variant"] == r["reference"] else ""),
            str(r["n_packings"]) + (f" ({r['n_excluded']} left out)" if r.get("n_excluded") else ""),
            _fmt(r.get("fe_median"), digits=4),
            _fmt(r.get("cost_ratio_fe")), _fmt(r.get("cost_ratio_seconds")),
            _fmt(r.get("dev_E_rel"), r.get("dev_E_rel_err")),
            *(_fmt(r.get(f"dev_{q}"), r.get(f"dev_{q}_err")) for q in QUANTITIES),
            _fmt(r.get("score"), digits=2),
            _fmt(r.get("dev_A_G_star_E"), r.get("dev_A_G_star_E_err")),
            _fmt(r.get("dev_beta_E"), r.get("dev_beta_E_err")),
            "yes" if r.get("on_front") else ""]) + " |")
    if records[0].get("fit_rule"):
        lines += ["", f"dA_G*(E=0), dbeta_E: the scaling fits' ({records[0]['fit_rule']})."]
    return "\n".join(lines)


def compute(table, s, distributions) -> list:
    """The reducer's step: the variants of the reference's physical system compared packing by
    packing (``compare``: packings of other systems are named in a note and compared in
    ``campaign.results.systems``), each record with the fit range its table entries come from."""
    vsys, everything = table.systems, table.everything
    ref_sys = vsys.get(s.reference)
    same = np.isin(np.asarray(everything.variant, dtype=str), [v for v, d in vsys.items() if d == ref_sys])
    if not same.all() and ref_sys is not None:
        others = sorted({str(v) for v in everything.variant[~same]})
        table.notes.append(f"variants {', '.join(others)} are other systems than {s.reference!r}: compared in "
                           "systems.md, not packing by packing")
    pick = same if ref_sys is not None else np.ones(len(everything), bool)
    records, notes = compare(everything.subset(pick), table.extrapolated, s.reference, n_boot=s.n_boot,
                             seed=s.boot_seed, usable=table.good[pick])
    table.notes.extend(notes)
    return with_fit_rule(records, s)  # their A_G* and exponents come from the scaling fits


#: what campaign reduce prints above the variants' table
CONSOLE_TITLE = ("\nVariants against {!r} (cost: ratio of summed force evaluations / seconds over the same "
                 "packings; deviations: mean paired difference; bias in units of the reference's "
                 "packing-to-packing spread)\n\n")


#: The speed against accuracy comparison as a section of the reducer (campaign.results.sections):
#: variants.csv in every output, /reduced/variants, summary.json's "variants", the console's table.
SECTION = Section(
    name="tradeoff", compute=compute,
    tables=lambda records: {"variants.csv": records_csv(records)},
    reduced=lambda records: {"variants": Group(records)} if records else {},
    console=lambda records: CONSOLE_TITLE.format(records[0]["reference"]) + table_markdown(records) if records else "",
    json=lambda records: {"variants": records})
