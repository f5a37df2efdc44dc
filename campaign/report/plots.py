"""The paper's figures of a reduced campaign, per variant, and ``make_figures``, which writes them.

Matplotlib, the ``plot`` extra. ``make_figures(reduction, out_dir)`` writes one PNG per figure of
the paper that a campaign can produce, plus the goodness-of-fit, width-scaling and extrapolation
figures, then those of the sections the reduction holds (``campaign.report.sectionplots``). Every
function takes a ``Reduction`` (campaign.results.reduce) and never reads files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from campaign.errors import UserError
from campaign.report.plotkit import Cells, colors, dist, fit_for, per_energy, placeholder, sci
from campaign.report.sectionplots import SECTION_FIGURES


def _plt():
    """matplotlib's ``pyplot`` with the figures' style, or a UserError naming the plot extra."""
    try:  # the plot extra: imported when figures are drawn, not with this module
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise UserError("plotting needs matplotlib: pip install 'jamming-campaign[plot]'") from None
    plt.rcParams.update({"figure.dpi": 90, "font.size": 9, "axes.titlesize": 9,
                         "figure.constrained_layout.use": True,
                         "legend.fontsize": 7, "savefig.bbox": "tight"})
    return plt


# --------------------------------------------------------------------------- the paper's figures
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
    for col, N in zip(colors(len(cs.Ns)), cs.Ns):
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
           title=rf"$E_G={sci(E0)[1:-1]}$, best Gaussians" if E0 else "")
    a1.legend()
    N = 512 if 512 in cs.Ns else cs.largest_N()
    for col, E in zip(colors(len(cs.Es), "plasma"), cs.Es):
        for i in cs.at(N=N, E=E):
            e, k = _area_hist(red, i)
            if e is None:
                continue
            a2.stairs(k / k.sum() / np.diff(e), e, color=col, label=rf"$E_G=${sci(E)}")
    a2.set(xlabel=r"$A_G$", ylabel=r"$P(A_G)$", title=rf"$N_G={N}$")
    a2.legend(ncol=2)
    return fig


def fig_width_scaling(red, cs, plt):
    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    c = red.cells
    for col, E in zip(colors(len(cs.Es), "plasma"), cs.Es):
        i = cs.at(E=E)
        i = i[np.isfinite(c["A_G_gauss_sigma"][i])]
        if len(i) == 0:
            continue
        ax.errorbar(c["N"][i], c["A_G_gauss_sigma"][i], c["A_G_gauss_sigma_err"][i], fmt="o",
                    ms=3, color=col, label=rf"$E_G=${sci(E)}")
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


_XLAB = {"E_G": r"$E_G$", "delta_Z": r"$\Delta Z$"}
_YLAB = {"A_G": r"$\Delta A_G = A_G - A_G^*$", "psi_O": r"$\Delta\Psi_O = \Psi_O - \Psi_O^*$"}


def _range_label(f):
    """``, E_G <= 1e-5``: the highest grid energy of a fit (its range starts at the lowest)."""
    hi = f.get("E_max", np.nan)
    return rf", $E_G\leq${sci(hi)}" if hi is not None and np.isfinite(hi) else ""


def fig_scaling(red, cs, plt, quantity):
    """Delta A_G (or Delta Psi_O) against E_G and Delta Z per N_G with the fitted power laws;
    cells outside a fit's range are open markers."""
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    c = red.cells
    for ax, absc in zip(axes, ("E_G", "delta_Z")):
        shown = False
        for col, N in zip(colors(len(cs.Ns)), cs.Ns):
            f = fit_for(red, cs.v, N, quantity, absc)
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
            placeholder(ax, "no fit (too few cells)")
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
        for col, N in zip(colors(len(cs.Ns)), cs.Ns):
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
            placeholder(ax, "no fit")
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


