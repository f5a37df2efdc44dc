"""Nonlinear conjugate-gradient energy minimiser (Polak-Ribiere+, numba).

The minimiser the paper names ("non-linear conjugate-gradient"), next to FIRE 2.0
(``kernels.fire``); the O'Hern search (``kernels.protocol``) calls either.

Directions: ``d <- F + beta d`` with ``beta = max(0, min(F.(F - F_old), F.F) / F_old.F_old)``
(Polak-Ribiere+ bounded by Fletcher-Reeves, the hybrid of Gilbert and Nocedal, SIAM J.
Optim. 2, 21 (1992); ``F`` the net forces, minus the gradient). The bound matters near
jamming: with the plain PR+ beta, packings of N = 1024 at E_G = 1e-12 cost 1-5 times
more force evaluations (docs/MINIMIZERS.md). The direction restarts at
steepest descent (``d = F``) every ``RESTART_EVERY`` iterations, when ``d`` is not a
descent direction (``F.d <= 0``), and after a line search that had to stop at the
displacement cap or fell back to a shorter step.

Line search along ``d`` (``kernels.linesearch``, shared with the Newton endgame): a
bracketing secant search on the directional derivative ``phi'(t) = -F(x + t d).d`` with the
strong Wolfe curvature condition (``SIGMA``) and Armijo's condition, or, where two energies
differ by less than their float64 resolution, the "approximate Wolfe" rule of Hager and
Zhang. With ``SIGMA < 1 - 2 C1`` the curvature condition implies the Armijo condition of the
local quadratic model. Hence the guarantee: **across an accepted step the computed energy
never rises by more than its resolution, and it falls by at least C1 t |phi'(0)| whenever the
fall is resolved.** A line search that finds no acceptable step within
``LS_MAX`` evaluations takes no step and restarts from steepest descent; two such
failures in a row end the minimisation with status ``STALLED``.

No disk moves more than ``DISP_CAP`` times the Verlet skin in one trial point (which
also keeps coordinates within a quarter box of the wrapped ones, as the force loop
needs). The Verlet list is rebuilt at any trial point where a disk is more than half
the skin away from the list's reference positions.

Stopping rules (``e_tol``):

* ``e_tol = 0`` (default): the rattler-aware force residual of ``kernels.fire``
  (``_residual_core``) below ``tol``, as FIRE.
* ``e_tol > 0``: the paper's literal rule, "an energy minimum to within a desired
  tolerance (10^-16 in our case)", read as: stop as soon as one accepted CG step
  changes the energy per disk by less than ``e_tol`` (absolute, ``|Delta E| / n``).
  Nothing guarantees force balance then: the final force residual is still computed
  and returned, and it is usually far above ``tol`` (see docs/MINIMIZERS.md).

Both rules also stop on ``max_steps`` CG iterations and on an energy below
``e_abort`` (status ``BELOW``). With the force rule, a minimisation whose residual has
not halved during ``max(STALL_MIN, STALL_PER_DISK n)`` iterations ends with ``STALLED``:
that happens at the float64 floor (``kernels.jamming.energy_floor``), where force
differences between nearby points are rounding noise and conjugacy is lost (measured:
N = 1024 at E_G = 1e-16 stagnates near a residual of 3e-6, docs/MINIMIZERS.md).
Status codes and the returned tuple are FIRE's.

Jitted core, same calling convention as ``kernels.fire._fire_core`` but for the
line search's first step and the energy rule:
``_cg_core(positions, radii, box, alpha, tol, max_steps, skin, step0, e_abort, e_tol)``.
Checked wrapper: ``minimize(...) -> FireResult``.
"""

import numpy as np
from numba import njit

from kernels.minimiser import (_checked_minimize_inputs, _residual_core, _starting_timestep, _verlet_rows,
                               fire_result)
from kernels.linesearch import (C1, E_ROUND, LS_MAX, _dot, _line_search,  # noqa: F401 (C1, E_ROUND, LS_MAX: re-exported)
                                _max_norm2, energy_resolution)
