"""Linear response (kernels.response): elastic constants, vibrational modes, gaps and forces.

Expected values come from physics (the triangular crystal, finite strains re-minimised with
FIRE), from a dense reference written here pair by pair with its own chain rule and numpy's
pseudo-inverse, and from brute-force gap and force lists.
"""

import math
from functools import lru_cache

import numpy as np
import pytest

import kernels
import kernels.hessian
from kernels import response
from kernels.analysis import analyze
from kernels.fire import minimize
from helpers import random_configuration, triangular_crystal
from references import ref_kept_contacts, ref_moduli, ref_response


@lru_cache(maxsize=None)
def jammed(n, energy, seed, exponent=2.0, box=(1.0, 1.0)):
    return kernels.jam(n, energy, seed, exponent=exponent, box=box)


# ----------------------------------------------------------------------------- references

def _voigt(m, prefix=""):
    c = {k: m[prefix + k] if prefix + k in m else np.nan for k in ("c11", "c22", "c12", "c66", "c16", "c26")}
    return np.array([[c["c11"], c["c12"], c["c16"]], [c["c12"], c["c22"], c["c26"]],
                     [c["c16"], c["c26"], c["c66"]]])


# ----------------------------------------------------------------------------- the crystal

@pytest.mark.parametrize("nx,ny", [(8, 8), (6, 10), (12, 4)])
def test_triangular_crystal_at_vanishing_overlap(nx, ny):
    """Equal disks, harmonic, overlap 1e-10 of the contact distance: B sigma^2 = sqrt(3)/2,
    G / B = 1/2, c11 = c22 = 3 sqrt(3)/4, c66 = c12 = sqrt(3)/4 (nearest-neighbour springs of
    stiffness 1/sigma^2, every disk a centre of inversion: no non-affine relaxation)."""
    pos, rad, box = triangular_crystal(nx, ny, overlap=1e-10)
    sigma = 2 * rad[0]
    m = response.moduli(pos, rad, box)
    assert m["moduli_ok"] and m["moduli_status"] == 0
    r3 = math.sqrt(3)
    assert m["B"] * sigma**2 == pytest.approx(r3 / 2, rel=1e-7)
    assert m["G"] / m["B"] == pytest.approx(0.5, rel=1e-7)
    assert m["c11"] * sigma**2 == pytest.approx(3 * r3 / 4, rel=1e-7)
    assert m["c22"] * sigma**2 == pytest.approx(3 * r3 / 4, rel=1e-7)
    assert m["c66"] * sigma**2 == pytest.approx(r3 / 4, rel=1e-7)
    assert m["c12"] * sigma**2 == pytest.approx(r3 / 4, rel=1e-7)
    assert abs(m["c16"]) * sigma**2 < 1e-7 and abs(m["c26"]) * sigma**2 < 1e-7
    # affine: nothing relaxes
    for k in ("c11", "c22", "c12", "c66"):
        assert m[k + "_affine"] == pytest.approx(m[k], rel=1e-9)
    assert m["contact_distance"] == pytest.approx(sigma, rel=1e-15)
    # the smallest eigenvalue of the Voigt matrix [[c11, c12, 0], [c12, c22, 0], [0, 0, c66]]
    assert m["c_min"] * sigma**2 == pytest.approx(r3 / 4, rel=1e-7)
    s, counts = response.modes(pos, rad, box)
    assert s["n_zero_modes"] == 2 and s["n_unstable_modes"] == 0 and s["modes_ok"]
    assert counts.sum() == 2 * nx * ny - 2


# ----------------------------------------------------------------------------- the dense reference

CASES = [(64, 1e-4, 2.0, (1.0, 1.0), 1), (96, 1e-7, 2.5, (1.3, 0.8), 2), (64, 1e-10, 3.0, (1.0, 1.0), 3),
         (48, 1e-6, 2.0, (0.7, 1.4), 4)]


