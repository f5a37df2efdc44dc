"""The Newton endgame (kernels.newton): it lands on FIRE's minimum, never climbs, ends at a
certified minimum, is reproducible, and its settings are checked."""

import numpy as np
import pytest

import kernels
from kernels import newton
from kernels.fire import _fire_core
from kernels.minimiser import _dt_for, _verlet_rows, nonrattlers
from kernels.hessian import hessian
from kernels.linesearch import energy_resolution
from kernels.network import network
from kernels.potential import _energy_forces_rows, energy
from kernels.space import _as_box


def _perturbed(n, e, seed, amplitude):
    """A FIRE packing, its radii grown a little (a step of the O'Hern search) and its positions
    shaken by ``amplitude`` typical overlaps: a minimisation Newton can finish."""
    p = kernels.jam(n, e, seed=seed)
    rng = np.random.default_rng(seed)
    x = np.sqrt(e)
    pos = np.array(p.positions) + rng.standard_normal((n, 2)) * amplitude * x * 2 * p.radii.mean()
    rad, box = np.array(p.radii) * (1 + 0.3 * x), _as_box(p.box)
    # FIRE until the residual is below Newton's hand-over level: both methods start from here
    md = 2 * rad.mean()
    _fire_core(pos, rad, box, 2.0, 0.3 * newton.HANDOFF, 2_000_000, 0.3 * md,
               _dt_for(rad, 2.0, energy(pos, rad, box) / n), 0.0)
    return pos, rad, box


def _minimize(method, pos, rad, box, tol=1e-9):
    pos = pos.copy()
    md = 2 * rad.mean()
    dt0 = _dt_for(rad, 2.0, energy(pos, rad, box) / len(rad))
    if method == "fire":
        r = _fire_core(pos, rad, box, 2.0, tol, 2_000_000, 0.3 * md, dt0, 0.0)
    else:
        r = newton._fire_newton(pos, rad, box, 2.0, tol, 2_000_000, 0.3 * md, dt0, 0.0,
                                newton.PATTERN_SKIN * md)
    return pos, r


@pytest.mark.slow
def test_newton_reaches_fires_minimum():
    """From the same start (a jammed packing compressed by a third of a typical overlap and
    shaken by 0.3 of one, relaxed by FIRE to the hand-over residual) Newton lands on FIRE's
    minimum: the same contact network, the load-bearing disks where FIRE put them within what
    the tolerance allows. Where the start lies near a rearrangement the two may fall into
    neighbouring minima (one seed in twelve here); both are then minima of nearly equal energy."""
    same = 0
    for seed in range(1, 13):
        pos, rad, box = _perturbed(64, 1e-8, seed, amplitude=0.3)
        p_fire, r_fire = _minimize("fire", pos, rad, box)
        p_newt, r_newt = _minimize("newton", pos, rad, box)
        assert r_fire[0] == r_newt[0] == 0
        assert r_newt[7] > 0, "Newton never took over"
        assert abs(r_newt[3] - r_fire[3]) <= 1e-4 * r_fire[3]
        n_f, n_n = network(p_fire, rad, box), network(p_newt, rad, box)
        if not (np.array_equal(n_f["bi"], n_n["bi"]) and np.array_equal(n_f["bj"], n_n["bj"])):
            continue
        same += 1
        alive = nonrattlers(p_fire, rad, box)
        assert np.array_equal(alive, nonrattlers(p_newt, rad, box))
        # a residual force tol <f> displaces a disk by about tol <f> / (k lambda_min / k_max)
        d = p_newt - p_fire
        d -= box[:2] * np.round(d / box[:2])
        d -= d[alive].mean(axis=0)  # the translations are free
        assert np.abs(d[alive]).max() < 1e-6 * 2 * rad.mean()
        assert abs(r_fire[3] - r_newt[3]) <= 1e-9 * r_fire[3]
    assert same >= 10


