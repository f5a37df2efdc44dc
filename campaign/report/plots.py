"""Figures of a reduced campaign (matplotlib, the ``plot`` extra).

``make_figures(reduction, out_dir)`` writes one PNG per figure of the paper that a
campaign can produce, plus the goodness-of-fit, width-scaling and extrapolation
figures. Every function takes a ``Reduction`` (campaign.results.reduce) and never reads files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from campaign.errors import UserError


def _plt():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise UserError("plotting needs matplotlib: pip install 'jamming-campaign[plot]'") from None
    plt.rcParams.update({"figure.dpi": 90, "font.size": 9, "axes.titlesize": 9,
                         "figure.constrained_layout.use": True,
                         "legend.fontsize": 7, "savefig.bbox": "tight"})
    return plt


def _colors(n, cmap="viridis"):
    import matplotlib

    cm = matplotlib.colormaps[cmap]
    return [cm(x) for x in np.linspace(0.0, 0.85, max(n, 1))]


def _sci(e):
    m, x = f"{e:.0e}".split("e")
    return rf"$10^{{{int(x)}}}$" if m == "1" else rf"${m}\times10^{{{int(x)}}}$"


class _Cells:
    """Index helpers over the reduction's cells for one variant."""

    def __init__(self, red, variant):
        c = red.cells
        self.red = red
        self.v = variant
        self.idx = np.flatnonzero((c["variant"] == variant) & (c["n_packings"] > 0))
        self.Ns = sorted({int(n) for n in c["N"][self.idx]})
        self.Es = sorted({float(e) for e in c["E"][self.idx]})

    def at(self, N=None, E=None):
        c = self.red.cells
        m = np.ones(len(self.idx), bool)
        if N is not None:
            m &= c["N"][self.idx] == N
        if E is not None:
            m &= c["E"][self.idx] == E
        return self.idx[m]

    def largest_N(self):
        return self.Ns[-1] if self.Ns else None

    def lowest_E(self):
        return self.Es[0] if self.Es else None


def _dist(red, name, i):
    d = red.distributions.get(name)
    if d is None:
        return None, None
    e = d["edges"]
    return 0.5 * (e[1:] + e[:-1]), d["density"][i]


def _placeholder(ax, text):
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, fontsize=8)


# --------------------------------------------------------------------------- figures
def _area_hist(red, i):
    """Edges and counts of a cell's P(A_G) histogram (its bins only), or (None, None)."""
    e = red.area_hist["edges"][i]
    e = e[np.isfinite(e)]
    if len(e) < 2:
        return None, None
    k = red.area_hist["counts"][i][:len(e) - 1]
    return (e, k) if k.sum() > 0 else (None, None)


def fig_area_distributions(red, cs, plt):
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.5))
    E0 = cs.lowest_E()
    for col, N in zip(_colors(len(cs.Ns)), cs.Ns):
        for i in cs.at(N=N, E=E0):
            e, k = _area_hist(red, i)
            if e is None:
                continue
            dens = k / k.sum() / np.diff(e)
            a1.stairs(dens, e, color=col, label=rf"$N_G={N}$")
            mu, sd = red.cells["A_G_gauss_mean"][i], red.cells["A_G_gauss_sigma"][i]
            x = np.linspace(mu - 4 * sd, mu + 4 * sd, 200)
            a1.plot(x, np.exp(-0.5 * ((x - mu) / sd) ** 2) / (sd * np.sqrt(2 * np.pi)), color=col,
                    lw=1)
    a1.set(xlabel=r"$A_G$", ylabel=r"$P(A_G)$",
           title=rf"$E_G={_sci(E0)[1:-1]}$, best Gaussians" if E0 else "")
    a1.legend()
    N = 512 if 512 in cs.Ns else cs.largest_N()
    for col, E in zip(_colors(len(cs.Es), "plasma"), cs.Es):
        for i in cs.at(N=N, E=E):
            e, k = _area_hist(red, i)
            if e is None:
                continue
            a2.stairs(k / k.sum() / np.diff(e), e, color=col, label=rf"$E_G=${_sci(E)}")
    a2.set(xlabel=r"$A_G$", ylabel=r"$P(A_G)$", title=rf"$N_G={N}$")
    a2.legend(ncol=2)
    return fig


