"""FIRE 2.0 energy minimiser and force-balance residual on non-rattlers (numba).

FIRE 2.0 (Guenole et al., Comput. Mater. Sci. 175, 109584 (2020)): semi-implicit
Euler steps with unit masses, velocity mixing ``v <- (1 - a) v + a |v| F/|F|``, a
half step back and zero velocity when the power ``P = F.v`` turns non-positive, a
delay of ``N_DELAY`` steps before the time step may grow, time step bounds
``[dt_min, dt_max] = [DT_MIN_FACTOR, DT_MAX_FACTOR] * dt0`` and an exit after
``N_NEG_MAX`` consecutive non-positive power steps (a stall).

Forces come from a Verlet list with a skin built by ``kernels.cells``; it is rebuilt
whenever a disk has moved more than half the skin since the last build (and at
every call, so radius changes between calls are always seen). Positions are wrapped
into the box at every rebuild (the skin must stay below half a box side).

Convergence is relative, never absolute: the *force residual* is

    max over non-rattlers |F_net| / mean over non-rattler contacts |f_contact|

where rattlers are found by iteratively removing disks with fewer than 3 contacts or
with all contacts in a closed half-plane (``_nonrattler_mask_core``): neither can
balance repulsive forces, so they carry no load in a force-balanced packing. The cheap bound ``max over all disks |F_net| / mean
|f_contact|`` is checked every step; the rattler-aware residual every
``CHECK_EVERY`` steps and before declaring convergence. A packing without any
contact has nothing to balance: its residual is 0.

Jitted cores, usable from other numba code:

* ``_nonrattler_mask_core(n, ci, cj, dx, dy) -> bool (n,)`` from contact pairs
  (``ci < cj``) and their displacements ``r_cj - r_ci``.
* ``_contacts_core(positions, radii, box, pi, pj) -> (ci, cj, dx, dy)``: the
  overlapping pairs among the candidates.
* ``_residual_core(positions, radii, box, pi, pj, alpha, forces) -> (residual,
  n_nonrattlers, mean_contact_force)``; ``forces`` is scratch (n, 2).
* ``_fire_core(...)``: the whole minimisation loop, see its docstring.

Checked wrappers: ``minimize(...) -> FireResult`` and ``nonrattlers(...)``.
"""

from dataclasses import dataclass

import numpy as np
from numba import njit

from kernels.cells import _as_radii, _candidate_pairs_core
from kernels.network import HALF_PLANE_TOL, _overlapping_core, _rattlers_core
from kernels.potential import (_energy_forces_core, _energy_forces_rows, _pair_inv_sigma,
                               _rows_from_pairs, check_exponent, pair_energy_force)
from kernels import rules
from kernels.rules import (A_START, BELOW, CHECK_EVERY, CONVERGED, DT_FACTOR, DT_MAX_FACTOR,
                           DT_MIN_FACTOR, MAX_STEPS, N_NEG_MAX, STALLED, STATUS_NAMES)
from kernels.space import _as_box, _as_positions, _wrap_core, _wrap_inplace, separation

# FIRE's rules (constants, status codes, the time-step adaptation) are kernels.rules', compiled
# here for the CPU minimisers; the GPU block compiles the same functions (kernels.gpu.block).
_fire_adapt = njit(cache=True)(rules.fire_adapt)
_dt_from_diameter = njit(cache=True, inline="always")(rules.dt_from_diameter)


@njit(cache=True)
def _dt_for(radii, alpha, e_per_disk):
    """Initial FIRE time step for ``radii`` at ``e_per_disk`` (``rules.dt_from_diameter`` at
    their mean diameter)."""
    s = 0.0
    for i in range(radii.shape[0]):
        s += radii[i]
    s = 2.0 * s / radii.shape[0]
    return _dt_from_diameter(s, alpha, e_per_disk)


# The two thin wrappers below are inlined (numba IR) into their jitted callers: a separately
# compiled layer optimises and generates the machine code of everything it calls once more.


@njit(cache=True, inline="always")
def _nonrattler_mask_core(n, ci, cj, dx, dy):
    """Iteratively remove disks with fewer than 3 contacts or all contacts in a closed
    half-plane; True for the rest.

    The one implementation of rattler removal is ``kernels.network._rattlers_core``.
    """
    return ~_rattlers_core(n, ci, cj, dx, dy, HALF_PLANE_TOL)


@njit(cache=True, inline="always")
def _contacts_core(positions, radii, box, pi, pj):
    """The candidate pairs that overlap: centre distance < r_i + r_j (minimum image),
    with their displacements ``r_j - r_i``."""
    return _overlapping_core(positions, radii, box, pi, pj)


