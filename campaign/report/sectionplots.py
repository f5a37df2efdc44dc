"""The figures of the reducer's sections (``campaign.results.sections``), by section name
(``SECTION_FIGURES``): the Pareto front of the variants compared (``tradeoff``), the protocols
compared (``protocols``), the systems' universality (``systems``) and the linear response
(``response``). ``campaign.report.plots.make_figures`` draws them beside the paper's figures.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from campaign.plan.targets import in_fit_range
from campaign.report.plotkit import colors, fit_for, per_energy, placeholder, sci
from campaign.results import protocols, response, tradeoff

_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">")


# --------------------------------------------------------------------------- variants and protocols
def fig_pareto(red, plt):
    """Cost against deviation from the reference variant (campaign.results.tradeoff): the Pareto front.

    Log axes; deviations below 1e-12 (the reference itself, or variants that reproduce its
    packings to rounding) are drawn at 1e-12."""
    from matplotlib.ticker import FormatStrFormatter  # the plot extra, imported when a figure is drawn

    floor = 1e-12
    recs = [r for r in red.tradeoff if np.isfinite(r.get("cost_ratio_fe", np.nan))]
    labels = {"A_G": r"$|\Delta A_G|$", "delta_Z": r"$|\Delta\,\Delta Z|$", "psi_O": r"$|\Delta \Psi_O|$",
              "iso_excess": r"$|\Delta(N_C/2 - 2N_G + 1)|$"}
    fig = plt.figure(figsize=(10.0, 6.2))
    grid = fig.add_gridspec(2, len(tradeoff.QUANTITIES))
    ax0 = fig.add_subplot(grid[0, :])
    axes = [fig.add_subplot(grid[1, k]) for k in range(len(tradeoff.QUANTITIES))]
    x = np.array([r["cost_ratio_fe"] for r in recs])
    ref = recs[0]["reference"] if recs else ""

    def label(ax, ys):
        for r, xi, yi in zip(recs, x, ys):
            ax.annotate(r["variant"], (xi, yi), fontsize=6, xytext=(3, 2), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(FormatStrFormatter(""))

    sc = np.maximum([r.get("score", np.nan) for r in recs], floor)
    front = sorted((r for r in recs if r.get("on_front")), key=lambda r: r["cost_ratio_fe"])
    ax0.step([r["cost_ratio_fe"] for r in front], [max(r["score"], floor) for r in front], where="post",
             color="0.6", zorder=0, label="Pareto front")
    ax0.scatter(x, sc, c=["C3" if r.get("on_front") else "C0" for r in recs], s=20, zorder=2)
    label(ax0, sc)
    ax0.xaxis.set_minor_formatter(FormatStrFormatter("%g"))
    ax0.set_xlabel(f"cost / cost({ref})  (force evaluations over the same packings)")
    ax0.set_ylabel("largest |bias| / packing spread")
    ax0.legend(loc="lower left")
    for ax, q in zip(axes, tradeoff.QUANTITIES):
        y = np.array([abs(r.get(f"dev_{q}", np.nan)) for r in recs])
        e = np.array([r.get(f"dev_{q}_err", np.nan) for r in recs])
        yc = np.maximum(y, floor)
        lo = np.minimum(np.where(np.isfinite(e), e, 0.0), yc - floor)
        ax.errorbar(x, yc, yerr=[lo, np.where(np.isfinite(e), e, 0.0)], fmt="o", ms=3, capsize=2)
        label(ax, yc)
        ax.set_xlabel(f"cost / cost({ref})")
        ax.set_ylabel(labels[q])
    return fig


def fig_protocols(red, plt):
    """(a) A_G against Delta Z per protocol: the cells' means at the largest size every variant has,
    with their standard errors; (b) the same near jamming (the fit range's cells, where the
    N_G -> inf values come from); (c) each variant's difference from the reference in its errors
    (z), per N_G -> inf quantity, filled where it is significant at the family-wise rate (Holm)."""
    prot = red.protocols.comparison
    variants = [r["variant"] for r in prot["values"]]
    cols = dict(zip(variants, colors(len(variants), "tab10")))
    c = red.cells
    N = min(max(int(n) for n in c["N"][c["variant"] == v]) for v in variants)
    dmax = red.meta.get("fit_overlap", np.inf)
    fig, (a1, a1z, a2) = plt.subplots(1, 3, figsize=(14.0, 4.2))
    for k, v in enumerate(variants):
        i = np.flatnonzero((c["variant"] == v) & (c["N"] == N) & (c["n_packings"] > 0))
        x, y = c["mean_delta_Z"][i], c["mean_A_G"][i]
        ok = np.isfinite(x) & np.isfinite(y) & (x > 0)
        near = in_fit_range(c["E"][i], prot["values"][k].get("exponent", 2.0), dmax)
        for ax, m in ((a1, ok), (a1z, ok & near)):
            ax.errorbar(x[m], y[m], xerr=c["sem_delta_Z"][i][m], yerr=c["sem_A_G"][i][m],
                        fmt=_MARKERS[k % 9] + "-", ms=3, lw=0.7, capsize=1.5, color=cols[v], label=v)
    for ax, title in ((a1, f"(a) N_G = {N}, every energy"), (a1z, f"(b) N_G = {N}, typical overlap <= {dmax:g}")):
        ax.set_xscale("log")
        ax.set_xlabel(r"$\Delta Z$ (cell mean)")
        ax.set_ylabel(r"$A_G$ (cell mean)")
        ax.set_title(title, fontsize=9)
    a1.legend(fontsize=7)
    others = [v for v in variants if v != prot["reference"]]
    for k, v in enumerate(others):
        ps = [p for p in prot["pairs"] if p["variant"] == v]
        ys = np.arange(len(ps)) + (k - (len(others) - 1) / 2) * 0.12
        z = np.clip([p["z"] for p in ps], -12, 12)
        sig = np.array([p["significant"] for p in ps])
        mk = _MARKERS[(variants.index(v)) % 9]
        a2.scatter(z[~sig], ys[~sig], facecolors="none", edgecolors=cols[v], marker=mk, s=22)
        a2.scatter(z[sig], ys[sig], color=cols[v], marker=mk, s=22)
    a2.axvline(0, color="0.5", lw=0.7)
    for x in (-2, 2):
        a2.axvline(x, color="0.8", lw=0.7, ls="--")
    a2.set_xlim(-12.5, 12.5)
    a2.set_yticks(np.arange(len(protocols.QUANTITIES)))
    a2.set_yticklabels([protocols.LABELS[q] for q in protocols.QUANTITIES], fontsize=8)
    a2.invert_yaxis()
    a2.set_xlabel(f"(variant - {prot['reference']}) / error   (filled: significant, Holm)")
    a2.set_title("(c) N_G -> inf, differences (clipped at 12)", fontsize=9)
    return fig


# --------------------------------------------------------------------------- systems


def _system_label(r):
    return rf"{r['variant']}: $\alpha={r['alpha']:g}$, {r['sizes']}"


def _system_colors(red):
    return dict(zip((r["variant"] for r in red.systems), colors(len(red.systems))))


def _universality_points(red, v, N):
    """``(x, dA, fit)`` of one (variant, N_G): the cells' mean Delta Z and
    ``<A_G> - A_G*(Delta Z = 0)``, with the fit of A_G against delta_Z; cells where either is
    not positive are left out (log axes). ``(None, None, None)`` without a fit."""
    f = fit_for(red, v, N, "A_G", "delta_Z")
    if not f or not f["ok"] or not np.isfinite(f["intercept"]):
        return None, None, None
    c = red.cells
    i = np.flatnonzero((c["variant"] == v) & (c["N"] == N) & (c["n_packings"] > 0))
    x = c["mean_delta_Z"][i]
    y = c["mean_A_G"][i] - f["intercept"]
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    return x[ok], y[ok], f


def fig_universality(red, plt):
    """(a) Delta A_G against Delta Z for every system and N_G, with the fitted power laws;
    (b) the same divided by each fit's coefficient: one line x^beta_Z if beta_Z is universal."""
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.8))
    cols = _system_colors(red)
    ref = next((r for r in red.systems if r["variant"] == r["reference"]), red.systems[0])
    xs = []
    sizes = sorted({int(n) for n in red.cells["N"]})  # one marker per N_G, the same in every system
    for r in red.systems:
        v = r["variant"]
        Ns = sorted({int(n) for n in red.cells["N"][red.cells["variant"] == v]})
        for k, N in enumerate(Ns):
            x, y, f = _universality_points(red, v, N)
            if x is None or not len(x):
                continue
            largest = k == len(Ns) - 1
            light = 1.0 if largest else 0.25 + 0.5 * (k + 1) / len(Ns)
            kw = dict(color=cols[v], alpha=light, ms=4 if largest else 3, ls="none",
                      marker=_MARKERS[sizes.index(N) % len(_MARKERS)])
            lab = _system_label(r) + rf", $\beta_Z={f['exponent']:.3f}$ ($N_G={N}$)" if largest else None
            a1.plot(x, y, label=lab, **kw)
            xs.append(x)
            line = f["x_min"] > 0 and f["x_max"] > f["x_min"]
            if line:
                xx = np.geomspace(f["x_min"], f["x_max"], 50)
                a1.plot(xx, f["coeff"] * xx ** f["exponent"], color=cols[v], alpha=light, lw=0.8)
            if np.isfinite(f["coeff"]) and f["coeff"] > 0:
                a2.plot(x, y / f["coeff"], **kw)
                if line:
                    a2.plot(xx, xx ** f["exponent"], color=cols[v], alpha=light, lw=0.8)
    for N in sizes:  # the markers' key
        a2.plot([], [], ls="none", marker=_MARKERS[sizes.index(N) % len(_MARKERS)], color="0.4",
                label=rf"$N_G={N}$")
    if xs:
        x_all = np.concatenate(xs)
        bz = ref["beta_Z"] if np.isfinite(ref["beta_Z"]) else ref["beta_Z_largest"]
        if np.isfinite(bz):
            xx = np.geomspace(x_all.min(), x_all.max(), 50)
            a2.plot(xx, xx ** bz, "k--", lw=1,
                    label=rf"$\Delta Z^{{\beta_Z}}$, $\beta_Z={bz:.3f}$ ({ref['variant']})")
        for ax in (a1, a2):
            ax.set(xscale="log", yscale="log")
            if ax.get_legend_handles_labels()[0]:
                ax.legend()
    else:
        for ax in (a1, a2):
            placeholder(ax, "no fit of A_G against Delta Z")
    a1.set(xlabel=r"$\langle\Delta Z\rangle$",
           ylabel=r"$\Delta A_G = \langle A_G\rangle - A_G^*(\Delta Z=0)$",
           title="(a) every system; lighter: smaller $N_G$")
    a2.set(xlabel=r"$\langle\Delta Z\rangle$", ylabel=r"$\Delta A_G / B$",
           title=r"(b) rescaled by each fit's $B$ in $\Delta A_G = B\,\Delta Z^{\beta_Z}$")
    return fig