def fig_width_scaling(red, cs, plt):
    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    c = red.cells
    for col, E in zip(_colors(len(cs.Es), "plasma"), cs.Es):
        i = cs.at(E=E)
        i = i[np.isfinite(c["A_G_gauss_sigma"][i])]
        if len(i) == 0:
            continue
        ax.errorbar(c["N"][i], c["A_G_gauss_sigma"][i], c["A_G_gauss_sigma_err"][i], fmt="o",
                    ms=3, color=col, label=rf"$E_G=${_sci(E)}")
        w = next((w for w in red.width_scaling if w["variant"] == cs.v and w["E"] == E), None)
        if w and np.isfinite(w["gamma"]):
            n = np.array([min(cs.Ns), max(cs.Ns)], float)
            ax.plot(n, np.exp(w["log_prefactor"]) * n ** -w["gamma"], color=col, lw=0.8)
    if cs.Ns:
        i = cs.at(E=cs.lowest_E())
        s0 = np.nanmax(c["A_G_gauss_sigma"][i]) if len(i) else np.nan
        if np.isfinite(s0):
            n = np.array([min(cs.Ns), max(cs.Ns)], float)
            ax.plot(n, s0 * (n / n[0]) ** -0.5, "k--", lw=1, label=r"$\propto N_G^{-1/2}$")
    ax.set(xscale="log", yscale="log", xlabel=r"$N_G$", ylabel=r"width $\sigma(A_G)$")
    ax.legend(ncol=2)
    return fig


def _fit_for(red, v, N, q, a):
    return next((f for f in red.fits if f["variant"] == v and f["N_G"] == N
                 and f["quantity"] == q and f["abscissa"] == a), None)


_XLAB = {"E_G": r"$E_G$", "delta_Z": r"$\Delta Z$"}
_YLAB = {"A_G": r"$\Delta A_G = A_G - A_G^*$", "psi_O": r"$\Delta\Psi_O = \Psi_O - \Psi_O^*$"}


def _range_label(f):
    """``, E_G <= 1e-5``: the highest grid energy of a fit (its range starts at the lowest)."""
    hi = f.get("E_max", np.nan)
    return rf", $E_G\leq${_sci(hi)}" if hi is not None and np.isfinite(hi) else ""


def fig_scaling(red, cs, plt, quantity):
    """Delta A_G (or Delta Psi_O) against E_G and Delta Z per N_G with the fitted power laws;
    cells outside a fit's range are open markers."""
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    c = red.cells
    for ax, absc in zip(axes, ("E_G", "delta_Z")):
        shown = False
        for col, N in zip(_colors(len(cs.Ns)), cs.Ns):
            f = _fit_for(red, cs.v, N, quantity, absc)
            if not f or not f["ok"]:
                continue
            i = cs.at(N=N)
            x = c[f"mean_{absc}"][i]
            y = c[f"mean_{quantity}"][i] - f["intercept"]
            ye = c[f"sem_{quantity}"][i]
            ok = (x > 0) & (y > 0)
            E = c["E"][i]
            fitted = ok & (E >= f.get("E_min", 0.0) * (1 - 1e-9)) & (E <= f.get("E_max", np.inf) * (1 + 1e-9))
            lab = rf"$N_G={N}$: $\beta={f['exponent']:.3f}$" + _range_label(f)
            ax.errorbar(x[fitted], y[fitted], ye[fitted], fmt="o", ms=3, color=col, label=lab)
            if (ok & ~fitted).any():  # cells outside the fit range: open markers
                ax.errorbar(x[ok & ~fitted], y[ok & ~fitted], ye[ok & ~fitted], fmt="o", ms=3, color=col,
                            mfc="none", lw=0.6)
            shown = True
            if f["x_min"] > 0 and f["x_max"] > f["x_min"]:
                xx = np.geomspace(f["x_min"], f["x_max"], 50)
                ax.plot(xx, f["coeff"] * xx ** f["exponent"], color=col, lw=0.8)
        if not shown:
            _placeholder(ax, "no fit (too few cells)")
        else:
            ax.set(xscale="log", yscale="log")
            ax.legend()
        ax.set(xlabel=_XLAB[absc], ylabel=_YLAB[quantity])
    return fig