@njit(cache=True)
def _residual_core(positions, radii, box, pi, pj, alpha, forces):
    """Force residual on non-rattlers (see module docstring).

    Returns ``(residual, n_nonrattlers, mean_contact_force)``. With no non-rattler,
    the residual is taken over all disks and all contacts; with no contact at all it
    is 0.
    """
    res, ng, mean, alive = _residual_alive(positions, radii, box, pi, pj, alpha, forces)
    return res, ng, mean


@njit(cache=True)
def _residual_alive(positions, radii, box, pi, pj, alpha, forces):
    """``_residual_core`` and the non-rattler mask it used (all False without contacts)."""
    n = positions.shape[0]
    _energy_forces_core(positions, box, pi, pj, _pair_inv_sigma(radii, pi, pj), alpha, forces)
    ci, cj, cdx, cdy = _contacts_core(positions, radii, box, pi, pj)
    if ci.shape[0] == 0:
        return 0.0, 0, 0.0, np.zeros(n, dtype=np.bool_)
    alive = _nonrattler_mask_core(n, ci, cj, cdx, cdy)
    ng = 0
    for i in range(n):
        if alive[i]:
            ng += 1
    use_all = ng == 0
    fsum = 0.0
    nc = 0
    for k in range(ci.shape[0]):
        i = ci[k]
        j = cj[k]
        if use_all or (alive[i] and alive[j]):
            dx, dy = separation(positions[j, 0] - positions[i, 0], positions[j, 1] - positions[i, 1], box)
            r = np.sqrt(dx * dx + dy * dy)
            fsum += pair_energy_force(r, radii[i] + radii[j], alpha)[1]
            nc += 1
    fmax2 = 0.0
    for i in range(n):
        if use_all or alive[i]:
            f2 = forces[i, 0] * forces[i, 0] + forces[i, 1] * forces[i, 1]
            if f2 > fmax2:
                fmax2 = f2
    mean = fsum / nc
    if mean == 0.0:
        return 0.0, ng, 0.0, alive
    return np.sqrt(fmax2) / mean, ng, mean, alive


@njit(cache=True)
def _verlet_rows(positions, radii, box, skin, sigma_radii, ref):
    """(Re)build the Verlet list around ``positions``: candidate pairs within ``skin`` at
    ``radii``, their ``1/s`` from ``sigma_radii`` (the same radii, or the pressure route's
    unscaled ones), in row form; ``ref`` records the positions it was built at.
    Returns ``(pi, pj, start, nbr, inv_s)``."""
    pi, pj = _candidate_pairs_core(positions, radii, box, skin)
    inv_s = _pair_inv_sigma(sigma_radii, pi, pj)
    start, nbr = _rows_from_pairs(positions.shape[0], pi, pj)
    for i in range(positions.shape[0]):
        ref[i, 0] = positions[i, 0]
        ref[i, 1] = positions[i, 1]
    return pi, pj, start, nbr, inv_s


# One FIRE 2.0 step in passes over the disks, shared by ``_fire_core`` and the pressure
# route (``kernels.barostat``), which adds its radius degree of freedom to the sums by
# passing it as the starting value.


@njit(cache=True)
def _fire_power(frc, vel, ff, p):
    """Largest |F|^2, and ``ff + |F|^2`` and the power ``p + F.v``."""
    fmax2 = 0.0
    for i in range(frc.shape[0]):
        f2 = frc[i, 0] * frc[i, 0] + frc[i, 1] * frc[i, 1]
        ff += f2
        p += frc[i, 0] * vel[i, 0] + frc[i, 1] * vel[i, 1]
        if f2 > fmax2:
            fmax2 = f2
    return fmax2, ff, p


@njit(cache=True)
def _fire_retreat(positions, vel, dt):
    """After a step with non-positive power: half a step back, velocities to zero."""
    for i in range(positions.shape[0]):
        positions[i, 0] -= 0.5 * dt * vel[i, 0]
        positions[i, 1] -= 0.5 * dt * vel[i, 1]
        vel[i, 0] = 0.0
        vel[i, 1] = 0.0


@njit(cache=True)
def _fire_kick(vel, frc, dt, vv):
    """Semi-implicit Euler ``v += dt F``; returns ``vv + |v|^2``."""
    for i in range(vel.shape[0]):
        vel[i, 0] += dt * frc[i, 0]
        vel[i, 1] += dt * frc[i, 1]
        vv += vel[i, 0] * vel[i, 0] + vel[i, 1] * vel[i, 1]
    return vv


