"""The tilted periodic cell (kernels.space) and the shear-stabilised minimum (kernels.cellrelax).

Checks: the nearest image against a brute-force search over lattice images; one packing
described in two cells of the same lattice (a tilt changed by a whole period) analyses the
same; a triangular crystal in its own tilted cell against the same crystal in a rectangular
box; the shear stress against finite differences of the energy in the tilt; a
shear-stabilised packing is a minimum of the energy in the positions and the cell's shape
(the Hessian with the cell's rows, by finite differences of the exact gradient, is positive
definite but for the two translations); refusals.
"""

from functools import lru_cache

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from numba import njit

import kernels
from kernels.analysis import analyze
from kernels.cells import candidate_pairs
from kernels.names import DEFAULT_OBSERVABLES
from kernels.network import contact_bonds
from kernels.potential import energy, forces, stress_from_bonds
from kernels.space import separation, wrap
from references import ref_nearest_image


@njit
def _sep(dx, dy, box):
    return separation(dx, dy, box)


@lru_cache(maxsize=None)
def shear_packing(n, e, seed):
    return kernels.jam(n, e, seed, cell="shear")


@settings(deadline=None, max_examples=200)
@given(lx=st.floats(0.5, 2.0), ly=st.floats(0.5, 2.0), xy=st.floats(-1.0, 1.0),
       fx=st.floats(-2.0, 2.0), fy=st.floats(-2.0, 2.0), r=st.floats(0.0, 0.249),
       angle=st.floats(0.0, 2 * np.pi))
def test_separation_finds_the_only_image_in_range(lx, ly, xy, fx, fy, r, angle):
    """A separation of length r < min(Lx, Ly)/4 shifted by any lattice vector is found back."""
    box = np.array([lx, ly, xy])
    true = r * min(lx, ly) * np.array([np.cos(angle), np.sin(angle)])
    k, m = round(fy), round(fx)
    dx = true[0] + m * lx + k * xy * ly
    dy = true[1] + k * ly
    got = np.array(_sep(dx, dy, box))
    assert np.allclose(got, true, atol=1e-12)
    assert np.allclose(got, ref_nearest_image(dx, dy, box), atol=1e-12)


def test_wrap_folds_by_lattice_vectors_into_the_rectangle():
    rng = np.random.default_rng(0)
    box = np.array([1.3, 0.8, -0.37])
    p = rng.uniform(-5, 5, (200, 2))
    w = wrap(p, box)
    assert np.all(w >= 0) and np.all(w < box[:2])
    k = (p[:, 1] - w[:, 1]) / box[1]
    m = (p[:, 0] - w[:, 0] - k * box[2] * box[1]) / box[0]
    assert np.allclose(k, np.round(k), atol=1e-9) and np.allclose(m, np.round(m), atol=1e-9)


def _same_analysis(a, b, rtol=1e-9):
    for k, v in a.scalars.items():
        w = b.scalars[k]
        if k == "gamma":
            continue
        if isinstance(v, float) and not np.isnan(v):
            assert w == pytest.approx(v, rel=rtol, abs=1e-13), k
        elif isinstance(v, float):
            assert np.isnan(w), k
        else:
            assert v == w, k
    assert a.identities == b.identities
    for name, c in a.histograms.items():
        assert np.abs(c - b.histograms[name]).sum() <= 2, name


@pytest.mark.parametrize("shift", [1.0, -1.0])
def test_a_whole_period_of_tilt_is_the_same_lattice(shift):
    """Rectangular (xy = 0) and xy = +-1 describe one lattice: same analysis, same pairs."""
    p = kernels.jam(64, 1e-6, 3)
    obs = list(DEFAULT_OBSERVABLES) + ["moduli"]
    a = analyze(p.positions, p.radii, p.box, obs)
    tilted = np.array([p.box[0], p.box[1], shift])
    b = analyze(p.positions, p.radii, tilted, obs)
    _same_analysis(a, b)
    assert b.scalars["gamma"] == shift and a.scalars["gamma"] == 0.0
    pa = candidate_pairs(p.positions, p.radii, p.box, 0.05)
    pb = candidate_pairs(p.positions, p.radii, tilted, 0.05)
    assert all(np.array_equal(u, v) for u, v in zip(pa, pb))


