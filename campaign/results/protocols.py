"""The jamming point of every variant and the protocols compared (docs/PROTOCOLS.md).

**The jamming point.** Per (variant, N_G), the packing fraction ``phi`` and the rattler fraction
``N_R / N`` of the cells in the fit range (the scaling fits' cells: typical overlap
``(alpha E_G / 2)^(1/alpha)`` within ``fit_overlap``, at least ``min_packings`` packings) are fitted
by a line in that overlap ``x``: ``q = q_J + b x``. At harmonic contacts ``phi - phi_J`` is
proportional to the overlap near jamming (O'Hern et al., PRE 68, 011306 (2003)), so the intercept is
``phi_J(N_G)``; for the rattler fraction the line is a low-order description, judged by its chi^2.
The cells are weighted by their packing counts (the size's pooled within-cell variance, the same
for every cell, cancels). Errors: the scaling fits' bootstrap (``bootstrap.replica_weights``: seeds
within each cell, every variant drawing the same seeds, whole seeds along an energy ladder), the
line refitted in every replica. ``phi_J`` and the rattler fraction are then extrapolated in 1/N_G
(``fits.line_in_inverse_n``), the rule of the rest of the ``N_G -> inf`` row.

**Protocols compared.** For each quantity of ``QUANTITIES`` (the ``N_G -> inf`` row's entries and
the two above), every variant of the reference's system against the reference: the difference, its
error from the paired bootstrap (the difference in every replica: the variants' packings of one seed
are drawn together, so a protocol whose packings follow the reference's from the same random start
has the smaller error of their difference), ``z`` and its two-sided normal p-value; beside them the
errors in quadrature and their ``z`` (separate ensembles, the check), and the correlation of paired
packings; and one homogeneity test per quantity over all the variants (chi^2 of the values about
their mean, both with the replicas' covariance, K - 1 degrees of freedom). Multiple comparisons: Holm's step-down adjustment, over the pairwise tests
together and over the homogeneity tests together; a difference is called significant when its
adjusted p-value is below ``ALPHA`` (the family-wise error rate).

A section of the reducer (``SECTION``, ``campaign.results.sections``), present in every reduction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from campaign.plan.targets import FITS, in_fit_range, typical_overlap
from campaign.results import bootstrap, fits
from campaign.results.sections import Group, Section
from campaign.results.tables import fmt_err, records_csv

#: the N_G -> inf entries compared across protocols: the table's, then the jamming point's
QUANTITIES = ("A_G_star_E", "beta_E", "A_G_star_Z", "beta_Z", "psi_O_star", "phi_J", "rattler_fraction")
LABELS = {"A_G_star_E": "A_G*(E_G=0)", "beta_E": "beta_E", "A_G_star_Z": "A_G*(Delta Z=0)", "beta_Z": "beta_Z",
          "psi_O_star": "Psi_O*", "phi_J": "phi_J", "rattler_fraction": "N_R/N"}
#: the family-wise error rate of the tests
ALPHA = 0.05


def _columns(fin):
    s = fin.scalars
    nan = np.full(len(fin), np.nan)
    if "N_R" in s and "N" in s:
        rat = s["N_R"] / s["N"]
    elif "N_G" in s and "N" in s:
        rat = (s["N"] - s["N_G"]) / s["N"]
    else:
        rat = nan
    return {"phi_J": s.get("phi", nan), "rattler_fraction": rat}


def size_fit(x, values, weights) -> dict:
    """The jamming-point fit of one (variant, N_G): a line ``q = q_J + b x`` through the fit range's
    cells, ``x`` (K,) their typical overlaps, ``values`` their packings' values (K arrays), ``weights``
    their replica weights (K arrays (B, n_c) of ``bootstrap.replica_weights``, or None). The cells are
    weighted by their packings. Returns ``value``, ``err`` (the replicas' spread), ``replicas`` (B,),
    ``slope``, ``chi2`` (with the size's pooled within-cell variance), ``dof``, ``n_cells``,
    ``n_packings``; the value NaN with a ``note`` when the cells cannot give it."""
    cells = [(xk, np.asarray(v, float), w) for xk, v, w in zip(x, values, weights)]
    cells = [(xk, v[np.isfinite(v)], None if w is None else w[:, np.isfinite(v)]) for xk, v, w in cells]
    cells = [c for c in cells if len(c[1]) >= 2]
    out = {"n_cells": len(cells), "n_packings": int(sum(len(c[1]) for c in cells)), "value": np.nan, "err": np.nan,
           "replicas": np.zeros(0), "slope": np.nan, "chi2": np.nan, "dof": 0, "note": ""}
    if len(cells) < 3:
        out["note"] = f"{len(cells)} cell(s) in the fit range (3 needed: a line and a degree of freedom)"
        return out
    xs = np.array([c[0] for c in cells])
    n = np.array([len(c[1]) for c in cells], float)
    boot = all(c[2] is not None and len(c[2]) > 1 for c in cells)
    means = np.column_stack([bootstrap.cell_moments(c[1][:, None], c[2] if boot else None)[0][:, 0] for c in cells])
    X = np.column_stack([np.ones(len(xs)), xs])
    coef = np.linalg.solve((X.T * n) @ X, (X.T * n) @ means.T).T    # (1 + B, 2)
    resid = means[0] - X @ coef[0]
    pooled = sum(float(np.sum((c[1] - c[1].mean()) ** 2)) for c in cells) / float(np.sum(n - 1))
    out["value"], out["slope"], out["dof"] = float(coef[0, 0]), float(coef[0, 1]), len(cells) - 2
    if pooled > 0:  # every packing of each cell alike: no goodness of fit
        out["chi2"] = float(np.sum(n * resid ** 2) / pooled)
    if boot:
        out["replicas"] = coef[1:, 0]
        out["err"] = fits.spread(coef[1:, 0])
    if not np.isfinite(out["err"]):
        out["note"] = "no bootstrap error (fewer than 2 resamples)"
    return out


def jamming_point(table, s) -> tuple[list, dict, dict]:
    """Per (variant, N_G) the fits of ``phi_J`` and the rattler fraction (records), per variant
    their ``N_G -> inf`` values (``{variant: {key, key_err, key_slope, key_chi2_dof, key_sizes,
    key_limited}}``), and their lines (``(variant, key) -> fits.Line``, with the replicas). ``table``: the reducer's
    (``campaign.results.reduce.Table``), whose usable packings, grid, systems and replica weights it
    takes; ``s`` the reducer's settings."""
    fin, g = table.fin, table.grid
    cols = _columns(fin)
    rows, out, lines = [], {}, {}
    for v in sorted(set(g.cv)):
        alpha = table.systems.get(v, {}).get("exponent", 2.0)
        # the fit range's cells of this variant, with enough packings
        in_range = (g.cv == v) & (g.n_done >= s.min_packings) & in_fit_range(g.cE, alpha, s.fit_overlap, s.fit_energies)
        per = {k: [] for k in cols}
        for n in sorted({int(x) for x in g.cN[g.cv == v]}):
            here = np.flatnonzero(in_range & (g.cN == n))
            rec = {"variant": v, "N_G": n}
            for k, val in cols.items():
                val = np.asarray(val, float)
                f = size_fit(typical_overlap(g.cE[here], alpha), [val[g.packings(c)] for c in here],
                             [table.replica_weights.get(c) for c in here])
                rec[k], rec[f"{k}_err"], rec[f"{k}_slope"] = f["value"], f["err"], f["slope"]
                rec[f"{k}_chi2_dof"] = f["chi2"] / f["dof"] if f["dof"] > 0 else np.nan
                rec[f"{k}_p"] = fits.chi2_p_value(f["chi2"], f["dof"])
                rec["n_cells"], rec["n_packings"] = f["n_cells"], f["n_packings"]
                rec[f"{k}_note"] = f["note"]
                per[k].append((n, f["value"], f["replicas"]))
            rows.append(rec)
        ex = {}
        for k, pts in per.items():
            pts = [p for p in pts if np.isfinite(p[1])]
            B = min((len(p[2]) for p in pts), default=0)
            r = fits.line_in_inverse_n([p[0] for p in pts], [p[1] for p in pts],
                                       np.column_stack([p[2][:B] for p in pts]) if pts and B else np.zeros((0, len(pts))))
            ex[k], ex[f"{k}_err"], ex[f"{k}_slope"] = r.value, r.err, r.slope
            ex[f"{k}_chi2_dof"], ex[f"{k}_n_sizes"] = r.chi2_dof, r.n_points
            ex[f"{k}_sizes"] = " ".join(str(n) for n in r.sizes)
            ex[f"{k}_limited"] = "limited by its sizes" if r.limited else ""
            lines[(v, k)] = r
        out[v] = ex
    return rows, out, lines


def holm(p) -> np.ndarray:
    """Holm's step-down adjusted p-values (NaN stays NaN): reject where adjusted < alpha controls
    the family-wise error rate at alpha for any dependence between the tests."""
    p = np.asarray(p, float)
    adj = np.full(p.shape, np.nan)
    idx = np.flatnonzero(np.isfinite(p))
    m = len(idx)
    order = idx[np.argsort(p[idx], kind="stable")]
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        adj[i] = running
    return adj


def _pair_correlation(fin, usable, variant, reference, q="A_G"):
    """The correlation, over packings of the same task (N, E, seed) in both variants, of their
    deviations of ``q`` from their cells' means: near 0 when the variant's packings are independent
    of the reference's, as the errors in quadrature assume."""
    if q not in fin.scalars:
        return np.nan
    x = np.where(usable, np.asarray(fin.scalars[q], float), np.nan)
    var = np.asarray(fin.variant, str)
    dev = np.full(len(x), np.nan)
    keys = {}
    for i, k in enumerate(zip(var.tolist(), fin.N.tolist(), fin.E.tolist())):
        keys.setdefault(k, []).append(i)
    for rows in keys.values():
        r = np.array(rows)
        dev[r] = x[r] - np.nanmean(x[r]) if np.isfinite(x[r]).any() else np.nan
    ref = {(n, e, sd): i for i, (v, n, e, sd) in
           enumerate(zip(var.tolist(), fin.N.tolist(), fin.E.tolist(), fin.seed.tolist())) if v == reference}
    a, b = [], []
    for i, (v, n, e, sd) in enumerate(zip(var.tolist(), fin.N.tolist(), fin.E.tolist(), fin.seed.tolist())):
        j = ref.get((n, e, sd)) if v == variant else None
        if j is not None and np.isfinite(dev[i]) and np.isfinite(dev[j]):
            a.append(dev[i])
            b.append(dev[j])
    if len(a) < 3 or np.std(a) == 0 or np.std(b) == 0:
        return np.nan
    return float(np.corrcoef(a, b)[0, 1])


def replicas_of(table, lines) -> dict:
    """``(variant, quantity) -> (replicas, inflation)`` of every quantity of ``QUANTITIES``: the
    ``N_G -> inf`` value in each bootstrap replica (the table's laws and the jamming point's
    ``lines``), drawn with the same seeds for every variant, and the factor its error carries."""
    out = {}
    for (v, quantity, absc), (_, shared, line) in table.shared_fits.items():
        key, bkey = next((k, b) for q, a, k, b in FITS if (q, a) == (quantity, absc))
        out[(v, key)] = (line.replicas, line.inflation)
        out[(v, bkey)] = (shared.exponent_replicas, 1.0)
    for (v, k), line in lines.items():
        out[(v, k)] = (line.replicas, line.inflation)
    return out


def _paired(replicas, a, b):
    """The paired bootstrap error of ``a - b`` (variants' keys into ``replicas``): the spread of the
    difference over the replicas, times the larger of the two values' inflations (NaN without)."""
    ra, ia = replicas.get(a, (np.zeros(0), 1.0))
    rb, ib = replicas.get(b, (np.zeros(0), 1.0))
    if len(ra) < 2 or len(ra) != len(rb):
        return np.nan
    return fits.spread(np.asarray(ra) - np.asarray(rb)) * max(ia, ib)


def compare(extrapolated, jamming, reference, variants, fin=None, usable=None, replicas=None) -> dict:
    """The protocols compared (see the module docstring): ``{"values": [per variant], "pairs": [per
    (variant, quantity)], "homogeneity": [per quantity], "reference", "alpha"}``; empty lists with
    fewer than two variants. ``variants``: the variants of the reference's system, in order;
    ``replicas``: ``replicas_of``'s (without it, the errors in quadrature decide)."""
    replicas = replicas or {}
    vals = []
    for v in variants:
        rec = {"variant": v}
        for q in QUANTITIES:
            src = jamming.get(v, {}) if q in ("phi_J", "rattler_fraction") else extrapolated.get(v, {})
            rec[q], rec[f"{q}_err"] = float(src.get(q, np.nan)), float(src.get(f"{q}_err", np.nan))
        vals.append(rec)
    out = {"reference": reference, "alpha": ALPHA, "values": vals, "pairs": [], "homogeneity": []}
    if len(variants) < 2 or reference not in variants:
        return out
    ref = vals[variants.index(reference)]
    pairs = []
    for rec in vals:
        if rec["variant"] == reference:
            continue
        corr = _pair_correlation(fin, usable, rec["variant"], reference) if fin is not None else np.nan
        for q in QUANTITIES:
            d = rec[q] - ref[q]
            eq = float(np.hypot(rec[f"{q}_err"], ref[f"{q}_err"]))
            ep = _paired(replicas, (rec["variant"], q), (reference, q))
            e = ep if np.isfinite(ep) and ep > 0 else eq
            z = d / e if e > 0 else np.nan
            zq = d / eq if eq > 0 else np.nan
            pairs.append({"variant": rec["variant"], "reference": reference, "quantity": q, "difference": d,
                          "error": e, "z": z, "p": fits.normal_p_value(z), "error_quadrature": eq,
                          "z_quadrature": zq, "pair_correlation_A_G": corr})
    for r, a in zip(pairs, holm([r["p"] for r in pairs])):
        r["p_holm"] = float(a)
        r["significant"] = bool(np.isfinite(a) and a < ALPHA)
    hom = []
    for q in QUANTITIES:
        x = np.array([r[q] for r in vals])
        e = np.array([r[f"{q}_err"] for r in vals])
        ok = np.isfinite(x) & np.isfinite(e) & (e > 0)
        rec = {"quantity": q, "n_variants": int(ok.sum()), "mean": np.nan, "chi2": np.nan, "dof": 0, "p": np.nan}
        if ok.sum() >= 2:
            cov = _covariance(replicas, [v for v, o in zip(variants, ok) if o], q, e[ok])
            Winv = np.linalg.pinv(cov)
            one = np.ones(int(ok.sum()))
            m = float(one @ Winv @ x[ok] / (one @ Winv @ one))
            r = x[ok] - m
            chi2 = float(r @ Winv @ r)
            rec.update(mean=m, chi2=chi2, dof=int(ok.sum() - 1), p=fits.chi2_p_value(chi2, int(ok.sum() - 1)))
        hom.append(rec)
    for r, a in zip(hom, holm([r["p"] for r in hom])):
        r["p_holm"] = float(a)
        r["significant"] = bool(np.isfinite(a) and a < ALPHA)
    out["pairs"], out["homogeneity"] = pairs, hom
    return out


def _covariance(replicas, variants, q, errors):
    """The covariance of the variants' values of ``q`` over the shared replicas, each scaled to its
    reported error (the replicas' spread times any inflation); without replicas, the errors alone."""
    reps = [replicas.get((v, q), (np.zeros(0), 1.0))[0] for v in variants]
    B = min(len(r) for r in reps)
    if B < 3 or any(len(r) != B for r in reps):
        return np.diag(np.asarray(errors) ** 2)
    R = np.column_stack(reps)
    corr = np.atleast_2d(np.corrcoef(R.T))
    corr = np.where(np.isfinite(corr), corr, np.eye(len(variants)))
    return corr * np.outer(errors, errors)


def _fmt(x, e=None):
    if e is not None:
        return fmt_err(x, e)
    return "--" if x is None or not np.isfinite(x) else f"{x:.3g}"


def _p(p):
    return "--" if not np.isfinite(p) else ("<1e-4" if p < 1e-4 else f"{p:.2g}")


def markdown(jamming_rows, jamming, comparison) -> str:
    """protocols.md: the jamming point per size and N_G -> inf, then (with two variants or more)
    the values side by side, the homogeneity tests and the differences from the reference."""
    lines = ["# The jamming point and the protocols compared", "",
             "phi_J and the rattler fraction N_R/N per size: a line in the typical overlap through the fit "
             "range's cells, its intercept; errors from the table's bootstrap over seeds; N_G -> inf a line in 1/N_G "
             "(the smallest sizes left out while it fails its chi^2 test).", "",
             "| variant | N_G | cells | packings | phi_J | chi2/dof | N_R/N | chi2/dof |", "|---|---|---|---|---|---|---|---|"]
    for r in jamming_rows:
        lines.append(f"| {r['variant']} | {r['N_G']} | {r['n_cells']} | {r['n_packings']} | "
                     f"{_fmt(r['phi_J'], r['phi_J_err'])} | {_fmt(r['phi_J_chi2_dof'])} | "
                     f"{_fmt(r['rattler_fraction'], r['rattler_fraction_err'])} | {_fmt(r['rattler_fraction_chi2_dof'])} |")
    for v, x in sorted(jamming.items()):
        lines.append(f"| {v} | inf | | | {_fmt(x['phi_J'], x['phi_J_err'])} | {_fmt(x['phi_J_chi2_dof'])} | "
                     f"{_fmt(x['rattler_fraction'], x['rattler_fraction_err'])} | {_fmt(x['rattler_fraction_chi2_dof'])} |")
    if not comparison.get("pairs"):
        return "\n".join(lines) + "\n"
    ref = comparison["reference"]
    lines += ["", "## N_G -> inf per variant", "",
              "| variant | " + " | ".join(LABELS[q] for q in QUANTITIES) + " |", "|---" * (len(QUANTITIES) + 1) + "|"]
    for r in comparison["values"]:
        lines.append(f"| {r['variant']}{' (ref)' if r['variant'] == ref else ''} | "
                     + " | ".join(_fmt(r[q], r[f'{q}_err']) for q in QUANTITIES) + " |")
    lines += ["", f"## Does it depend on the protocol? (family-wise error rate {comparison['alpha']:g}, Holm)", "",
              "One test per quantity over all variants: chi^2 of the values about their weighted mean, "
              "with the correlations their bootstrap replicas share (K - 1 degrees of freedom).", "",
              "| quantity | variants | chi2 / dof | p | p (Holm) | depends |", "|---|---|---|---|---|---|"]
    for h in comparison["homogeneity"]:
        lines.append(f"| {LABELS[h['quantity']]} | {h['n_variants']} | {_fmt(h['chi2'])} / {h['dof']} | "
                     f"{_p(h['p'])} | {_p(h['p_holm'])} | {'yes' if h['significant'] else 'no'} |")
    lines += ["", f"Each variant minus `{ref}`: the error of the difference over the replicas drawn with the same seeds "
              "(paired), z, two-sided normal p, Holm over all "
              f"{len(comparison['pairs'])} differences. corr: the correlation of paired packings' A_G "
              "(deviations from their cell means), near 0 when the ensembles are independent.", "",
              "| variant | corr | " + " | ".join(LABELS[q] for q in QUANTITIES) + " |",
              "|---" * (len(QUANTITIES) + 2) + "|"]
    by_v = {}
    for p in comparison["pairs"]:
        by_v.setdefault(p["variant"], []).append(p)
    for v, ps in by_v.items():
        cells = []
        for p in ps:
            mark = " **" if p["significant"] else ""
            cells.append(f"{_fmt(p['difference'], p['error'])} (z {p['z']:+.1f}, {_p(p['p_holm'])}){mark}"
                         if np.isfinite(p["z"]) else "--")
        lines.append(f"| {v} | {_fmt(ps[0]['pair_correlation_A_G'])} | " + " | ".join(cells) + " |")
    lines += ["", "** significant at the family-wise rate (Holm-adjusted p below it)."]
    return "\n".join(lines) + "\n"


@dataclass
class Protocols:
    """The section's result: the jamming point per size and ``N_G -> inf``, and the protocols
    compared (summary.json's ``"jamming"`` is ``jamming_sizes``, its ``"protocols"`` the comparison
    with ``"jamming"``: ``jamming_limits``)."""

    jamming_sizes: list = field(default_factory=list)   # per (variant, N_G): phi_J, N_R/N, their fits
    jamming_limits: dict = field(default_factory=dict)  # per variant: their N_G -> inf values
    comparison: dict = field(default_factory=dict)      # compare's: "reference", "alpha", "values", ...


def compute(table, s, distributions) -> Protocols:
    """The reducer's step: the jamming point of every variant, then the variants of the reference's
    system compared (in the order of the cells), each value with its variant's potential exponent."""
    vsys, g = table.systems, table.grid
    sizes, limits, lines = jamming_point(table, s)
    ref_sys = vsys.get(s.reference)
    same_sys = [v for v in sorted(set(g.cv), key=list(g.cv).index) if ref_sys is None or vsys.get(v) == ref_sys]
    comparison = compare(table.extrapolated, limits, s.reference, same_sys, fin=table.everything, usable=table.good,
                         replicas=replicas_of(table, lines))
    for rec in comparison["values"]:
        rec["exponent"] = float(vsys[rec["variant"]]["exponent"])  # the potential's alpha
    return Protocols(sizes, limits, comparison)


def _files(p) -> dict:
    out = {"protocols.md": markdown(p.jamming_sizes, p.jamming_limits, p.comparison)} if p.jamming_sizes else {}
    if p.comparison.get("pairs"):
        out.update({"protocols.csv": records_csv(p.comparison["pairs"]),
                    "protocol_tests.csv": records_csv(p.comparison["homogeneity"])})
    return out


def _reduced(p) -> dict:
    out = {"jamming": Group(p.jamming_sizes)} if p.jamming_sizes else {}
    c = p.comparison
    if c.get("pairs"):
        out["protocols"] = Group(attrs={"reference": c["reference"], "alpha": c["alpha"]})
        out.update({f"protocols/{k}": Group(c[k]) for k in ("values", "pairs", "homogeneity")})
    return out


def _console(p) -> str:
    """protocols.md without its title, with two variants of one system or more."""
    if not p.comparison.get("pairs"):
        return ""
    return "\n" + markdown(p.jamming_sizes, p.jamming_limits, p.comparison).split("\n", 2)[2]


#: The jamming point and the protocols compared as a section of the reducer
#: (campaign.results.sections): jamming.csv in every output, protocols.md (and protocols.csv,
#: protocol_tests.csv with a comparison), /reduced/jamming and /reduced/protocols, summary.json's
#: "jamming" and "protocols", the console's comparison.
SECTION = Section(
    name="protocols", compute=compute, empty=Protocols,
    tables=lambda p: {"jamming.csv": records_csv(p.jamming_sizes)},
    files=_files, reduced=_reduced, console=_console,
    json=lambda p: {"jamming": p.jamming_sizes, "protocols": {**p.comparison, "jamming": p.jamming_limits}})
