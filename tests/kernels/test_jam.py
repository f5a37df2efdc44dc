"""jam(): packings in the energy window with balanced forces, isostaticity, determinism,
input checking."""

import math

import numpy as np
import pytest

import kernels
from kernels.jamming import DEFAULTS, STATUS_CODES, Packing, species_counts
from references import ref_packing_measures


CASES = [(n, e) for e in (1e-4, 1e-8, 1e-14) for n in (32, 64, 128, 256)]


@pytest.mark.parametrize("n, target", CASES)
def test_packing_in_window_with_balanced_forces(n, target):
    for seed in (0, 1):
        p = kernels.jam(n, target, seed)
        assert isinstance(p, Packing) and p.status == "converged" and p.status_code == 0
        e, resid, n_g, n_c = ref_packing_measures(p)
        assert target <= p.energy <= target * 1.1
        assert e == pytest.approx(p.energy, rel=1e-9)
        assert resid < DEFAULTS["force_tolerance"]
        # the two residuals differ by float64 rounding of forces that nearly cancel:
        # position resolution eps * L against the contact overlap x s
        noise = 10 * np.finfo(float).eps * p.box.max() / (np.sqrt(2 * target) * 2 * p.radii.min())
        assert resid == pytest.approx(p.force_residual, rel=1e-6, abs=noise)
        assert n_g == p.n_nonrattlers
        assert p.energy_nonrattler == pytest.approx(p.energy * n / n_g, rel=1e-12)
        assert p.phi == pytest.approx(np.pi * np.sum(p.radii ** 2), rel=1e-12)
        assert 0.80 < p.phi < 0.87  # phi_J ~ 0.84 for this mixture
        assert p.pressure > 0
        if target == 1e-14:
            # isostatic: contacts among non-rattlers = 2 N_G - 1. Over these 16
            # packings no extra contact occurs (measured); a rare extra would show here.
            assert n_c == 2 * n_g - 1, (n, seed, n_c - (2 * n_g - 1))
        if target == 1e-4:
            assert n_c > 2 * n_g - 1  # far from jamming: hyperstatic


def test_isostatic_extras_are_rare_at_1e14():
    # count the packings with extra contacts over more seeds (N = 64)
    extras = []
    for seed in range(2, 12):
        p = kernels.jam(64, 1e-14, seed)
        _, _, n_g, n_c = ref_packing_measures(p)
        extras.append(n_c - (2 * n_g - 1))
    assert min(extras) >= 0
    assert sum(x > 0 for x in extras) <= 1, extras


def test_same_inputs_same_bytes_other_seeds_differ():
    a = kernels.jam(64, 1e-8, 42)
    b = kernels.jam(64, 1e-8, 42)
    c = kernels.jam(64, 1e-8, 43)
    d = kernels.jam(64, 1e-8, np.random.SeedSequence(42))
    for f in ("positions", "radii", "box", "species"):
        assert getattr(a, f).tobytes() == getattr(b, f).tobytes() == getattr(d, f).tobytes()
    assert (a.energy, a.pressure, a.force_evaluations) == (b.energy, b.pressure,
                                                           b.force_evaluations)
    assert not np.array_equal(a.positions, c.positions)
    assert a.positions.dtype == np.float64 and a.species.dtype == np.int32
    assert not a.positions.flags.writeable


def test_species_layout_and_custom_distribution():
    p = kernels.jam(64, 1e-6, 1)
    assert np.array_equal(p.species, np.r_[np.zeros(32), np.ones(32)])
    assert np.allclose(p.radii[p.species == 0] / p.radii[p.species == 1][0], 1.4, rtol=1e-14)
    # three species, counts by largest remainder
    sp = ((0.3, 1.0), (0.3, 1.2), (0.4, 1.5))
    assert species_counts(33, [0.3, 0.3, 0.4]).tolist() == [10, 10, 13]
    assert species_counts(10, [0.25, 0.25, 0.5]).tolist() == [3, 2, 5]
    p = kernels.jam(50, 1e-6, 2, species=sp)
    assert p.status == "converged"
    assert np.bincount(p.species).tolist() == [15, 15, 20]
    ratios = p.radii / p.radii[0]
    assert np.allclose(np.unique(ratios), [1.0, 1.2, 1.5], rtol=1e-14)


def test_rectangular_box_hertz_and_halving_search():
    p = kernels.jam(60, 1e-6, 3, box=(2.0, 0.75))
    e, resid, *_ = ref_packing_measures(p)
    assert p.status == "converged" and 1e-6 <= e <= 1.1e-6 and resid < 1e-6
    assert np.all(p.positions < np.array([2.0, 0.75]))
    p = kernels.jam(64, 1e-7, 3, exponent=2.5)
    e, resid, *_ = ref_packing_measures(p)
    assert p.status == "converged" and 1e-7 <= e <= 1.1e-7 and resid < 1e-6
    p = kernels.jam(64, 1e-6, 3, search="halving")
    e, resid, *_ = ref_packing_measures(p)
    assert p.status == "converged" and 1e-6 <= e <= 1.1e-6 and resid < 1e-6


