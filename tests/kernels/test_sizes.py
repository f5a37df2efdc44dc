"""Continuous size distributions (uniform, log-normal): the radii follow the requested law,
are a deterministic function of the task, and give valid packings."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

import kernels
from kernels.jamming import initial_state, relative_radii

BI = ((0.5, 1.4), (0.5, 1.0))


@pytest.mark.parametrize("dist", ["uniform", "lognormal"])
@pytest.mark.parametrize("delta", [0.05, 0.2, 0.5])
def test_relative_radii_follow_the_distribution(dist, delta):
    n = 200_000
    r = relative_radii(np.random.default_rng(12345), n, dist, delta)
    # mean 1 and standard deviation delta, within five standard errors of the sample moments
    d = r - r.mean()
    m4 = np.mean(d ** 4)
    assert abs(r.mean() - 1.0) < 5 * delta / math.sqrt(n)
    assert abs(np.var(r) - delta ** 2) < 5 * math.sqrt((m4 - np.var(r) ** 2) / n)
    # and the whole law (Kolmogorov-Smirnov against scipy's own distribution)
    if dist == "uniform":
        h = math.sqrt(3) * delta
        law = stats.uniform(loc=1 - h, scale=2 * h)
        assert r.min() >= 1 - h and r.max() <= 1 + h
    else:
        s = math.sqrt(math.log1p(delta ** 2))
        law = stats.lognorm(s, scale=math.exp(-s * s / 2))
    assert stats.kstest(r, law.cdf).pvalue > 1e-3
    assert math.isclose(law.mean(), 1.0, rel_tol=1e-12) and math.isclose(law.std(), delta, rel_tol=1e-12)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(n=st.integers(2, 300), dist=st.sampled_from(["uniform", "lognormal"]), delta=st.floats(1e-6, 0.5),
       seed=st.integers(0, 2 ** 32 - 1), phi=st.floats(0.1, 0.9))
def test_initial_state_radii_are_positive_and_fill_phi(n, dist, delta, seed, phi):
    pos, rad, spc = initial_state(n, seed, (1.0, 1.0), BI, phi, (dist, delta))
    assert np.all(np.isfinite(rad)) and np.all(rad > 0)
    assert math.isclose(math.pi * np.sum(rad ** 2), phi, rel_tol=1e-12)
    assert spc.dtype == np.int32 and not spc.any()
    # the positions come first from the seed's stream: the same as the discrete mixture's
    pos_bi, _, _ = initial_state(n, seed, (1.0, 1.0), BI, phi)
    assert pos.tobytes() == pos_bi.tobytes()


def test_polydisperse_packing_is_deterministic_and_valid():
    a = kernels.jam(96, 1e-7, [5, 6], sizes=("lognormal", 0.2))
    b = kernels.jam(96, 1e-7, [5, 6], sizes=("lognormal", 0.2))
    c = kernels.jam(96, 1e-7, [5, 7], sizes=("lognormal", 0.2))
    for f in ("positions", "radii", "box", "species"):
        assert getattr(a, f).tobytes() == getattr(b, f).tobytes()
    assert not np.array_equal(a.radii, c.radii)
    assert a.converged and 1e-7 <= a.energy <= 1.1e-7
    assert len(np.unique(a.radii)) == 96 and not a.species.any()
    rel = a.radii / a.radii.mean()
    assert 0.1 < rel.std() < 0.3  # 96 draws of a 20% distribution
    res = kernels.analyze(a.positions, a.radii, a.box, exponent=2.0, species=a.species)
    assert res.scalars["identities_ok"], res.identities
    assert math.isclose(res.scalars["A_G"] + res.scalars["A_V"], 1.0, rel_tol=1e-12)


def test_worker_runs_the_variants_system(monkeypatch):
    """The worker jams with the system of the task's variant (the context's ``systems``)."""
    from campaign.run.worker import KernelTask

    poly = {"box": [1.0, 1.0], "potential": {"exponent": 2.0},
            "sizes": {"distribution": "uniform", "polydispersity": 0.3}}
    base = {"box": [1.0, 1.0], "potential": {"exponent": 2.0},
            "species": [["A", 0.5, 1.4], ["B", 0.5, 1.0]]}
    ctx = {"system": base, "systems": {"default": base, "poly": poly}, "observables": ["scalars"],
           "histograms": [], "configurations": True}
    task = KernelTask()
    out = {}
    for v in ("default", "poly", "poly"):
        payload = {"index": 0, "id": "x", "variant": v, "N": 32, "E": 1e-4, "seed": 0,
                   "entropy": [1, 2, 3], "protocol": {}}
        scalars, _, conf = task.run(payload, ctx)
        assert scalars["jam_status"] == 0 and scalars["identities_ok"] == 1
        out.setdefault(v, []).append(conf)
    assert len(np.unique(out["default"][0]["radii"])) == 2
    r = out["poly"][0]["radii"]
    assert len(np.unique(r)) == 32 and r.max() / r.min() <= (1 + 0.3 * 3 ** 0.5) / (1 - 0.3 * 3 ** 0.5)
    assert r.tobytes() == out["poly"][1]["radii"].tobytes()


@pytest.mark.parametrize("sizes, match", [
    (("gamma", 0.2), "expected a distribution among"),
    (("uniform", 0.0), "expected a finite number > 0"),
    (("lognormal", 0.6), r"expected a polydispersity in \(0, 0.5\]"),
    ("uniform", "expected None or"),
])
def test_bad_sizes_are_refused(sizes, match):
    with pytest.raises(ValueError, match=match):
        kernels.jam(16, 1e-4, 0, sizes=sizes)