@pytest.mark.parametrize("n,energy,alpha,box,seed", CASES)
def test_moduli_against_the_dense_reference(n, energy, alpha, box, seed):
    p = jammed(n, energy, seed, alpha, box)
    C, A, stress, _ = ref_moduli(p.positions, p.radii, p.box, alpha)
    m = response.moduli(p.positions, p.radii, p.box, alpha)
    assert m["moduli_ok"] and m["moduli_residual"] < 1e-14
    scale = np.abs(C).max()
    np.testing.assert_allclose(_voigt(m), C, rtol=0, atol=1e-11 * scale)
    np.testing.assert_allclose([m["c11_affine"], m["c22_affine"], m["c12_affine"], m["c66_affine"]],
                               A[[0, 1, 0, 2], [0, 1, 1, 2]], rtol=1e-12)
    np.testing.assert_allclose([m["stress_xx"], m["stress_yy"], m["stress_xy"]], stress, rtol=1e-11,
                               atol=1e-12 * np.abs(stress).max())
    assert m["B"] == pytest.approx((C[0, 0] + C[1, 1] + 2 * C[0, 1]) / 4, rel=1e-11)
    assert m["G"] == pytest.approx((4 * C[2, 2] + C[0, 0] + C[1, 1] - 2 * C[0, 1]) / 8, rel=1e-9)
    assert m["c_min"] == pytest.approx(np.linalg.eigvalsh(C)[0], rel=1e-9, abs=1e-11 * scale)
    # the virial pressure of the analysis is minus the mean normal stress
    a = analyze(p.positions, p.radii, p.box, ["scalars"], exponent=alpha)
    assert -(m["stress_xx"] + m["stress_yy"]) / 2 == pytest.approx(a.scalars["pressure"], rel=1e-6)


def test_mixed_derivatives_are_orthogonal_to_translations():
    p = jammed(64, 1e-6, 5)
    n = len(p.radii)
    from kernels.network import network

    net = network(p.positions, p.radii, p.box)
    index, m = response._kept_index(net["rattler"])
    out = response._response_blocks_core(p.radii, net["bi"], net["bj"], net["dx"], net["dy"], index, m, 2.0)
    xi = out[4]
    assert m == n - net["rattler"].sum()
    scale = np.abs(xi).max()
    for comp in range(2):
        assert np.all(np.abs(xi[comp::2].sum(axis=0)) < 1e-12 * scale * math.sqrt(m))


def test_the_pinned_disk_does_not_matter():
    p = jammed(96, 1e-8, 6)
    base = response.moduli(p.positions, p.radii, p.box)
    m = len(p.radii) - int(kernels.analyze(p.positions, p.radii, p.box, ["scalars"]).scalars["N_R"])
    for pin in (1, m // 3, m - 1):
        other = response.moduli(p.positions, p.radii, p.box, pin=pin)
        np.testing.assert_allclose(_voigt(other), _voigt(base), rtol=0,
                                   atol=1e-11 * np.abs(_voigt(base)).max())
    with pytest.raises(ValueError, match="pin"):
        response.moduli(p.positions, p.radii, p.box, pin=m)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_translation_and_relabelling(seed):
    p = jammed(64, 1e-7, 7)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(p.radii))
    shifted = (p.positions + rng.random(2) * p.box)[perm]
    if seed == 2:
        shifted = shifted + 3 * p.box  # unwrapped
    a = response.moduli(p.positions, p.radii, p.box)
    b = response.moduli(shifted, p.radii[perm], p.box)
    np.testing.assert_allclose(_voigt(b), _voigt(a), rtol=0, atol=1e-10 * np.abs(_voigt(a)).max())
    sa, ca = response.modes(p.positions, p.radii, p.box)
    sb, cb = response.modes(shifted, p.radii[perm], p.box)
    assert sb["omega_min"] == pytest.approx(sa["omega_min"], rel=1e-8)
    assert np.abs(ca - cb).sum() <= 2  # a frequency within rounding of a bin edge may move


# ----------------------------------------------------------------------------- finite strain

def _strained_energies(pos, rad, box, alpha, eps, tol):
    """Energies re-minimised after stretching box and positions by 1 +- eps along x, along
    y, and isotropically (the same as every radius divided by 1 +- eps)."""
    out = {}
    for name in ("x", "y", "iso"):
        us = []
        for s in (1, -1):
            f = np.array([1.0 + s * eps if name == "x" else 1.0, 1.0 + s * eps if name == "y" else 1.0])
            r = rad / (1.0 + s * eps) if name == "iso" else rad
            res = minimize(pos * f, r, box * f, alpha, force_tolerance=tol, max_steps=200_000)
            assert res.status == "converged"
            us.append(res.energy)
        out[name] = us
    return out