def test_bounds_give_a_status_not_a_wrong_packing():
    p = kernels.jam(64, 1e-10, 1, max_search=2)
    assert p.status == "max_search" and p.iterations == 2
    assert not (1e-10 <= p.energy <= 1.1e-10 and p.force_residual < 1e-6)
    p = kernels.jam(64, 1e-4, 1, max_steps=5)
    assert p.status == "max_steps" and p.force_residual > DEFAULTS["force_tolerance"]
    assert set(STATUS_CODES) >= {"converged", "max_search", "max_steps"}


@pytest.mark.parametrize("args, kw, match", [
    ((1, 1e-6, 0), {}, r"n: expected an integer >= 2, got 1"),
    ((2.5, 1e-6, 0), {}, r"n: expected an integer >= 2"),
    ((64, 0.0, 0), {}, r"energy: expected a finite number > 0, got 0.0"),
    ((64, -1e-6, 0), {}, r"energy: expected"),
    ((64, math.inf, 0), {}, r"energy: expected a finite number > 0, got inf"),
    ((64, math.nan, 0), {}, r"energy: expected"),
    ((64, 1e-6, 0), dict(window=0.0), r"window: expected a finite number > 0, got 0.0"),
    ((64, 1e-6, 0), dict(window=-0.1), r"window: expected"),
    ((64, 1e-6, 0), dict(exponent=1.5), r"exponent: expected a number in \[2, 3\], got 1.5"),
    ((64, 1e-6, 0), dict(exponent=4), r"exponent: expected"),
    ((64, 1e-6, 0), dict(box=(10.0, 0.05)), r"box: expected a box large enough"),
    ((4, 1e-6, 0), {}, r"box: expected a box large enough"),
    ((64, 1e-6, 0), dict(box=(1.0, -1.0)), r"box: expected two positive"),
    ((64, 1e-6, 0), dict(species=((0.5, 1.4), (0.4, 1.0))), r"species: expected fractions summing to 1"),
    ((64, 1e-6, 0), dict(species=((0.5, 1.4, 2.0),)), r"species: expected a non-empty sequence"),
    ((64, 1e-6, 0), dict(species=((0.5, -1.4), (0.5, 1.0))), r"species: expected positive"),
    ((64, 1e-6, 0), dict(species=()), r"species: expected a non-empty"),
    ((64, 1e-6, 0), dict(species=5), r"species: expected a sequence"),
    ((64, 1e-6, 0), dict(force_tolerance=0), r"force_tolerance: expected"),
    ((64, 1e-6, 0), dict(phi_start=1.2), r"phi_start: expected a number below 1"),
    ((64, 1e-6, 0), dict(max_search=0), r"max_search: expected an integer >= 1, got 0"),
    ((64, 1e-6, 0), dict(max_steps=1.5), r"max_steps: expected an integer >= 1"),
    ((64, 1e-6, 0), dict(skin=0), r"skin: expected"),
    ((64, 1e-6, 0), dict(minimizer="bfgs"), r"minimizer: expected one of \['fire', 'cg'\], got 'bfgs'"),
    ((64, 1e-6, 0), dict(search="newton"), r"search: expected one of"),
    ((64, 1e-6, 0), dict(temperature=1), r"settings: expected names among"),
    ((64, 1e-6, -1), {}, r"seed: expected a non-negative int"),
    ((64, 1e-6, "x"), {}, r"seed: expected"),
])
def test_bad_input(args, kw, match):
    with pytest.raises(ValueError, match=match):
        kernels.jam(*args, **kw)


def test_float64_floor_is_refused_not_silently_missed():
    with pytest.raises(ValueError, match=r"energy: expected at least 2.7\de-16 for n=4096"):
        kernels.jam(4096, 1e-16, 0)
    # the floor scales as (eps L / (s_min tol))^alpha: a looser tolerance lowers it
    from kernels.jamming import energy_floor, initial_state

    _, rad, _ = initial_state(4096, 0, (1.0, 1.0), DEFAULTS["species"], 0.86)
    box = np.array([1.0, 1.0])
    assert energy_floor(rad, box, 2.0, 1e-5) == pytest.approx(
        energy_floor(rad, box, 2.0, 1e-6) / 100, rel=1e-12)


def test_deep_packing_at_1e16():
    p = kernels.jam(128, 1e-16, 5)
    e, resid, n_g, n_c = ref_packing_measures(p)
    assert p.status == "converged" and 1e-16 <= e <= 1.1e-16
    assert resid < 1e-6 and n_c == 2 * n_g - 1
