"""The pressure route (kernels.barostat): the barostat force is the virial, enthalpy minima sit
at the target pressure, jam(route="pressure") lands in the window with balanced forces,
determinism, bounds, bad settings and the route in the task identity."""

import numpy as np
import pytest

import kernels
from campaign.errors import UserError
from campaign.plan.parse import parse_spec
from campaign.plan.tasks import expand
from kernels.barostat import BARO_SCALE, PRESSURE_TOL, _enthalpy_core
from kernels.fire import _fire_core
from kernels.jamming import DEFAULTS, initial_state
from kernels.potential import energy, pressure
from kernels.protocol import _dt_for
from references import ref_packing_measures


def _state(n, seed, phi=0.86):
    pos, rad, _ = initial_state(n, seed, (1.0, 1.0), DEFAULTS["species"], phi)
    return pos, rad, np.array([1.0, 1.0, 0.0])  # the kernels' cell [Lx, Ly, xy]


def test_barostat_force_is_the_virial():
    # dU/d ln(lambda) at fixed positions equals W = 2 A P (radii lambda r0): central
    # differences of the energy against the virial pressure of the same state
    pos, rad, box = _state(64, 3)
    for alpha in (2.0, 2.5, 3.0):
        h = 1e-6
        up = energy(pos, rad * np.exp(h), box, alpha)
        dn = energy(pos, rad * np.exp(-h), box, alpha)
        w = 2.0 * pressure(pos, rad, box, alpha)
        # truncation error ~ h^2 relative; rounding ~ eps U / h
        assert (up - dn) / (2 * h) == pytest.approx(w, rel=1e-8)


@pytest.mark.parametrize("alpha, e_aim", [(2.0, 1e-6), (2.0, 1e-10), (2.5, 1e-7)])
def test_enthalpy_minimum_is_at_the_target_pressure_and_force_balanced(alpha, e_aim):
    n = 128
    pos, rad, box = _state(n, 1)
    md = 2 * rad.mean()
    p_t = n * (alpha * e_aim / 2) ** ((alpha - 1) / alpha)  # N_c = 2 n contacts
    st, lam, steps, nf, e, w, res = _enthalpy_core(
        pos, rad, box, alpha, p_t, 1.0, 1e-6, PRESSURE_TOL, 2_000_000, 0.3 * md,
        _dt_for(rad, alpha, 1e-6), BARO_SCALE * md * np.sqrt(n), 10.0)
    assert st == 0 and nf == steps + 1
    radii = lam * rad
    assert pressure(pos, radii, box, alpha) == pytest.approx(p_t, rel=PRESSURE_TOL)
    assert w / 2 == pytest.approx(pressure(pos, radii, box, alpha), rel=1e-12)
    assert e == pytest.approx(energy(pos, radii, box, alpha), rel=1e-12)
    # a minimum of the energy at these radii too: FIRE at fixed radii has nothing to do
    q = pos.copy()
    out = _fire_core(q, radii, box, alpha, 1e-6, 10, 0.3 * md * lam, _dt_for(radii, alpha, e / n),
                     0.0)
    assert out[0] == 0 and out[1] == 0 and out[5] == pytest.approx(res, rel=1e-9)
    # the energy follows the pressure with the scaling exponent within a factor of a few
    assert 0.2 < (e / n) / e_aim < 5


CASES = [(64, 1e-6), (128, 1e-10), (64, 1e-14), (128, 1e-16)]


@pytest.mark.parametrize("n, target", CASES)
def test_pressure_route_lands_in_window_with_balanced_forces(n, target):
    for seed in (0, 1, 2):
        p = kernels.jam(n, target, seed, route="pressure")
        assert p.status == "converged", (n, target, seed, p.status)
        e, resid, n_g, n_c = ref_packing_measures(p)
        assert target <= e <= target * 1.1
        assert e == pytest.approx(p.energy, rel=1e-9)
        assert resid < DEFAULTS["force_tolerance"] and p.force_residual < DEFAULTS["force_tolerance"]
        assert 0.80 < p.phi < 0.87 and p.pressure > 0
        assert p.settings["route"] == "pressure"
        if target <= 1e-14:
            assert n_c >= 2 * n_g - 1  # at least isostatic


