"""The reducer's maths: power-law fits, bootstrap errors (and where the two seed bootstraps differ),
1/N extrapolation, exact peaks."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import curve_fit

from helpers import fit_cells as _fit_cells

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


def test_cell_moments_are_deterministic_and_scatter_as_a_cell_mean_does():
    """A replica's mean, scaled by sqrt(n / (n - 1)), scatters by the standard error of the mean
    (the sample's, n - 1 in the denominator), not the (n - 1) / n of it a plain resample gives;
    its covariance is the sample covariance of the packings drawn."""
    rng = np.random.default_rng(5)
    for n in (4, 50, 200):
        g = rng.normal([0, 3], [1, 2], (n, 2))
        w = bootstrap.seed_weights(bootstrap.generator(7), n, 4000)
        m1, c1 = bootstrap.cell_moments(g, w)
        m2, c2 = bootstrap.cell_moments(g, w)
        assert m1.shape == (4001, 2) and c1.shape == (4001, 2, 2)
        np.testing.assert_array_equal(m1, m2)
        np.testing.assert_array_equal(c1, c2)
        np.testing.assert_array_equal(m1[0], g.mean(0))
        np.testing.assert_allclose(c1[0], np.cov(g.T), rtol=1e-12)
        sem = g.std(ddof=1, axis=0) / np.sqrt(n)
        np.testing.assert_allclose(m1[1:].std(axis=0), sem, rtol=0.06)
        k = 17  # one replica, computed by hand
        drawn = np.repeat(g, w[k].astype(int), axis=0)
        np.testing.assert_allclose(m1[k + 1], g.mean(0) + np.sqrt(n / (n - 1)) * (drawn.mean(0) - g.mean(0)))
        np.testing.assert_allclose(c1[k + 1], np.cov(drawn.T), rtol=1e-9, atol=1e-12)


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


SIZES5 = np.array([64, 128, 256, 512, 1024], float)


def _sizes_draw(rng, truth, sd, boot=400):
    """One campaign's per-size values about ``truth`` (G,) with errors ``sd`` (G,), and bootstrap
    replicas about those values drawn with the same errors (what a bootstrap of the packings gives)."""
    y = truth + sd * rng.normal(size=len(sd))
    return y, y + sd * rng.normal(size=(boot, len(sd)))


def test_the_n_inf_value_of_exact_sizes_on_a_line_or_a_parabola_is_exact():
    """Without noise the average of line and parabola is the truth whichever carries the weight:
    the line through sizes on a line, the parabola (weight 1) through sizes that curve."""
    rng = np.random.default_rng(3)
    sd = 1e-4 * np.sqrt(64 / SIZES5)
    noise = sd * rng.normal(size=(400, 5))
    line = 0.446 - 0.6 / SIZES5
    r = fits.line_in_inverse_n(SIZES5, line, line + noise)
    assert r.value == pytest.approx(0.446, abs=1e-12) and r.slope == pytest.approx(-0.6, rel=1e-9)
    assert r.parabola_weight < 0.5 and not r.left_out and not r.limited
    curved = line - 40.0 / SIZES5**2
    r = fits.line_in_inverse_n(SIZES5, curved, curved + noise)
    assert r.parabola_weight > 0.999 and r.value == pytest.approx(0.446, abs=1e-9)
    assert r.chi2_dof > 10 and not r.left_out   # the line is off; the parabola holds them


@pytest.mark.parametrize("a_2", [0.0, -40.0])
def test_the_n_inf_error_covers_the_truth_with_and_without_a_correction_beyond_1_over_n(a_2):
    """Over many campaigns (sizes 64..1024, errors falling like 1/sqrt(N)): with intercepts on a line,
    and with a 1/N^2 term (1e-2 at N 64, 6e-4 at 256, a few errors at the small sizes), the
    2-sigma intervals hold the truth about 95% of the time and the values are unbiased. The line
    alone (the parabola's weight held at 0) misses the curved truth."""
    rng = np.random.default_rng(11 if a_2 else 12)
    sd = 4e-4 * np.sqrt(64 / SIZES5)
    truth = 0.446 - 0.6 / SIZES5 + a_2 / SIZES5**2
    z, z_line = [], []
    for _ in range(300):
        y, R = _sizes_draw(rng, truth, sd)
        r = fits.line_in_inverse_n(SIZES5, y, R)
        z.append((r.value - 0.446) / r.err)
        X = np.column_stack([np.ones(5), 1 / SIZES5])
        W = np.linalg.inv(np.cov(R.T))
        M = np.linalg.solve(X.T @ W @ X, X.T @ W)
        z_line.append(((M @ y)[0] - 0.446) / fits.spread(R @ M[0]))
    z, z_line = np.array(z), np.array(z_line)
    assert 0.92 <= np.mean(np.abs(z) <= 2) <= 0.99, np.mean(np.abs(z) <= 2)
    assert abs(np.median(z)) < 0.2
    if a_2:
        assert np.mean(np.abs(z_line) <= 2) < 0.8   # the mutation: no parabola


def test_sizes_off_every_model_leave_out_the_smallest_then_limit_the_value():
    """A smallest size far off both models is left out and named; three sizes that still do not lie
    on a line make the value limited, its error inflated by sqrt(chi^2/dof)."""
    rng = np.random.default_rng(5)
    sd = 1e-4 * np.ones(5)
    noise = sd * rng.normal(size=(400, 5))
    y = 0.446 - 0.6 / SIZES5
    y[0] += 0.01                                # N 64 off everything
    y[1] += 0.003 * (-1)                        # N 128 off too, the other way
    r = fits.line_in_inverse_n(SIZES5, y, y + noise)
    assert r.left_out == (64,) or r.left_out == (64, 128)
    assert 64 not in r.sizes
    zig = 0.446 - 0.6 / SIZES5[2:] + np.array([0.0, 0.002, 0.0])
    r3 = fits.line_in_inverse_n(SIZES5[2:], zig, zig + noise[:, :3])
    assert r3.limited and r3.inflation > 3 and r3.parabola_weight == 0
    plain = fits.spread(r3.replicas)
    assert r3.err == pytest.approx(plain * r3.inflation)


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


def _grid(cells, seeds):
    """A ``Grid`` of ``cells`` ((variant, N, E) each) whose packings are the seeds ``seeds[i]``."""
    from campaign.results.cells import Grid

    seed_of = np.concatenate([np.asarray(s) for s in seeds])
    bounds = np.concatenate([[0], np.cumsum([len(s) for s in seeds])])
    C = len(cells)
    z = np.zeros(C, np.int64)
    g = Grid(cv=np.array([c[0] for c in cells]), cN=np.array([c[1] for c in cells]),
             cE=np.array([c[2] for c in cells], float), cell=np.repeat(np.arange(C), np.diff(bounds)),
             n_done=np.diff(bounds), n_excluded=z, n_failed=z, n_pending=z, order=np.arange(len(seed_of)),
             bounds=bounds)
    return g, seed_of


def test_replica_weights_draw_seeds_jointly_across_variants_and_whole_seeds_along_a_ladder():
    """The variants of one cell draw the same seeds (a paired bootstrap); a ladder's variant draws a
    seed at every energy of its size together; a variant missing some seeds takes those it holds;
    the same key, the same draws."""
    cells = [("a", 64, 1e-3), ("b", 64, 1e-3), ("a", 64, 1e-5), ("b", 64, 1e-5), ("a", 128, 1e-3),
             ("l", 64, 1e-3), ("l", 64, 1e-5)]
    seeds = [np.arange(8), np.arange(8), np.arange(8), np.arange(2, 8), np.arange(8), np.arange(6), np.arange(6)]
    g, seed_of = _grid(cells, seeds)
    w = bootstrap.replica_weights(g, seed_of, range(len(cells)), {"l"}, 300, boot_seed=11)
    assert [w[i].shape for i in range(len(cells))] == [(300, len(s)) for s in seeds]
    np.testing.assert_array_equal(w[0], w[1])         # variants of one cell: the same seeds
    np.testing.assert_array_equal(w[3], w[2][:, 2:])  # the variant without seeds 0 and 1 takes the rest
    np.testing.assert_array_equal(w[5], w[6])         # a ladder: a seed at every energy
    assert not np.array_equal(w[0], w[2]) and not np.array_equal(w[0], w[4])  # cells draw apart
    assert np.all(w[0].sum(1) == 8)                   # a resample of the 8 seeds
    again = bootstrap.replica_weights(g, seed_of, range(len(cells)), {"l"}, 300, boot_seed=11)
    assert all(np.array_equal(w[i], again[i]) for i in w)
    other = bootstrap.replica_weights(g, seed_of, range(len(cells)), {"l"}, 300, boot_seed=12)
    assert not np.array_equal(w[0], other[0])