@njit(cache=True)
def _fire_mix_move(positions, vel, frc, a, mix, dt, ref):
    """FIRE's mixing ``v <- (1 - a) v + mix F`` and the move ``x += dt v``; returns the
    largest squared displacement from ``ref``."""
    disp2 = 0.0
    for i in range(positions.shape[0]):
        vel[i, 0] = (1.0 - a) * vel[i, 0] + mix * frc[i, 0]
        vel[i, 1] = (1.0 - a) * vel[i, 1] + mix * frc[i, 1]
        positions[i, 0] += dt * vel[i, 0]
        positions[i, 1] += dt * vel[i, 1]
        ddx = positions[i, 0] - ref[i, 0]
        ddy = positions[i, 1] - ref[i, 1]
        d2 = ddx * ddx + ddy * ddy
        if d2 > disp2:
            disp2 = d2
    return disp2


@njit(cache=True)
def _fire_core(positions, radii, box, alpha, tol, max_steps, skin, dt0, e_abort):
    """Minimise the total energy in place (``positions`` is overwritten).

    ``tol``: force-residual tolerance; ``max_steps``: bound on FIRE steps;
    ``skin``: Verlet skin (absolute length); ``dt0``: initial time step;
    ``e_abort``: stop with status ``BELOW`` as soon as the total energy is below it
    (0 disables).

    Returns ``(status, steps, force_evaluations, energy, virial, residual,
    n_contacts)``: total energy and virial ``sum r f`` at the final positions.
    """
    vel = np.zeros((positions.shape[0], 2))
    return _fire_run(positions, radii, box, alpha, tol, max_steps, skin, e_abort, vel,
                     _fire_state(dt0))


@njit(cache=True)
def _fire_state(dt0):
    """FIRE's state between calls of ``_fire_run``: ``[dt0, dt, a, n_pos, n_neg, steps]``,
    fresh (the velocities are the caller's array, zero for a fresh start)."""
    s = np.empty(6)
    s[0] = dt0
    s[1] = dt0
    s[2] = A_START
    s[3] = 0.0
    s[4] = 0.0
    s[5] = 0.0
    return s


@njit(cache=True)
def _fire_run(positions, radii, box, alpha, tol, max_steps, skin, e_abort, vel, state):
    """``_fire_core`` resumed from the velocities ``vel`` and the ``state`` of
    ``_fire_state`` (both updated in place), for at most ``max_steps`` more steps: a
    minimisation interrupted (by the Newton endgame's tries) and resumed keeps FIRE's
    momentum and time step. Returns ``_fire_core``'s tuple (``steps``: of this call)."""
    n = positions.shape[0]
    dt0 = state[0]
    dt_max = DT_MAX_FACTOR * dt0
    dt_min = DT_MIN_FACTOR * dt0
    dt = state[1]
    a = state[2]
    n_pos = int(state[3])
    n_neg = int(state[4])
    total = int(state[5])
    frc = np.empty((n, 2))
    scratch = np.empty((n, 2))
    _wrap_inplace(positions, box)
    ref = np.empty((n, 2))
    pi, pj, start, nbr, inv_s = _verlet_rows(positions, radii, box, skin, radii, ref)
    half2 = 0.25 * skin * skin
    energy, virial, nc, fsum = _energy_forces_rows(positions, box, start, nbr, inv_s, alpha, frc)
    nforce = 1
    status = MAX_STEPS
    residual = np.inf
    step = 0
    while True:
        # convergence tests on the current state
        if e_abort > 0.0 and energy < e_abort:
            status = BELOW
            residual = -1.0
            break
        if nc == 0:
            status = CONVERGED
            residual = 0.0
            break
        # one pass: largest force, |F|^2 and the power P = F.v
        fmax2, ff, p = _fire_power(frc, vel, 0.0, 0.0)
        mean_f = fsum / nc
        bound = np.sqrt(fmax2) / mean_f if mean_f > 0.0 else 0.0
        if bound < tol or step % CHECK_EVERY == 0 or step >= max_steps:
            residual = _residual_core(positions, radii, box, pi, pj, alpha, scratch)[0]
            if residual < tol:
                status = CONVERGED
                break
        if step >= max_steps:
            status = MAX_STEPS
            break
        step += 1
        total += 1
        # FIRE 2.0 step
        n_pos, n_neg, dt, a = _fire_adapt(p, total, n_pos, n_neg, dt, a, dt_min, dt_max)
        if p <= 0.0:
            if n_neg > N_NEG_MAX:
                status = STALLED
                residual = _residual_core(positions, radii, box, pi, pj, alpha, scratch)[0]
                break
            _fire_retreat(positions, vel, dt)
        vv = _fire_kick(vel, frc, dt, 0.0)
        mix = a * np.sqrt(vv / ff) if ff > 0.0 else 0.0
        disp2 = _fire_mix_move(positions, vel, frc, a, mix, dt, ref)
        if disp2 > half2:
            _wrap_inplace(positions, box)
            pi, pj, start, nbr, inv_s = _verlet_rows(positions, radii, box, skin, radii, ref)
        energy, virial, nc, fsum = _energy_forces_rows(positions, box, start, nbr, inv_s, alpha,
                                                       frc)
        nforce += 1
    state[1] = dt
    state[2] = a
    state[3] = n_pos
    state[4] = n_neg
    state[5] = total
    return status, step, nforce, energy, virial, residual, nc