def test_shear_packing_analyses_the_same_after_a_lattice_reduction():
    p = shear_packing(48, 1e-6, 2)
    Lx, Ly, xy = p.box
    other = np.array([Lx, Ly, xy - np.sign(xy) * Lx / Ly])  # b -> b -+ a: the same lattice
    obs = list(DEFAULT_OBSERVABLES) + ["moduli"]
    _same_analysis(analyze(p.positions, p.radii, p.box, obs, cell="shear"),
                   analyze(p.positions, p.radii, other, obs, cell="shear"))


def _triangular(m, d, overlap):
    """m x m disks of diameter d (1 + overlap) on a triangular lattice of spacing d, in its own
    tilted cell a = (m d, 0), b = m (d/2, d sqrt3/2): xy = 1/sqrt3."""
    i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    pos = np.stack([d * (i + 0.5 * j), d * np.sqrt(3) / 2 * j], axis=-1).reshape(-1, 2)
    Lx, Ly = m * d, m * d * np.sqrt(3) / 2
    box = np.array([Lx, Ly, 0.5 * Lx / Ly])
    return pos, np.full(m * m, 0.5 * d * (1 + overlap)), box


def _triangular_rect(m, d, overlap):
    """The same crystal (m even) in a rectangular box of m rows of m disks."""
    i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    pos = np.stack([d * (i + 0.5 * (j % 2)), d * np.sqrt(3) / 2 * j], axis=-1).reshape(-1, 2)
    return pos, np.full(m * m, 0.5 * d * (1 + overlap)), np.array([m * d, m * d * np.sqrt(3) / 2])


def test_triangular_crystal_in_its_tilted_cell():
    m, d, x = 8, 0.1, 1e-3
    pos, rad, box = _triangular(m, d, x)
    obs = list(DEFAULT_OBSERVABLES) + ["moduli"]
    a = analyze(pos, rad, box, obs)
    s = a.scalars
    n = m * m
    # exact: six contacts per disk (N_C counts both ends), every void a triangle; the grain
    # polygon is the hexagon of contact points at d/2: 3 sqrt3 d^2 / 8 of the sqrt3 d^2 / 2 per disk
    assert s["N_C"] == 6 * n and s["N_V"] == 2 * n and s["psi_O"] == 1.0 and s["N_R"] == 0
    assert s["identities_ok"]
    assert s["A_G"] == pytest.approx(0.75, rel=1e-12) and s["A_V"] == pytest.approx(0.25, rel=1e-11)
    # harmonic contact force f = x / s at overlap x: p = (1 / 2A) 3 n r f
    sig = d * (1 + x)
    p_exact = 3 * n * d * (x / (1 + x)) / sig / (2 * box[0] * box[1])
    assert s["pressure"] == pytest.approx(p_exact, rel=1e-12)
    assert abs(s["sigma_xy"]) <= 1e-12 * p_exact  # isotropic stress
    # a Bravais lattice does not relax: the moduli are the affine ones, and equal to those of
    # the same crystal in a rectangular box
    for k in ("c11", "c22", "c12", "c66"):
        assert s[k] == pytest.approx(s[k + "_affine"], rel=1e-9), k
    r = analyze(*_triangular_rect(m, d, x), obs).scalars
    for k in ("pressure", "c11", "c22", "c12", "c66", "B", "G", "A_G", "phi", "E_G"):
        assert s[k] == pytest.approx(r[k], rel=1e-9), k
    # the hexagonal symmetry: c11 = c22, no shear couplings
    assert s["c11"] == pytest.approx(s["c22"], rel=1e-9)
    assert abs(s["c16"]) <= 1e-9 * s["c11"] and abs(s["c26"]) <= 1e-9 * s["c11"]
    # exact Born moduli of the harmonic nearest-neighbour crystal: contact stiffness k = 1/sigma^2,
    # tension f = (1 - d/sigma)/sigma; three bonds per disk whose n_x^2 n_y^2 sum to 3/8 give
    # c66 = (sqrt3/4)(k - f/d); the Cauchy relations hold up to the pressure terms of C's
    # convention: c12 = c66 + p/2, c11 = 3 c66 + p/2
    k, f = 1 / sig ** 2, (1 - d / sig) / sig
    assert s["c66"] == pytest.approx(np.sqrt(3) / 4 * (k - f / d), rel=1e-9)
    assert s["c12"] == pytest.approx(s["c66"] + p_exact / 2, rel=1e-9)
    assert s["c11"] == pytest.approx(3 * s["c66"] + p_exact / 2, rel=1e-9)


