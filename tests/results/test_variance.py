"""The model of the spread between packings that weights the scaling fits (campaign.results.variance):
maximum likelihood recovered on chi^2 variances of known truth, its invariances, and Bartlett's
test holding its level under the null."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from campaign.results import variance


def _cells(rng, G=4, K=10, n_of=lambda rng, K: np.full(K, 6), lam=None, gamma=0.0, reps=1):
    """Sample variances of normal packings: per size g and cell k, sigma^2 = exp(lam_g + gamma u_k)."""
    lam = np.linspace(-9, -7, G) if lam is None else np.asarray(lam, float)
    u = np.tile(np.arange(K) - (K - 1) / 2, G).astype(float)
    size = np.repeat(np.arange(G), K)
    n = np.concatenate([n_of(rng, K) for _ in range(G)]).astype(float)
    truth = np.exp(lam[size] + gamma * u)
    v = truth * rng.chisquare(n - 1, size=(reps, len(n))) / (n - 1)
    return v, n, size, u, truth


def test_the_model_recovers_a_spread_that_changes_with_energy_and_size():
    """Cells of 3 to 24 packings, a spread growing 1.5-fold across the energies: the model's variances
    are within a few percent of the truth (each cell's own is off by tens of percent), and the
    fitted trend is the truth's."""
    rng = np.random.default_rng(1)
    gamma = np.log(1.5) / 9
    v, n, size, u, truth = _cells(rng, K=10, n_of=lambda r, K: r.integers(3, 25, K), gamma=gamma, reps=200)
    model = variance.pooled_model(v, n, size, u, 4)
    own = np.median(np.abs(v / truth - 1))
    fitted = np.median(np.abs(model / truth - 1))
    assert fitted < 0.1 and fitted < own / 3
    assert np.abs(np.median(model / truth, axis=0) - 1).max() < 0.05  # no bias worth the name
    t = [variance.trend(v[r:r + 1], n, size, u, 4) for r in range(50)]
    assert np.median(t) == pytest.approx(gamma / np.log(10), rel=0.25)


def test_equal_variances_are_returned_as_they_are():
    n = np.full(12, 5.0)
    size = np.repeat([0, 1], 6)
    u = np.tile(np.arange(6) - 2.5, 2)
    v = np.where(size == 0, 2e-6, 5e-7)[None, :]
    np.testing.assert_allclose(variance.pooled_model(v, n, size, u, 2), v, rtol=1e-9)
    assert variance.trend(v, n, size, u, 2) == pytest.approx(0.0, abs=1e-9)


@settings(max_examples=30, deadline=None)
@given(scale=st.floats(1e-8, 1e8), seed=st.integers(0, 2**31 - 1))
def test_the_model_is_equivariant_under_a_scale_of_the_quantity(scale, seed):
    """Measuring A_G in other units scales every variance alike: the weights' ratios do not move."""
    v, n, size, u, _ = _cells(np.random.default_rng(seed), G=3, K=7, n_of=lambda r, K: r.integers(2, 12, K))
    a = variance.pooled_model(v, n, size, u, 3)
    b = variance.pooled_model(v * scale, n, size, u, 3)
    np.testing.assert_allclose(b, a * scale, rtol=1e-8)


def test_one_energy_fits_no_trend():
    v, n, size, u, _ = _cells(np.random.default_rng(3), G=2, K=1)
    m = variance.pooled_model(v, n, size, np.zeros_like(u), 2)
    np.testing.assert_allclose(m, v, rtol=1e-9)  # one cell a size: its own variance


def test_bartletts_test_holds_its_level_and_finds_unequal_spreads():
    rng = np.random.default_rng(4)
    def p(**kw):
        v, n, *_ = _cells(rng, G=1, K=10, **kw)
        return variance.homogeneity(v[0], n)

    p_null = [p() for _ in range(2000)]
    assert abs(np.mean(np.array(p_null) < 0.05) - 0.05) < 0.015
    p_alt = [p(gamma=0.35) for _ in range(200)]  # a 23-fold spread across the cells
    assert np.mean(np.array(p_alt) < 0.05) > 0.8
    assert np.isnan(variance.homogeneity([1e-4], [5])) and np.isnan(variance.homogeneity([0.0, 0.0], [4, 4]))


def test_packings_alike_to_the_last_bit_still_fit_their_law():
    """Every packing of a cell the same (no spread between them: the model's variance would be
    zero and the weights infinite) and the cells exactly on y = 0.369 + 0.6 E^0.27 at two sizes: the
    law's fit still returns the law (the weights are floored at the values' last bit; unfloored,
    the fits' weighted sums overflow and the exponent ends at the search bound)."""
    from campaign.results import scaling

    energies = 10.0 ** -np.arange(8.0, 12.0)
    R1, moments, cells_by_size, n_done, logE = 21, {}, {}, {}, {}
    for g, N in enumerate((16, 32)):
        for k, E in enumerate(energies):
            c = 10 * g + k
            means = np.tile([0.369 + 0.6 * E ** 0.27, E], (R1, 1))
            moments[c] = (means, np.zeros((R1, 2, 2)))
            cells_by_size.setdefault(N, []).append(c)
            n_done[c], logE[c] = 4, np.log10(E)
    law = scaling._law(moments, cells_by_size, 0, 1, n_done, logE, (0.02, 3.0), per_size=True)
    assert law.shared.exponent == pytest.approx(0.27, abs=1e-6) and not law.shared.at_bound
    assert np.allclose(law.shared.intercepts, 0.369, atol=1e-9)
    for N in (16, 32):
        assert law.per_size[N].exponent == pytest.approx(0.27, abs=1e-6)


def _nll(v, n, size, u, s2):
    m = (np.asarray(n, float) - 1.0) / 2.0
    return float(np.sum(m * (v / s2 + np.log(s2))))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), outlier=st.floats(1.0, 1e4), small=st.integers(2, 4))