def fig_residuals(red, cs, plt):
    fig, axes = plt.subplots(2, 2, figsize=(9, 6), sharey=True)
    c = red.cells
    for ax, (q, a) in zip(axes.ravel(), [("A_G", "E_G"), ("A_G", "delta_Z"), ("psi_O", "E_G"),
                                         ("psi_O", "delta_Z")]):
        for col, N in zip(_colors(len(cs.Ns)), cs.Ns):
            k = next((j for j, f in enumerate(red.fits) if f["variant"] == cs.v
                      and f["N_G"] == N and f["quantity"] == q and f["abscissa"] == a), None)
            if k is None or not red.fits[k]["ok"]:
                continue
            r = red.residuals[k]
            i = np.flatnonzero(np.isfinite(r))
            ax.plot(c[f"mean_{a}"][i], r[i], "o-", ms=3, lw=0.6, color=col,
                    label=rf"$N_G={N}$, $\chi^2/\nu={red.fits[k]['chi2_dof']:.2f}$")
        ax.axhline(0, color="k", lw=0.6)
        for s in (-2, 2):
            ax.axhline(s, color="0.6", lw=0.6, ls=":")
        ax.set(xscale="log", xlabel=_XLAB[a],
               ylabel=rf"$({q.replace('psi_O', chr(92) + 'Psi_O')} - \mathrm{{fit}})/\mathrm{{s.e.}}$")
        ax.set_title({"A_G": r"$A_G$", "psi_O": r"$\Psi_O$"}[q] + " against " + _XLAB[a])
        if ax.get_legend_handles_labels()[0]:
            ax.legend()
        else:
            _placeholder(ax, "no fit")
    return fig


def fig_extrapolation(red, cs, plt):
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    rows = [r for r in red.rows if r["variant"] == cs.v]
    ex = red.extrapolated.get(cs.v, {})
    for ax, keys, lab in ((axes[0], (("A_G_star_E", r"$A_G^*(E_G=0)$"),
                                     ("A_G_star_Z", r"$A_G^*(\Delta Z=0)$")), r"$A_G^*$"),
                          (axes[1], (("psi_O_star", r"$\Psi_O^*(E_G=0)$"),
                                     ("psi_O_star_Z", r"$\Psi_O^*(\Delta Z=0)$")), r"$\Psi_O^*$")):
        for (k, name), col, m in zip(keys, ("C0", "C3"), ("o", "s")):
            n = np.array([r["N_G"] for r in rows], float)
            y = np.array([r[k] for r in rows], float)
            e = np.array([r[f"{k}_err"] for r in rows], float)
            ok = np.isfinite(y)
            ax.errorbar(1 / n[ok], y[ok], np.where(np.isfinite(e[ok]), e[ok], 0), fmt=m, ms=4,
                        color=col, label=name)
            if np.isfinite(ex.get(k, np.nan)) and ok.any():
                xx = np.linspace(0, (1 / n[ok]).max() * 1.05, 20)
                ax.plot(xx, ex[k] + ex[f"{k}_slope"] * xx, color=col, lw=0.8)
                ax.errorbar([0], [ex[k]], [ex[f"{k}_err"] if np.isfinite(ex[f"{k}_err"]) else 0],
                            fmt=m, mfc="none", color=col)
        ax.set(xlabel=r"$1/N_G$", ylabel=lab)
        ax.set_xlim(left=-0.0005)
        ax.legend()
    return fig