def _shear_energy(pos, rad, box, h):
    """Energy after a change h of the tilt, fractional coordinates fixed."""
    q = pos.copy()
    q[:, 0] += h * pos[:, 1]
    return energy(q, rad, np.array([box[0], box[1], box[2] + h]))


@pytest.mark.parametrize("cell", ["fixed", "shear"])
def test_shear_stress_is_minus_the_energy_derivative_in_the_tilt(cell):
    p = kernels.jam(48, 1e-5, 4, cell=cell)
    box = np.append(np.asarray(p.box, float), 0.0)[:3]
    A = box[0] * box[1]
    h = 1e-6
    dU = (_shear_energy(p.positions, p.radii, box, h)
          - _shear_energy(p.positions, p.radii, box, -h)) / (2 * h)
    s = analyze(p.positions, p.radii, p.box, ["scalars"], cell=cell).scalars
    assert s["sigma_xy"] == pytest.approx(p.sigma_xy, rel=1e-9, abs=1e-15)
    assert -dU / A == pytest.approx(s["sigma_xy"], rel=1e-5, abs=1e-6 * s["pressure"])
    if cell == "fixed":  # a fixed box keeps a shear stress of the order of the pressure / sqrt(N)
        assert abs(s["sigma_xy"]) > 1e-4 * s["pressure"]


def _gradient(pos, rad, box, g, e):
    """Gradient of the energy in (positions, gamma, eps) at the deformation F = [[e^e, g], [0,
    e^-e]] of the configuration (positions and cell)."""
    F = np.array([[np.exp(e), g], [0.0, np.exp(-e)]])
    q = pos @ F.T
    H = F @ np.array([[box[0], box[2] * box[1]], [0.0, box[1]]])
    b = np.array([H[0, 0], H[1, 1], H[0, 1] / H[1, 1]])
    f = forces(q, rad, b)
    bi, bj, dx, dy = contact_bonds(q, rad, b)
    sxx, syy, sxy = stress_from_bonds(rad, bi, bj, dx, dy, 2.0)
    # dU/dg and dU/de at fixed fractional coordinates, from the deformed state: the derivative
    # of F(g, e) F0^-1 at the point, applied to the deformed separations
    ee = np.exp(e)
    dFdg = np.array([[0.0, 1.0], [0.0, 0.0]]) @ np.linalg.inv(F)
    dFde = np.array([[ee, 0.0], [0.0, -1.0 / ee]]) @ np.linalg.inv(F)
    S = np.array([[sxx, sxy], [sxy, syy]])
    return np.concatenate([-(f @ F).ravel(), [-np.sum(S * dFdg), -np.sum(S * dFde)]])


@pytest.mark.parametrize("n,e,seed", [(32, 1e-6, 1), (32, 1e-9, 2), (48, 1e-7, 3)])
def test_shear_packing_is_a_minimum_in_positions_and_cell(n, e, seed):
    p = shear_packing(n, e, seed)
    assert p.converged
    box = np.asarray(p.box, float)
    pos = np.asarray(p.positions, float)
    rad = np.asarray(p.radii, float)
    a = analyze(pos, rad, box, ["scalars", "moduli"], cell="shear")
    # the rattlers out of the packing (fixing them instead would pin it by their contacts'
    # stiffness): the energy of the rest in its positions and the cell
    keep = np.flatnonzero(~a.rattler)
    pos, rad, n = pos[keep], rad[keep], len(keep)
    dof = np.arange(2 * n + 2)
    h = 1e-8 * box[0]
    hess = np.zeros((len(dof), len(dof)))
    for c, k in enumerate(dof):
        step = np.zeros(2 * n + 2)
        step[k] = h
        d = []
        for sgn in (1, -1):
            q = pos + sgn * step[:2 * n].reshape(-1, 2)
            d.append(_gradient(q, rad, box, sgn * step[2 * n], sgn * step[2 * n + 1]))
        hess[:, c] = ((d[0] - d[1]) / (2 * h))[dof]
    hess = 0.5 * (hess + hess.T)
    ev = np.linalg.eigvalsh(hess)
    scale = np.abs(ev).max()
    # two translations are zero modes; everything else strictly positive
    assert np.all(ev[:2] > -1e-6 * scale) and np.all(np.abs(ev[:2]) < 1e-6 * scale)
    assert ev[2] > 1e-6 * scale, ev[:4]
    s = a.scalars
    assert s["G"] > 0 and s["c66"] > 0 and s["c11"] + s["c22"] - 2 * s["c12"] > 0
    # stress residuals within the force tolerance, isostatic count of the ensemble
    assert abs(s["sigma_xy"]) <= 1e-6 * s["pressure"]
    assert abs(s["stress_xx"] - s["stress_yy"]) <= 2e-6 * s["pressure"]
    assert s["N_C"] // 2 >= 2 * s["N_G"] + 1 and s["delta_Z"] >= 0


