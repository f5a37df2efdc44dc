"""What the figures share: colours, labels, a variant's cells, curves per energy, empty panels.

NumPy only: the figures' functions are handed matplotlib's ``pyplot``, and the colour maps are read
when a figure is drawn."""

from __future__ import annotations

import numpy as np


def colors(n, cmap="viridis"):
    """``n`` colours of the colour map ``cmap``, spread over its first 85%."""
    import matplotlib  # the plot extra: imported when a figure is drawn

    cm = matplotlib.colormaps[cmap]
    return [cm(x) for x in np.linspace(0.0, 0.85, max(n, 1))]


def sci(e):
    """A number as a TeX power of ten, one digit: ``$10^{-6}$``, ``$2\\times10^{-8}$``."""
    m, x = f"{e:.0e}".split("e")
    return rf"$10^{{{int(x)}}}$" if m == "1" else rf"${m}\times10^{{{int(x)}}}$"


class Cells:
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


def dist(red, name, i):
    """Bin centres and density of histogram ``name`` in cell ``i`` ((None, None) without it)."""
    d = red.distributions.get(name)
    if d is None:
        return None, None
    e = d["edges"]
    return 0.5 * (e[1:] + e[:-1]), d["density"][i]


def placeholder(ax, text):
    """A panel with nothing to draw says why."""
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, fontsize=8)


def fit_for(red, v, N, q, a):
    """The scaling fit of ``q`` against ``a`` at (variant ``v``, ``N``), or None."""
    return next((f for f in red.fits if f["variant"] == v and f["N_G"] == N
                 and f["quantity"] == q and f["abscissa"] == a), None)


def per_energy(red, cs, plt, ax, name, N, transform=None, positive=False, step=False, **kw):
    """One curve per energy at size N.

    ``step``: draw the histogram as steps (isolated spikes, such as the three-disk peaks
    near zero energy, stay visible); ``positive``: log axes -- empty bins are clipped
    (steps) or hidden (lines), and the axis starts just below the smallest value.
    """
    shown = False
    smallest = np.inf
    for col, E in zip(colors(len(cs.Es), "plasma"), cs.Es):
        for i in cs.at(N=N, E=E):
            x, y = dist(red, name, i)
            if x is None or not np.any(np.isfinite(y)):
                continue
            if transform:
                x, y = transform(x, y)
            if positive and np.any(y > 0):
                smallest = min(smallest, np.nanmin(y[y > 0]))
            lab = rf"$E_G=${sci(E)}"
            if step:
                ax.stairs(np.nan_to_num(y), red.distributions[name]["edges"], color=col, lw=0.9,
                          label=lab, **kw)
            else:
                if positive:
                    y = np.where(y > 0, y, np.nan)
                ax.plot(x, y, color=col, lw=0.9, label=lab, **kw)
            shown = True
    if not shown:
        placeholder(ax, f"no {name} histogram in this file")
    elif positive:
        ax.set_yscale("log", nonpositive="clip")
        if np.isfinite(smallest):
            ax.set_ylim(bottom=0.5 * smallest)
    return shown
