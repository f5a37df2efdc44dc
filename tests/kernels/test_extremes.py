"""Numerical stability at the extremes: energies down to the float64 floor, tiny and
large systems, radius ratios 1 to 3, polydisperse mixtures, stiff exponents, the
ordered fraction of crystallising packings, and degenerate configurations handed to
the analysis.

Every packing test asserts what the packing promises (status, energy window, force
balance recomputed here by brute force, the identities of docs/PHYSICS.md); every bad
request asserts a clear refusal. ``pytest -m slow tests/kernels/test_extremes.py`` runs the
long ones (N = 16384, full energy ladders).
"""

import math

import numpy as np
import pytest

import kernels
from campaign.cli import main as cli_main
from kernels.analysis import analyze
from kernels.network import network
from kernels.jamming import species_counts
from helpers import triangular_crystal
from references import ref_packing_measures_kdtree, ref_psi6_per_grain

EPS = np.finfo(np.float64).eps
TOL = 1e-6  # kernels.jam's default force_tolerance
BIDISPERSE = ((0.5, 1.4), (0.5, 1.0))


# ----------------------------------------------------------------------------- references


def floor_formula(n, alpha, tol, species=BIDISPERSE, phi_start=0.86, box=(1.0, 1.0)):
    """The documented float64 floor, restated: a coordinate is known to eps L, so a contact
    force x^(alpha-1)/s is known to (alpha-1) eps L / (x s); demanding tol gives
    x_min = (alpha-1) eps L / (s_min tol) and E_G >= (2/alpha) x_min^alpha, s_min the
    smallest contact distance at the random start (radii scaled to phi_start)."""
    counts = species_counts(n, [f for f, _ in species])
    rel = np.repeat([r for _, r in species], counts)
    r = rel * math.sqrt(phi_start * box[0] * box[1] / (math.pi * np.sum(rel ** 2)))
    x_min = (alpha - 1) * EPS * max(box) / (2 * r.min() * tol)
    return 2 / alpha * x_min ** alpha


def assert_packing(p, target, window=0.1, tol=TOL, isostatic=None, may_fail=()):
    """Converged, inside the window, forces balanced (recomputed), identities hold
    (except the flags named in ``may_fail``)."""
    assert p.status == "converged", p.status
    assert target <= p.energy <= target * (1 + window)
    e, resid, n_g, n_c, mean_x = ref_packing_measures_kdtree(p)
    assert e == pytest.approx(p.energy, rel=1e-9)
    assert p.force_residual <= tol
    # the recomputed residual differs by the float64 noise the floor is about:
    # (alpha - 1) eps L / (x s) relative, x the typical overlap (sum order differs)
    x = (p.exponent * target / 2) ** (1 / p.exponent)
    noise = 10 * (p.exponent - 1) * EPS * p.box.max() / (x * 2 * p.radii.min())
    assert resid <= tol + noise, (resid, noise)
    assert n_g == p.n_nonrattlers
    if isostatic is not None:
        assert n_c - (2 * n_g - 1) in isostatic, (n_c, n_g)
    a = analyze(p.positions, p.radii, p.box, exponent=p.exponent)
    failed = [k for k, v in a.identities.items() if not v]
    assert set(failed) <= set(may_fail), failed
    assert a.scalars["identities_ok"] is (not failed)
    assert a.scalars["N_C"] == 2 * n_c and a.scalars["N_G"] == n_g
    assert a.scalars["E_G"] == pytest.approx(p.energy, rel=1e-9)
    return a, mean_x


def assert_no_silent_nan(a):
    """A scalar that is NaN never comes with identities_ok."""
    nans = [k for k, v in a.scalars.items() if isinstance(v, float) and math.isnan(v)]
    if nans:
        assert a.scalars["identities_ok"] is False, nans
        assert a.identities["network_nonempty"] is False


# ----------------------------------------------------------------------------- energy floor


@pytest.mark.parametrize("n, alpha", [(64, 2.0), (256, 2.0), (64, 2.5)])
def test_just_above_the_floor_converges_just_below_is_refused(n, alpha):
    floor = floor_formula(n, alpha, TOL)
    assert floor < 1e-16 if alpha == 2.0 else floor < 1e-20  # deeper than the paper goes
    p = kernels.jam(n, 3 * floor, 1, exponent=alpha)
    assert_packing(p, 3 * floor, isostatic={0} if alpha == 2.0 else {0, 1})
    with pytest.raises(ValueError, match=rf"energy: expected at least {floor:.3g} for n={n}") as err:
        kernels.jam(n, 0.9 * floor, 1, exponent=alpha)
    assert f"got {0.9 * floor!r}" in str(err.value)