@pytest.mark.parametrize("n,energy,alpha,box", [pytest.param(256, 1e-6, 2.0, (1.0, 1.0), marks=pytest.mark.slow),
                                           (128, 1e-5, 2.5, (1.3, 0.8))])
def test_finite_strain_with_reminimisation(n, energy, alpha, box):
    """Central second differences of the re-minimised energy per box area against c11, c22
    and 4 B; the first difference against the stress."""
    p = jammed(n, energy, 5, alpha, box)
    tol = 1e-10
    r0 = minimize(p.positions, p.radii, p.box, alpha, force_tolerance=tol, max_steps=200_000)
    assert r0.status == "converged"
    pos, rad, b = r0.positions, p.radii, np.asarray(p.box, float)
    m = response.moduli(pos, rad, b, alpha)
    eps = 1e-6
    u = _strained_energies(pos, rad, b, alpha, eps, tol)
    area = b.prod()

    def second(name):
        return (u[name][0] + u[name][1] - 2 * r0.energy) / (area * eps**2)

    assert second("x") == pytest.approx(m["c11"], rel=1e-5)
    assert second("y") == pytest.approx(m["c22"], rel=1e-5)
    assert second("iso") == pytest.approx(4 * m["B"], rel=1e-5)
    assert (u["x"][0] - u["x"][1]) / (2 * eps * area) == pytest.approx(m["stress_xx"], rel=1e-5)
    # the non-affine relaxation matters: the affine constants are far off
    assert m["B_affine"] > 1.2 * m["B"]


def _lattice_energy(pos, rad, M, alpha):
    """Energy, gradient and dense Hessian of disks in the periodic cell spanned by the columns
    of ``M`` (any shape: a sheared box too), minimum image in lattice coordinates."""
    n = len(rad)
    d = pos[None, :, :] - pos[:, None, :]
    f = d @ np.linalg.inv(M).T
    d = (f - np.round(f)) @ M.T
    i, j = np.triu_indices(n, 1)
    d = d[i, j]
    r = np.hypot(d[:, 0], d[:, 1])
    s = rad[i] + rad[j]
    c = r < s
    i, j, d, r, s = i[c], j[c], d[c], r[c], s[c]
    x = 1 - r / s
    v1 = -x ** (alpha - 1) / s
    v2 = (alpha - 1) * x ** (alpha - 2) / s**2
    u = d / r[:, None]
    g = np.zeros_like(pos)
    np.add.at(g, j, v1[:, None] * u)
    np.add.at(g, i, -v1[:, None] * u)
    H = np.zeros((2 * n, 2 * n))
    for k in range(len(i)):
        nn = np.outer(u[k], u[k])
        K = v2[k] * nn + v1[k] / r[k] * (np.eye(2) - nn)
        for a, b, sign in ((i[k], i[k], 1), (j[k], j[k], 1), (i[k], j[k], -1), (j[k], i[k], -1)):
            H[2 * a:2 * a + 2, 2 * b:2 * b + 2] += sign * K
    return float(np.sum(x**alpha / alpha)), g, H


def _relaxed(pos, rad, M, alpha):
    """The energy after Newton steps to the nearest minimum (translations projected out):
    converges quadratically, so the energy is exact to rounding."""
    p = pos.copy()
    for _ in range(30):
        U, g, H = _lattice_energy(p, rad, M, alpha)
        w, v = np.linalg.eigh(H)
        keep = np.argsort(np.abs(w))[2:]
        step = -(v[:, keep] / w[keep]) @ (v[:, keep].T @ g.ravel())
        p = p + step.reshape(-1, 2)
        if np.abs(step).max() < 1e-14 * np.abs(p).max():
            break
    assert w[keep].min() > 0
    return _lattice_energy(p, rad, M, alpha)[0]