def _per_E(red, cs, plt, ax, name, N, transform=None, positive=False, step=False, **kw):
    """One curve per energy at size N.

    ``step``: draw the histogram as steps (isolated spikes, such as the three-disk peaks
    near zero energy, stay visible); ``positive``: log axes -- empty bins are clipped
    (steps) or hidden (lines), and the axis starts just below the smallest value.
    """
    shown = False
    smallest = np.inf
    for col, E in zip(_colors(len(cs.Es), "plasma"), cs.Es):
        for i in cs.at(N=N, E=E):
            x, y = _dist(red, name, i)
            if x is None or not np.any(np.isfinite(y)):
                continue
            if transform:
                x, y = transform(x, y)
            if positive and np.any(y > 0):
                smallest = min(smallest, np.nanmin(y[y > 0]))
            lab = rf"$E_G=${_sci(E)}"
            if step:
                ax.stairs(np.nan_to_num(y), red.distributions[name]["edges"], color=col, lw=0.9,
                          label=lab, **kw)
            else:
                if positive:
                    y = np.where(y > 0, y, np.nan)
                ax.plot(x, y, color=col, lw=0.9, label=lab, **kw)
            shown = True
    if not shown:
        _placeholder(ax, f"no {name} histogram in this file")
    elif positive:
        ax.set_yscale("log", nonpositive="clip")
        if np.isfinite(smallest):
            ax.set_ylim(bottom=0.5 * smallest)
    return shown


def fig_angles_lengths(red, cs, plt):
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.5))
    N = 2048 if 2048 in cs.Ns else cs.largest_N()
    if _per_E(red, cs, plt, a1, "sin_theta", N, positive=True, step=True):
        s = np.linspace(0, 0.995, 200)
        a1.plot(s, 2 / np.pi / np.sqrt(1 - s * s), "k--", lw=1,
                label=r"random: $\frac{2}{\pi}\frac{1}{\sqrt{1-\sin^2\theta}}$")
        a1.legend(ncol=2)
    a1.set(xlabel=r"$\sin\theta$", ylabel=r"$P(\sin\theta)$", title=rf"$N_G={N}$")
    if _per_E(red, cs, plt, a2, "contact_length", N):
        a2.legend(ncol=2)
    a2.set(xlabel=r"$(1-r)/\sqrt{E_G}$, $r=|\vec r_{g,c}|/\sigma_g$",
           ylabel=r"$P\left((1-r)/\sqrt{E_G}\right)$", title=rf"$N_G={N}$")
    return fig


def fig_connectivity(red, cs, plt):
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.5))
    N = cs.largest_N()
    for ax, name, lab in ((a1, "z_g", "z_g"), (a2, "z_v", "z_v")):
        if _per_E(red, cs, plt, ax, name, N, positive=True, marker="o", ms=3):
            d = red.distributions[name]
            used = np.flatnonzero(d["counts"][cs.at(N=N)].sum(axis=0) > 0)
            if len(used):
                c = 0.5 * (d["edges"][1:] + d["edges"][:-1])
                ax.set_xlim(c[used[0]] - 1, c[used[-1]] + 1)
            ax.legend(ncol=2)
        ax.set(xlabel=rf"${lab}$", ylabel=rf"$P({lab})$", title=rf"$N_G={N}$")
    return fig


def fig_polygon_areas(red, cs, plt):
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.5))
    N = 2048 if 2048 in cs.Ns else cs.largest_N()
    pk = red.peaks.get(cs.v) or {"alpha_e": (), "alpha_v": ()}
    for ax, name, lab, peaks in ((a1, "alpha_e", r"\alpha_e", pk["alpha_e"]),
                                 (a2, "alpha_v", r"\alpha_v", pk["alpha_v"])):
        if _per_E(red, cs, plt, ax, name, N, positive=True, step=True):
            for k, p in enumerate(peaks):
                ax.axvline(p, color="0.4", lw=0.6, ls="--",
                           label="three-disk peaks" if k == 0 else None)
            ax.legend(ncol=2)
        ax.set(xlabel=rf"${lab}$", ylabel=rf"$P({lab})$", title=rf"$N_G={N}$")
    a2.set_xlim(0, 1.2)
    return fig


def fig_radial(red, cs, plt):
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.5))
    N = 1024 if 1024 in cs.Ns else cs.largest_N()

    def per_annulus(x, y):  # density per 2 pi r dr
        with np.errstate(divide="ignore", invalid="ignore"):
            return x, np.where(x > 0, y / (2 * np.pi * x), np.nan)

    for ax, name, lab in ((a1, "radial_grains", r"P^{g}_{\rm radial}(r)"),
                          (a2, "radial_contacts", r"P^{c}_{\rm radial}(r)")):
        if _per_E(red, cs, plt, ax, name, N, transform=per_annulus):
            ax.legend(ncol=2)
        ax.set(xlabel=r"$r$" + (r" $= r_{g,g'}/\sigma_g$" if "grains" in name else
                                r" $= r_{c,c'}/\sigma_g$"), ylabel=rf"${lab}$",
               title=rf"$N_G={N}$")
    return fig