def test_floor_scales_with_n_and_tolerance():
    """The floor grows as s_min^-alpha ~ N^(alpha/2) and falls as tol^alpha: refused at
    N = 8192, 1e-16 with the default tolerance, accepted with tol 1e-5 (floor / 100)."""
    f8192 = floor_formula(8192, 2.0, TOL)
    assert f8192 > 1e-16 > floor_formula(1024, 2.0, TOL)
    assert floor_formula(4096, 2.0, TOL) == pytest.approx(f8192 / 2, rel=1e-3)
    with pytest.raises(ValueError, match=rf"expected at least {f8192:.3g} for n=8192"):
        kernels.jam(8192, 1e-16, 0)
    assert floor_formula(8192, 2.0, 1e-5) == pytest.approx(f8192 / 100, rel=1e-12)


def test_validate_refuses_a_hertz_grid_below_its_floor(tmp_path, capsys):
    floor = floor_formula(1024, 2.5, TOL)
    p = tmp_path / "hertz.yaml"
    p.write_text("name: hertz\nseed: 1\nsystem: {box: [1.0, 1.0], species: [{name: A, fraction: 0.5, "
                 "radius: 1.4}, {name: B, fraction: 0.5, radius: 1.0}], potential: {exponent: 2.5}}\n"
                 f"grid: {{N_G: [1024], E_G: [{float(floor) / 2!r}, 1.0e-6], seeds: 1}}\n")
    assert cli_main(["validate", str(p)]) == 2
    err = capsys.readouterr().err
    assert f"{floor:.3g}" in err and "N_G = 1024" in err and "Traceback" not in err


def test_high_energy_1e2_overlaps_of_ten_percent():
    """E_G = 1e-2 is far above jamming: ~8% overlaps, hyperstatic, still balanced."""
    p = kernels.jam(128, 1e-2, 3)
    a, mean_x = assert_packing(p, 1e-2)
    # E_G = sum x^2/2 / N with N_C/2 contacts: x_rms = sqrt(4 E_G / <z>)
    z = a.scalars["z_g_mean"]
    assert 5.0 < z <= 6.0
    assert mean_x == pytest.approx(math.sqrt(4 * 1e-2 * a.scalars["N"] / (z * a.scalars["N_G"])), rel=0.2)
    assert 0.05 < mean_x < 0.15
    assert p.phi > 0.95


# ----------------------------------------------------------------------------- system size


@pytest.mark.parametrize("n", [2, 3, 4])
def test_too_few_disks_for_the_minimum_image_are_refused(n):
    """Diameters must stay below half the box side; at phi_start = 0.86 that needs N >= 5
    (monodisperse) whatever the skin, so 2, 3 and 4 disks are refused."""
    for species in (BIDISPERSE, ((1.0, 1.0),)):
        with pytest.raises(ValueError, match=r"box: expected a box large enough for \d+ disks.*"
                                             r"largest radius below"):
            kernels.jam(n, 1e-6, 0, species=species, skin=0.01)


@pytest.mark.parametrize("target", [1e-4, 1e-12, 1e-17])
def test_eight_disks(target):
    """N = 8 fits the box with a small Verlet skin; the packing is balanced and valid, but
    tiny systems are often ordered and hyperstatic (measured: 3 extra contacts)."""
    for seed in (0, 2):
        p = kernels.jam(8, target, seed, skin=0.05)
        assert_packing(p, target)


@pytest.mark.parametrize("box", [(1e3, 1e3), (1e-3, 1e-3), (4.0, 0.5)])
def test_box_scale_and_aspect(box):
    """Every tolerance is relative: a box of side 1e3 or 1e-3, or of aspect 8, jams alike."""
    p = kernels.jam(256, 1e-12, 5, box=box)
    assert np.array_equal(p.box, box)
    a, _ = assert_packing(p, 1e-12, isostatic={0})
    assert a.scalars["A_G"] + a.scalars["A_V"] == pytest.approx(1.0, rel=1e-12)
    assert a.scalars["area_G"] + a.scalars["area_V"] == pytest.approx(box[0] * box[1], rel=1e-12)