@pytest.mark.parametrize("n,energy,alpha,seed", [(32, 1e-3, 2.0, 4), (40, 1e-4, 2.5, 1)])
def test_shear_and_mixed_strains_with_exact_relaxation(n, energy, alpha, seed):
    """Every constant, shear included, from the relaxed energy of sheared periodic cells
    (``F`` applied to the cell and the positions, then Newton on the positions): second
    differences along e1, e2, e3 and along e1 + e2 (c12) and e1 + e3 (c16) against C."""
    p = jammed(n, energy, seed, alpha)
    pos, rad, box = np.asarray(p.positions), np.asarray(p.radii), np.asarray(p.box)
    keep = ~kernels.analyze(pos, rad, box, ["scalars"]).rattler
    pos, rad = pos[keep], rad[keep]
    m = response.moduli(pos, rad, box, alpha)
    C = _voigt(m)
    M0 = np.diag(box)
    U0 = _relaxed(pos, rad, M0, alpha)
    h = 1e-6
    for e in ((1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1)):
        e = np.asarray(e, float)
        us = []
        for sign in (1, -1):
            F = np.eye(2) + sign * h * np.array([[e[0], e[2] / 2], [e[2] / 2, e[1]]])
            us.append(_relaxed(pos @ F.T, rad, F @ M0, alpha))
        second = (us[0] + us[1] - 2 * U0) / (box.prod() * h**2)
        assert second == pytest.approx(e @ C @ e, rel=1e-4, abs=1e-4 * np.abs(C).max()), e


# ----------------------------------------------------------------------------- failures

def _square_lattice(n, overlap):
    a = 1.0 / n
    j, i = np.divmod(np.arange(n * n), n)
    pos = np.stack([(i + 0.5) * a, (j + 0.5) * a], axis=1)
    return pos, np.full(n * n, 0.5 * a * (1 + overlap)), np.array([1.0, 1.0])


def test_an_unstable_network_gives_nan_and_a_flag():
    """A compressed square lattice: rows slide under their own prestress (negative modes);
    no disk is a rattler, the Hessian is not positive definite."""
    pos, rad, box = _square_lattice(8, 1e-4)
    H, _, _, _, alive = ref_response(pos, rad, box, 2.0)
    assert alive.all() and np.linalg.eigvalsh(H)[0] < -1e-6
    m = response.moduli(pos, rad, box)
    assert m["moduli_ok"] is False and m["moduli_status"] == 2
    assert all(math.isnan(m[k]) for k in ("c11", "c22", "c12", "c66", "B", "G", "c_min"))
    assert m["B_affine"] > 0  # the affine part is still defined
    s, counts = response.modes(pos, rad, box)
    assert s["n_unstable_modes"] > 0 and not s["modes_ok"]
    s, _ = response.modes(pos, rad, box, dense_max=10)  # shift-invert cannot factor it
    assert not s["modes_ok"] and math.isnan(s["n_unstable_modes"]) and math.isnan(s["omega_min"])


def test_an_unrelaxed_configuration_is_flagged_not_trusted():
    """Random disks at phi = 1 after 100 FIRE steps (far from a minimum): the non-rattler
    network survives, its Hessian has negative eigenvalues; no constants come out."""
    pos, rad, box = random_configuration(64, 1, phi=1.0)
    pos = minimize(pos, rad, box, max_steps=100).positions
    H, _, _, _, alive = ref_response(pos, rad, box, 2.0)
    w = np.linalg.eigvalsh(H)
    assert alive.sum() == 64 and w[0] < -1e-3 * w[-1]
    m = response.moduli(pos, rad, box)
    assert not m["moduli_ok"] and m["moduli_status"] == 2 and math.isnan(m["B"])
    s, _ = response.modes(pos, rad, box)
    assert s["n_unstable_modes"] == np.sum(w < -1e-10 * s["omega_scale"] ** 2) > 0


def test_too_few_nonrattlers():
    pos = np.array([[0.1, 0.1], [0.6, 0.6], [0.3, 0.8]])
    m = response.moduli(pos, np.full(3, 0.01), (1.0, 1.0))
    assert m["moduli_status"] == 1 and not m["moduli_ok"] and math.isnan(m["G"])
    s, c = response.modes(pos, np.full(3, 0.01), (1.0, 1.0))
    assert not s["modes_ok"] and c.sum() == 0