def fig_fictitious(red, cs, plt):
    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    E0 = cs.lowest_E()
    shown = None
    for col, N in zip(_colors(len(cs.Ns)), cs.Ns):
        for i in cs.at(N=N, E=E0):
            x, y = _dist(red, "fictitious_length", i)
            if x is None:
                continue
            ok = (x > 0) & (y > 0)
            if not ok.any():
                continue
            ax.plot(x[ok], y[ok], color=col, lw=0.9, label=rf"$N_G={N}$")
            shown = (x[ok], y[ok])
    if shown is not None:
        x, y = shown  # reference line through the data's first decade
        lo = x[0]
        near = x < 10 * lo
        amp = np.median(y[near] * np.sqrt(x[near]))
        xx = np.geomspace(lo, 10 * lo, 10)
        ax.plot(xx, 0.5 * amp / np.sqrt(xx), "k--", lw=1, label=r"$\propto 1/\sqrt{r-1}$")
        ax.set(xscale="log", yscale="log")
        ax.legend()
    else:
        _placeholder(ax, "no fictitious_length histogram in this file")
    ax.set(xlabel=r"$r-1$, $r=|\vec r_{g,g'}|/(\sigma_g+\sigma_{g'})$", ylabel=r"$P(r-1)$",
           title=rf"$E_G=${_sci(E0)}" if E0 else "")
    return fig


_SYMBOL = {"contact_angle": r"\theta", "contact_length": r"(1-r)/\sqrt{E_G}", "z_g": "z_g",
           "z_v": "z_v", "alpha_e": r"\alpha_e", "alpha_v": r"\alpha_v",
           "fictitious_length": "r-1"}


def fig_self_averaging(red, cs, plt):
    """Spread over packings of <x^n>_Omega / <x^n> against N_G (-> 0 when self-averaging)."""
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    E0 = cs.lowest_E()
    names = sorted(red.self_averaging)
    for n, ax in enumerate(axes):
        shown = False
        for col, name in zip(_colors(len(names), "tab10"), names):
            sa = red.self_averaging[name]
            i = cs.at(E=E0)
            y = sa["ratio_std"][i, n]
            ok = np.isfinite(y) & (y > 0)
            if not ok.any():
                continue
            sym = _SYMBOL.get(name, name.replace("_", " "))
            ax.plot(red.cells["N"][i][ok], y[ok], "o-", ms=3, lw=0.8, color=col,
                    label=rf"${sym}$")
            shown = True
        if shown:
            if cs.Ns:
                nn = np.array([min(cs.Ns), max(cs.Ns)], float)
                ax.plot(nn, 0.5 * (nn / nn[0]) ** -0.5, "k--", lw=0.8, label=r"$\propto N_G^{-1/2}$")
            ax.set(xscale="log", yscale="log")
            ax.legend(ncol=2)
        else:
            _placeholder(ax, "no per-object distributions in this file")
        k = n + 1
        ax.set(xlabel=r"$N_G$",
               ylabel=rf"spread of $\langle x^{k}\rangle_\Omega / \langle x^{k}\rangle$",
               title=rf"$E_G=${_sci(E0)}" if E0 else "")
    return fig


FIGURES = {
    "area_distributions": fig_area_distributions,
    "area_width_scaling": fig_width_scaling,
    "scaling_A_G": lambda red, cs, plt: fig_scaling(red, cs, plt, "A_G"),
    "scaling_psi_O": lambda red, cs, plt: fig_scaling(red, cs, plt, "psi_O"),
    "fit_residuals": fig_residuals,
    "extrapolation": fig_extrapolation,
    "contact_angles_lengths": fig_angles_lengths,
    "connectivity": fig_connectivity,
    "polygon_areas": fig_polygon_areas,
    "radial": fig_radial,
    "fictitious_length": fig_fictitious,
    "self_averaging": fig_self_averaging,
}


