"""The reducer's maths: power-law fits, bootstrap errors (and where the two seed bootstraps differ),
1/N extrapolation, exact peaks."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import curve_fit

from campaign.results import bootstrap, fits

E_GRID = np.logspace(-15, -3, 13)
Z_GRID = np.logspace(-3, 0, 10)


@pytest.mark.parametrize("x, a, c, beta", [
    (E_GRID, 0.446, 0.5, 0.28),     # A_G against E_G (the paper's law)
    (Z_GRID, 0.4453, 0.15, 1.0),    # A_G against Delta Z
    (E_GRID, 0.369, 0.9, 0.27),     # Psi_O against E_G
    (np.logspace(-4, 0, 9), -1.0, 2.0, 2.5),
])
def test_exact_power_law_is_recovered(x, a, c, beta):
    y = a + c * x**beta
    err = np.full(x.size, 1e-4)
    f = fits.fit_power_law(x, y, err)
    assert f.ok and f.dof == x.size - 3
    assert f.exponent == pytest.approx(beta, rel=1e-7)
    assert f.intercept == pytest.approx(a, abs=1e-9 * abs(c))
    assert f.coeff == pytest.approx(c, rel=1e-6)
    assert f.chi2 < 1e-8


def test_noisy_fit_agrees_with_scipy_curve_fit():
    rng = np.random.default_rng(3)
    x = E_GRID
    err = 2e-4 * (1 + rng.random(x.size))
    y = 0.446 + 0.5 * x**0.28 + rng.normal(0, 1, x.size) * err
    f = fits.fit_power_law(x, y, err)

    def model(x, a, lc, b):  # log of the prefactor keeps curve_fit well conditioned
        return a + np.exp(lc) * x**b

    p, cov = curve_fit(model, x, y, p0=(0.44, np.log(0.4), 0.3), sigma=err, absolute_sigma=True,
                       maxfev=20000)
    perr = np.sqrt(np.diag(cov))
    assert f.intercept == pytest.approx(p[0], abs=1e-3 * perr[0])
    assert f.exponent == pytest.approx(p[2], abs=1e-3 * perr[2])
    chi2_ref = np.sum(((y - model(x, *p)) / err) ** 2)
    assert f.chi2 == pytest.approx(chi2_ref, rel=1e-6)


def _cells(rng, x_true, a, c, beta, n, noise):
    """Per-packing samples: y = a + c x^beta + noise, x jittered like a measured E_G."""
    groups = []
    for xt in x_true:
        xs = xt * (1 + 0.1 * rng.random(n))
        ys = a + c * xs**beta + rng.normal(0, noise, n)
        groups.append(np.column_stack([xs, ys]))
    return groups


def _fit_cells(groups, n_boot, seed):
    x = np.array([g[:, 0].mean() for g in groups])
    y = np.array([g[:, 1].mean() for g in groups])
    ye = np.array([g[:, 1].std(ddof=1) / np.sqrt(len(g)) for g in groups])
    boot = bootstrap.cell_means(groups, n_boot, seed=seed)
    return fits.fit_power_law(x, y, ye, boot_x=boot[..., 0], boot_y=boot[..., 1])


def test_noisy_cells_recover_truth_within_bootstrap_errors():
    rng = np.random.default_rng(11)
    f = _fit_cells(_cells(rng, E_GRID, 0.446, 0.5, 0.28, 40, 0.003), 400, seed=1)
    assert abs(f.intercept - 0.446) < 4 * f.intercept_err
    assert abs(f.exponent - 0.28) < 4 * f.exponent_err
    assert 0 < f.intercept_err < 1e-3 and 0 < f.exponent_err < 0.05
    assert 0.2 < f.chi2_dof < 3.0


def test_bootstrap_errors_cover_truth_at_the_stated_rate():
    """About 68% of the experiments have |estimate - truth| < one bootstrap error."""
    rng = np.random.default_rng(2024)
    M = 160
    hit_a = hit_b = 0
    for m in range(M):
        groups = _cells(rng, E_GRID[::2], 0.446, 0.5, 0.28, 25, 0.004)
        f = _fit_cells(groups, 150, seed=m)
        hit_a += abs(f.intercept - 0.446) < f.intercept_err
        hit_b += abs(f.exponent - 0.28) < f.exponent_err
    band = 3 * np.sqrt(0.683 * 0.317 / M)  # binomial 3 sigma
    for hits in (hit_a, hit_b):
        assert abs(hits / M - 0.683) < band + 0.04, hits / M


def test_bootstrap_cell_means_is_deterministic_and_matches_the_standard_error():
    rng = np.random.default_rng(5)
    groups = [rng.normal(0, 1, (50, 2)), rng.normal(3, 2, (200, 2))]
    b1 = bootstrap.cell_means(groups, 2000, seed=7)
    b2 = bootstrap.cell_means(groups, 2000, seed=7)
    assert b1.shape == (2000, 2, 2)
    np.testing.assert_array_equal(b1, b2)
    for k, g in enumerate(groups):
        sem = g.std(ddof=0, axis=0) / np.sqrt(len(g))
        np.testing.assert_allclose(b1[:, k].std(axis=0), sem, rtol=0.08)
        assert np.all(np.abs(b1[:, k].mean(axis=0) - g.mean(axis=0)) < 4 * sem / np.sqrt(2000))
    assert not np.array_equal(b1, bootstrap.cell_means(groups, 2000, seed=8))


@settings(max_examples=25, deadline=None)
@given(shift=st.floats(-10, 10), scale=st.floats(1e-6, 1e6), beta=st.floats(0.1, 2.0))
def test_fit_is_covariant_under_shift_of_y_and_scale_of_x(shift, scale, beta):
    """y -> y + s moves only the intercept; x -> k x divides c by k^beta."""
    x = np.logspace(-6, 0, 8)
    y = 1.0 + 0.3 * x**beta + 1e-4 * np.sin(7 * np.arange(8))
    err = np.full(8, 1e-4)
    f0 = fits.fit_power_law(x, y, err)
    f1 = fits.fit_power_law(x * scale, y + shift, err)
    assert f1.exponent == pytest.approx(f0.exponent, abs=1e-6)
    assert f1.intercept - shift == pytest.approx(f0.intercept, abs=1e-6)
    assert f1.coeff * scale**f1.exponent == pytest.approx(f0.coeff, rel=1e-4)


def test_fit_refuses_too_few_points():
    f = fits.fit_power_law([1e-3, 1e-5, 1e-7], [1, 2, 3], [0.1] * 3)
    assert not f.ok and "at least 4" in f.message


def test_inverse_n_extrapolation_recovers_a_known_law():
    N = np.array([64, 128, 256, 512, 1024], float)
    exact = fits.fit_inverse_n(N, 0.446 - 0.6 / N, np.full(5, 1e-4))
    assert exact.value == pytest.approx(0.446, abs=1e-12)
    assert exact.slope == pytest.approx(-0.6, rel=1e-9)
    # analytic error of a weighted straight line: sqrt(Sxx / (S Sxx - Sx^2)) * sigma
    u = 1 / N
    S, Sx, Sxx = len(u), u.sum(), (u * u).sum()
    assert exact.err == pytest.approx(1e-4 * np.sqrt(Sxx / (S * Sxx - Sx**2)), rel=1e-9)
    rng = np.random.default_rng(9)
    pulls = []
    for _ in range(400):
        err = 2e-4 * (1 + rng.random(5))
        r = fits.fit_inverse_n(N, 0.446 - 0.6 / N + rng.normal(0, 1, 5) * err, err)
        pulls.append((r.value - 0.446) / r.err)
    pulls = np.array(pulls)
    assert abs(pulls.mean()) < 0.2
    # the error is inflated by sqrt(chi2/dof) when that exceeds 1, so coverage >= 68%
    assert 0.68 <= np.mean(np.abs(pulls) < 1) <= 0.85


def test_width_scaling_recovers_inverse_square_root():
    N = np.array([64, 128, 256, 512, 1024], float)
    r = fits.fit_width_scaling(N, 0.03 / np.sqrt(N), 1e-3 * 0.03 / np.sqrt(N))
    assert r.value == pytest.approx(0.5, abs=1e-9)
    assert np.exp(r.slope) == pytest.approx(0.03, rel=1e-9)


def test_gaussian_mle_of_a_large_normal_sample():
    v = np.random.default_rng(0).normal(0.44, 0.002, 20000)
    mu, sd, mu_err, sd_err = fits.gaussian_mle(v)
    assert abs(mu - 0.44) < 4 * mu_err and abs(sd - 0.002) < 4 * sd_err


def test_three_disk_peaks_match_the_paper():
    alpha_e, theta, alpha_v = fits.three_disk_peaks([1.4, 1.0])
    np.testing.assert_allclose(alpha_e, [0.473803, 0.454530, 0.433013, 0.406116, 0.378775],
                               atol=1e-6)
    np.testing.assert_allclose(theta, [1.245653, 1.141021, 1.047198, 0.947970, 0.859551],
                               atol=1e-6)
    np.testing.assert_allclose(alpha_v, [0.433013, 0.338430, 0.270553, 0.220925], atol=1e-6)
    # equal disks: one angle (pi/3), one edge triangle (sqrt(3)/4), one void
    a, t, v = fits.three_disk_peaks([0.7])
    np.testing.assert_allclose(t, [np.pi / 3])
    np.testing.assert_allclose(a, [np.sqrt(3) / 4])
    np.testing.assert_allclose(v, [np.sqrt(3) / 4])
    # scale invariance: the peaks depend on the radius ratio only
    for x, y in zip(fits.three_disk_peaks([1.4, 1.0]), fits.three_disk_peaks([0.014, 0.01])):
        np.testing.assert_allclose(x, y, rtol=1e-12)


def test_sin_theta_of_uniform_angles_is_the_random_curve():
    te = np.linspace(0, np.pi, 3601)
    counts = np.full(te.size - 1, 1000)
    se = np.linspace(0, 0.99, 100)
    d = fits.sin_theta_density(counts, te, se)
    # exact bin averages of (2/pi)/sqrt(1-s^2): (2/pi) (asin s1 - asin s0) / (s1 - s0)
    exact = (2 / np.pi) * np.diff(np.arcsin(se)) / np.diff(se)
    np.testing.assert_allclose(d, exact, rtol=1e-3)


def test_sin_theta_maps_both_branches_to_one_value():
    te = np.linspace(0, np.pi, 181)
    c1 = np.zeros(180)
    c1[40] = 7  # theta ~ 0.70 rad
    c2 = c1[::-1].copy()  # pi - theta: same sine
    se = np.linspace(0, 1, 51)
    d1 = fits.sin_theta_density(c1, te, se)
    d2 = fits.sin_theta_density(c2, te, se)
    np.testing.assert_allclose(d1, d2, atol=1e-12)
    assert np.sum(d1 * np.diff(se)) == pytest.approx(1.0)
    centre = np.sin(0.5 * (te[40] + te[41]))
    mass_bins = np.flatnonzero(d1 > 0)
    assert se[mass_bins[0]] <= centre <= se[mass_bins[-1] + 1]


def test_zero_abscissa_is_a_point_at_the_intercept():
    """Isostatic cells have Delta Z = 0 exactly; they pin the intercept (x^beta = 0)."""
    x = np.r_[0.0, np.logspace(-3, 0, 8)]
    y = 0.4453 + 0.15 * x**1.0
    f = fits.fit_power_law(x, y, np.full(x.size, 1e-4))
    assert f.exponent == pytest.approx(1.0, rel=1e-7)
    assert f.intercept == pytest.approx(0.4453, abs=1e-10)
    with pytest.raises(ValueError, match=">= 0"):
        fits.fit_power_law(-x[::-1], y, np.full(x.size, 1e-4))


def _ladder(rng, seeds, missing):
    """Two cells of one size, every seed in the first, the second without the seeds ``missing``."""
    a = rng.normal(0, 1, (seeds, 1))
    keep = np.setdiff1d(np.arange(seeds), missing)
    return [a, a[keep] + 1.0], [np.arange(seeds), keep]


def test_the_seed_bootstraps_differ_only_where_a_replica_misses_a_cells_seeds():
    rng = np.random.default_rng(5)
    for missing in ((), (0, 1, 2, 3, 4, 5, 6)):
        groups, seeds = _ladder(rng, 8, list(missing))
        means = bootstrap.seed_means(groups, seeds, 400, seed=3)
        counts = np.zeros((8, 2))
        sums = np.zeros((8, 2))
        for c, (g, sd) in enumerate(zip(groups, seeds)):
            np.add.at(counts[:, c], sd, 1.0)
            np.add.at(sums[:, c], sd, g[:, 0])
        nb, mb = bootstrap.seed_cell_means(counts, sums, 400, bootstrap.generator(3))
        # the same seeds drawn in the same order: the replicas that hold every cell agree
        full = bootstrap.seed_weights(bootstrap.generator(3), 8, 400) @ counts
        held = np.all(full > 0, axis=1)
        np.testing.assert_allclose(means[held, :, 0], mb, rtol=1e-12)
        if not missing:
            assert held.all()
        else:  # a replica without seed 7 keeps the cell at its mean in one, and is dropped in the other
            assert not held.all() and len(mb) == held.sum() < 400
            np.testing.assert_array_equal(means[~held, 1, 0], groups[1].mean())