# ----------------------------------------------------------------------------- size distributions


@pytest.mark.parametrize("seed", [0, 1])
def test_monodisperse_crystallises_and_is_detected(seed):
    """Equal disks crystallise: most grains have six-fold contact order (measured 0.64 to
    1.0 at N = 256, 18 packings), the 1:1.4 mixture about 0.1. Grains at a crystallite's
    edge may hold their contacts within a half-plane: they carry no load and are rattlers,
    so every identity holds."""
    p = kernels.jam(256, 1e-8, seed, species=((1.0, 1.0),))
    a, _ = assert_packing(p, 1e-8)
    q = kernels.jam(256, 1e-8, seed)
    b, _ = assert_packing(q, 1e-8)
    assert a.scalars["ordered_fraction"] > 0.5 > 0.2 > b.scalars["ordered_fraction"]


@pytest.mark.parametrize("species", [
    ((0.5, 3.0), (0.5, 1.0)),                                        # ratio 3
    ((0.5, 2.0), (0.5, 1.0)),                                        # ratio 2
    tuple((0.2, r) for r in (1.0, 1.2, 1.4, 1.6, 1.8)),              # 5 species
    tuple((0.1, r) for r in np.linspace(1.0, 2.0, 10)),              # 10 species 1..2
], ids=["ratio3", "ratio2", "poly5", "poly10"])
def test_size_distributions(species):
    p = kernels.jam(128, 1e-10, 4, species=species)
    a, _ = assert_packing(p, 1e-10)
    assert np.unique(np.round(p.radii / p.radii.min(), 9)).size == len(species)
    assert 0.78 < p.phi < 0.9


@pytest.mark.parametrize("alpha, target", [(2.5, 1e-6), (2.5, 1e-18), (3.0, 1e-6), (3.0, 1e-20), (3.0, 1e-24)])
def test_stiffer_exponents(alpha, target):
    # alpha = 3 at 1e-24: the first minimisation's time step must be sized for the random start's
    # overlaps, not the target's (it was not: every run ended max_steps below ~1e-21)
    p = kernels.jam(64 if target > 1e-21 else 32, target, 2, exponent=alpha)
    assert p.exponent == alpha
    assert_packing(p, target, isostatic={0} if target < 1e-14 else None)


# ----------------------------------------------------------------------------- ordered fraction


def test_ordered_fraction_exact_cases():
    # triangular crystal: six contacts at multiples of 60 degrees, |psi_6| = 1
    pos, rad, box = triangular_crystal(8, 8, overlap=1e-7)
    assert analyze(pos, rad, box, ["scalars"]).scalars["ordered_fraction"] == 1.0
    # square lattice: four contacts at 90 degrees, psi_6 = (1 - 1 + 1 - 1)/4 = 0
    m = 8
    i, j = np.divmod(np.arange(m * m), m)
    sq = np.stack([i, j], axis=1) / m + 0.5 / m
    a = analyze(sq, np.full(m * m, 0.5 / m * (1 + 1e-6)), (1.0, 1.0), ["scalars"])
    assert a.scalars["N_G"] == m * m and a.scalars["ordered_fraction"] == 0.0
    # no grain left: undefined, and said so
    a = analyze(np.array([[0.1, 0.1], [0.5, 0.5]]), np.full(2, 0.01), (1.0, 1.0))
    assert math.isnan(a.scalars["ordered_fraction"]) and a.scalars["identities_ok"] is False


def test_ordered_fraction_matches_reference():
    for species in (BIDISPERSE, ((1.0, 1.0),)):
        p = kernels.jam(96, 1e-9, 11, species=species)
        ref = ref_psi6_per_grain(p.positions, p.radii, p.box)
        a = analyze(p.positions, p.radii, p.box, ["scalars"])
        assert a.scalars["N_G"] == len(ref)
        expected = sum(v > 0.9 for v in ref.values()) / len(ref)
        assert a.scalars["ordered_fraction"] == expected
        assert not any(abs(v - 0.9) < 1e-9 for v in ref.values())  # no grain on the threshold


# ----------------------------------------------------------------------------- degenerate input


