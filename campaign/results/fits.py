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


def _minimise_profile(chi2_of, n, bounds):
    """The exponent minimising ``chi2_of(beta)`` (beta: (n,) or (G, n) -> same shape) for n
    problems at once: a 121-point grid over ``bounds``, then golden section in the bracket
    around the grid minimum."""
    lo, hi = bounds
    grid = np.linspace(lo, hi, _GRID)
    chi_grid = chi2_of(np.broadcast_to(grid[:, None], (_GRID, n)).copy())  # (G, n)
    chi_grid = np.where(np.isfinite(chi_grid), chi_grid, np.inf)
    k = np.argmin(chi_grid, axis=0)
    left = grid[np.clip(k - 1, 0, _GRID - 1)]
    right = grid[np.clip(k + 1, 0, _GRID - 1)]
    g = (np.sqrt(5.0) - 1.0) / 2.0
    p = right - g * (right - left)
    q = left + g * (right - left)
    fp = chi2_of(p)
    fq = chi2_of(q)
    for _ in range(_GOLDEN_ITERS):
        move = fp > fq  # minimum in [p, right]
        left = np.where(move, p, left)
        right = np.where(move, right, q)
        newp = right - g * (right - left)
        newq = left + g * (right - left)
        # reuse one evaluation per side
        p_next = np.where(move, q, newp)
        q_next = np.where(move, newq, p)
        f_keep = np.where(move, fq, fp)
        f_new = chi2_of(np.where(move, q_next, p_next))
        fp = np.where(move, f_keep, f_new)
        fq = np.where(move, f_new, f_keep)
        p, q = p_next, q_next
    return 0.5 * (left + right)


def fit_power_law_batch(x, y, yerr, bounds=BETA_BOUNDS):
    """Fit ``y = a + c x**beta`` to each row of ``x``, ``y`` (shape (B, K)).

    ``yerr`` (K,) or (B, K) are the standard errors used as weights 1/yerr^2.
    Returns arrays ``a, c, beta, chi2`` of shape (B,). ``x`` must be >= 0.
    """
    x = np.atleast_2d(np.asarray(x, float))
    y = np.atleast_2d(np.asarray(y, float))
    w = 1.0 / np.asarray(yerr, float) ** 2
    lu, lref = _log_abscissa(x)

    def profile(beta):  # beta (B,) or (G, B)
        return _solve_linear(np.exp(beta[..., None] * lu), y, w)

    beta = _minimise_profile(lambda b: profile(b)[2], x.shape[0], bounds)
    a, c_scaled, chi2 = profile(beta)
    return a, c_scaled * np.exp(-beta * lref), beta, chi2


def fit_shared_exponent_batch(x, y, yerr, bounds=BETA_BOUNDS):
    """``y_gk = a_g + c_g x_gk**beta``: one exponent shared by the G groups of each of B data
    sets, an intercept and an amplitude per group (the finite-size table's sizes: the exponent
    belongs to the transition, the intercept and amplitude to the size).

    ``x``, ``y``: (B, G, K) or (G, K), groups padded to K cells with ``yerr = inf`` (weight 0);
    ``yerr`` (G, K) or (B, G, K). Returns ``a, c`` (B, G), ``beta, chi2`` (B,).
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    squeeze = x.ndim == 2
    if squeeze:
        x, y = x[None], y[None]
    w = 1.0 / np.asarray(yerr, float) ** 2
    x = np.where(w > 0, x, 1.0)  # padding: any positive abscissa, weight 0
    lu, lref = _log_abscissa(x)   # (B, G, K), (B, G)

    def profile(beta):  # beta (B,) or (Q, B)
        return _solve_linear(np.exp(beta[..., None, None] * lu), y, w)

    beta = _minimise_profile(lambda b: profile(b)[2].sum(axis=-1), x.shape[0], bounds)
    a, c_scaled, chi2 = profile(beta)
    c = c_scaled * np.exp(-beta[:, None] * lref)
    out = a, c, beta, chi2.sum(axis=-1)
    return tuple(v[0] for v in out) if squeeze else out


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


def fit_power_law(x, y, yerr, *, boot_x=None, boot_y=None, bounds=BETA_BOUNDS) -> PowerLawFit:
    """Fit one data set; errors are the std over the bootstrap replicas (B, K), if given."""
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
        ba, bc, bb, _ = fit_power_law_batch(boot_x, boot_y, yerr, bounds)
        out.intercept_err = float(np.std(ba, ddof=1))
        out.coeff_err = float(np.std(bc, ddof=1))
        out.exponent_err = float(np.std(bb, ddof=1))
        out.boot_at_bound = float(np.mean(_at_bound(bb, bounds)))
        out.n_boot = len(boot_x)
    return out


@dataclass
class SharedFit:
    """``y_gk = a_g + c_g x_gk**beta`` over G groups (sizes) with one exponent, bootstrap errors."""

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


def fit_shared_exponent(xs, ys, yerrs, *, boot_xs=None, boot_ys=None, bounds=BETA_BOUNDS) -> SharedFit:
    """One exponent for several groups of cells (lists of 1-d arrays, one per group), each group
    with its own intercept and amplitude; a group needs 3 cells (3 positive abscissae) to inform
    the exponent and is refused below. ``boot_xs``, ``boot_ys``: per group (B, K_g) replicas of
    its cell means (the bootstrap of packings within cells); the errors are their refits' std."""
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
        ba, _, bb, _ = fit_shared_exponent_batch(BX, BY, W, bounds)
        out.exponent_err = float(np.std(bb, ddof=1))
        out.intercept_errs = np.std(ba, axis=0, ddof=1)
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