def test_a_replica_far_from_the_pooled_start_still_fits(seed, outlier, small):
    """A bootstrap replica of cells of a few packings can put one cell's variance far above the others'
    (an outlying packing drawn twice) and another's at the last bit (one packing drawn thrice); the
    scoring from the pooled start then overshoots. The fit stays finite, within the data's range, and
    no worse in likelihood than the start; where the data are tame it is the likelihood's maximum
    (against scipy's minimiser, a slow reference)."""
    from scipy.optimize import minimize

    rng = np.random.default_rng(seed)
    v, n, size, u, _ = _cells(rng, G=3, K=7, n_of=lambda r, K: np.where(r.random(K) < 0.5, small, 20))
    tame = v[0].copy()
    v = tame.copy()
    v[rng.integers(len(v))] *= outlier
    v[rng.integers(len(v))] = 1e-33
    s2 = variance.pooled_model(v[None], n, size, u, 3)[0]
    assert np.all(np.isfinite(s2)) and np.all(s2 > 0)
    # the model's range: no cell's variance beyond what a trend through the data can reach
    assert s2.max() / s2.min() < 1e8
    X = np.column_stack([np.eye(3)[size], u])
    m = (n - 1) / 2
    pooled = np.array([np.sum((v * m)[size == g]) / np.sum(m[size == g]) for g in range(3)])
    start = np.exp(np.log(pooled)[size])
    assert _nll(v, n, size, u, s2) <= _nll(v, n, size, u, start) + 1e-9 * abs(_nll(v, n, size, u, start))
    # the same cells untouched (chi^2 variances of one truth): the maximum of the likelihood
    s2 = variance.pooled_model(tame[None], n, size, u, 3)[0]
    pooled = np.array([np.sum((tame * m)[size == g]) / np.sum(m[size == g]) for g in range(3)])
    best = minimize(lambda th: _nll(tame, n, size, u, np.exp(X @ th)),
                    np.append(np.log(pooled), 0.0), method="BFGS", options={"gtol": 1e-10})
    assert _nll(tame, n, size, u, s2) == pytest.approx(best.fun, rel=1e-7, abs=1e-7)
