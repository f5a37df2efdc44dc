"""The spread between packings that weights the scaling fits: one model per law and variant, pooled
over the cells of the fit range (docs/REDUCED.md, "Error bars that hold").

A cell's mean enters a fit with the weight ``n_c / sigma_c^2``, ``n_c`` its packings and ``sigma_c^2``
the variance between them of what the fit measures: ``y - s x``, the quantity ``y`` less the
abscissa's scatter carried through the law's local slope ``s = c beta x^(beta - 1)`` (for ``x =
Delta Z`` most of a packing's ``A_G`` follows its own excess contacts). Each cell's own sample
variance comes from a few packings (at 4 packings a quarter of them fall below 0.40 of the truth), and
a weight built on it makes the fit lean on the cells whose spread came out low, whose errors the same
number makes small. So ``sigma_c^2`` is not a cell's own: it is a model fitted to all the cells of a
variant's fit range,

    log sigma_c^2 = lambda_N + gamma u_c,        u_c = log10 E_c - its mean over the cells,

an amplitude per size and one trend with energy shared by the sizes (the spread is the same at
every energy when ``gamma = 0``; a spread growing 1.5-fold across the ten decades of the default fit
range is ``gamma = 0.035``), by maximum likelihood: ``(n_c - 1) v_c / sigma_c^2`` is chi^2 with
``n_c - 1`` degrees of freedom for normal packings (Fisher scoring from the pooled variances, which
it starts from). Tens to hundreds of packings determine each parameter, so the weights hardly move
with the noise of a few. The same model is fitted again in every bootstrap replica, from the
replica's packings. ``homogeneity`` is Bartlett's test of equal variances over a size's cells, the
check every fit records (``spread_p`` in fits.csv).
"""

from __future__ import annotations

import numpy as np

from campaign.results.fits import chi2_p_value

#: Fisher-scoring steps from the pooled start (converged to 1e-6 in log sigma^2 by 4 on every
#: synthetic and real campaign tried)
SCORING_STEPS = 6
#: a scoring step that does not lower a replica's negative log-likelihood is halved at most this often
HALVINGS = 30


def pooled_model(v, n, size, u, G):
    """``sigma^2`` of every cell under ``log sigma^2 = lambda_size + gamma u`` for each row of ``v``.

    ``v`` (R, K): the cells' sample variances, a row per replica (row 0 the data's); ``n`` (K,) their
    packings (a cell needs 2); ``size`` (K,) each cell's size index in 0 .. G-1; ``u`` (K,) its
    centred log10 energy. Returns (R, K). A size whose cells all have zero variance keeps a tiny one
    (its packings are alike: the others' weights decide)."""
    v = np.asarray(v, float)
    m = (np.asarray(n, float) - 1.0) / 2.0
    X = np.zeros((len(m), G + 1))
    X[np.arange(len(m)), size] = 1.0
    X[:, G] = u
    if np.ptp(u) == 0:  # one energy: no trend to fit
        X = X[:, :G]
    held = (X[:, :G] * m[:, None]).sum(0)
    pooled = (v * m) @ X[:, :G] / np.maximum(held, 1e-300)
    theta = np.zeros((v.shape[0], X.shape[1]))
    theta[:, :G] = np.log(np.maximum(pooled, 1e-300))
    inv = np.linalg.pinv((X.T * m) @ X)

    def nll(th, rows=slice(None)):  # the rows' negative log-likelihood, up to constants
        eta = th @ X.T
        with np.errstate(over="ignore", invalid="ignore"):
            return ((v[rows] * np.exp(-eta) + eta) * m).sum(1)

    cur = nll(theta)
    for _ in range(SCORING_STEPS):
        s2 = np.exp(theta @ X.T)
        step = (((v / s2) - 1.0) * m) @ X @ inv.T
        new = theta + step
        got = nll(new)
        # a full step that raises a row's likelihood's negative (a replica of few packings per cell far
        # from the pooled start) is halved until it does not: undamped, such a row's trend ran to
        # weights 1e-87 .. 1e76 and the fits' sums to 0/0
        bad = ~(got <= cur + 1e-9 * np.abs(cur))
        for _ in range(HALVINGS):
            if not bad.any():
                break
            step[bad] *= 0.5
            new[bad] = theta[bad] + step[bad]
            got[bad] = nll(new[bad], bad)
            bad &= ~(got <= cur + 1e-9 * np.abs(cur))
        new[bad], got[bad] = theta[bad], cur[bad]
        theta, cur = new, got
    return np.exp(theta @ X.T)


def trend(v, n, size, u, G) -> float:
    """The fitted ``gamma`` of the data (row 0): how log10 sigma^2 changes per decade of energy."""
    v = np.asarray(v, float)[:1]
    s2 = pooled_model(v, n, size, u, G)[0]
    X = np.column_stack([np.eye(G)[size], u])
    coef, *_ = np.linalg.lstsq(X, np.log(s2), rcond=None)
    return float(coef[-1] / np.log(10.0))


def homogeneity(v, n) -> float:
    """Bartlett's test that cells with sample variances ``v`` of ``n`` packings share one variance:
    its p-value (NaN with fewer than two cells of 2 packings or more, or a zero variance)."""
    v, n = np.asarray(v, float), np.asarray(n, float)
    ok = (n >= 2) & np.isfinite(v) & (v > 0)
    v, nu = v[ok], n[ok] - 1.0
    k = len(v)
    if k < 2:
        return np.nan
    N = nu.sum()
    sp = (nu * v).sum() / N
    stat = (N * np.log(sp) - (nu * np.log(v)).sum()) / (1.0 + ((1.0 / nu).sum() - 1.0 / N) / (3.0 * (k - 1)))
    return chi2_p_value(stat, k - 1)