def test_all_rattlers_tiny_disks_in_a_big_box():
    rng = np.random.default_rng(0)
    for box in ((1.0, 1.0), (1e6, 2e6)):
        pos = rng.random((2000, 2)) * box
        a = analyze(pos, np.full(2000, 1e-5 * box[0]), box)
        s = a.scalars
        assert s["contacts_total"] == 0 and s["N_G"] == 0 and s["N_R"] == 2000
        assert s["E_G"] == 0.0 and s["pressure"] == 0.0 and s["A_G"] == 0.0
        assert a.identities["network_nonempty"] is False and s["identities_ok"] is False
        assert_no_silent_nan(a)


def test_single_contact_and_collinear_chains():
    box = np.array([1.0, 1.0])
    # one contact: energy of the one overlap, no network
    a = analyze(np.array([[0.3, 0.5], [0.5, 0.5]]), np.full(2, 0.11), box)
    assert a.scalars["contacts_total"] == 1 and a.scalars["N_G"] == 0
    assert a.scalars["E_G"] == pytest.approx((1 - 0.2 / 0.22) ** 2 / 2 / 2, rel=1e-12)
    assert_no_silent_nan(a)
    # three disks in a line: two contacts, both collinear, no network
    a = analyze(np.array([[0.3, 0.5], [0.5, 0.5], [0.7, 0.5]]), np.full(3, 0.1001), box)
    assert a.scalars["contacts_total"] == 2 and a.scalars["N_G"] == 0
    assert_no_silent_nan(a)
    # a compressed chain wrapping around the box: force balanced with E_G > 0, yet every
    # disk has two contacts, so all are rattlers and the flags say so
    n = 10
    chain = np.stack([np.arange(n) / n, np.full(n, 0.5)], axis=1)
    a = analyze(chain, np.full(n, 0.5 / n * 1.01), box)
    assert a.scalars["contacts_total"] == n and a.scalars["E_G"] > 0 and a.scalars["N_G"] == 0
    assert a.scalars["identities_ok"] is False
    assert_no_silent_nan(a)


def hex_patch(rings):
    """A hexagonal patch of triangular crystal (unit spacing), 3R(R+1)+1 disks."""
    pts = [(i + 0.5 * j, j * math.sqrt(3) / 2)
           for i in range(-rings, rings + 1) for j in range(-rings, rings + 1) if abs(i + j) <= rings]
    return np.array(pts), np.full(len(pts), 0.5 * (1 + 1e-6))


@pytest.mark.parametrize("rings, side", [(1, 40.0), (3, 1e6)])
def test_finite_crystal_in_a_much_larger_box(rings, side):
    """A patch of crystal far from its images carries no load: its outermost grains have
    all their contacts in a half-plane, and removing them exposes the next ring, so the
    analysis finds no network at all. Kept whole (no rattler removal) it is a planar graph:
    Euler's formula with the outer face is N_G - N_C/2 + N_V = 2 (not 0 as on the torus)
    and the outer face's area cancels the rest (not the box area)."""
    pos, rad = hex_patch(rings)
    n = 3 * rings * (rings + 1) + 1
    a = analyze(pos + side / 2, rad, (side, side))
    s = a.scalars
    assert s["N_G"] == 0 and s["N_R"] == n and a.rattler.all()
    assert s["contacts_total"] == 3 * rings * (3 * rings + 1)          # bonds of the patch
    assert a.identities["network_nonempty"] is False and s["identities_ok"] is False
    net = network(pos + side / 2, rad, (side, side), remove_rattlers=False)
    n_c = net["src"].size
    n_v = net["sides"].size
    assert n_c == 2 * 3 * rings * (3 * rings + 1)
    assert n_v == 6 * rings ** 2 + 1                                   # triangles + outside
    assert n - n_c // 2 + n_v == 2
    a_g = net["edge_area"].sum()
    assert abs(a_g + net["void_area"].sum()) <= 1e-12 * a_g


def _edge_variants(pos, box, k):
    """The configuration with disk k's x at 0, at Lx (the same point), at 1 - 1e-17 of
    the box (rounds to Lx) and at -1e-300 (rounds to Lx when wrapped)."""
    base = pos.copy()
    base[:, 0] = (base[:, 0] - base[k, 0]) % box[0]
    assert base[k, 0] == 0.0
    out = {"zero": base}
    for name, x in (("Lx", box[0]), ("1-1e-17", box[0] * (1 - 1e-17)), ("-1e-300", -1e-300)):
        v = base.copy()
        v[k, 0] = x
        out[name] = v
    return out


