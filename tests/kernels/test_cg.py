"""Conjugate-gradient minimiser (kernels.cg) and the paper's literal protocol settings."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import kernels
from kernels import cg, fire
from kernels.cg import E_ROUND
from kernels.potential import energy, forces
from helpers import random_dense
from references import ref_contact_arrays, ref_energy_and_residual, ref_hessian_finite_differences, ref_nonrattlers

EPS = np.finfo(float).eps


def _disp(pos, box, i, j):
    d = pos[j] - pos[i]
    return d - box * np.round(d / box)


def energy_resolution(pos, rad, box, alpha):
    """The kernel's stated float64 resolution of a total energy (see kernels.cg)."""
    _, _, r, s = ref_contact_arrays(pos, rad, box)
    return E_ROUND * EPS * box.max() * np.sum((1 - r / s) ** (alpha - 1) / s)


@pytest.mark.parametrize("seed, alpha", [(12, 2.0), (13, 2.0), (14, 2.5)])
def test_cg_reaches_the_fire_minimum(seed, alpha):
    # Start near a minimum well above jamming (hyperstatic, one basin around it) and
    # minimise with both to tol = 1e-10: same contact network among non-rattlers, and
    # non-rattler positions (up to the network's global translation) within the
    # distance the residual forces allow in the harmonic approximation,
    # |dx| <= (|F_fire| + |F_cg|) / lambda_min, with lambda_min the smallest non-zero
    # eigenvalue of the Hessian (finite differences of the forces).
    pos, rad, box = random_dense(seed, n=48, phi=0.88)
    d = 2 * rad.mean()
    start = fire.minimize(pos, rad, box, alpha, force_tolerance=1e-6).positions
    start = start + 0.02 * d * np.random.default_rng(seed).standard_normal(start.shape)
    a = fire.minimize(start, rad, box, alpha, force_tolerance=1e-10)
    b = cg.minimize(start, rad, box, alpha, force_tolerance=1e-10)
    assert a.status == b.status == "converged" and a.residual < 1e-10 and b.residual < 1e-10
    ia, ja, *_ = ref_contact_arrays(a.positions, rad, box)
    ib, jb, *_ = ref_contact_arrays(b.positions, rad, box)
    keep = ref_nonrattlers(len(rad), ia, ja, _disp(a.positions, box, ia, ja))
    assert np.array_equal(keep, ref_nonrattlers(len(rad), ib, jb, _disp(b.positions, box, ib, jb)))
    assert keep.sum() > 30
    net_a = {(i, j) for i, j in zip(ia, ja) if keep[i] and keep[j]}
    net_b = {(i, j) for i, j in zip(ib, jb) if keep[i] and keep[j]}
    assert net_a == net_b
    assert b.energy == pytest.approx(a.energy, rel=1e-9)
    dx = b.positions - a.positions
    dx -= box * np.round(dx / box)
    dx = dx[keep] - dx[keep].mean(axis=0)
    hess = ref_hessian_finite_differences(a.positions, rad, box, alpha, keep, h=1e-7 * d)
    lam = np.linalg.eigvalsh(hess)
    assert abs(lam[1]) < 1e-6 * lam[-1] and lam[2] > 1e-6 * lam[-1]  # two translations only
    f_a = np.linalg.norm(forces(a.positions, rad, box, alpha)[keep])
    f_b = np.linalg.norm(forces(b.positions, rad, box, alpha)[keep])
    bound = (f_a + f_b) / lam[2]
    assert np.linalg.norm(dx) <= 2 * bound, (np.linalg.norm(dx), bound)
    assert bound < 1e-6 * d  # the comparison is not empty


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(16, 40), phi=st.floats(0.8, 1.0),
       alpha=st.sampled_from([2.0, 2.5, 3.0]))
def test_energy_never_rises_across_an_accepted_step(seed, n, phi, alpha):
    # The run with max_steps = k stops after exactly k iterations of the same
    # deterministic run, so E(k) is the energy after the k-th step. It never rises by
    # more than the stated float64 resolution of the energy (a bound far below the
    # energies and their changes here).
    pos, rad, box = random_dense(seed, n=n, phi=phi)
    full = cg.minimize(pos, rad, box, alpha, force_tolerance=1e-12, max_steps=300)
    k_max = min(full.steps, 120)
    e0 = prev_e = energy(pos, rad, box, alpha)
    prev_pos = pos
    rises = 0
    for k in range(1, k_max + 1):
        r = cg.minimize(pos, rad, box, alpha, force_tolerance=1e-12, max_steps=k)
        res = energy_resolution(prev_pos, rad, box, alpha)
        assert res < 1e-9 * e0
        assert r.energy <= prev_e + res, (k, r.energy - prev_e, res)
        rises += r.energy > prev_e
        prev_e, prev_pos = r.energy, r.positions
    assert prev_e < 0.9 * e0 and rises <= k_max // 4