@dataclass(frozen=True)
class FireResult:
    positions: np.ndarray  # wrapped into the box
    energy: float  # total pair energy
    pressure: float
    residual: float
    steps: int
    force_evaluations: int
    status: str


def default_timestep(radii, exponent, energy_per_disk):
    """Initial FIRE time step (see ``_dt_for``)."""
    return _dt_for(np.asarray(radii, dtype=np.float64), float(exponent), float(energy_per_disk))


def _checked_minimize_inputs(positions, radii, box, exponent, force_tolerance, max_steps, skin):
    """Inputs of a checked minimiser wrapper (FIRE's and CG's): a copy of the positions,
    radii, box, exponent, tolerance and skin (default 0.3 mean diameters), or ValueError."""
    pos = _as_positions(positions).copy()
    rad = _as_radii(radii, pos.shape[0])
    b = _as_box(box)
    a = check_exponent(exponent)
    tol = float(force_tolerance)
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"force_tolerance: expected a finite number > 0, got {force_tolerance!r}")
    if int(max_steps) != max_steps or max_steps < 0:
        raise ValueError(f"max_steps: expected an integer >= 0, got {max_steps!r}")
    if skin is None:
        skin = 0.6 * float(np.mean(rad))
    if not (np.isfinite(skin) and skin > 0):
        raise ValueError(f"skin: expected a finite number > 0, got {skin!r}")
    return pos, rad, b, a, tol, float(skin)


def _starting_timestep(pos, rad, b, a):
    """``default_timestep`` at the configuration's own energy per disk."""
    pi, pj = _candidate_pairs_core(pos, rad, b, 0.0)
    e0 = _energy_forces_core(pos, b, pi, pj, _pair_inv_sigma(rad, pi, pj), a, np.empty_like(pos))[0]
    return default_timestep(rad, a, e0 / len(rad))


def minimize(positions, radii, box, exponent=2.0, *, force_tolerance=1e-6, max_steps=100_000,
             skin=None, dt=None):
    """Minimise the pair energy with FIRE 2.0 at fixed radii (checked wrapper).

    ``skin`` defaults to 0.3 times the mean diameter; ``dt`` to ``default_timestep``
    at the starting energy.
    """
    pos, rad, b, a, tol, skin = _checked_minimize_inputs(positions, radii, box, exponent,
                                                         force_tolerance, max_steps, skin)
    if dt is None:
        dt = _starting_timestep(pos, rad, b, a)
    res = _fire_core(pos, rad, b, a, tol, int(max_steps), skin, float(dt), 0.0)
    return fire_result(pos, b, res)


def fire_result(pos, b, res):
    """``FireResult`` of a minimiser core's return tuple (positions minimised in place)."""
    status, steps, nforce, e, w, residual, nc = res
    return FireResult(positions=_wrap_core(pos, b), energy=e, pressure=w / (2 * b[0] * b[1]),
                      residual=residual, steps=steps, force_evaluations=nforce,
                      status=STATUS_NAMES[status])


def nonrattlers(positions, radii, box):
    """Boolean mask of non-rattlers: disks left after iteratively removing those with
    fewer than 3 contacts or all contacts in a closed half-plane (contact: centre
    distance < r_i + r_j, minimum image)."""
    pos = _as_positions(positions)
    rad = _as_radii(radii, pos.shape[0])
    b = _as_box(box)
    pi, pj = _candidate_pairs_core(pos, rad, b, 0.0)
    ci, cj, dx, dy = _contacts_core(pos, rad, b, pi, pj)
    return _nonrattler_mask_core(pos.shape[0], ci, cj, dx, dy)