def _alpha_offsets(records, step=0.03):
    """x positions: alpha, systems of the same alpha spread by ``step`` around it."""
    groups = {}
    for r in records:
        groups.setdefault(r["alpha"], []).append(r["variant"])
    out = {}
    for a, vs in groups.items():
        for k, v in enumerate(vs):
            out[v] = a + step * (k - (len(vs) - 1) / 2)
    return out


def fig_exponents_vs_alpha(red, plt):
    """beta_E and beta_Z against the potential exponent alpha: extrapolated (filled, with
    errors) and at the largest N_G (open); the prediction beta_Z/(2 alpha) from the reference
    system's beta_Z, with its error band."""
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.5))
    recs = red.systems
    cols = _system_colors(red)
    xpos = _alpha_offsets(recs)
    ref = next((r for r in recs if r["variant"] == r["reference"]), recs[0])

    def errs(e):
        return e if np.isfinite(e) else 0.0

    for ax, key in ((a1, "beta_E"), (a2, "beta_Z")):
        for r in recs:
            v, x = r["variant"], xpos[r["variant"]]
            if np.isfinite(r[key]):
                ax.errorbar([x], [r[key]], [errs(r[f"{key}_err"])], fmt="o", ms=4, capsize=2,
                            color=cols[v], label=_system_label(r))
            if np.isfinite(r[f"{key}_largest"]):
                ax.errorbar([x + 0.01], [r[f"{key}_largest"]], [errs(r[f"{key}_largest_err"])],
                            fmt="o", ms=4, mfc="none", capsize=2, color=cols[v],
                            label=None if np.isfinite(r[key]) else _system_label(r))
    alphas = np.array([r["alpha"] for r in recs], float)
    aa = np.linspace(alphas.min() - 0.2, alphas.max() + 0.2, 100)
    bz, bz_err, which = ref["beta_Z"], ref["beta_Z_err"], r"N_G\to\infty"
    if not np.isfinite(bz):
        bz, bz_err, which = ref["beta_Z_largest"], ref["beta_Z_largest_err"], rf"N_G={ref['N_G_largest']}"
    if np.isfinite(bz):
        a1.plot(aa, bz / (2 * aa), "k--", lw=1,
                label=rf"$\beta_Z/(2\alpha)$, $\beta_Z={bz:.3f}$ ({ref['variant']}, ${which}$)")
        a2.axhline(bz, color="k", ls="--", lw=1, label=rf"$\beta_Z$ of {ref['variant']}")
        if np.isfinite(bz_err):
            a1.fill_between(aa, (bz - bz_err) / (2 * aa), (bz + bz_err) / (2 * aa), color="0.8", lw=0)
            a2.axhspan(bz - bz_err, bz + bz_err, color="0.8", lw=0)
    for ax, lab in ((a1, r"$\beta_E$"), (a2, r"$\beta_Z$")):
        ax.set(xlabel=r"potential exponent $\alpha$", ylabel=lab,
               title=lab + r": filled $N_G\to\infty$, open largest $N_G$")
        ax.set_xlim(aa[0], aa[-1])
        if ax.get_legend_handles_labels()[0]:
            ax.legend()
    return fig