def test_energy_rises_only_within_rounding_near_1e16():
    # deep in the noise regime: a packing at E_G ~ 1e-16, slightly compressed
    p = kernels.jam(64, 1e-16, 3)
    rad = p.radii * (1 + 2e-9)
    pos, box = np.array(p.positions), p.box
    full = cg.minimize(pos, rad, box, force_tolerance=1e-6)
    assert full.status == "converged" and full.residual < 1e-6 and full.steps > 100
    # the first steps and the last ones (where the energy differences are below rounding)
    for ks in (range(0, 40), range(full.steps - 60, full.steps + 1)):
        prev = None
        for k in ks:
            r = cg.minimize(pos, rad, box, force_tolerance=1e-6, max_steps=k)
            if prev is not None:
                assert r.energy <= prev.energy + energy_resolution(prev.positions, rad, box, 2.0)
            prev = r
    assert r.positions.tobytes() == full.positions.tobytes()


def test_energy_stop_is_the_literal_rule():
    # stop = energy: the last accepted step changed E/n by less than the tolerance, every
    # earlier one by at least that much (or not at all: a failed line search)
    pos, rad, box = random_dense(4, n=40, phi=0.86)
    n = len(rad)
    tol = 1e-9
    r = cg.minimize(pos, rad, box, energy_tolerance=tol)
    assert r.status == "converged" and r.steps >= 2
    es = [energy(pos, rad, box)] + [cg.minimize(pos, rad, box, energy_tolerance=tol,
                                                max_steps=k).energy for k in range(1, r.steps + 1)]
    assert es[-1] == r.energy
    changes = np.abs(np.diff(es)) / n
    assert changes[-1] < tol
    assert np.all((changes[:-1] >= tol) | (changes[:-1] == 0.0))
    # the residual is computed, not bounded: it is far from force balance here
    assert r.residual > 1e-6


def test_deterministic_and_max_steps():
    pos, rad, box = random_dense(9, n=64, phi=0.88)
    a = cg.minimize(pos, rad, box)
    b = cg.minimize(pos, rad, box)
    assert a.positions.tobytes() == b.positions.tobytes()
    assert (a.steps, a.force_evaluations, a.energy) == (b.steps, b.force_evaluations, b.energy)
    c = cg.minimize(pos, rad, box, force_tolerance=1e-12, max_steps=10)
    assert c.status == "max_steps" and c.steps == 10 and c.residual > 1e-12


def test_dilute_disks_and_crystal():
    pos, rad, box = random_dense(3, n=64, phi=0.5)
    res = cg.minimize(pos, rad, box)
    assert res.status == "converged" and res.energy == 0.0 and res.residual == 0.0
    nx, ny = 6, 4
    box = np.array([1.0, np.sqrt(3) / 2 * ny / nx])
    a = 1.0 / nx
    pos = np.array([[(i + 0.5 * (j % 2)) * a, j * a * np.sqrt(3) / 2]
                    for j in range(ny) for i in range(nx)])
    res = cg.minimize(pos, np.full(len(pos), 0.51 * a), box)
    assert res.status == "converged" and res.steps == 0 and res.residual < 1e-12


@pytest.mark.parametrize("kw, match", [
    (dict(force_tolerance=0.0), r"force_tolerance: expected a finite number > 0, got 0.0"),
    (dict(energy_tolerance=-1e-16), r"energy_tolerance: expected None or a finite number > 0"),
    (dict(energy_tolerance=float("nan")), r"energy_tolerance: expected"),
    (dict(max_steps=-1), r"max_steps: expected an integer >= 0, got -1"),
    (dict(skin=0.0), r"skin: expected a finite number > 0"),
    (dict(step=-1.0), r"step: expected a finite number > 0, got -1.0"),
])
def test_bad_minimize_settings(kw, match):
    pos, rad, box = random_dense(1, n=8, phi=0.5)
    with pytest.raises(ValueError, match=match):
        cg.minimize(pos, rad, box, 2.0, **kw)