def fig_pareto(red, plt):
    """Cost against deviation from the reference variant (campaign.results.tradeoff): the Pareto front.

    Log axes; deviations below 1e-12 (the reference itself, or variants that reproduce its
    packings to rounding) are drawn at 1e-12."""
    from matplotlib.ticker import FormatStrFormatter

    from campaign.results.tradeoff import QUANTITIES

    floor = 1e-12
    recs = [r for r in red.tradeoff if np.isfinite(r.get("cost_ratio_fe", np.nan))]
    labels = {"A_G": r"$|\Delta A_G|$", "delta_Z": r"$|\Delta\,\Delta Z|$", "psi_O": r"$|\Delta \Psi_O|$",
              "iso_excess": r"$|\Delta(N_C/2 - 2N_G + 1)|$"}
    fig = plt.figure(figsize=(10.0, 6.2))
    grid = fig.add_gridspec(2, len(QUANTITIES))
    ax0 = fig.add_subplot(grid[0, :])
    axes = [fig.add_subplot(grid[1, k]) for k in range(len(QUANTITIES))]
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
    for ax, q in zip(axes, QUANTITIES):
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
    from campaign.plan.targets import in_fit_range
    from campaign.results.protocols import LABELS, QUANTITIES

    prot = red.protocols.comparison
    variants = [r["variant"] for r in prot["values"]]
    cols = dict(zip(variants, _colors(len(variants), "tab10")))
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
    a2.set_yticks(np.arange(len(QUANTITIES)))
    a2.set_yticklabels([LABELS[q] for q in QUANTITIES], fontsize=8)
    a2.invert_yaxis()
    a2.set_xlabel(f"(variant - {prot['reference']}) / error   (filled: significant, Holm)")
    a2.set_title("(c) N_G -> inf, differences (clipped at 12)", fontsize=9)
    return fig


# --------------------------------------------------------------------------- systems
_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">")


def _system_label(r):
    return rf"{r['variant']}: $\alpha={r['alpha']:g}$, {r['sizes']}"


def _system_colors(red):
    return dict(zip((r["variant"] for r in red.systems), _colors(len(red.systems))))


def _universality_points(red, v, N):
    """``(x, dA, fit)`` of one (variant, N_G): the cells' mean Delta Z and
    ``<A_G> - A_G*(Delta Z = 0)``, with the fit of A_G against delta_Z; cells where either is
    not positive are left out (log axes). ``(None, None, None)`` without a fit."""
    f = _fit_for(red, v, N, "A_G", "delta_Z")
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
            _placeholder(ax, "no fit of A_G against Delta Z")
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
    alpha = cs.alpha
    if not c:
        for ax in axes.ravel():
            _placeholder(ax, "no response data")
        return fig
    cols = _colors(len(cs.Ns))
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
            _placeholder(ax, "no positive means")
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
        _placeholder(ax, "no moduli")
    return fig