def test_pressure_route_other_box_and_exponent():
    p = kernels.jam(60, 1e-6, 3, box=(2.0, 0.75), route="pressure")
    e, resid, *_ = ref_packing_measures(p)
    assert p.status == "converged" and 1e-6 <= e <= 1.1e-6 and resid < 1e-6
    for alpha in (2.5, 3.0):
        p = kernels.jam(64, 1e-9, 3, exponent=alpha, route="pressure")
        e, resid, *_ = ref_packing_measures(p)
        assert p.status == "converged" and 1e-9 <= e <= 1.1e-9 and resid < 1e-6


def test_pressure_route_is_bit_identical():
    a = kernels.jam(96, 1e-12, 7, route="pressure")
    b = kernels.jam(96, 1e-12, 7, route="pressure")
    c = kernels.jam(96, 1e-12, 7)
    for f in ("positions", "radii"):
        assert getattr(a, f).tobytes() == getattr(b, f).tobytes()
    assert (a.energy, a.pressure, a.force_evaluations, a.iterations) == (
        b.energy, b.pressure, b.force_evaluations, b.iterations)
    assert not np.array_equal(a.radii, c.radii)  # another route, another minimum


def test_pressure_route_bounds():
    # 1e-12 needs a stage at 1e-6, ... : one minimisation is not enough
    p = kernels.jam(64, 1e-12, 1, route="pressure", max_search=1)
    assert p.status == "max_search" and p.iterations == 1
    p = kernels.jam(64, 1e-12, 1, route="pressure", max_search=3)
    assert p.status == "max_search" and p.iterations == 3
    assert not 1e-12 <= p.energy <= 1.1e-12
    p = kernels.jam(64, 1e-4, 1, route="pressure", max_steps=5)
    assert p.status == "max_steps" and p.iterations == 1 and p.force_evaluations == 6
    # too small a box for growing disks: stops with too_dense, not a wrong packing
    p = kernels.jam(32, 1.0, 0, route="pressure", box=(0.5, 0.5), phi_start=0.3)
    assert p.status == "too_dense"


@pytest.mark.parametrize("route", ["newton", "", None, 1])
def test_bad_route(route):
    with pytest.raises(ValueError, match=r"route: expected one of \['ohern', 'pressure'\]"):
        kernels.jam(64, 1e-6, 0, route=route)


SPEC = """\
name: t
seed: 11
grid: {N_G: [16], E_G: [1.0e-3, 1.0e-6], seeds: 2}
"""


def test_route_in_task_identity():
    base = {(t.N, t.E, t.seed): t.id for t in expand(parse_spec(SPEC))}
    # the default route, written out, keeps the ids
    same = expand(parse_spec(SPEC + "protocol: {route: ohern}\n"))
    assert {(t.N, t.E, t.seed): t.id for t in same} == base
    other = expand(parse_spec(SPEC + "protocol: {route: pressure}\n"))
    assert {t.id for t in other}.isdisjoint(base.values())
    assert dict(other[0].protocol)["route"] == "pressure"
    v = expand(parse_spec(SPEC + "variants: [{name: p, route: pressure}]\n"))
    assert {t.id for t in v if t.variant == "p"} == {t.id for t in other}
    with pytest.raises(UserError, match=r"protocol\.route: unknown route 'fast'"):
        parse_spec(SPEC + "protocol: {route: fast}\n")


def test_pressure_route_refuses_the_other_minimisers():
    with pytest.raises(ValueError, match="route: route 'pressure' relaxes with FIRE"):
        kernels.jam(32, 1e-6, 0, route="pressure", minimizer="cg")
    with pytest.raises(UserError, match="route 'pressure' relaxes with FIRE"):
        parse_spec("name: x\ngrid: {N_G: [16], E_G: [1.0e-4], seeds: 1}\n"
                   "protocol: {route: pressure, minimizer: cg}\n")