@pytest.mark.parametrize("kw, match", [
    (dict(minimizer="newton"), r"minimizer: expected one of \['fire', 'cg'\], got 'newton'"),
    (dict(minimizer=None), r"minimizer: expected one of"),
    (dict(stop="residual"), r"stop: expected one of \['force', 'energy'\], got 'residual'"),
    (dict(stop="energy"), r"stop: stop 'energy' counts conjugate-gradient steps: it needs minimizer 'cg'.*; got minimizer 'fire'"),
    (dict(minimizer="cg", stop="energy", energy_tolerance=0.0),
     r"energy_tolerance: expected a finite number > 0, got 0.0"),
    (dict(energy_tolerance="small"), r"energy_tolerance: expected a finite number > 0"),
    (dict(search="bisection"), r"search: expected one of \['halving', 'secant', 'paper'\]"),
])
def test_bad_jam_settings(kw, match):
    with pytest.raises(ValueError, match=match):
        kernels.jam(32, 1e-6, 0, **kw)


@pytest.mark.parametrize("n, target, search", [(64, 1e-4, "secant"), (128, 1e-10, "secant"),
                                               (64, 1e-14, "halving"), (64, 1e-8, "paper")])
def test_jam_with_cg(n, target, search):
    for seed in (0, 1):
        p = kernels.jam(n, target, seed, minimizer="cg", search=search)
        e, resid = ref_energy_and_residual(p)
        assert p.status == "converged", (seed, p.status)
        assert target <= e <= 1.1 * target and e == pytest.approx(p.energy, rel=1e-9)
        assert resid < 1e-6 and p.force_residual < 1e-6
        assert p.settings["minimizer"] == "cg"
    q = kernels.jam(n, target, 1, minimizer="cg", search=search)
    for f in ("positions", "radii"):
        assert getattr(p, f).tobytes() == getattr(q, f).tobytes()
    assert (p.force_evaluations, p.iterations) == (q.force_evaluations, q.iterations)


def test_paper_protocol_records_its_residual():
    # cg + energy stop + Delta halved after every minimisation: the window is reached,
    # the force residual is recorded (and is what the reference computes), not bounded
    p = kernels.jam(64, 1e-8, 2, minimizer="cg", stop="energy", search="paper")
    e, resid = ref_energy_and_residual(p)
    assert p.status == "converged" and 1e-8 <= e <= 1.1e-8
    assert p.force_residual == pytest.approx(resid, rel=1e-6)
    q = kernels.jam(64, 1e-8, 2, minimizer="cg", stop="energy", search="paper")
    assert p.positions.tobytes() == q.positions.tobytes()


def test_paper_search_is_bounded():
    # The k-th rescaling is by 1 + delta 2^-(k-1): the radii can change by at most
    # prod_k (1 + delta 2^-k) <= exp(2 delta) either way. From phi_start = 0.95 the
    # jamming point (phi ~ 0.84, a radius factor ~0.94) is out of reach with
    # delta = 0.01: the search must end (max_search) once the steps vanish below float64
    # resolution (about 50 minimisations), not loop until max_search = 10^6.
    from kernels.jamming import initial_state, DEFAULTS

    kw = dict(phi_start=0.95, max_search=10 ** 6, minimizer="cg", search="paper")
    p = kernels.jam(32, 1e-6, 0, **kw)
    assert p.status == "max_search" and 40 <= p.iterations <= 60
    _, r0, _ = initial_state(32, 0, DEFAULTS["box"], DEFAULTS["species"], 0.95)
    scale = p.radii[0] / r0[0]
    assert np.exp(-2 * 0.01) <= scale < 1.0
    assert scale == pytest.approx(1 / np.prod(1 + 0.01 * 0.5 ** np.arange(60)), rel=1e-12)


SPEC = """\
name: t
seed: 11
grid: {N_G: [16], E_G: [1.0e-6], seeds: 1}
variants: [{name: halving, search: halving}]
"""