from kernels.potential import _energy_forces_rows
from kernels.rules import BELOW, CHECK_EVERY, CONVERGED, DT_FACTOR, MAX_STEPS, STALLED
from kernels.space import _wrap_inplace, _wrap_with

SIGMA = 0.1  # strong Wolfe curvature parameter
RESTART_EVERY = 1000  # iterations between forced steepest-descent restarts
DISP_CAP = 0.5  # largest displacement of any disk in one trial point, in units of the skin
FAILS_MAX = 2  # consecutive failed line searches that end the minimisation (STALLED)
STALL_MIN = 20_000  # iterations without the force residual halving that end it (STALLED) ...
STALL_PER_DISK = 100  # ... or this many per disk, whichever is larger


@njit(cache=True)
def _cg_core(positions, radii, box, alpha, tol, max_steps, skin, step0, e_abort, e_tol):
    """Minimise the total energy in place (``positions`` is overwritten).

    ``tol``: force-residual tolerance (used when ``e_tol == 0``); ``max_steps``: bound
    on CG iterations (line searches); ``skin``: Verlet skin (absolute length);
    ``step0``: first trial step of the first line search (displacement = step0 * F,
    about 1/stiffness of a contact); ``e_abort``: stop with status ``BELOW`` once the
    total energy is below it (0 disables); ``e_tol``: > 0 selects the energy-change
    rule (per disk, absolute) instead of the force residual.

    Returns ``(status, steps, force_evaluations, energy, virial, residual,
    n_contacts)`` as ``_fire_core``.
    """
    n = positions.shape[0]
    frc = np.empty((n, 2))
    ftr = np.empty((n, 2))
    d = np.empty((n, 2))
    trial = np.empty((n, 2))
    scratch = np.empty((n, 2))
    _wrap_inplace(positions, box)
    ref = np.empty((n, 2))
    pi, pj, start, nbr, inv_s = _verlet_rows(positions, radii, box, skin, radii, ref)
    cap = DISP_CAP * skin
    energy, virial, nc, fsum = _energy_forces_rows(positions, box, start, nbr, inv_s, alpha, frc)
    nforce = 1
    for i in range(n):
        d[i, 0] = frc[i, 0]
        d[i, 1] = frc[i, 1]
    restart = True
    since_restart = 0
    t_prev = step0
    g_prev = 0.0
    fails = 0
    status = MAX_STEPS
    residual = np.inf
    step = 0
    e_change = np.inf
    stall_iters = max(STALL_MIN, STALL_PER_DISK * n)
    res_ref = np.inf  # residual at the last halving
    step_ref = 0
    while True:
        if e_abort > 0.0 and energy < e_abort:
            status = BELOW
            residual = -1.0
            break
        if nc == 0:
            status = CONVERGED
            residual = 0.0
            break
        ff = _dot(frc, frc)
        if ff == 0.0:
            status = CONVERGED
            residual = _residual_core(positions, radii, box, pi, pj, alpha, scratch)[0]
            break
        if e_tol > 0.0:
            if e_change < e_tol * n:
                status = CONVERGED
                residual = _residual_core(positions, radii, box, pi, pj, alpha, scratch)[0]
                break
        else:
            mean_f = fsum / nc
            bound = np.sqrt(_max_norm2(frc)) / mean_f if mean_f > 0.0 else 0.0
            if bound < tol or step % CHECK_EVERY == 0 or step >= max_steps:
                residual = _residual_core(positions, radii, box, pi, pj, alpha, scratch)[0]
                if residual < tol:
                    status = CONVERGED
                    break
                if residual < 0.5 * res_ref:
                    res_ref = residual
                    step_ref = step
                elif step - step_ref >= stall_iters:
                    status = STALLED
                    break
        if step >= max_steps:
            status = MAX_STEPS
            if e_tol > 0.0:
                residual = _residual_core(positions, radii, box, pi, pj, alpha, scratch)[0]
            break
        step += 1

        # ---- direction: d = F (restart) or PR+ update done after the previous step
        g0 = -_dot(frc, d)
        if restart or since_restart >= RESTART_EVERY or g0 >= 0.0:
            for i in range(n):
                d[i, 0] = frc[i, 0]
                d[i, 1] = frc[i, 1]
            g0 = -ff
            since_restart = 0
            restart = False
        since_restart += 1
        steepest = since_restart == 1

        # ---- line search on phi(t) = E(x + t d), phi'(t) = -F(x + t d).d
        _wrap_with(positions, ref, box)
        dmax = np.sqrt(_max_norm2(d))
        t_cap = cap / dmax
        if g_prev < 0.0:
            t = t_prev * g_prev / g0  # Nocedal-Wright: same first-order change as last time
        else:
            t = step0
        if t > t_cap:
            t = t_cap
        e_res = energy_resolution(box, fsum)
        accepted, at_cap, t, e_t, w_t, nc_t, fs_t, nf, pi, pj, start, nbr, inv_s = _line_search(
            positions, d, t, t_cap, g0, energy, e_res, SIGMA, ref, radii, box, skin, alpha, pi, pj,
            start, nbr, inv_s, trial, ftr)
        nforce += nf
        if not accepted:
            fails += 1
            restart = True
            g_prev = 0.0
            if fails >= FAILS_MAX and steepest:
                status = STALLED
                residual = _residual_core(positions, radii, box, pi, pj, alpha, scratch)[0]
                break
            continue
        fails = 0
        # ---- accept: PR+ direction for the next iteration
        ff_new = _dot(ftr, ftr)
        fy = min(ff_new - _dot(ftr, frc), ff_new)
        beta = fy / ff if fy > 0.0 else 0.0
        for i in range(n):
            positions[i, 0] = trial[i, 0]
            positions[i, 1] = trial[i, 1]
            frc[i, 0] = ftr[i, 0]
            frc[i, 1] = ftr[i, 1]
            d[i, 0] = ftr[i, 0] + beta * d[i, 0]
            d[i, 1] = ftr[i, 1] + beta * d[i, 1]
        e_change = abs(e_t - energy)
        energy = e_t
        virial = w_t
        nc = nc_t
        fsum = fs_t
        t_prev = t
        g_prev = g0
        if at_cap:
            restart = True
            g_prev = 0.0
    _wrap_inplace(positions, box)
    return status, step, nforce, energy, virial, residual, nc