@pytest.mark.slow
def test_an_accepted_step_never_raises_the_energy():
    pos, rad, box = _perturbed(128, 1e-10, 4, amplitude=3.0)
    md = 2 * rad.mean()
    dt0 = _dt_for(rad, 2.0, 1e-10)
    # FIRE until Newton may start, then one Newton iteration at a time
    _fire_core(pos, rad, box, 2.0, 1e-3, 2_000_000, 0.3 * md, dt0, 0.0)
    energies = [energy(pos, rad, box)]
    steps = 0
    for _ in range(40):
        st, it, nf, e, w, res, nc, fa, sy = newton._newton_core(pos, rad, box, 2.0, 1e-10, 1,
                                                                newton.PATTERN_SKIN * md, 0.0)
        steps += it
        energies.append(e)
        # the resolution of the total energy: float64 rounding of the sum of contact forces
        _, _, start, nbr, inv_s = _verlet_rows(pos, rad, box, 0.3 * md, rad, pos.copy())
        fsum = _energy_forces_rows(pos, box, start, nbr, inv_s, 2.0, np.zeros_like(pos))[3]
        assert e <= energies[-2] + energy_resolution(box, fsum), (energies[-2], e)
        if st != newton.MAX_STEPS:
            break
    assert steps >= 3 and energies[-1] < energies[0]


def _lowest_modes(p):
    """Eigenvalues of the load-bearing network's Hessian / the largest, and its contacts beyond
    2 N_G - 1 (the isostatic count in a fixed box)."""
    hb = hessian(p.positions, p.radii, p.box, rattlers=False)
    ev = np.linalg.eigvalsh(hb.dense())
    return ev / ev[-1], len(hb.pairs_i) - (2 * len(hb.nodes) - 1)


@pytest.mark.slow
@pytest.mark.parametrize("n, e, seed", [(96, 1e-12, 5), (512, 1e-13, 1), (512, 1e-15, 2)])
def test_the_end_point_is_a_certified_minimum(n, e, seed):
    """At a Newton packing the load-bearing network's Hessian has the two translations as its
    only zero modes and no negative curvature beyond round-off. Near jamming a saddle's
    negative curvature is of the prestress's size (f / d, 4e-10 .. 7e-8 of the largest
    eigenvalue at E_G 1e-16 .. 1e-13, measured): a certification shift of 1e-6 k0 accepted such saddles,
    hypostatic packings one or two contacts short (these cases did)."""
    p = kernels.jam(n, e, seed=seed, endgame="newton")
    assert p.converged and p.factorizations > 0
    ev, excess = _lowest_modes(p)
    assert ev[0] > -1e-12, ev[:3]
    assert np.sum(np.abs(ev) < 1e-12) == 2
    assert excess >= 0


@pytest.mark.slow
def test_reproducible_bits():
    a = kernels.jam(128, 1e-13, seed=9, endgame="newton")
    b = kernels.jam(128, 1e-13, seed=9, endgame="newton")
    assert a.positions.tobytes() == b.positions.tobytes()
    assert a.radii.tobytes() == b.radii.tobytes()
    assert a.force_evaluations == b.force_evaluations and a.factorizations == b.factorizations


@pytest.mark.slow
@pytest.mark.parametrize("alpha", [2.0, 2.5, 3.0])
def test_newton_packings_are_in_their_window_and_balanced(alpha):
    e = {2.0: 1e-14, 2.5: 1e-17, 3.0: 1e-20}[alpha]
    p = kernels.jam(128, e, seed=2, endgame="newton", exponent=alpha)
    assert p.converged, p.status
    assert e <= p.energy <= 1.1 * e
    assert p.force_residual < 1e-6


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match=r"endgame: expected one of \['none', 'newton'\]"):
        kernels.jam(32, 1e-6, seed=0, endgame="quasi-newton")
    with pytest.raises(ValueError, match="endgame"):
        kernels.jam(32, 1e-6, seed=0, endgame="newton", minimizer="cg")
    with pytest.raises(ValueError, match="endgame"):
        kernels.jam(32, 1e-6, seed=0, endgame="newton", route="pressure")