def test_settings_are_protocol_keys_and_part_of_the_task_identity():
    from campaign.errors import UserError
    from campaign.plan.parse import parse_spec
    from campaign.plan.tasks import expand

    ids = {t.variant: t.id for t in expand(parse_spec(SPEC))}
    # ids computed by the code before the minimiser settings existed: unchanged
    assert ids == {"default": "d07a19fe1150827a7f171e7cdaa17e5b",
                   "halving": "a110b2c54f6da5e93fb0b8fc5f2ed544"}
    more = SPEC.replace("]\n", ", {name: cg, minimizer: cg}, {name: paper, minimizer: cg, stop: energy, "
                              "search: paper}, {name: paper-1e-20, minimizer: cg, stop: energy, search: paper, "
                              "energy_tolerance: 1.0e-20}, {name: forced, stop: force, search: paper}]\n")
    spec = parse_spec(more)
    tasks = {t.variant: t for t in expand(spec)}
    assert tasks["default"].id == ids["default"] and tasks["halving"].id == ids["halving"]
    assert len({t.id for t in tasks.values()}) == len(tasks)
    assert tasks["paper"].payload()["protocol"] == {"window": 0.1, "force_tolerance": 1e-6, "minimizer": "cg",
                                                    "stop": "energy", "search": "paper"}
    assert tasks["paper-1e-20"].payload()["protocol"]["energy_tolerance"] == 1e-20
    # an explicit default stop rule is the default: same packings, same id
    same = parse_spec(SPEC.replace("search: halving}", "search: halving, stop: force}"))
    assert {t.variant: t.id for t in expand(same)} == ids
    # a variant that goes back to force stopping drops the inherited energy tolerance
    base = parse_spec(SPEC.replace("variants: [{name: halving, search: halving}]",
                                   "protocol: {minimizer: cg, stop: energy, energy_tolerance: 1.0e-18}\n"
                                   "variants: [{name: forces, stop: force}]"))
    assert "energy_tolerance" not in base.variants[1].protocol_dict
    with pytest.raises(UserError, match=r"protocol\.stop: unknown stop rule 'energies'"):
        parse_spec(SPEC + "protocol: {stop: energies}\n")
    with pytest.raises(UserError, match=r"protocol\.minimizer: unknown minimizer 'lbfgs'"):
        parse_spec(SPEC + "protocol: {minimizer: lbfgs}\n")
    with pytest.raises(UserError, match=r"protocol\.energy_tolerance: value -1e-16 out of range"):
        parse_spec(SPEC + "protocol: {minimizer: cg, stop: energy, energy_tolerance: -1.0e-16}\n")
    # the worker hands the effective protocol to jam(): every key is a jam() setting
    from kernels.jamming import DEFAULTS
    for t in tasks.values():
        assert set(t.payload()["protocol"]) <= set(DEFAULTS)


RUN_SPEC = """\
name: minimizers
seed: 5
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-5], seeds: 3}
protocol: {window: 0.1, force_tolerance: 1.0e-6}
variants:
  - {name: cg, minimizer: cg}
  - {name: paper, minimizer: cg, stop: energy, search: paper}
observables: [scalars, connectivity]
output: out.h5
"""


def test_a_campaign_with_minimizer_variants_runs_and_reduces(tmp_path, capsys):
    # the real kernels through the engine, then the trade table of the reducer
    import csv

    import h5py

    from campaign import cli

    spec = tmp_path / "s.yaml"
    spec.write_text(RUN_SPEC)
    out = tmp_path / "o.h5"
    assert cli.main(["validate", str(spec)]) == 0
    rc = cli.main(["run", str(spec), "--out", str(out), "--launcher", "inline", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    with h5py.File(out, "r") as f:
        assert (f["tasks/status"][...] == 1).all()
        resid = f["scalars/force_residual"][...]
    assert np.all(np.isfinite(resid))
    assert cli.main(["reduce", str(out), "--out", str(tmp_path / "red"), "--boot", "0"]) == 0
    text = capsys.readouterr().out
    assert "| cg |" in text and "| paper |" in text
    rows = {r["variant"]: r for r in csv.DictReader(open(tmp_path / "red" / "variants.csv"))}
    assert set(rows) == {"default", "cg", "paper"}
    assert int(rows["cg"]["n_pairs"]) == int(rows["paper"]["n_pairs"]) == 12
    assert float(rows["cg"]["cost_ratio_fe"]) > 0


def test_below_float64_resolution_the_minimisation_stalls_instead_of_running_on():
    # a residual of 1e-15 is below the rounding noise of these forces (eps L / (x s) ~ 5e-14):
    # the residual stops halving and the minimisation ends with "stalled", long before max_steps
    from kernels.cg import STALL_MIN

    pos, rad, box = random_dense(6, n=32, phi=0.9)
    r = cg.minimize(pos, rad, box, force_tolerance=1e-15, max_steps=10 ** 7)
    assert r.status == "stalled" and STALL_MIN <= r.steps < 10 * STALL_MIN
    assert 1e-15 < r.residual < 1e-11