def minimize(positions, radii, box, exponent=2.0, *, force_tolerance=1e-6, max_steps=100_000,
             skin=None, step=None, energy_tolerance=None):
    """Minimise the pair energy with Polak-Ribiere+ conjugate gradients (checked wrapper).

    ``force_tolerance``: stop on the force residual (as ``kernels.fire.minimize``);
    ``energy_tolerance`` (None: not used): stop instead once one CG step changes the
    energy per disk by less than it (the paper's rule). ``max_steps`` bounds the CG
    iterations. ``skin`` defaults to 0.3 times the mean diameter; ``step`` (the first
    trial step, in units of length / force) to one over a contact's stiffness at the
    starting energy.
    """
    pos, rad, b, a, tol, skin = _checked_minimize_inputs(positions, radii, box, exponent,
                                                         force_tolerance, max_steps, skin)
    e_tol = 0.0
    if energy_tolerance is not None:
        e_tol = float(energy_tolerance)
        if not (np.isfinite(e_tol) and e_tol > 0):
            raise ValueError("energy_tolerance: expected None or a finite number > 0, got "
                             f"{energy_tolerance!r}")
    if step is None:
        step = first_step(_starting_timestep(pos, rad, b, a))
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"step: expected a finite number > 0, got {step!r}")
    res = _cg_core(pos, rad, b, a, tol, int(max_steps), skin, float(step), 0.0, e_tol)
    return fire_result(pos, b, res)


def first_step(dt0):
    """First line-search step from a FIRE time step: ``dt0 = DT_FACTOR / sqrt(k)``
    (``kernels.minimiser._dt_for``) gives ``1 / k``, the step that would relax one
    contact of stiffness ``k`` exactly."""
    return (dt0 / DT_FACTOR) ** 2