@pytest.mark.parametrize("n,e,seed", [(64, 1e-12, 7), (128, 1e-4, 8), (24, 1e-8, 9)])
def test_shear_packings_are_stable_at_every_size_and_energy(n, e, seed):
    p = shear_packing(n, e, seed)
    assert p.converged, p.status
    assert p.box.shape == (3,) and abs(p.gamma * p.box[1]) <= p.box[0] / 2 and p.gamma == p.box[2]
    assert p.box[0] * p.box[1] == pytest.approx(1.0, rel=1e-12)
    assert abs(p.sigma_xy) <= 1e-6 * p.pressure
    s = analyze(p.positions, p.radii, p.box, ["scalars", "moduli"], cell="shear").scalars
    assert s["moduli_ok"] and s["G"] > 0 and s["c66"] > 0
    assert s["E_G"] == pytest.approx(p.energy, rel=1e-9)


def test_fixed_cell_is_unchanged_and_reports_zero_tilt():
    p = kernels.jam(32, 1e-6, 1)
    q = kernels.jam(32, 1e-6, 1, cell="fixed")
    assert p.box.shape == (2,) and p.gamma == 0.0
    assert p.positions.tobytes() == q.positions.tobytes() and p.sigma_xy == q.sigma_xy


def test_shear_ladder_keeps_the_cell():
    p = shear_packing(32, 1e-6, 1)
    q = kernels.jam(32, 1e-8, 0, start=p, cell="shear")
    assert q.converged and q.box.shape == (3,)
    assert q.box[0] * q.box[1] == pytest.approx(1.0, rel=1e-12)
    assert abs(q.sigma_xy) <= 1e-6 * q.pressure
    # the arrays with their cell (as a campaign's worker passes them) start the same search
    r = kernels.jam(32, 1e-8, 0, start=(p.positions, p.radii, p.species, p.box), cell="shear")
    assert r.positions.tobytes() == q.positions.tobytes() and r.box.tobytes() == q.box.tobytes()
    # a tilted start is refused in a fixed cell, and in a cell of another area
    with pytest.raises(ValueError, match="start: expected a packing in the box"):
        kernels.jam(32, 1e-8, 0, start=p)
    with pytest.raises(ValueError, match="start: expected a cell of area"):
        kernels.jam(32, 1e-8, 0, start=(p.positions, p.radii, p.species, 2 * p.box), cell="shear")


@pytest.mark.parametrize("kw,match", [
    (dict(cell="sheared"), "cell: expected one of"),
    (dict(cell="shear", minimizer="cg"), "cell: cell 'shear'"),
    (dict(cell="shear", endgame="newton"), "cell: cell 'shear'"),
    (dict(cell="shear", route="pressure"), "cell: cell 'shear'"),
])
def test_refusals_of_bad_cell_settings(kw, match):
    with pytest.raises(ValueError, match=match):
        kernels.jam(16, 1e-6, 0, **kw)


@pytest.mark.parametrize("box,match", [
    ([1.0, 1.0, 1.5], "tilt factor"),
    ([1.0, 1.0, 0.2, 0.0], "shape"),
    ([1.0, -1.0, 0.2], "positive"),
    ([1.0, 1.0, np.nan], "finite"),
])
def test_refusals_of_bad_cells(box, match):
    pos = np.random.default_rng(0).random((16, 2))
    with pytest.raises(ValueError, match=match):
        analyze(pos, np.full(16, 0.05), box)


def test_analyze_refuses_an_unknown_ensemble():
    pos = np.random.default_rng(0).random((16, 2))
    with pytest.raises(ValueError, match="cell: expected one of"):
        analyze(pos, np.full(16, 0.05), [1.0, 1.0], cell="tilted")