def test_disks_exactly_at_the_box_edge():
    p = kernels.jam(128, 1e-12, 3)
    for k in (0, 77):
        variants = _edge_variants(np.array(p.positions), p.box, k)
        ref = analyze(variants["zero"], p.radii, p.box)
        assert ref.ok
        for name, v in variants.items():
            a = analyze(v, p.radii, p.box)
            assert np.array_equal(a.contacts, ref.contacts), name
            assert a.identities == ref.identities and a.ok, name
            for key in ("N_G", "N_C", "N_V", "N_F", "psi_O", "ordered_fraction"):
                assert a.scalars[key] == ref.scalars[key], (name, key)
            for key in ("E_G", "A_G", "A_V", "pressure"):
                assert a.scalars[key] == pytest.approx(ref.scalars[key], rel=1e-12), (name, key)
    # a whole crystal row on the edge: every x is 0 or Lx
    pos, rad, box = triangular_crystal(8, 8, overlap=1e-7)
    on_edge = pos.copy()
    on_edge[on_edge[:, 0] == 0.0, 0] = box[0]
    assert analyze(on_edge, rad, box).scalars == analyze(pos, rad, box).scalars


def test_edge_coordinates_through_campaign_analyze(tmp_path, capsys):
    pos, rad, box = triangular_crystal(8, 8, overlap=1e-7)
    assert box[0] == 1.0
    rows = ["%r %r" % tuple(map(float, box))]
    for (x, y), r in zip(pos, rad):
        if x == 0.0 and y == 0.0:
            xs = "-1e-300"
        elif x == 0.0:
            xs = "0.99999999999999999"  # 1 - 1e-17: reads as 1.0, the box side
        else:
            xs = repr(float(x))
        rows.append(f"{xs} {float(y)!r} {float(r)!r}")
    f = tmp_path / "edge.txt"
    f.write_text("\n".join(rows) + "\n")
    assert cli_main(["analyze", str(f), "--json"]) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    ref = analyze(pos, rad, box).scalars
    assert out["identities_ok"] is True and out["N_G"] == 64 and out["ordered_fraction"] == 1.0
    assert out["N_C"] == ref["N_C"] and out["A_G"] == pytest.approx(ref["A_G"], rel=1e-12)


def test_positions_far_from_the_box_lose_digits():
    """analyze takes unwrapped positions at face value: 100 box lengths away the network is
    the same; at 1e8 box lengths a coordinate keeps only ~1e-8 of L, as coarse as the
    contact overlaps at E_G = 1e-12, and the contact network changes (which the identity
    flags then report). campaign analyze refuses centres more than one box length out."""
    p = kernels.jam(128, 1e-12, 3)
    ref = analyze(p.positions, p.radii, p.box)
    near = analyze(p.positions + 100.0, p.radii, p.box)
    assert np.array_equal(near.contacts, ref.contacts) and near.ok
    far = analyze(p.positions + 1e8, p.radii, p.box)
    assert not np.array_equal(far.contacts, ref.contacts)
    assert far.scalars["N_G"] != ref.scalars["N_G"]


# ----------------------------------------------------------------------------- slow


@pytest.mark.slow
@pytest.mark.parametrize("n", [32, 128, 1024])
def test_energy_ladder_down_to_the_floor(n):
    """Every decade from 1e-2 to the floor: converged, in the window, balanced; the
    isostatic count 2 N_G - 1 holds from 1e-12 down (rare extras allowed)."""
    floor = floor_formula(n, 2.0, TOL)
    energies = [10.0 ** -k for k in range(2, 17)] + [3 * floor]
    extras = []
    for e in energies:
        p = kernels.jam(n, e, 0)
        assert_packing(p, e)
        _, _, n_g, n_c, _ = ref_packing_measures_kdtree(p)
        if e <= 1e-12:
            extras.append(n_c - (2 * n_g - 1))
        elif e >= 1e-4:
            assert n_c > 2 * n_g - 1  # hyperstatic
    assert min(extras) >= 0 and sum(x > 0 for x in extras) <= 1, extras


