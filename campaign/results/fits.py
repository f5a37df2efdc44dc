"""Fitting maths of the reducer: pure functions of arrays, no I/O.

* ``fit_power_law``: ``y = a + c x**beta`` by weighted least squares. For a fixed
  exponent the model is linear in ``(a, c)``, so the exponent is found by
  profiling chi^2 over beta (a grid, then a golden-section refinement) and the
  intercept and prefactor follow in closed form. The same code fits many data
  sets at once (``fit_power_law_batch``), which is what makes the bootstrap cheap (its
  replicas: ``campaign.results.bootstrap``).
* ``chi2_p_value``: the goodness of a fit as a p-value; ``normal_p_value``: a z's two-sided one.
* ``fit_inverse_n``: ``y = y_inf + b / N`` (finite-size extrapolation).
* ``gaussian_mle`` and ``fit_width_scaling``: the best Gaussian of P(A_G) and the
  law ``sigma ~ N**-gamma``.
* ``three_disk_peaks``: exact edge-triangle and void-area values of three disks in
  mutual contact, from the radii by the law of cosines.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

BETA_BOUNDS = (0.02, 4.0)
_GRID = 121
_GOLDEN_ITERS = 36


# --------------------------------------------------------------------------- power law
def _solve_linear(f, y, w):
    """Weighted LS of y = a + c f for every row: f, y (..., K), w (K,) or (..., K)."""
    S = np.sum(w * np.ones_like(f), axis=-1)
    Sf = np.sum(w * f, axis=-1)
    Sff = np.sum(w * f * f, axis=-1)
    Sy = np.sum(w * y, axis=-1)
    Sfy = np.sum(w * f * y, axis=-1)
    det = S * Sff - Sf * Sf
    with np.errstate(invalid="ignore", divide="ignore"):
        c = (S * Sfy - Sf * Sy) / det
        a = (Sy - c * Sf) / S
    r = y - a[..., None] - c[..., None] * f
    chi2 = np.sum(w * r * r, axis=-1)
    return a, c, chi2


def _log_abscissa(x):
    """log(x / x_ref) per row (x_ref the geometric mean of the row's positive x, for conditioning);
    -inf where x = 0 (e.g. isostatic packings, Delta Z = 0: there x^beta = 0 for beta > 0)."""
    pos = x > 0
    with np.errstate(divide="ignore"):
        lx = np.where(pos, np.log(np.where(pos, x, 1.0)), -np.inf)
    lref = (np.where(pos, lx, 0.0).sum(axis=-1) / np.maximum(pos.sum(axis=-1), 1))[..., None]
    return lx - lref, lref[..., 0]


@njit(cache=True)
def _chi2_at(beta, lu, y, w, a, c, f):
    """chi^2 of the groups of one data set at exponent ``beta``, each group's intercept and (scaled)
    amplitude in closed form into ``a``, ``c``; ``f`` a scratch row."""
    G, K = lu.shape
    total = 0.0
    for g in range(G):
        S = Sf = Sff = Sy = Sfy = 0.0
        for k in range(K):
            wk = w[g, k]
            fk = math.exp(beta * lu[g, k]) if (wk != 0.0 and lu[g, k] > -math.inf) else 0.0
            f[k] = fk
            S += wk
            Sf += wk * fk
            Sff += wk * fk * fk
            Sy += wk * y[g, k]
            Sfy += wk * fk * y[g, k]
        cg = (S * Sfy - Sf * Sy) / (S * Sff - Sf * Sf)
        ag = (Sy - cg * Sf) / S
        a[g] = ag
        c[g] = cg
        for k in range(K):
            if w[g, k] != 0.0:
                r = y[g, k] - ag - cg * f[k]
                total += w[g, k] * r * r
    return total


@njit(cache=True)
def _grid_argmin(lu, y, w, lo, step, n_grid, F, E):
    """The index of the smallest chi^2 on the grid ``lo + step * i``, i < ``n_grid``: ``_chi2_at`` at
    every point, its powers ``x**beta`` stepped by one multiplication each (``F`` *= ``E`` =
    ``x**step``; relative drift ~ n_grid * 1e-16, nothing beside the chi^2 differences the grid
    resolves) instead of an exponential: the grid is 3/4 of a fit's evaluations. ``F``, ``E``
    (G, K) scratch."""
    G, K = lu.shape
    for g in range(G):
        for k in range(K):
            if w[g, k] != 0.0 and lu[g, k] > -math.inf:
                F[g, k] = math.exp(lo * lu[g, k])
                E[g, k] = math.exp(step * lu[g, k])
            else:
                F[g, k] = 0.0
                E[g, k] = 0.0
    best = math.inf
    kbest = 0
    for i in range(n_grid):
        total = 0.0
        for g in range(G):
            S = Sf = Sff = Sy = Sfy = 0.0
            for k in range(K):
                wk = w[g, k]
                fk = F[g, k]
                S += wk
                Sf += wk * fk
                Sff += wk * fk * fk
                Sy += wk * y[g, k]
                Sfy += wk * fk * y[g, k]
            cg = (S * Sfy - Sf * Sy) / (S * Sff - Sf * Sf)
            ag = (Sy - cg * Sf) / S
            for k in range(K):
                if w[g, k] != 0.0:
                    r = y[g, k] - ag - cg * F[g, k]
                    total += w[g, k] * r * r
                F[g, k] *= E[g, k]
        if total < best:  # a NaN or infinite chi^2 never wins
            best = total
            kbest = i
    return kbest


@njit(cache=True)
def _profile_fits(lu, y, w, lo, hi, n_grid, n_golden):
    """For each data set r of ``lu``, ``y``, ``w`` (R, G, K): the exponent minimising chi^2 (a grid of
    ``n_grid`` points over [lo, hi], then golden section in the bracket around the grid's minimum),
    with each group's intercept and scaled amplitude. Returns a, c (R, G), beta, chi2 (R,)."""
    R, G, K = lu.shape
    A = np.empty((R, G))
    C = np.empty((R, G))
    B = np.empty(R)
    X2 = np.empty(R)
    a = np.empty(G)
    c = np.empty(G)
    f = np.empty(K)
    F = np.empty((G, K))
    E = np.empty((G, K))
    gr = (math.sqrt(5.0) - 1.0) / 2.0
    step = (hi - lo) / (n_grid - 1)
    for r in range(R):
        lur, yr, wr = lu[r], y[r], w[r]
        kbest = _grid_argmin(lur, yr, wr, lo, step, n_grid, F, E)
        left = lo + step * max(kbest - 1, 0)
        right = lo + step * min(kbest + 1, n_grid - 1)
        p = right - gr * (right - left)
        q = left + gr * (right - left)
        fp = _chi2_at(p, lur, yr, wr, a, c, f)
        fq = _chi2_at(q, lur, yr, wr, a, c, f)
        for _ in range(n_golden):
            if fp > fq:  # the minimum in [p, right]
                left, p, fp = p, q, fq
                q = left + gr * (right - left)
                fq = _chi2_at(q, lur, yr, wr, a, c, f)
            else:
                right, q, fq = q, p, fp
                p = right - gr * (right - left)
                fp = _chi2_at(p, lur, yr, wr, a, c, f)
        B[r] = 0.5 * (left + right)
        X2[r] = _chi2_at(B[r], lur, yr, wr, a, c, f)
        A[r] = a
        C[r] = c
    return A, C, B, X2


def fit_shared_exponent_batch(x, y, yerr, bounds=BETA_BOUNDS):
    """``y_gk = a_g + c_g x_gk**beta``: one exponent shared by the G groups of each of B data
    sets, an intercept and an amplitude per group (the finite-size table's sizes: the exponent
    belongs to the transition, the intercept and amplitude to the size). For a fixed exponent the
    model is linear in each group's ``(a_g, c_g)``, so chi^2 is profiled over ``beta``: a 121-point
    grid over ``bounds``, then golden section in the bracket around the grid's minimum (compiled:
    a bootstrap refits thousands of data sets).

    ``x``, ``y``: (B, G, K) or (G, K), groups padded to K cells with ``yerr = inf`` (weight 0);
    ``yerr`` broadcast to their shape. Returns ``a, c`` (B, G), ``beta, chi2`` (B,).
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    squeeze = x.ndim == 2
    if squeeze:
        x, y = x[None], y[None]
    w = np.broadcast_to(1.0 / np.asarray(yerr, float) ** 2, x.shape)
    x = np.where(w > 0, x, 1.0)  # padding: any positive abscissa, weight 0
    y = np.where(w > 0, y, 0.0)
    lu, lref = _log_abscissa(x)   # (B, G, K), (B, G)
    a, c_scaled, beta, chi2 = _profile_fits(np.ascontiguousarray(lu), np.ascontiguousarray(y),
                                            np.ascontiguousarray(w), float(bounds[0]), float(bounds[1]),
                                            _GRID, _GOLDEN_ITERS)
    out = a, c_scaled * np.exp(-beta[:, None] * lref), beta, chi2
    return tuple(v[0] for v in out) if squeeze else out


def fit_power_law_batch(x, y, yerr, bounds=BETA_BOUNDS):
    """Fit ``y = a + c x**beta`` to each row of ``x``, ``y`` (shape (B, K)): the shared fit of one
    group. ``yerr`` (K,) or (B, K) are the standard errors used as weights 1/yerr^2.
    Returns arrays ``a, c, beta, chi2`` of shape (B,). ``x`` must be >= 0.
    """
    x = np.atleast_2d(np.asarray(x, float))
    y = np.atleast_2d(np.asarray(y, float))
    yerr = np.broadcast_to(np.asarray(yerr, float), x.shape)
    a, c, beta, chi2 = fit_shared_exponent_batch(x[:, None, :], y[:, None, :], yerr[:, None, :], bounds)
    return a[:, 0], c[:, 0], beta, chi2


@dataclass
class PowerLawFit:
    """Result of ``y = a + c x**beta`` with bootstrap errors."""

    intercept: float = np.nan
    coeff: float = np.nan
    exponent: float = np.nan
    intercept_err: float = np.nan
    coeff_err: float = np.nan
    exponent_err: float = np.nan
    chi2: float = np.nan
    dof: int = 0
    n_points: int = 0
    n_boot: int = 0
    ok: bool = False
    message: str = ""
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (y - model)/yerr
    at_bound: bool = False
    boot_at_bound: float = np.nan   # fraction of the bootstrap refits whose exponent is at a bound

    @property
    def chi2_dof(self):
        return self.chi2 / self.dof if self.dof > 0 else np.nan

    @property
    def undetermined(self) -> str:
        """Why this fit's exponent is not a measurement ("" when it is): no fit, the exponent at
        a search bound, no finite bootstrap error, or a bootstrap distribution cut by a bound."""
        return undetermined_reason(self.ok, self.exponent, self.exponent_err, self.at_bound,
                                   self.boot_at_bound, self.message)


#: A fit whose bootstrap refits reach a search bound more often than this is undetermined: its
#: 95% interval does not lie inside the range searched, so its error is not an error.
MAX_BOOT_AT_BOUND = 0.025


def undetermined_reason(ok, exponent, err, at_bound, boot_at_bound, message=""):
    if not ok or not np.isfinite(exponent):
        return message or "no fit"
    if at_bound:
        return f"exponent {exponent:.3g} at the search bound"
    if not (np.isfinite(err) and err > 0):
        return "no bootstrap error"
    if np.isfinite(boot_at_bound) and boot_at_bound > MAX_BOOT_AT_BOUND:
        return f"{100 * boot_at_bound:.0f}% of its bootstrap refits at a search bound"
    return ""


def _at_bound(beta, bounds):
    return np.minimum(beta - bounds[0], bounds[1] - beta) < 1e-3 * (bounds[1] - bounds[0])


def spread(replicas, axis=0):
    """The error a bootstrap gives: half the central 68.27% interval of its replicas along ``axis``
    (the standard deviation for a normal distribution, and for a skewed or heavy-tailed one the
    1-sigma interval it stands for: a few replicas far out, a weakly determined fit wandering, do
    not make it). NaN replicas are left out; NaN with fewer than two."""
    r = np.moveaxis(np.asarray(replicas, float), axis, 0)
    ok = np.isfinite(r)
    with np.errstate(invalid="ignore"):
        lo, hi = np.nanquantile(np.where(ok, r, np.nan), [0.15865525393145707, 0.8413447460685429], axis=0)
    out = np.where(ok.sum(0) >= 2, (hi - lo) / 2.0, np.nan)
    return float(out) if out.ndim == 0 else out


def fit_power_law(x, y, yerr, *, boot_x=None, boot_y=None, boot_err=None, bounds=BETA_BOUNDS) -> PowerLawFit:
    """Fit one data set with weights ``1 / yerr^2``; the errors are the spread (``spread``) of the
    refits of the bootstrap replicas ``boot_x``, ``boot_y`` (B, K), each with its own weights
    ``boot_err`` (B, K) when given (the reducer's: its weights are redone in every replica), else
    ``yerr``'s."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    yerr = np.asarray(yerr, float)
    K = x.size
    if np.any(x < 0):
        raise ValueError(f"fit_power_law: x must be >= 0, got min {x.min()}")
    if K < 4:
        return PowerLawFit(n_points=K, message=f"needs at least 4 cells, has {K}")
    a, c, beta, chi2 = (v[0] for v in fit_power_law_batch(x[None], y[None], yerr, bounds))
    res = (y - a - c * x**beta) / yerr
    at_bound = bool(_at_bound(beta, bounds))
    out = PowerLawFit(a, c, beta, chi2=chi2, dof=K - 3, n_points=K, ok=bool(np.isfinite(chi2)),
                      residuals=res, at_bound=at_bound,
                      message="exponent at the search bound" if at_bound else "")
    if boot_x is not None and boot_y is not None and len(boot_x) > 1:
        ba, bc, bb, _ = fit_power_law_batch(boot_x, boot_y, yerr if boot_err is None else boot_err, bounds)
        out.intercept_err, out.coeff_err, out.exponent_err = spread(ba), spread(bc), spread(bb)
        out.boot_at_bound = float(np.mean(_at_bound(bb, bounds)))
        out.n_boot = len(boot_x)
    return out


@dataclass
class SharedFit:
    """``y_gk = a_g + c_g x_gk**beta`` over G groups (sizes) with one exponent, bootstrap errors;
    ``intercept_replicas`` (B, G) the replicas' intercepts (what the 1/N_G line is drawn through)."""

    exponent: float = np.nan
    exponent_err: float = np.nan
    intercepts: np.ndarray = field(default_factory=lambda: np.zeros(0))
    intercept_errs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    coeffs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    chi2: float = np.nan
    dof: int = 0
    n_points: int = 0
    n_boot: int = 0
    ok: bool = False
    at_bound: bool = False
    boot_at_bound: float = np.nan
    message: str = ""
    intercept_replicas: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    exponent_replicas: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def chi2_dof(self):
        return self.chi2 / self.dof if self.dof > 0 else np.nan

    @property
    def undetermined(self) -> str:
        return undetermined_reason(self.ok, self.exponent, self.exponent_err, self.at_bound,
                                   self.boot_at_bound, self.message)


def _pad(groups, fill):
    """Stack groups of shape (..., K_g) into (..., G, K), K the longest, padded with ``fill``."""
    groups = [np.asarray(r, float) for r in groups]
    K = max(r.shape[-1] for r in groups)
    out = np.full(groups[0].shape[:-1] + (len(groups), K), fill)
    for i, r in enumerate(groups):
        out[..., i, :r.shape[-1]] = r
    return out


def fit_shared_exponent(xs, ys, yerrs, *, boot_xs=None, boot_ys=None, boot_errs=None,
                        bounds=BETA_BOUNDS) -> SharedFit:
    """One exponent for several groups of cells (lists of 1-d arrays, one per group), each group
    with its own intercept and amplitude; a group needs 3 cells (3 positive abscissae) to inform
    the exponent and is refused below. ``boot_xs``, ``boot_ys``: per group (B, K_g) replicas of
    its cell means, ``boot_errs`` their errors (weights) when they differ from ``yerrs``; the errors
    are their refits' spread (``spread``)."""
    G = len(xs)
    if G == 0:
        return SharedFit(message="no size with 3 cells in the fit range")
    for x in xs:
        if np.count_nonzero(np.asarray(x, float) > 0) < 3:
            raise ValueError("fit_shared_exponent: every group needs 3 cells with a positive abscissa")
        if np.any(np.asarray(x, float) < 0):
            raise ValueError("fit_shared_exponent: x must be >= 0")
    X, Y, W = _pad(xs, 1.0), _pad(ys, 0.0), _pad(yerrs, np.inf)
    a, c, beta, chi2 = fit_shared_exponent_batch(X, Y, W, bounds)
    K = sum(len(x) for x in xs)
    at_bound = bool(_at_bound(beta, bounds))
    out = SharedFit(float(beta), intercepts=a, coeffs=c, chi2=float(chi2), dof=K - 2 * G - 1,
                    n_points=K, ok=bool(np.isfinite(chi2)), at_bound=at_bound,
                    intercept_errs=np.full(G, np.nan),
                    message="exponent at the search bound" if at_bound else "")
    if boot_xs is not None and boot_ys is not None and len(boot_xs[0]) > 1:
        BX, BY = _pad(boot_xs, 1.0), _pad(boot_ys, 0.0)   # (B, G, K)
        BW = W if boot_errs is None else _pad(boot_errs, np.inf)
        ba, _, bb, _ = fit_shared_exponent_batch(BX, BY, BW, bounds)
        out.exponent_err = spread(bb)
        out.intercept_errs = spread(ba)
        out.intercept_replicas, out.exponent_replicas = ba, bb
        out.boot_at_bound = float(np.mean(_at_bound(bb, bounds)))
        out.n_boot = BX.shape[0]
    return out


# --------------------------------------------------------------------------- goodness of fit
#: A power law with an intercept needs its three parameters and one degree of freedom.
MIN_CELLS = 4


def chi2_p_value(chi2, dof):
    """P(chi^2_dof >= chi2): the probability of a worse fit if the model and the errors hold
    (``scipy.special.chdtrc``, what ``scipy.stats.chi2.sf`` computes, without importing scipy.stats)."""
    from scipy.special import chdtrc  # half a second to import: paid by a reduction, not by `campaign --help`

    return float(chdtrc(dof, chi2)) if dof > 0 and np.isfinite(chi2) else np.nan


def normal_p_value(z):
    """P(|Z| >= |z|) for a standard normal Z: the two-sided p-value of ``z`` (NaN for NaN)."""
    from scipy.special import erfc  # as in chi2_p_value

    return float(erfc(abs(z) / math.sqrt(2))) if np.isfinite(z) else np.nan


# --------------------------------------------------------------------------- linear fits
def weighted_linear_fit(X, y, yerr):
    """Weighted least squares ``y = X @ p``. Returns p, cov (absolute sigma), chi2, dof."""
    X = np.asarray(X, float)
    y = np.asarray(y, float)
    w = 1.0 / np.asarray(yerr, float)
    A = X * w[:, None]
    b = y * w
    p, *_ = np.linalg.lstsq(A, b, rcond=None)
    cov = np.linalg.pinv(A.T @ A)
    r = b - A @ p
    return p, cov, float(r @ r), len(y) - X.shape[1]


@dataclass
class LinearResult:
    value: float = np.nan      # intercept (y at 1/N -> 0), or log-prefactor
    err: float = np.nan
    slope: float = np.nan
    slope_err: float = np.nan
    chi2_dof: float = np.nan
    n_points: int = 0
    message: str = ""


def fit_inverse_n(N, y, yerr) -> LinearResult:
    """Extrapolate ``y = y_inf + b / N`` to N -> infinity (weighted).

    Errors come from the covariance with the given standard errors, scaled by
    sqrt(chi^2/dof) when that exceeds 1 (the data scatter more than their errors say).
    """
    N = np.asarray(N, float)
    y = np.asarray(y, float)
    yerr = np.asarray(yerr, float)
    good = np.isfinite(y) & np.isfinite(yerr) & (yerr > 0)
    n = int(good.sum())
    if n < 2:
        return LinearResult(n_points=n, message=f"needs at least 2 sizes with a value, has {n}")
    X = np.column_stack([np.ones(n), 1.0 / N[good]])
    p, cov, chi2, dof = weighted_linear_fit(X, y[good], yerr[good])
    scale = np.sqrt(max(1.0, chi2 / dof)) if dof > 0 else 1.0
    return LinearResult(p[0], np.sqrt(cov[0, 0]) * scale, p[1], np.sqrt(cov[1, 1]) * scale,
                        chi2 / dof if dof > 0 else np.nan, n,
                        "" if dof > 0 else "two sizes: exact line, no goodness of fit")


#: Below this p-value of its chi^2 the best model of the sizes (line or parabola in 1/N_G) is off:
#: the smallest size is left out and the models drawn again, down to three sizes (docs/REDUCED.md,
#: "Sizes off the 1/N_G line")
LINE_P = 0.05


@dataclass
class Line:
    """``y = y_inf + b / N (+ c / N^2)`` through the sizes' values, with what the rule of
    ``line_in_inverse_n`` did: the sizes it kept and left out, the weight of the parabola, and
    whether the sizes are still off (``limited``)."""

    value: float = np.nan
    err: float = np.nan
    slope: float = np.nan
    slope_err: float = np.nan
    chi2_dof: float = np.nan     # of the line through the sizes kept
    p: float = np.nan            # its chi^2 p-value
    n_points: int = 0
    sizes: tuple = ()
    left_out: tuple = ()
    limited: bool = False        # the best model through the sizes kept still fails its chi^2 test
    inflation: float = 1.0       # sqrt(chi^2/dof) applied to err when limited
    replicas: np.ndarray = field(default_factory=lambda: np.zeros(0))  # the value in each replica
    message: str = ""
    parabola_weight: float = 0.0  # the Akaike weight of the 1/N_G^2 term (0 with three sizes or fewer)


def _polys_in_inverse_n(N, Y, Winv, degrees):
    """Per row of ``Y`` (R, G) and per degree: the intercept, the 1/N coefficient and the Akaike
    criterion ``chi^2 + 2 k`` of the generalised least-squares polynomial in 1/N (weights ``Winv``)."""
    out = []
    for deg in degrees:
        X = np.column_stack([N ** -k for k in range(deg + 1)])
        M = np.linalg.pinv(X.T @ Winv @ X) @ X.T @ Winv
        C = Y @ M.T
        r = Y - C @ X.T
        out.append((C[:, 0], C[:, 1], np.einsum("bi,ij,bj->b", r, Winv, r), deg + 1))
    return out


def _averaged(fits_):
    """Line and parabola averaged with their Akaike weights: value, slope, parabola weight."""
    if len(fits_) == 1:
        (v, b, _, _), = fits_
        return v, b, np.zeros_like(v)
    (v1, b1, c1, k1), (v2, b2, c2, k2) = fits_
    w2 = 1.0 / (1.0 + np.exp(np.clip(((c2 + 2 * k2) - (c1 + 2 * k1)) / 2, -700, 700)))
    return (1 - w2) * v1 + w2 * v2, (1 - w2) * b1 + w2 * b2, w2


def line_in_inverse_n(sizes, values, replicas, p_min=LINE_P) -> Line:
    """The ``N_G -> inf`` value of per-size ``values`` (G,) from their bootstrap ``replicas`` (B, G)
    (drawn together: a shared exponent correlates the sizes' intercepts). Two models by generalised
    least squares with the replicas' covariance: the line ``y_inf + b / N`` and, with four sizes or
    more, the parabola ``y_inf + b / N + c / N^2``; the value is their average with Akaike weights
    (``exp(-(chi^2 + 2 k) / 2)``, k parameters), and every replica is averaged the same way with
    its own weights, so its error, the spread of the replicas, holds the choice between them. Where
    the sizes curve, the parabola takes the weight as seeds are added; where they lie on a line
    it costs little. The rule for sizes off both: while the better model's chi^2 has a p-value
    below ``p_min`` and more than three sizes remain, the smallest size is left out (a correction
    beyond 1/N_G is largest there); if the line through the last three still fails, the value is
    ``limited`` by its sizes and its error inflated by ``sqrt(chi^2/dof)``. Without replicas (no
    bootstrap) the line is unweighted and has no error."""
    N = np.asarray(sizes, float)
    y = np.asarray(values, float)
    R = np.asarray(replicas, float).reshape(-1, len(N)) if len(N) else np.zeros((0, 0))
    keep = np.isfinite(y)
    if len(R):
        keep &= np.isfinite(R).all(0)
        R = R[np.isfinite(R[:, keep]).all(1)] if keep.any() else R
    dropped = []
    while True:
        idx = np.flatnonzero(keep)
        G = len(idx)
        if G < 2:
            return Line(n_points=G, left_out=tuple(int(n) for n in dropped),
                        message=f"needs at least 2 sizes with a value, has {G}")
        boot = len(R) > 2
        Winv = np.linalg.pinv(np.atleast_2d(np.cov(R[:, idx].T))) if boot else np.eye(G)
        degrees = (1, 2) if (boot and G >= 4) else (1,)
        data = _polys_in_inverse_n(N[idx], y[idx][None, :], Winv, degrees)
        chi2s = [float(f[2][0]) for f in data]
        dofs = [G - f[3] for f in data]
        best = int(np.argmin([c + 2 * f[3] for c, f in zip(chi2s, data)]))
        p_best = chi2_p_value(chi2s[best], dofs[best]) if boot else np.nan
        if np.isfinite(p_best) and p_best < p_min and G > 3:
            dropped.append(N[idx[0]])
            keep[idx[0]] = False
            continue
        value, slope, w2 = (float(a[0]) for a in _averaged(data))
        chi2, dof = chi2s[0], dofs[0]
        p = chi2_p_value(chi2, dof) if (dof > 0 and boot) else np.nan
        limited = bool(np.isfinite(p_best) and p_best < p_min)
        inflation = float(np.sqrt(chi2s[best] / dofs[best])) if limited else 1.0
        if boot:
            reps, slopes, _ = _averaged(_polys_in_inverse_n(N[idx], R[:, idx], Winv, degrees))
        else:
            reps = slopes = np.zeros(0)
        return Line(value, spread(reps) * inflation if boot else np.nan, slope,
                    spread(slopes) * inflation if boot else np.nan, chi2 / dof if dof > 0 and boot else np.nan, p,
                    G, tuple(int(n) for n in N[idx]), tuple(int(n) for n in dropped), limited, inflation, reps,
                    "" if dof > 0 else "two sizes: exact line, no goodness of fit", w2)


def gaussian_mle(values):
    """Best Gaussian (maximum likelihood) of a sample: mean, sigma and their errors."""
    v = np.asarray(values, float)
    n = v.size
    if n < 2:
        return np.nan, np.nan, np.nan, np.nan
    mu = v.mean()
    sd = v.std(ddof=1)
    return mu, sd, sd / np.sqrt(n), sd / np.sqrt(2.0 * (n - 1))


def fit_width_scaling(N, sigma, sigma_err) -> LinearResult:
    """Fit ``sigma = s0 N**-gamma`` (linear in logs). ``value`` is gamma, ``slope`` log s0."""
    N = np.asarray(N, float)
    s = np.asarray(sigma, float)
    e = np.asarray(sigma_err, float)
    good = np.isfinite(s) & (s > 0) & np.isfinite(e) & (e > 0)
    n = int(good.sum())
    if n < 2:
        return LinearResult(n_points=n, message=f"needs at least 2 sizes, has {n}")
    X = np.column_stack([np.ones(n), -np.log(N[good])])
    p, cov, chi2, dof = weighted_linear_fit(X, np.log(s[good]), e[good] / s[good])
    scale = np.sqrt(max(1.0, chi2 / dof)) if dof > 0 else 1.0
    return LinearResult(p[1], np.sqrt(cov[1, 1]) * scale, p[0], np.sqrt(cov[0, 0]) * scale,
                        chi2 / dof if dof > 0 else np.nan, n)


# --------------------------------------------------------------------------- three disks
def _triangle_angle(d1, d2, d_opposite):
    return np.arccos((d1 * d1 + d2 * d2 - d_opposite**2) / (2.0 * d1 * d2))


def three_disk_peaks(radii):
    """Exact peaks of three disks in mutual contact at zero overlap.

    ``radii``: the distinct disk radii (any units). Returns ``(alpha_e, theta, alpha_v)``:
    sorted unique values of the edge-triangle area ``a/sigma_g^2 = sin(theta)/2`` (theta the
    angle at the central disk, law of cosines), the angles, and the void-triangle areas
    ``a_v / sigma_max^2`` (triangle of the three contact points).
    """
    r = np.unique(np.asarray(radii, float))
    alpha_e, theta = set(), set()
    for rg in r:
        for r1, r2 in itertools.combinations_with_replacement(r, 2):
            t = _triangle_angle(rg + r1, rg + r2, r1 + r2)
            theta.add(round(float(t), 12))
            alpha_e.add(round(float(np.sin(t) / 2.0), 12))
    alpha_v = set()
    for r1, r2, r3 in itertools.combinations_with_replacement(r, 3):
        # centres: disk 1 at origin, disk 2 on the x axis, disk 3 above
        c1 = np.array([0.0, 0.0])
        c2 = np.array([r1 + r2, 0.0])
        t = _triangle_angle(r1 + r2, r1 + r3, r2 + r3)
        c3 = (r1 + r3) * np.array([np.cos(t), np.sin(t)])
        pts = [ci + ri / (ri + rj) * (cj - ci)
               for (ci, ri), (cj, rj) in (((c1, r1), (c2, r2)), ((c2, r2), (c3, r3)),
                                          ((c3, r3), (c1, r1)))]
        (ax, ay), (bx, by), (cx, cy) = pts
        area = 0.5 * abs((bx - ax) * (cy - ay) - (cx - ax) * (by - ay))
        alpha_v.add(round(float(area / r.max() ** 2), 12))
    return (np.array(sorted(alpha_e, reverse=True)), np.array(sorted(theta, reverse=True)),
            np.array(sorted(alpha_v, reverse=True)))


# --------------------------------------------------------------------------- sin(theta)
def sin_theta_density(theta_counts, theta_edges, s_edges):
    """Transform a histogram of theta in (0, pi) into the density of s = sin(theta).

    Counts are taken uniform inside each theta bin; both branches theta and
    pi - theta contribute to one s. Mass outside (0, pi) is ignored. Returns the
    density on ``s_edges`` (integrates to the fraction of mass inside (0, pi)).
    """
    theta_counts = np.asarray(theta_counts, float)
    te = np.asarray(theta_edges, float)
    total = theta_counts.sum(axis=-1, keepdims=True)
    cdf = np.concatenate([np.zeros(theta_counts.shape[:-1] + (1,)),
                          np.cumsum(theta_counts, axis=-1)], axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cdf = cdf / total

    def F(t):
        t = np.clip(t, te[0], te[-1])
        return np.stack([np.interp(t, te, row) for row in cdf.reshape(-1, cdf.shape[-1])]
                        ).reshape(cdf.shape[:-1] + t.shape)

    s = np.asarray(s_edges, float)
    t1 = np.arcsin(np.clip(s, 0.0, 1.0))
    low = F(t1)                      # branch theta in (0, pi/2)
    high = F(np.pi - t1)             # branch theta in (pi/2, pi), decreasing in s
    mass = np.diff(low, axis=-1) - np.diff(high, axis=-1)
    # masses are fractions of the total: differences of the CDF below 1e-12 are round-off
    mass = np.where(np.abs(mass) < 1e-12, 0.0, mass)
    return mass / np.diff(s)