# --------------------------------------------------------------------------- linear response
def _resp_cells(red, v):
    """The response records of variant ``v`` (campaign.results.response), as column arrays."""
    recs = [r for r in red.response.get("cells", []) if r["variant"] == v]
    keys = recs[0].keys() if recs else ()
    return {k: np.array([r.get(k, np.nan) for r in recs]) for k in keys if k not in ("variant",)
            and not k.endswith("_message")}


def _resp_fit(red, v, N, name):
    return next((f for f in red.response.get("fits", []) if f["variant"] == v and f["N_G"] == N
                 and f["fit"] == name), None)


def _alpha_of(red, v):
    """The variant's potential exponent (kept by campaign.results.response for the guide lines)."""
    return float(red.response.get("alpha", {}).get(v, 2.0))


def fig_response_moduli(red, cs, plt):
    """G and B against p, G against Delta Z, omega_min against Delta Z (dimensionless: lengths
    in the mean contact distance s, frequencies in sqrt(<k>)), with the fitted power laws
    (solid over the fitted cells); the fraction of packings with G < 0 (and c_min < 0) against
    the finite-size scaling variable p s^2 N^2."""
    fig, axes = plt.subplots(2, 2, figsize=(9, 7))
    c = _resp_cells(red, cs.v)
    alpha = _alpha_of(red, cs.v)
    if not c:
        for ax in axes.ravel():
            placeholder(ax, "no response data")
        return fig
    cols = colors(len(cs.Ns))
    panels = ((axes[0, 0], "p_s2", "G_s2", "G_vs_p", r"$p\,s^2$", r"$G\,s^2$ (filled), $B\,s^2$ (open)"),
              (axes[0, 1], "delta_Z", "G_s2", "G_vs_dZ", r"$\Delta Z$", r"$G\,s^2$"),
              (axes[1, 0], "delta_Z", "omega_min_scaled", "omega_min_vs_dZ", r"$\Delta Z$",
               r"$\omega_{\min}/\sqrt{\langle k\rangle}$"))
    for ax, xk, yk, fname, xl, yl in panels:
        shown = False
        for col, N in zip(cols, cs.Ns):
            m = c["N"] == N
            x, y, ye = c[f"mean_{xk}"][m], c[f"mean_{yk}"][m], c[f"sem_{yk}"][m]
            ok = (x > 0) & (y > 0)
            f = _resp_fit(red, cs.v, N, fname)
            lab = rf"$N_G={N}$"
            if f and np.isfinite(f["exponent"]):
                lab += rf": $\beta={f['exponent']:.2f}\pm{f['exponent_err']:.2f}$"
            ax.errorbar(x[ok], y[ok], ye[ok], fmt="o", ms=3, color=col, label=lab)
            if yk == "G_s2":
                xb, yb = c["mean_p_s2"][m] if xk == "p_s2" else x, c["mean_B_s2"][m]
                okb = (xb > 0) & (yb > 0)
                if xk == "p_s2":
                    ax.plot(xb[okb], yb[okb], "o", ms=3, mfc="none", color=col)
            if f and np.isfinite(f["exponent"]):
                sel = ok & (c["E"][m] >= f["E_min"] * (1 - 1e-9)) & (c["E"][m] <= f["E_max"] * (1 + 1e-9))
                if sel.any():
                    xx = np.geomspace(x[sel].min(), x[sel].max(), 20)
                    ax.plot(xx, f["prefactor"] * xx ** f["exponent"], color=col, lw=0.8)
            shown = shown or ok.any()
        if not shown:
            placeholder(ax, "no positive means")
            continue
        ax.set(xscale="log", yscale="log", xlabel=xl, ylabel=yl)
        ax.legend(fontsize=6)
    # literature guides: G ~ p^((alpha - 3/2)/(alpha - 1)) ~ Delta Z (O'Hern et al. 2003)
    ax = axes[0, 0]
    if ax.lines:
        beta = (alpha - 1.5) / (alpha - 1.0)
        ax.set_title(rf"expected $G\sim p^{{{beta:.2f}}}$, $B\sim p^{{{(alpha - 2) / (alpha - 1):.2f}}}$")
    # G ~ k_eff Delta Z with k_eff ~ overlap^(alpha - 2) ~ Delta Z^(2 alpha - 4)
    axes[0, 1].set_title(rf"expected $G\sim\Delta Z^{{{2 * alpha - 3:.2g}}}$")
    axes[1, 0].set_title(r"lowest non-zero frequency")
    ax = axes[1, 1]
    shown = False
    for col, N in zip(cols, cs.Ns):
        m = c["N"] == N
        x = c["mean_p_s2"][m] * N**2
        ok = np.isfinite(c["frac_G_negative"][m]) & (x > 0)
        if ok.any():
            ax.errorbar(x[ok], c["frac_G_negative"][m][ok], c["frac_G_negative_err"][m][ok], fmt="o-", ms=3,
                        lw=0.6, color=col, label=rf"$N_G={N}$, $G<0$")
            ax.plot(x[ok], c["frac_c_min_negative"][m][ok], "s:", ms=3, mfc="none", lw=0.6, color=col)
            shown = True
    if shown:
        ax.set(xscale="log", xlabel=r"$p\,s^2 N^2$", ylabel="fraction of packings",
               title=r"$G<0$ (filled), $c_{\min}<0$ (open)")
        ax.legend(fontsize=6)
    else:
        placeholder(ax, "no moduli")
    return fig