def fig_response_distributions(red, cs, plt):
    """The density of states per energy at the size with full spectra at the most energies; the gap
    distribution P(h) and the small-force distributions (all contacts, extended ones) per size,
    summed over the cells closest to jamming (campaign.results.response.POOL_OVERLAP), with the pooled
    exponents (response_exponents.csv) over their fit windows and the literature's as guides."""
    from campaign.results.response import POOL_OVERLAP

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8))
    ax = axes[0]
    om = red.distributions.get("omega")
    # the size with full spectra at the most energies (the larger one on a tie)
    ncells = {N: sum(bool(om["counts"][i].sum()) for i in cs.at(N=N)) for N in cs.Ns} if om is not None else {}
    dense = sorted((n, N) for N, n in ncells.items() if n)
    dense = [N for _, N in dense]
    if dense and _per_E(red, cs, plt, ax, "omega", dense[-1]):
        top = max(om["edges"][1:][om["counts"][i] > 0].max() for i in cs.at(N=dense[-1]) if om["counts"][i].any())
        ax.set(xlabel=r"$\omega/\sqrt{\langle k\rangle}$", ylabel=r"$D(\omega)$", xlim=(0, 1.05 * top),
               title=rf"density of states, $N_G={dense[-1]}$")
        ax.legend(fontsize=5, ncol=2)
    else:
        _placeholder(ax, "no density of states (N_G above the dense limit, or no modes)")
    c = red.cells
    near = {N: [i for i in cs.at(N=N) if (cs.alpha * c["E"][i] / 2) ** (1 / cs.alpha) <= POOL_OVERLAP * (1 + 1e-9)]
            for N in cs.Ns}
    pooled = {r["N_G"]: r for r in red.response.get("exponents", []) if r["variant"] == cs.v}
    panels = ((axes[1], (("gap", "gamma", -1.0),), r"$h = r/s - 1$", r"$P(h)$", [(-0.41, r"$h^{-0.41}$", ":")],
               1e-2),
              (axes[2], (("force", "theta", 1.0), ("force_extended", "theta_ext", 1.0)), r"$f/\langle f\rangle$",
               r"$P(f/\langle f\rangle)$", [(0.17, r"$f^{0.17}$", ":"), (0.42, r"$f^{0.42}$", "-.")], 1e-1))
    for ax, names, xl, yl, guides, anchor in panels:
        shown = False
        y_anchor = []
        for col, N in zip(_colors(len(cs.Ns)), cs.Ns):
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
            _placeholder(ax, f"no {names[0][0]} histogram near jamming")
            continue
        lo = ax.get_xlim()[0]
        for (expo, glab, gst), ya in zip(guides, (min(y_anchor), max(y_anchor))):
            xx = np.geomspace(max(lo, anchor * 1e-6), anchor, 10)  # through the data at the anchor
            ax.plot(xx, ya * (xx / anchor) ** expo, "k", ls=gst, lw=1, label=glab + " (literature)")
        ax.set(xscale="log", yscale="log", xlabel=xl, ylabel=yl,
               title=rf"typical overlap $\leq${_sci(POOL_OVERLAP)}, exponents of the pooled fits")
        ax.legend(fontsize=5, ncol=2)
    return fig


#: per-variant figures of the linear response, drawn when the store holds it
RESPONSE_FIGURES = {"response_moduli": fig_response_moduli,
                    "response_distributions": fig_response_distributions}


SYSTEM_FIGURES = {"universality": fig_universality, "exponents_vs_alpha": fig_exponents_vs_alpha}
#: per-variant figures drawn from the scaling fits: their title names the fit range or rule
FIT_FIGURES = ("scaling_A_G", "scaling_psi_O", "fit_residuals", "extrapolation")


def make_figures(red, out_dir, *, dpi=90):
    """Write every figure for every variant; return the list of PNG paths."""
    plt = _plt()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    variants = sorted({str(v) for v in red.cells["variant"]})
    rule = "fits: " + str(red.meta.get("fit_rule_name", "every energy"))
    written = []
    for v in variants:
        cs = _Cells(red, v)
        suffix = "" if len(variants) == 1 else f"_{v}"
        cs.alpha = _alpha_of(red, v)
        figures = dict(FIGURES, **(RESPONSE_FIGURES if red.response else {}))
        for name, fn in figures.items():
            fig = fn(red, cs, plt)
            title = [f"variant {v}"] if len(variants) > 1 else []
            if name in FIT_FIGURES:  # the range or rule the fits drawn come from
                title.append(rule)
            if title:
                fig.suptitle("; ".join(title), fontsize=9)
            p = out / f"{name}{suffix}.png"
            fig.savefig(p, dpi=dpi)
            plt.close(fig)
            written.append(p)
    if red.tradeoff:
        fig = fig_pareto(red, plt)
        p = out / "pareto.png"
        fig.savefig(p, dpi=dpi)
        plt.close(fig)
        written.append(p)
    if red.protocols.comparison.get("pairs"):
        fig = fig_protocols(red, plt)
        p = out / "protocols.png"
        fig.savefig(p, dpi=dpi)
        plt.close(fig)
        written.append(p)
    if red.systems:  # two physical systems or more (campaign.results.systems)
        for name, fn in SYSTEM_FIGURES.items():
            fig = fn(red, plt)
            fig.suptitle(rule, fontsize=9)  # the range or rule the exponents come from
            p = out / f"{name}.png"
            fig.savefig(p, dpi=dpi)
            plt.close(fig)
            written.append(p)
    return written
