"""The learned cost model: prior, recovery of a known law, behaviour with uninformative data."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from campaign.plan import tasks
from campaign.plan.costmodel import CostModel

SIZES = np.array([64, 128, 256, 512, 1024])
ENERGIES = 10.0 ** -np.arange(3, 16)


def _grid(reps=4):
    N, E = np.meshgrid(SIZES, ENERGIES, indexing="ij")
    return np.repeat(N.ravel(), reps), np.repeat(E.ravel(), reps)


def _median(model, N, E, protocols=None):
    return model.seconds(N, E, protocols) / math.exp(0.5 * model.scatter ** 2)


def test_prior_is_the_calibrated_model():
    """Before any data the learning model's expected seconds are the calibrated means."""
    model = CostModel.prior()
    for N in (16, 256, 4096):
        for E in (1e-2, 1e-3, 1e-9, 1e-15):
            for proto in ({"force_tolerance": 1e-6}, {"force_tolerance": 1e-3}, {"endgame": "newton"},
                          {"endgame": "auto"}):
                assert model.seconds(N, E, [proto])[0] == pytest.approx(tasks.cost(N, E, proto), rel=1e-12)
                assert model.seconds(N, E, [dict(proto, start="ladder")], [E * 10])[0] == pytest.approx(
                    tasks.cost(N, E, dict(proto, start="ladder"), parent_E=E * 10), rel=1e-12)


def test_no_usable_data_gives_the_prior():
    fitted = CostModel.fit([64, 128], [1e-4, 1e-6], [0.0, float("nan")])
    assert fitted.n_points == 0
    np.testing.assert_array_equal(fitted.theta, CostModel.prior().theta)
    assert fitted.sigma is None and fitted.scatter == CostModel.prior().scatter


def test_recovers_a_known_law_from_noisy_timings():
    """The truth differs from the prior in level, size exponent and energy dependence."""
    rng = np.random.default_rng(7)
    N, E = _grid()
    static = np.array([tasks.cost(n, e) for n, e in zip(N, E)])
    L = np.log10(tasks.E_REF / E)
    mu = np.log(static) + 1.3 + 0.4 * np.log(N / 256) - 0.3 * np.log1p(L)
    t = np.exp(mu + rng.normal(0, 0.2, size=N.size))
    model = CostModel.fit(N, E, t)
    assert model.n_points == N.size
    assert model.theta[1] == pytest.approx(0.4, abs=0.03)
    assert model.theta[2] == pytest.approx(-0.3, abs=0.06)
    np.testing.assert_allclose(_median(model, N, E), np.exp(mu), rtol=0.1)
    assert 0.17 < model.sigma < 0.23
    # the expected total of the campaign agrees with the true log-normal mean to a few percent
    predicted = model.seconds(N, E).sum()
    truth = np.exp(mu + 0.5 * 0.2 ** 2).sum()
    assert predicted == pytest.approx(truth, rel=0.05)


def test_one_size_only_keeps_the_prior_exponent_and_learns_the_scale():
    """Timings at one N say nothing about the N exponent; they set the level at that N."""
    rng = np.random.default_rng(1)
    E = np.repeat(ENERGIES, 5)
    N = np.full(E.size, 256)
    prior = CostModel.prior()
    t = 7.0 * _median(prior, N, E) * np.exp(rng.normal(0, 0.1, E.size))  # 7x slower machine
    model = CostModel.fit(N, E, t)
    assert abs(model.theta[1]) < 0.05  # no size information: the prior's exponent stays
    np.testing.assert_allclose(_median(model, N, E) / _median(prior, N, E), 7.0, rtol=0.1)


@settings(max_examples=30, deadline=None)
@given(scale=st.floats(0.01, 100.0), n_exp=st.floats(1.0, 2.5), seed=st.integers(0, 2 ** 31))
def test_learned_model_is_monotone_in_size_and_energy(scale, n_exp, seed):
    rng = np.random.default_rng(seed)
    N, E = _grid(reps=2)
    L = np.log10(1e-3 / E)
    t = scale * 1e-5 * N ** n_exp * (1 + L) * np.exp(rng.normal(0, 0.3, N.size))
    model = CostModel.fit(N, E, t)
    by_size = model.seconds(SIZES, np.full(SIZES.size, 1e-8))
    by_energy = model.seconds(np.full(ENERGIES.size, 256), ENERGIES)
    assert np.all(np.diff(by_size) > 0)
    assert np.all(np.diff(by_energy) >= 0)
