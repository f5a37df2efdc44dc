"""The jamming point of every variant and the protocols compared (docs/PROTOCOLS.md).

**The jamming point.** Per (variant, N_G), the packing fraction ``phi`` and the rattler fraction
``N_R / N`` of the cells in the fit range (the scaling fits' cells: typical overlap
``(alpha E_G / 2)^(1/alpha)`` within ``fit_overlap``, at least ``min_packings`` packings) are fitted
by a line in that overlap ``x``: ``q = q_J + b x``. At harmonic contacts ``phi - phi_J`` is
proportional to the overlap near jamming (O'Hern et al., PRE 68, 011306 (2003)), so the intercept is
``phi_J(N_G)``; for the rattler fraction the line is a low-order description, judged by its chi^2.
The cells are weighted by their packing counts over the size's pooled within-cell variance. Errors:
a bootstrap over seeds, each replica drawing whole seeds of the size (a seed's packings at every
energy together), which keeps the correlations of an energy ladder, whose packings of one seed
share a history, and holds for independent packings too (``bootstrap.seed_cell_means``: a replica
that draws no seed of some cell is dropped). ``phi_J`` and the rattler fraction are
then extrapolated linearly in 1/N_G (``fits.fit_inverse_n``), the convention of the rest of the
``N_G -> inf`` row.

**Protocols compared.** For each quantity of ``QUANTITIES`` (the ``N_G -> inf`` row's entries and
the two above), every variant of the reference's system against the reference: the difference, its
error (the two errors in quadrature: the variants' packings are separate ensembles; the correlation
of paired packings is reported to check it), ``z`` and its two-sided normal p-value; and one
homogeneity test per quantity over all the variants (chi^2 of the values about their weighted mean,
K - 1 degrees of freedom). Multiple comparisons: Holm's step-down adjustment, over the pairwise tests
together and over the homogeneity tests together; a difference is called significant when its
adjusted p-value is below ``ALPHA`` (the family-wise error rate).

A section of the reducer (``SECTION``, ``campaign.results.sections``), present in every reduction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from campaign.plan.targets import in_fit_range, typical_overlap
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


def _line_fits(x, Y, w):
    """Weighted lines ``y = a + b x`` for many ``y``: Y (R, C), weights w (R, C) or (C,): the
    intercepts, slopes (R,)."""
    w = np.broadcast_to(w, Y.shape)
    S = w.sum(1)
    Sx = (w * x).sum(1)
    Sxx = (w * x * x).sum(1)
    Sy = (w * Y).sum(1)
    Sxy = (w * x * Y).sum(1)
    det = S * Sxx - Sx * Sx
    with np.errstate(invalid="ignore", divide="ignore"):
        a = (Sxx * Sy - Sx * Sxy) / det
        b = (S * Sxy - Sx * Sy) / det
    return a, b


def size_fit(E, seed, values, alpha, n_boot, rng):
    """The jamming-point fit of one (variant, N_G): ``E``, ``seed``, ``values`` per packing (the fit
    range's cells only). Returns a dict: ``value``, ``err`` (bootstrap over seeds), ``slope``,
    ``chi2``, ``dof``, ``n_cells``, ``n_packings``; the value NaN with a ``note`` when the cells
    cannot give it."""
    ok = np.isfinite(values)
    E, seed, values = E[ok], seed[ok], values[ok]
    energies = np.unique(E)
    seeds = np.unique(seed)
    out = {"n_cells": len(energies), "n_packings": len(values), "value": np.nan, "err": np.nan,
           "slope": np.nan, "chi2": np.nan, "dof": 0, "note": ""}
    if len(energies) < 3:
        out["note"] = f"{len(energies)} cell(s) in the fit range (3 needed: a line and a degree of freedom)"
        return out
    ci = np.searchsorted(energies, E)
    si = np.searchsorted(seeds, seed)
    S, C = len(seeds), len(energies)
    M = np.zeros((S, C))
    V = np.zeros((S, C))
    np.add.at(M, (si, ci), 1.0)
    np.add.at(V, (si, ci), values)
    n = M.sum(0)
    mean = V.sum(0) / n
    resid = values - mean[ci]
    dof_w = len(values) - C
    pooled = float(np.sum(resid ** 2) / dof_w) if dof_w > 0 else np.nan
    x = typical_overlap(energies, alpha)
    if not (pooled > 0):  # every packing of each cell alike: weights by counts alone
        pooled = np.nan
    w = n / (pooled if np.isfinite(pooled) else 1.0)
    a, b = _line_fits(x, mean[None, :], w[None, :])
    out["value"], out["slope"] = float(a[0]), float(b[0])
    if np.isfinite(pooled):
        out["chi2"] = float(np.sum(w * (mean - a[0] - b[0] * x) ** 2))
    out["dof"] = C - 2
    if n_boot > 1 and S >= 2:
        nb, mb = bootstrap.seed_cell_means(M, V, n_boot, rng)
        if len(nb) >= 2:
            ab, _ = _line_fits(x, mb, nb)
            out["err"] = float(np.std(ab, ddof=1))
    if not np.isfinite(out["err"]):
        out["note"] = "no bootstrap error (fewer than 2 seeds)"
    return out


def jamming_point(fin, g, s, exponents) -> tuple[list, dict]:
    """Per (variant, N_G) the fits of ``phi_J`` and the rattler fraction (records), and per variant
    their ``N_G -> inf`` values (``{variant: {key, key_err, key_slope, key_chi2_dof, key_sizes}}``).
    ``fin``: the usable packings, ``g`` their grid, ``s`` the reducer's settings."""
    cols = _columns(fin)
    cell = g.cell
    E_pack = g.cE[cell]
    rows, out = [], {}
    for vi, v in enumerate(sorted(set(g.cv))):
        alpha = (exponents or {}).get(v, 2.0)
        # the fit range's cells of this variant, with enough packings
        in_range = (g.cv == v) & (g.n_done >= s.min_packings) & in_fit_range(g.cE, alpha, s.fit_overlap, s.fit_energies)
        per = {k: [] for k in cols}
        for n in sorted({int(x) for x in g.cN[g.cv == v]}):
            pick = in_range[cell] & (g.cN[cell] == n)
            rec = {"variant": v, "N_G": n}
            for k, val in cols.items():
                rng = bootstrap.generator([s.boot_seed, 11, vi, n])
                f = size_fit(E_pack[pick], fin.seed[pick], np.asarray(val, float)[pick], alpha, s.n_boot, rng)
                rec[k], rec[f"{k}_err"], rec[f"{k}_slope"] = f["value"], f["err"], f["slope"]
                rec[f"{k}_chi2_dof"] = f["chi2"] / f["dof"] if f["dof"] > 0 else np.nan
                rec[f"{k}_p"] = fits.chi2_p_value(f["chi2"], f["dof"])
                rec["n_cells"], rec["n_packings"] = f["n_cells"], f["n_packings"]
                rec[f"{k}_note"] = f["note"]
                per[k].append((n, f["value"], f["err"]))
            rows.append(rec)
        ex = {}
        for k, pts in per.items():
            pts = [p for p in pts if np.isfinite(p[1]) and np.isfinite(p[2]) and p[2] > 0]
            r = fits.fit_inverse_n([p[0] for p in pts], [p[1] for p in pts], [p[2] for p in pts])
            ex[k], ex[f"{k}_err"], ex[f"{k}_slope"] = r.value, r.err, r.slope
            ex[f"{k}_chi2_dof"], ex[f"{k}_n_sizes"] = r.chi2_dof, r.n_points
            ex[f"{k}_sizes"] = " ".join(str(p[0]) for p in pts)
        out[v] = ex
    return rows, out


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


def compare(extrapolated, jamming, reference, variants, fin=None, usable=None) -> dict:
    """The protocols compared (see the module docstring): ``{"values": [per variant], "pairs": [per
    (variant, quantity)], "homogeneity": [per quantity], "reference", "alpha"}``; empty lists with
    fewer than two variants. ``variants``: the variants of the reference's system, in order."""
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
            e = float(np.hypot(rec[f"{q}_err"], ref[f"{q}_err"]))
            z = d / e if e > 0 else np.nan
            pairs.append({"variant": rec["variant"], "reference": reference, "quantity": q, "difference": d,
                          "error": e, "z": z, "p": fits.normal_p_value(z),
                          "pair_correlation_A_G": corr})
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
            w = 1.0 / e[ok] ** 2
            m = float(np.sum(w * x[ok]) / w.sum())
            chi2 = float(np.sum(w * (x[ok] - m) ** 2))
            rec.update(mean=m, chi2=chi2, dof=int(ok.sum() - 1), p=fits.chi2_p_value(chi2, int(ok.sum() - 1)))
        hom.append(rec)
    for r, a in zip(hom, holm([r["p"] for r in hom])):
        r["p_holm"] = float(a)
        r["significant"] = bool(np.isfinite(a) and a < ALPHA)
    out["pairs"], out["homogeneity"] = pairs, hom
    return out


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
             "range's cells, its intercept; errors from a bootstrap over seeds; N_G -> inf linear in 1/N_G.", "",
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
              "One test per quantity over all variants: chi^2 of the values about their weighted mean "
              "(K - 1 degrees of freedom).", "",
              "| quantity | variants | chi2 / dof | p | p (Holm) | depends |", "|---|---|---|---|---|---|"]
    for h in comparison["homogeneity"]:
        lines.append(f"| {LABELS[h['quantity']]} | {h['n_variants']} | {_fmt(h['chi2'])} / {h['dof']} | "
                     f"{_p(h['p'])} | {_p(h['p_holm'])} | {'yes' if h['significant'] else 'no'} |")
    lines += ["", f"Each variant minus `{ref}`: errors in quadrature, z, two-sided normal p, Holm over all "
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
    sizes, limits = jamming_point(table.fin, g, s, {v: d["exponent"] for v, d in vsys.items()})
    ref_sys = vsys.get(s.reference)
    same_sys = [v for v in sorted(set(g.cv), key=list(g.cv).index) if ref_sys is None or vsys.get(v) == ref_sys]
    comparison = compare(table.extrapolated, limits, s.reference, same_sys, fin=table.everything, usable=table.good)
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
