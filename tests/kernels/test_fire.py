"""FIRE 2.0 minimiser and the rattler-aware force residual."""

import numpy as np
import pytest

from kernels.fire import minimize
from kernels.minimiser import nonrattlers
from kernels.rules import STATUS_NAMES
from kernels.potential import energy
from helpers import compressed_packing, random_dense
from references import ref_contact_pairs, ref_force_residual, ref_nonrattler_mask


def test_nonrattlers_match_reference():
    # random overlapping disks erode completely (no load-bearing core) ...
    for seed in range(3):
        pos, rad, box = random_dense(seed, n=80, phi=1.2)
        ref = ref_nonrattler_mask(80, ref_contact_pairs(pos, rad, box), pos, box)
        assert np.array_equal(nonrattlers(pos, rad, box), ref)
    # ... force-balanced packings keep most disks, and lose a few by either rule
    for seed in range(3):
        pos, rad, box = compressed_packing(64, seed, phi=0.86)
        ref = ref_nonrattler_mask(64, ref_contact_pairs(pos, rad, box), pos, box)
        got = nonrattlers(pos, rad, box)
        assert np.array_equal(got, ref)
        assert 48 < ref.sum() <= 64


def test_nonrattlers_chain_removal():
    # a disk with 3 contacts, two of which are to disks with 1 contact: all rattlers
    box = np.array([10.0, 10.0])
    pos = np.array([[5.0, 5.0], [5.9, 5.0], [4.1, 5.0], [5.0, 5.9], [6.8, 5.0]])
    rad = np.full(5, 0.5)
    assert not nonrattlers(pos, rad, box).any()


@pytest.mark.parametrize("alpha", [2.0, 2.5])
def test_minimize_balances_forces(alpha):
    pos, rad, box = random_dense(7, n=64, phi=0.9)
    e0 = energy(pos, rad, box, alpha)
    res = minimize(pos, rad, box, alpha, force_tolerance=1e-8)
    assert res.status == "converged"
    assert res.energy < e0 and res.energy > 0  # phi = 0.9 is above jamming
    assert np.all(res.positions >= 0) and np.all(res.positions < 1)
    resid, keep = ref_force_residual(res.positions, rad, box, alpha)
    assert resid < 1e-8 and resid == pytest.approx(res.residual, rel=1e-6, abs=1e-12)
    assert keep.sum() > 48
    assert res.energy == pytest.approx(energy(res.positions, rad, box, alpha), rel=1e-12)


def test_minimize_separates_dilute_disks():
    # well below jamming the minimum has no overlap at all: nothing to balance
    pos, rad, box = random_dense(3, n=64, phi=0.5)
    res = minimize(pos, rad, box, 2.0)
    assert res.status == "converged" and res.energy == 0.0 and res.residual == 0.0


def test_triangular_crystal_is_a_minimum():
    # compressed triangular crystal: every force vanishes by symmetry
    nx, ny = 6, 4
    box = np.array([1.0, np.sqrt(3) / 2 * ny / nx])
    a = 1.0 / nx
    pos = np.array([[(i + 0.5 * (j % 2)) * a, j * a * np.sqrt(3) / 2]
                    for j in range(ny) for i in range(nx)])
    rad = np.full(len(pos), 0.51 * a)
    res = minimize(pos, rad, box, 2.0)
    assert res.status == "converged" and res.steps == 0
    assert res.residual < 1e-12
    # six contacts each at overlap 1 - a/(1.02 a)
    assert res.energy == pytest.approx(len(pos) * 3 * 0.5 * (1 - 1 / 1.02) ** 2, rel=1e-12)


def test_max_steps_is_reported():
    pos, rad, box = random_dense(5, n=64, phi=0.9)
    res = minimize(pos, rad, box, 2.0, force_tolerance=1e-12, max_steps=10)
    assert res.status == "max_steps" and res.steps == 10 and res.residual > 1e-12
    assert "max_steps" in STATUS_NAMES


def test_deterministic():
    pos, rad, box = random_dense(9, n=64, phi=0.88)
    a = minimize(pos, rad, box, 2.0)
    b = minimize(pos, rad, box, 2.0)
    assert a.positions.tobytes() == b.positions.tobytes() and a.steps == b.steps


@pytest.mark.parametrize("kw, match", [
    (dict(force_tolerance=0.0), "force_tolerance"),
    (dict(max_steps=-1), "max_steps"),
    (dict(skin=-0.1), "skin"),
])
def test_bad_settings(kw, match):
    pos, rad, box = random_dense(1, n=8, phi=0.5)
    with pytest.raises(ValueError, match=match):
        minimize(pos, rad, box, 2.0, **kw)


def test_verlet_list_never_misses_a_pair():
    # A tiny skin (rebuilt almost every step), the default and a huge one (rarely
    # rebuilt) reach the same minimum; the energy and forces each reports, computed
    # from its Verlet list, equal a from-scratch evaluation at the end.
    # (Bits differ: wrapping at each rebuild rounds coordinates differently.)
    pos, rad, box = random_dense(12, n=100, phi=0.88)
    d = 2 * rad.mean()
    # start near a minimum so that every run stays in its basin
    start = minimize(pos, rad, box, 2.0).positions
    start = start + 0.05 * d * np.random.default_rng(0).standard_normal(start.shape)
    runs = [minimize(start, rad, box, 2.0, skin=s * d, force_tolerance=1e-10)
            for s in (0.02, 0.3, 1.5)]
    for r in runs:
        assert r.status == "converged"
        assert r.energy == pytest.approx(energy(r.positions, rad, box, 2.0), rel=1e-12)
        resid, _ = ref_force_residual(r.positions, rad, box, 2.0)
        assert resid < 1e-10
    for r in runs[1:]:
        assert r.energy == pytest.approx(runs[0].energy, rel=1e-9)
        dpos = r.positions - runs[0].positions
        dpos -= box * np.round(dpos / box)
        assert np.abs(dpos).max() < 1e-6 * d
