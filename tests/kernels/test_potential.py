"""One-sided power-law potential: analytic values, gradients, virial, slow reference."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from kernels.potential import ALPHA_RANGE, energy, forces, pair_potential, pressure
from references import ref_energy

ALPHAS = [2.0, 2.5, 3.0]


def overlapping_system(seed, n=30, box=(1.0, 1.3), phi=1.0):
    rng = np.random.default_rng(seed)
    box = np.asarray(box, float)
    pos = rng.random((n, 2)) * box
    rel = np.where(np.arange(n) < n // 2, 1.4, 1.0)
    rad = rel * np.sqrt(phi * box.prod() / (np.pi * np.sum(rel ** 2)))
    return pos, rad, box


@pytest.mark.parametrize("alpha", ALPHAS)
def test_boundary_values(alpha):
    s = 0.7
    v, f = pair_potential([0.0, s / 2, s, 1.5 * s, s * (1 - 1e-12)], s, alpha)
    assert v[0] == pytest.approx(1.0 / alpha, rel=1e-15)
    assert f[0] == pytest.approx(1.0 / s, rel=1e-15)
    assert v[1] == pytest.approx(0.5 ** alpha / alpha, rel=1e-14)
    assert f[1] == pytest.approx(0.5 ** (alpha - 1) / s, rel=1e-14)
    assert v[2] == 0.0 and f[2] == 0.0 and v[3] == 0.0 and f[3] == 0.0
    assert 0 < v[4] < 1e-20 and 0 < f[4] < 1e-9  # continuous at contact


@pytest.mark.parametrize("alpha", ALPHAS)
def test_pair_force_is_minus_derivative(alpha):
    s = 1.3
    r = np.linspace(0.05, 1.25, 50)
    h = 1e-6
    v, f = pair_potential(r, s, alpha)
    vp, _ = pair_potential(r + h, s, alpha)
    vm, _ = pair_potential(r - h, s, alpha)
    assert np.allclose(f, -(vp - vm) / (2 * h), rtol=1e-7, atol=0)


@pytest.mark.parametrize("alpha", ALPHAS)
@pytest.mark.parametrize("seed", [0, 1])
def test_energy_matches_reference(alpha, seed):
    pos, rad, box = overlapping_system(seed)
    assert energy(pos, rad, box, alpha) == pytest.approx(ref_energy(pos, rad, box, alpha),
                                                        rel=1e-12)


@pytest.mark.parametrize("alpha", ALPHAS)
def test_forces_are_minus_gradient(alpha):
    pos, rad, box = overlapping_system(3)
    f = forces(pos, rad, box, alpha)
    h = 1e-7 * rad.mean()
    num = np.empty_like(pos)
    for i in range(len(pos)):
        for k in range(2):
            p = pos.copy()
            p[i, k] += h
            ep = energy(p, rad, box, alpha)
            p[i, k] -= 2 * h
            em = energy(p, rad, box, alpha)
            num[i, k] = -(ep - em) / (2 * h)
    scale = np.abs(f).max()
    assert scale > 0
    assert np.allclose(f, num, rtol=0, atol=1e-6 * scale)
    assert np.allclose(f.sum(axis=0), 0.0, atol=1e-12 * scale)  # Newton's third law


@pytest.mark.parametrize("alpha", ALPHAS)
def test_pressure_is_minus_dE_dA(alpha):
    # affine dilation of positions and box by lam: P = -dE/dA with A = lam^2 A0
    pos, rad, box = overlapping_system(4)
    h = 1e-6
    ep = energy(pos * (1 + h), rad, box * (1 + h), alpha)
    em = energy(pos * (1 - h), rad, box * (1 - h), alpha)
    a0 = box.prod()
    dE_dA = (ep - em) / (2 * h) / (2 * a0)
    assert pressure(pos, rad, box, alpha) == pytest.approx(-dE_dA, rel=1e-6)
    assert pressure(pos, rad, box, alpha) > 0


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), shift=st.tuples(st.floats(-5, 5), st.floats(-5, 5)),
       alpha=st.sampled_from(ALPHAS))
def test_translation_and_periodic_invariance(seed, shift, alpha):
    pos, rad, box = overlapping_system(seed, n=20)
    e0 = energy(pos, rad, box, alpha)
    e1 = energy(pos + np.array(shift), rad, box, alpha)
    assert e1 == pytest.approx(e0, rel=1e-9, abs=1e-300)
    f0 = forces(pos, rad, box, alpha)
    f1 = forces(pos + np.array(shift), rad, box, alpha)
    assert np.allclose(f0, f1, rtol=0, atol=1e-8 * (np.abs(f0).max() + 1e-300))


def test_harmonic_two_disks_analytic():
    # two disks overlapping across the boundary: V = (1/2)(1 - r/s)^2
    box = np.array([1.0, 1.0])
    pos = np.array([[0.05, 0.5], [0.95, 0.5]])  # distance 0.1 through the boundary
    rad = np.array([0.06, 0.07])
    s = 0.13
    assert energy(pos, rad, box, 2.0) == pytest.approx(0.5 * (1 - 0.1 / s) ** 2, rel=1e-12)
    f = forces(pos, rad, box, 2.0)
    mag = (1 - 0.1 / s) / s
    assert f[0] == pytest.approx([mag, 0.0], rel=1e-10, abs=1e-15)  # pushed to +x
    assert f[1] == pytest.approx([-mag, 0.0], rel=1e-10, abs=1e-15)
    assert pressure(pos, rad, box, 2.0) == pytest.approx(0.1 * mag / 2.0, rel=1e-10)


@pytest.mark.parametrize("bad", [1.5, 3.5, float("nan"), "two", None])
def test_exponent_out_of_range(bad):
    with pytest.raises(ValueError, match=r"exponent: expected a number in \[2, 3\]"):
        energy(np.zeros((2, 2)), np.ones(2) * 0.1, (1, 1), bad)
    assert ALPHA_RANGE == (2.0, 3.0)


@pytest.mark.parametrize("alpha", ALPHAS)
def test_row_form_equals_pair_form(alpha):
    from kernels.cells import candidate_pairs
    from kernels.potential import (_energy_forces_core, _energy_forces_rows, _pair_inv_sigma,
                                   _rows_from_pairs)

    pos, rad, box = overlapping_system(6, n=200, phi=0.9)
    i, j = candidate_pairs(pos, rad, box, 0.3 * rad.mean())
    q = _pair_inv_sigma(rad, i, j)
    f1 = np.empty_like(pos)
    f2 = np.empty_like(pos)
    cell = np.append(box, 0.0)  # the kernels' cell [Lx, Ly, xy]
    a = _energy_forces_core(pos, cell, i, j, q, alpha, f1)
    start, nbr = _rows_from_pairs(len(pos), i, j)
    b = _energy_forces_rows(pos, cell, start, nbr, q, alpha, f2)
    assert a[2] == b[2] and np.allclose(a, b, rtol=1e-13)
    assert np.allclose(f1, f2, rtol=0, atol=1e-13 * np.abs(f1).max())