def fig_angles_lengths(red, cs, plt):
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.5))
    N = 2048 if 2048 in cs.Ns else cs.largest_N()
    if per_energy(red, cs, plt, a1, "sin_theta", N, positive=True, step=True):
        s = np.linspace(0, 0.995, 200)
        a1.plot(s, 2 / np.pi / np.sqrt(1 - s * s), "k--", lw=1,
                label=r"random: $\frac{2}{\pi}\frac{1}{\sqrt{1-\sin^2\theta}}$")
        a1.legend(ncol=2)
    a1.set(xlabel=r"$\sin\theta$", ylabel=r"$P(\sin\theta)$", title=rf"$N_G={N}$")
    if per_energy(red, cs, plt, a2, "contact_length", N):
        a2.legend(ncol=2)
    a2.set(xlabel=r"$(1-r)/\sqrt{E_G}$, $r=|\vec r_{g,c}|/\sigma_g$",
           ylabel=r"$P\left((1-r)/\sqrt{E_G}\right)$", title=rf"$N_G={N}$")
    return fig


def fig_connectivity(red, cs, plt):
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.5))
    N = cs.largest_N()
    for ax, name, lab in ((a1, "z_g", "z_g"), (a2, "z_v", "z_v")):
        if per_energy(red, cs, plt, ax, name, N, positive=True, marker="o", ms=3):
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
        if per_energy(red, cs, plt, ax, name, N, positive=True, step=True):
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
        if per_energy(red, cs, plt, ax, name, N, transform=per_annulus):
            ax.legend(ncol=2)
        ax.set(xlabel=r"$r$" + (r" $= r_{g,g'}/\sigma_g$" if "grains" in name else
                                r" $= r_{c,c'}/\sigma_g$"), ylabel=rf"${lab}$",
               title=rf"$N_G={N}$")
    return fig


def fig_fictitious(red, cs, plt):
    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    E0 = cs.lowest_E()
    shown = None
    for col, N in zip(colors(len(cs.Ns)), cs.Ns):
        for i in cs.at(N=N, E=E0):
            x, y = dist(red, "fictitious_length", i)
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
        placeholder(ax, "no fictitious_length histogram in this file")
    ax.set(xlabel=r"$r-1$, $r=|\vec r_{g,g'}|/(\sigma_g+\sigma_{g'})$", ylabel=r"$P(r-1)$",
           title=rf"$E_G=${sci(E0)}" if E0 else "")
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
        for col, name in zip(colors(len(names), "tab10"), names):
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
            placeholder(ax, "no per-object distributions in this file")
        k = n + 1
        ax.set(xlabel=r"$N_G$",
               ylabel=rf"spread of $\langle x^{k}\rangle_\Omega / \langle x^{k}\rangle$",
               title=rf"$E_G=${sci(E0)}" if E0 else "")
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


#: per-variant figures drawn from the scaling fits: their title names the fit range or rule
FIT_FIGURES = ("scaling_A_G", "scaling_psi_O", "fit_residuals", "extrapolation")


def _save(fig, path, dpi, plt, written):
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    written.append(path)


def make_figures(red, out_dir, *, dpi=90):
    """Write every figure for every variant, then the sections' figures of the campaign; return the
    list of PNG paths."""
    plt = _plt()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    variants = sorted({str(v) for v in red.cells["variant"]})
    rule = "fits: " + str(red.meta.get("fit_rule_name", "every energy"))
    shown = {name: f for name, f in SECTION_FIGURES.items() if f.shows(red.sections[name])}
    written = []
    for v in variants:
        cs = Cells(red, v)
        suffix = "" if len(variants) == 1 else f"_{v}"
        figures = dict(FIGURES)
        for f in shown.values():
            figures.update(f.variant)
        for name, fn in figures.items():
            fig = fn(red, cs, plt)
            title = [f"variant {v}"] if len(variants) > 1 else []
            if name in FIT_FIGURES:  # the range or rule the fits drawn come from
                title.append(rule)
            if title:
                fig.suptitle("; ".join(title), fontsize=9)
            _save(fig, out / f"{name}{suffix}.png", dpi, plt, written)
    for f in shown.values():
        for name, fn in f.campaign.items():
            fig = fn(red, plt)
            if f.titled:
                fig.suptitle(rule, fontsize=9)  # the range or rule the exponents come from
            _save(fig, out / f"{name}.png", dpi, plt, written)
    return written