# ----------------------------------------------------------------------------- modes

@pytest.mark.parametrize("n,energy,alpha,box,seed", CASES[:3])
def test_spectrum_against_the_dense_reference(n, energy, alpha, box, seed):
    p = jammed(n, energy, seed, alpha, box)
    H, _, _, _, alive = ref_response(p.positions, p.radii, p.box, alpha)
    w = np.linalg.eigvalsh(H)
    s, counts = response.modes(p.positions, p.radii, p.box, alpha)
    kmean = s["omega_scale"] ** 2
    # <k>: the mean V'' over the network's contacts
    _, pairs = ref_kept_contacts(p.positions, p.radii, p.box)
    ks = [(alpha - 1) * (1 - np.hypot(*d) / (p.radii[i] + p.radii[j])) ** (alpha - 2)
          / (p.radii[i] + p.radii[j]) ** 2 for i, j, d in pairs]
    assert kmean == pytest.approx(np.mean(ks), rel=1e-12)
    zero = np.abs(w) <= 1e-10 * kmean
    assert zero.sum() == 2 and s["n_zero_modes"] == 2 and s["n_unstable_modes"] == 0
    assert s["modes_dense"] and s["modes_ok"] and s["n_modes"] == 2 * alive.sum()
    assert s["omega_min"] == pytest.approx(math.sqrt(w[~zero][0]), rel=1e-9)
    ref = np.histogram(np.sqrt(w[~zero]) / math.sqrt(kmean), response.RESPONSE_BINS["omega"])[0]
    assert np.abs(ref - counts).sum() <= 2 and counts.sum() == len(w) - 2
    # beyond the dense limit: the lowest modes by shift-invert, no density of states
    low, lc = response.modes(p.positions, p.radii, p.box, alpha, dense_max=8, low_modes=10)
    assert not low["modes_dense"] and low["n_modes"] == 10 and lc.sum() == 0
    assert low["n_zero_modes"] == 2 and low["omega_min"] == pytest.approx(s["omega_min"], rel=1e-8)


def test_shift_invert_finds_the_lowest_eigenvalues():
    p = jammed(128, 1e-9, 8)
    H, _, _, _, alive = ref_response(p.positions, p.radii, p.box, 2.0)
    w = np.linalg.eigvalsh(H)
    from kernels.network import network

    net = network(p.positions, p.radii, p.box)
    index, m = response._kept_index(net["rattler"])
    pi, pj, off, diag, *_ = response._response_blocks_core(p.radii, net["bi"], net["bj"], net["dx"],
                                                           net["dy"], index, m, 2.0)
    pos = np.asarray(p.positions)[~net["rattler"]] % p.box
    ev = response._low_eigenvalues(pos, p.box, pi, pj, off, diag, 12, 1e-8 * diag[:, 0].mean())
    np.testing.assert_allclose(ev, w[:12], rtol=1e-8, atol=1e-9 * w[-1])


# ----------------------------------------------------------------------------- gaps and forces