@pytest.mark.slow
@pytest.mark.parametrize("n, target", [(16384, 1e-6), (4096, 1e-15)])
def test_large_systems(n, target):
    p = kernels.jam(n, target, 0)
    a, _ = assert_packing(p, target)
    assert a.scalars["ordered_fraction"] < 0.2


@pytest.mark.slow
@pytest.mark.parametrize("alpha", [2.5, 3.0])
def test_hertz_ladder(alpha):
    for e in (1e-2, 1e-6, 1e-10, 1e-14, 1e-18):
        p = kernels.jam(128, e, 1, exponent=alpha)
        assert_packing(p, e, isostatic={0, 1} if e <= 1e-14 else None)


def test_ordered_fraction_reaches_the_store(tmp_path, capsys):
    """The new scalar flows like every analysis scalar: worker -> journal -> /scalars."""
    import h5py

    spec = tmp_path / "mono.yaml"
    spec.write_text("name: mono\nseed: 3\nsystem: {box: [1.0, 1.0], species: [{name: A, fraction: 1.0, "
                    "radius: 1.0}], potential: {exponent: 2.0}}\n"
                    "grid: {N_G: [32], E_G: [1.0e-6], seeds: 2}\nobservables: [scalars]\n"
                    "store: {configurations: true}\n")
    out = tmp_path / "o.h5"
    assert cli_main(["run", str(spec), "--out", str(out), "--launcher", "inline",
                     "--task-function", "kernels"]) == 0
    capsys.readouterr()
    with h5py.File(out, "r") as f:
        col = f["scalars/ordered_fraction"][:]
        ids = [t.decode() for t in f["tasks/id"][:]]
        assert col.shape == (2,)
        for k, tid in enumerate(ids):
            g = f[f"configurations/{tid}"]
            a = analyze(g["positions"][:], g["radii"][:], g["box"][:])
            assert col[k] == a.scalars["ordered_fraction"]
            assert 0.0 <= col[k] <= 1.0


@pytest.mark.parametrize("scale", [1e-95, 1e95])
def test_length_scales_at_the_ends_of_the_accepted_range(scale):
    """The analysis is scale invariant from lengths of 1e-97 (radii) to 1e95 (box)."""
    pos, rad, box = triangular_crystal(8, 8, overlap=1e-7)
    ref = analyze(pos, rad, box)
    a = analyze(pos * scale, rad * scale, box * scale)
    assert a.ok and a.scalars["N_C"] == ref.scalars["N_C"] == 6 * 64
    assert a.scalars["A_G"] == pytest.approx(0.75, abs=1e-6)
    assert a.scalars["E_G"] == pytest.approx(ref.scalars["E_G"], rel=1e-6)


@pytest.mark.parametrize("scale", [1e-160, 1e-170, 1e160])
def test_lengths_whose_squares_leave_float64_are_refused(scale, tmp_path, capsys):
    """Squared lengths of 1e-160 underflow (every contact vanished silently), the area of a
    1e-170 box is 0 (a division by zero): refused, in analyze and in campaign analyze."""
    pos, rad, box = triangular_crystal(8, 8, overlap=1e-7)
    with pytest.raises(ValueError, match=r"lengths: expected radii and box sides in \[1e-100, 1e\+100\].*got"):
        analyze(pos * scale, rad * scale, box * scale)
    f = tmp_path / "tiny.npz"
    np.savez(f, positions=pos * scale, radii=rad * scale, box=box * scale)
    assert cli_main(["analyze", str(f)]) == 2
    err = capsys.readouterr().err
    assert "lengths: expected" in err and str(f) in err and "Traceback" not in err


def test_all_rattlers_through_campaign_analyze(tmp_path, capsys):
    """No contact at all: exit 0, undefined scalars as null, the flags say why."""
    import json

    rng = np.random.default_rng(1)
    rows = ["1 1"] + [f"{x!r} {y!r} 1e-4" for x, y in rng.random((50, 2)).tolist()]
    f = tmp_path / "gas.txt"
    f.write_text("\n".join(rows) + "\n")
    assert cli_main(["analyze", str(f), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["N_G"] == 0 and out["N_R"] == 50 and out["E_G"] == 0.0
    assert out["z_g_mean"] is None and out["ordered_fraction"] is None
    assert out["identities_ok"] is False and out["identities"]["network_nonempty"] is False