def fig_response_distributions(red, cs, plt):
    """The density of states per energy at the size with full spectra at the most energies; the gap
    distribution P(h) and the small-force distributions (all contacts, extended ones) per size,
    summed over the cells closest to jamming (campaign.results.response.POOL_OVERLAP), with the pooled
    exponents (response_exponents.csv) over their fit windows and the literature's as guides."""
    alpha = _alpha_of(red, cs.v)
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8))
    ax = axes[0]
    om = red.distributions.get("omega")
    # the size with full spectra at the most energies (the larger one on a tie)
    ncells = {N: sum(bool(om["counts"][i].sum()) for i in cs.at(N=N)) for N in cs.Ns} if om is not None else {}
    dense = sorted((n, N) for N, n in ncells.items() if n)
    dense = [N for _, N in dense]
    if dense and per_energy(red, cs, plt, ax, "omega", dense[-1]):
        top = max(om["edges"][1:][om["counts"][i] > 0].max() for i in cs.at(N=dense[-1]) if om["counts"][i].any())
        ax.set(xlabel=r"$\omega/\sqrt{\langle k\rangle}$", ylabel=r"$D(\omega)$", xlim=(0, 1.05 * top),
               title=rf"density of states, $N_G={dense[-1]}$")
        ax.legend(fontsize=5, ncol=2)
    else:
        placeholder(ax, "no density of states (N_G above the dense limit, or no modes)")
    c = red.cells
    near = {N: [i for i in cs.at(N=N) if (alpha * c["E"][i] / 2) ** (1 / alpha) <= response.POOL_OVERLAP * (1 + 1e-9)]
            for N in cs.Ns}
    pooled = {r["N_G"]: r for r in red.response.get("exponents", []) if r["variant"] == cs.v}
    panels = ((axes[1], (("gap", "gamma", -1.0),), r"$h = r/s - 1$", r"$P(h)$", [(-0.41, r"$h^{-0.41}$", ":")],
               1e-2),
              (axes[2], (("force", "theta", 1.0), ("force_extended", "theta_ext", 1.0)), r"$f/\langle f\rangle$",
               r"$P(f/\langle f\rangle)$", [(0.17, r"$f^{0.17}$", ":"), (0.42, r"$f^{0.42}$", "-.")], 1e-1))
    for ax, names, xl, yl, guides, anchor in panels:
        shown = False
        y_anchor = []
        for col, N in zip(colors(len(cs.Ns)), cs.Ns):
            for (name, key, sign), style in zip(names, ("-", "--")):
                d = red.distributions.get(name)
                if d is None or not near[N]:
                    continue
                counts = d["counts"][near[N]].sum(axis=0)
                e = d["edges"]
                if counts.sum() == 0:
                    continue
                dens = counts / counts.sum() / np.diff(e)
                xc = np.sqrt(e[1:] * np.maximum(e[:-1], e[1] / 10))  # geometric centres
                ok = (dens > 0) & (e[:-1] > 0)
                r = pooled.get(N, {})
                lab = rf"$N_G={N}$" + (" extended" if name.endswith("extended") else "")
                if np.isfinite(r.get(key, np.nan)):
                    lab += rf": {sign * r[key]:+.2f}$\pm${r[f'{key}_err']:.2f}"
                ax.plot(xc[ok], dens[ok], style, color=col, lw=0.9, label=lab)
                y_anchor.append(np.interp(np.log(anchor), np.log(xc[ok]), dens[ok]))
                shown = True
        if not shown:
            placeholder(ax, f"no {names[0][0]} histogram near jamming")
            continue
        lo = ax.get_xlim()[0]
        for (expo, glab, gst), ya in zip(guides, (min(y_anchor), max(y_anchor))):
            xx = np.geomspace(max(lo, anchor * 1e-6), anchor, 10)  # through the data at the anchor
            ax.plot(xx, ya * (xx / anchor) ** expo, "k", ls=gst, lw=1, label=glab + " (literature)")
        ax.set(xscale="log", yscale="log", xlabel=xl, ylabel=yl,
               title=rf"typical overlap $\leq${sci(response.POOL_OVERLAP)}, exponents of the pooled fits")
        ax.legend(fontsize=5, ncol=2)
    return fig


@dataclass(frozen=True)
class SectionFigures:
    """The figures of one section: ``variant`` drawn for every variant beside the paper's
    (``fn(red, cells, plt)``), ``campaign`` drawn once (``fn(red, plt)``, titled with the fit range
    when ``titled``), each name a PNG; all of them when ``shows(result)`` says the section's result
    has something to draw."""

    shows: Callable = bool
    variant: dict = field(default_factory=dict)
    campaign: dict = field(default_factory=dict)
    titled: bool = False


#: The sections' figures by section name, in the order they are drawn.
SECTION_FIGURES = {
    "response": SectionFigures(variant={"response_moduli": fig_response_moduli,
                                        "response_distributions": fig_response_distributions}),
    "tradeoff": SectionFigures(campaign={"pareto": fig_pareto}),
    "protocols": SectionFigures(shows=lambda p: bool(p.comparison.get("pairs")), campaign={"protocols": fig_protocols}),
    # two physical systems or more; their exponents come from the fits: titled with the fit range
    "systems": SectionFigures(campaign={"universality": fig_universality, "exponents_vs_alpha": fig_exponents_vs_alpha},
                              titled=True),
}
