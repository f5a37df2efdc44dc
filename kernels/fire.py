"""FIRE 2.0 energy minimiser (numba).

FIRE 2.0 (Guenole et al., Comput. Mater. Sci. 175, 109584 (2020)): semi-implicit
Euler steps with unit masses, velocity mixing ``v <- (1 - a) v + a |v| F/|F|``, a
half step back and zero velocity when the power ``P = F.v`` turns non-positive, a
delay of ``N_DELAY`` steps before the time step may grow, time step bounds
``[dt_min, dt_max] = [DT_MIN_FACTOR, DT_MAX_FACTOR] * dt0`` and an exit after
``N_NEG_MAX`` consecutive non-positive power steps (a stall); the constants and the
adaptation are ``kernels.rules``'.

Forces come from Verlet rows with a skin (``kernels.minimiser._verlet_rows``); they are
rebuilt whenever a disk has moved more than half the skin since the last build (and at
every call, so radius changes between calls are always seen). Positions are wrapped
into the box at every rebuild (the skin must stay below half a box side). Convergence
is the minimisers' shared test on the force residual of the non-rattlers
(``kernels.minimiser``).

Jitted: ``_fire_core(...)``, the whole minimisation loop (see its docstring), and its
steps' passes, shared with the pressure route and the shear cell. Checked wrapper:
``minimize(...) -> FireResult``.
"""

import numpy as np
from numba import njit

from kernels import rules
from kernels.minimiser import (_checked_minimize_inputs, _residual_core, _starting_timestep, _verlet_rows,
                               fire_result)
from kernels.potential import _energy_forces_rows
from kernels.rules import (A_START, BELOW, CHECK_EVERY, CONVERGED, DT_MAX_FACTOR, DT_MIN_FACTOR, MAX_STEPS,
                           N_NEG_MAX, STALLED)
from kernels.space import _wrap_inplace

# FIRE's rules (constants, status codes, the time-step adaptation) are kernels.rules', compiled
# here for the CPU minimisers; the GPU block compiles the same functions (kernels.gpu.block).
_fire_adapt = njit(cache=True)(rules.fire_adapt)


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


