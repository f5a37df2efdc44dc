"""Fitting maths of the reducer: pure numpy, no I/O.

* ``fit_power_law``: ``y = a + c x**beta`` by weighted least squares. For a fixed
  exponent the model is linear in ``(a, c)``, so the exponent is found by
  profiling chi^2 over beta (a grid, then a golden-section refinement) and the
  intercept and prefactor follow in closed form. The same code fits many data
  sets at once (``fit_power_law_batch``), which is what makes the bootstrap cheap.
* ``bootstrap_cell_means``: resampling of packings within each cell, with a fixed
  seed, returning the resampled cell means of several quantities at once.
* ``chi2_p_value``: the goodness of a fit as a p-value.
* ``fit_inverse_n``: ``y = y_inf + b / N`` (finite-size extrapolation).
* ``gaussian_mle`` and ``fit_width_scaling``: the best Gaussian of P(A_G) and the
  law ``sigma ~ N**-gamma``.
* ``three_disk_peaks``: exact edge-triangle and void-area values of three disks in
  mutual contact, from the radii by the law of cosines.
"""

from __future__ import annotations

import itertools
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


def fit_power_law_batch(x, y, yerr, bounds=BETA_BOUNDS):
    """Fit ``y = a + c x**beta`` to each row of ``x``, ``y`` (shape (B, K)).

    ``yerr`` (K,) or (B, K) are the standard errors used as weights 1/yerr^2.
    Returns arrays ``a, c, beta, chi2`` of shape (B,). ``x`` must be >= 0.
    """
    x = np.atleast_2d(np.asarray(x, float))
    y = np.atleast_2d(np.asarray(y, float))
    w = 1.0 / np.asarray(yerr, float) ** 2
    # Work with x / x_ref (geometric mean of the positive x of each row) for conditioning.
    # x = 0 is allowed (e.g. isostatic packings, Delta Z = 0): there x^beta = 0 for beta > 0.
    pos = x > 0
    with np.errstate(divide="ignore"):
        lx = np.where(pos, np.log(np.where(pos, x, 1.0)), -np.inf)
    lref = (np.where(pos, lx, 0.0).sum(axis=-1) / np.maximum(pos.sum(axis=-1), 1))[:, None]
    lu = lx - lref

    def profile(beta):  # beta (B,) or (G, B)
        f = np.exp(beta[..., None] * lu)
        return _solve_linear(f, y, w)

    lo, hi = bounds
    grid = np.linspace(lo, hi, _GRID)
    chi_grid = profile(np.broadcast_to(grid[:, None], (_GRID, x.shape[0])).copy())[2]  # (G, B)
    chi_grid = np.where(np.isfinite(chi_grid), chi_grid, np.inf)
    k = np.argmin(chi_grid, axis=0)
    left = grid[np.clip(k - 1, 0, _GRID - 1)]
    right = grid[np.clip(k + 1, 0, _GRID - 1)]
    # Vectorised golden-section search inside the bracket around the grid minimum.
    g = (np.sqrt(5.0) - 1.0) / 2.0
    p = right - g * (right - left)
    q = left + g * (right - left)
    fp = profile(p)[2]
    fq = profile(q)[2]
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
        f_new = profile(np.where(move, q_next, p_next))[2]
        fp = np.where(move, f_keep, f_new)
        fq = np.where(move, f_new, f_keep)
        p, q = p_next, q_next
    beta = 0.5 * (left + right)
    a, c_scaled, chi2 = profile(beta)
    c = c_scaled * np.exp(-beta * lref[:, 0])
    return a, c, beta, chi2


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

    @property
    def chi2_dof(self):
        return self.chi2 / self.dof if self.dof > 0 else np.nan


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
    at_bound = bool(min(beta - bounds[0], bounds[1] - beta) < 1e-3 * (bounds[1] - bounds[0]))
    out = PowerLawFit(a, c, beta, chi2=chi2, dof=K - 3, n_points=K, ok=bool(np.isfinite(chi2)),
                      residuals=res, at_bound=at_bound,
                      message="exponent at the search bound" if at_bound else "")
    if boot_x is not None and boot_y is not None and len(boot_x) > 1:
        ba, bc, bb, _ = fit_power_law_batch(boot_x, boot_y, yerr, bounds)
        out.intercept_err = float(np.std(ba, ddof=1))
        out.coeff_err = float(np.std(bc, ddof=1))
        out.exponent_err = float(np.std(bb, ddof=1))
        out.n_boot = len(boot_x)
    return out


# --------------------------------------------------------------------------- goodness of fit
#: A power law with an intercept needs its three parameters and one degree of freedom.
MIN_CELLS = 4


def chi2_p_value(chi2, dof):
    """P(chi^2_dof >= chi2): the probability of a worse fit if the model and the errors hold."""
    from scipy.stats import chi2 as _chi2

    return float(_chi2.sf(chi2, dof)) if dof > 0 and np.isfinite(chi2) else np.nan


# --------------------------------------------------------------------------- bootstrap
def bootstrap_cell_means(groups, n_boot, seed=0, chunk=256):
    """Resample packings within each cell and return the replicas' cell means.

    ``groups``: list of K arrays of shape (n_k, q) (n_k packings, q quantities).
    Returns an array (n_boot, K, q). Deterministic for a given ``seed``.
    """
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed)))
    K = len(groups)
    q = groups[0].shape[1] if K else 0
    out = np.empty((n_boot, K, q))
    for k, g in enumerate(groups):
        g = np.asarray(g, float)
        n = g.shape[0]
        step = max(1, min(n_boot, (4_000_000 // max(n, 1))))
        for s in range(0, n_boot, step):
            b = min(step, n_boot - s)
            idx = rng.integers(0, n, size=(b, n))
            # how often each packing is drawn in each replica, then one matrix product
            flat = (idx + n * np.arange(b)[:, None]).ravel()
            counts = np.bincount(flat, minlength=b * n).reshape(b, n)
            out[s:s + b, k] = (counts @ g) / n
    return out


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