def test_gaps_and_forces_against_brute_force():
    p = jammed(128, 1e-10, 9)
    pos, rad, box = np.asarray(p.positions), np.asarray(p.radii), np.asarray(p.box)
    alive, pairs = ref_kept_contacts(pos, rad, box)
    gaps = []
    n = len(rad)
    for i in range(n):
        for j in range(i + 1, n):
            if not (alive[i] and alive[j]):
                continue
            d = pos[j] - pos[i]
            d = d - box * np.round(d / box)
            r = np.hypot(*d)
            s = rad[i] + rad[j]
            if s <= r < 2 * s:
                gaps.append(r / s - 1)
    z = np.zeros(n, int)
    for i, j, _ in pairs:
        z[i] += 1
        z[j] += 1
    f = np.array([(1 - np.hypot(*d) / (rad[i] + rad[j])) / (rad[i] + rad[j]) for i, j, d in pairs])
    ext = np.array([z[i] != 3 and z[j] != 3 for i, j, _ in pairs])
    a = analyze(pos, rad, box, ["gaps"])
    e = a.bin_edges
    # the overlaps of the weakest contacts (1e-7 of s) are known to about 1e-9: a value
    # within rounding of a log-spaced edge may land in the next bin
    for name, ref in (("gap", gaps), ("force", f / f.mean()), ("force_extended", f[ext] / f.mean())):
        want = np.histogram(ref, e[name])[0]
        assert a.histograms[name].sum() == want.sum() == len(ref) > 0, name
        assert np.abs(a.histograms[name] - want).sum() <= 2, name
    assert a.scalars["gap_min"] == pytest.approx(min(gaps), rel=1e-9)
    assert a.scalars["force_min"] == pytest.approx(f.min() / f.mean(), rel=1e-6)
    assert a.scalars["buckler_fraction"] == pytest.approx(np.mean(z[alive] == 3))
    sg, hg = response.gaps(pos, rad, box)  # the checked wrapper: the same
    assert sg == {k: a.scalars[k] for k in sg} and all(np.array_equal(hg[k], a.histograms[k]) for k in hg)
    assert e["gap"][0] == 0 and e["gap"][1] == 1e-16 and e["gap"][-1] == 1.0


# ----------------------------------------------------------------------------- kernels.analyze

def test_analyze_computes_the_response_only_when_asked():
    p = jammed(64, 1e-6, 1)
    base = analyze(p.positions, p.radii, p.box)
    assert not set(response.MODULI_KEYS) & set(base.scalars)
    assert "omega" not in base.histograms and "gap" not in base.histograms
    full = analyze(p.positions, p.radii, p.box, ["moduli", "modes", "gaps"])
    assert set(response.MODULI_KEYS + response.MODES_KEYS + response.GAPS_KEYS) <= set(full.scalars)
    assert set(full.histograms) == {"omega", "gap", "force", "force_extended"}
    assert full.scalars["G"] == response.moduli(p.positions, p.radii, p.box)["G"]
    for k, v in base.scalars.items():  # the network's scalars do not change
        assert full.scalars[k] == v or (isinstance(v, float) and math.isnan(v)), k


def test_the_three_solves_at_once_are_three_solves():
    """``_solve3_core`` reads the factor once for three right-hand sides: the same bits as
    ``kernels.sparse.solve`` column by column."""
    from kernels import sparse

    p = jammed(96, 1e-6, 2)
    hb = kernels.hessian.hessian(p.positions, p.radii, p.box, rattlers=False)
    diag = hb.diag.copy()
    diag[:, 0] += 1e-3 * diag[:, 0].mean()
    diag[:, 2] += 1e-3 * diag[:, 0].mean()
    sym = sparse.analyse(np.asarray(p.positions)[hb.nodes] % p.box, p.box, hb.pairs_i, hb.pairs_j)
    lval = sparse.factor(sym, diag, hb.offdiag)
    b = np.random.default_rng(1).standard_normal((2 * len(hb.nodes), 3))
    x = response._solve3_core(sym.perm, sym.sup_first, sym.upd_ptr, sym.upd_rows, sym.l_ptr, lval, b)
    for c in range(3):
        assert np.array_equal(x[:, c], sparse.solve(sym, lval, b[:, c].copy()))


def test_campaign_analyze_reports_the_response(tmp_path, capsys):
    import json

    from campaign.cli import main as cli_main

    p = jammed(64, 1e-6, 1)
    np.savez(tmp_path / "p.npz", positions=p.positions, radii=p.radii, box=p.box)
    assert cli_main(["analyze", str(tmp_path / "p.npz"), "--observables", "moduli,modes,gaps", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    ref = response.moduli(p.positions, p.radii, p.box)
    assert out["G"] == ref["G"] and out["moduli_ok"] is True and out["n_zero_modes"] == 2
    assert set(out["histograms"]) == {"omega", "gap", "force", "force_extended"}
    assert sum(out["histograms"]["omega"]["counts"]) == 2 * out["N_G"] - 2
    assert cli_main(["analyze", str(tmp_path / "p.npz"), "--observables", "all", "--json"]) == 0
    assert "c66" in json.loads(capsys.readouterr().out)
