"""Pressure route to a jammed packing: FIRE with a radius-scale degree of freedom (numba).

Instead of the O'Hern ladder (minimise at fixed radii, rescale, minimise again, ...),
the positions relax *together with* the common radius scale ``lambda`` (radii
``lambda r0`` in the fixed box; equivalent to a box scaled by ``1/lambda`` at fixed
radii) toward a target virial pressure ``P_t``. The function minimised is the
enthalpy-like

    H(x, lambda) = U(x, lambda r0) - 2 A P_t ln(lambda)

(``A = Lx Ly``). Since ``dU/d ln(lambda) = W = sum_pairs r f`` (the virial) at fixed
positions, ``-dH/d ln(lambda) = 2 A P_t - W = 2 A (P_t - P)``: a stationary point is a
force-balanced packing at pressure ``P_t`` (fixed-pressure jamming, e.g. Dagois-Bohy,
Tighe, Simon, Henkes and van Hecke, PRL 109, 095703 (2012); Goodrich, Liu and Nagel's
finite-size studies). H is bounded below (``U >= 0`` grows with ``lambda``; the log
term diverges as ``lambda -> 0``), so FIRE cannot run away.

The barostat coordinate is ``u = c ln(lambda)`` with ``c = BARO_SCALE * d sqrt(n)``
(``d`` the mean diameter at ``lambda = 1``): the affine stiffness ``d^2 H / d ln(lambda)^2
~ N_c (alpha - 1) x^(alpha - 2)`` grows with the number of contacts while a disk's
stiffness is ``~ (alpha - 1) x^(alpha - 2) / d^2``, so with this ``c`` the barostat mode is
about as stiff as the particle modes at every N and every exponent and the FIRE time
step of ``kernels.protocol._dt_for`` serves both.

Route (``_pressure_core``):

1. Relax the random start at its radii (FIRE at fixed radii to ``search_tolerance``, as
   the first minimisation of the O'Hern search; a start that unjams, ``E_G < E_min / 2``,
   goes straight to step 3 with the pressure of the scaling forms below).
2. Stages: minimise H at a target ``P_t`` aimed ``STAGE_STEP`` (100) lower in energy than
   the latest minimum, never below the goal ``E_goal = E_min (1 + AIM window)``. Near
   jamming ``E_G ~ P^(alpha / (alpha - 1))`` (``E_G ~ x^alpha``, ``P ~ x^(alpha - 1)`` with
   ``x`` the typical relative overlap), so ``P_t = P (E_stage / E_G)^((alpha - 1) / alpha)``
   from the measured ``P`` and ``E_G``. An enthalpy minimum has a particle force residual
   below ``search_tolerance`` and ``|P - P_t| <= PRESSURE_TOL P_t``.
3. At the goal: if ``E_G`` is in the window, polish at fixed radii to ``force_tolerance``
   with ``kernels.fire._fire_core``; done when the polished minimum is still in the
   window (a polish in which the energy creeps below ``E_min`` is stopped there and the
   same ``P_t`` recompresses the packing). Otherwise correct ``P_t`` by a secant step in
   ``(ln P, ln E)`` (slope from the two latest minima when it lies within a factor 2 of
   the scaling value ``alpha / (alpha - 1)``, else the scaling value) and minimise H
   again from the current state. Everything is done on pressures and forces: at
   ``E_G = 1e-16`` energy *differences* are below the float64 rounding of the total
   energy, the energy itself is not.

Each stage costs about as many force evaluations as one minimisation of the O'Hern
search with the secant rule (the slow part is the same: relaxing the soft modes near
jamming from a residual of 1e-2 to 1e-4), and there are half as many stages, but the
stages are larger steps: over seeds the two routes cost about the same
(docs/PRESSURE_ROUTE.md has the measurements).

Bounds, status codes and the returned tuple are those of ``kernels.protocol.ohern_search``:
``max_search`` bounds the minimisations (each enthalpy minimisation and each polish
counts one), ``max_steps`` the FIRE steps of each.
"""

import numpy as np
from numba import njit

from kernels.fire import _fire_adapt, _fire_core, _fire_kick, _fire_mix_move, _fire_power, _fire_retreat
from kernels.minimiser import _dt_for, _residual_core, _verlet_rows
from kernels.potential import _energy_forces_rows_scaled
from kernels.protocol import (ST_CONVERGED, ST_MAX_SEARCH, ST_MAX_STEPS, ST_STALLED, ST_TOO_DENSE,
                              _spatial_order)
from kernels.rules import (A_START, ABORT_FRACTION, AIM, BELOW, CHECK_EVERY, CONVERGED, DT_MAX_FACTOR,
                           DT_MIN_FACTOR, E_FIRST_GUESS, MAX_STEPS, N_NEG_MAX, STALLED)
from kernels.space import _wrap_core, _wrap_inplace

BARO_SCALE = 0.5  # barostat coordinate u = BARO_SCALE d sqrt(n) ln(lambda)
PRESSURE_TOL = 1e-3  # relative pressure accuracy of an enthalpy minimum
CONTACTS_PER_DISK = 2.0  # N_c / N of the first pressure estimate (isostatic: 2)
STAGE_STEP = 1e-2  # energy factor between pressure stages


@njit(cache=True)
def _enthalpy_core(positions, radii0, box, alpha, p_target, lam, tol, ptol, max_steps, skin,
                   dt0, c_baro, lam_max):
    """FIRE 2.0 on positions and ``u = c_baro ln(lambda)`` at target pressure ``p_target``.

    ``positions`` are overwritten. Converged when the particle force residual (on
    non-rattlers, relative to the mean contact force, at radii ``lambda radii0``) is
    below ``tol`` and ``|P - p_target| <= ptol p_target``. Stops with ``STALLED`` when
    ``lambda`` exceeds ``lam_max`` (the box is too small for the disks).

    Returns ``(status, lam, steps, force_evaluations, energy, virial, residual)``.
    """
    n = positions.shape[0]
    two_a_p = 2.0 * box[0] * box[1] * p_target
    dt_max = DT_MAX_FACTOR * dt0
    dt_min = DT_MIN_FACTOR * dt0
    dt = dt0
    a = A_START
    vel = np.zeros((n, 2))
    frc = np.empty((n, 2))
    scratch = np.empty((n, 2))
    radii = np.empty(n)
    s0max = 0.0
    for i in range(n):
        if 2.0 * radii0[i] > s0max:
            s0max = 2.0 * radii0[i]
    u = c_baro * np.log(lam)
    vu = 0.0
    _wrap_inplace(positions, box)
    ref = np.empty((n, 2))
    lam_ref = lam
    for i in range(n):
        radii[i] = lam * radii0[i]
    pi, pj, start, nbr, inv_s0 = _verlet_rows(positions, radii, box, skin, radii0, ref)
    energy, virial, nc, fsum = _energy_forces_rows_scaled(positions, box, start, nbr, inv_s0,
                                                          1.0 / lam, alpha, frc)
    fu = (two_a_p - virial) / c_baro
    nforce = 1
    n_pos = 0
    n_neg = 0
    status = MAX_STEPS
    residual = np.inf
    step = 0
    while True:
        fmax2, ff, p = _fire_power(frc, vel, fu * fu, fu * vu)
        p_ok = abs(virial - two_a_p) <= ptol * two_a_p
        mean_f = fsum / nc if nc > 0 else 0.0
        bound = np.sqrt(fmax2) / mean_f if mean_f > 0.0 else np.inf
        if p_ok and (bound < tol or step % CHECK_EVERY == 0 or step >= max_steps):
            for i in range(n):
                radii[i] = lam * radii0[i]
            residual = _residual_core(positions, radii, box, pi, pj, alpha, scratch)[0]
            if residual < tol and nc > 0:
                status = CONVERGED
                break
        if step >= max_steps:
            status = MAX_STEPS
            break
        if lam > lam_max:
            status = STALLED
            break
        step += 1
        n_pos, n_neg, dt, a = _fire_adapt(p, step, n_pos, n_neg, dt, a, dt_min, dt_max)
        if p <= 0.0:
            if n_neg > N_NEG_MAX:
                status = STALLED
                break
            _fire_retreat(positions, vel, dt)
            u -= 0.5 * dt * vu
            vu = 0.0
        vu += dt * fu
        vv = _fire_kick(vel, frc, dt, vu * vu)
        mix = a * np.sqrt(vv / ff) if ff > 0.0 else 0.0
        disp2 = _fire_mix_move(positions, vel, frc, a, mix, dt, ref)
        vu = (1.0 - a) * vu + mix * fu
        u += dt * vu
        lam = np.exp(u / c_baro)
        # a pair outside the list can only touch once 2 max|dr| + (lambda - lambda_ref)
        # s0_max exceeds the skin
        grow = (lam - lam_ref) * s0max
        if grow < 0.0:
            grow = 0.0
        if 2.0 * np.sqrt(disp2) + grow > skin:
            _wrap_inplace(positions, box)
            for i in range(n):
                radii[i] = lam * radii0[i]
            pi, pj, start, nbr, inv_s0 = _verlet_rows(positions, radii, box, skin, radii0, ref)
            lam_ref = lam
        energy, virial, nc, fsum = _energy_forces_rows_scaled(positions, box, start, nbr, inv_s0,
                                                              1.0 / lam, alpha, frc)
        fu = (two_a_p - virial) / c_baro
        nforce += 1
    return status, lam, step, nforce, energy, virial, residual


@njit(cache=True)
def _pressure_core(positions, radii0, box, alpha, e_min, window, tol, search_tol, max_search,
                   max_steps, skin_factor, max_radius, stage_step, baro_scale, verbose):
    """Run the pressure route in place; arguments and returned tuple as in
    ``kernels.protocol.ohern_search`` (``scale`` is the final ``lambda``)."""
    n = positions.shape[0]
    area = box[0] * box[1]
    e_max = e_min * (1.0 + window)
    e_goal = e_min * (1.0 + AIM * window)
    mean_d = 0.0
    rmax0 = 0.0
    for i in range(n):
        mean_d += 2.0 * radii0[i]
        if radii0[i] > rmax0:
            rmax0 = radii0[i]
    mean_d /= n
    lam_max = max_radius / rmax0
    c_baro = baro_scale * mean_d * np.sqrt(n)
    expo = alpha / (alpha - 1.0)  # E ~ P^expo near jamming
    # the pressure of E_goal from the scaling forms with N_c = CONTACTS_PER_DISK n contacts,
    # used when no jammed state has been measured
    x = (alpha * e_goal / CONTACTS_PER_DISK) ** (1.0 / alpha)
    p_goal = CONTACTS_PER_DISK * n * x ** (alpha - 1.0) / (2.0 * area)
    p_t = p_goal
    e_stage = np.inf
    order = np.arange(n)
    pos = positions.copy()
    rad0 = radii0.copy()
    radii = radii0.copy()
    lam = 1.0
    lp1 = 0.0
    le1 = 0.0
    have1 = False
    it = 0
    nforce = 0
    status = ST_MAX_SEARCH
    e_last = 0.0
    w_last = 0.0
    res_last = np.inf
    e_guess = max(e_goal, E_FIRST_GUESS)
    abort = ABORT_FRACTION * e_min * n
    while True:
        it += 1
        skin = skin_factor * mean_d * lam
        dt0 = _dt_for(rad0 * lam, alpha, e_guess)
        if it == 1:
            # relax the random start at its radii, as the first O'Hern minimisation
            st, steps, nf, e, w, res, nc = _fire_core(pos, radii, box, alpha, search_tol,
                                                      max_steps, skin, dt0, abort)
        else:
            st, lam, steps, nf, e, w, res = _enthalpy_core(pos, rad0, box, alpha, p_t, lam,
                                                           search_tol, PRESSURE_TOL, max_steps,
                                                           skin, dt0, c_baro, lam_max)
        nforce += nf
        if verbose:
            print(it, st, steps, nf, e / n, w / (2.0 * area) / p_t, res, lam)
        if it == 1:
            # the random start has relaxed: reorder the disks by cell
            perm = _spatial_order(pos, box, mean_d)
            pos = pos[perm].copy()
            rad0 = rad0[perm].copy()
            order = order[perm].copy()
        e_last = e
        w_last = w
        res_last = res
        eg = e / n
        if st == MAX_STEPS:
            status = ST_MAX_STEPS
            break
        if it == 1 and (st == BELOW or (st == CONVERGED and eg <= 0.0)):
            # unjammed at the start's radii: go straight to the goal's pressure
            e_stage = e_goal
            if it >= max_search:
                status = ST_MAX_SEARCH
                break
            continue
        if st != CONVERGED:
            status = ST_TOO_DENSE if lam > lam_max else ST_STALLED
            break
        if eg > 0.0:
            e_guess = eg
        if e_stage > e_goal and eg > e_max:
            # an intermediate stage: aim STAGE_STEP lower with the scaling exponent
            e_stage = max(e_goal, min(e_stage, eg) * stage_step)
            p_t = w / (2.0 * area) * (e_stage / eg) ** (1.0 / expo)
            if it >= max_search:
                status = ST_MAX_SEARCH
                break
            continue
        if e_min <= eg <= e_max:
            if it >= max_search:
                status = ST_MAX_SEARCH
                break
            it += 1
            for i in range(n):
                radii[i] = lam * rad0[i]
            skin = skin_factor * mean_d * lam
            dt0 = _dt_for(radii, alpha, e_guess)
            # stopped as soon as the energy leaves the window below: a polish that creeps
            # out of the window cannot end in it, and below E_min the forces approach
            # the float64 floor (a creep to 0.6 E_min stalled at a residual of 3e-6)
            st, steps, nf, e, w, res, nc = _fire_core(pos, radii, box, alpha, tol, max_steps,
                                                      skin, dt0, e_min * n)
            nforce += nf
            e_last = e
            w_last = w
            res_last = res
            eg = e / n
            if st == BELOW:
                # the packing rearranged and left the window below at these radii: back
                # to the same target pressure, which recompresses it (no secant from here)
                have1 = False
                if it >= max_search:
                    status = ST_MAX_SEARCH
                    break
                continue
            if st == MAX_STEPS:
                status = ST_MAX_STEPS
                break
            if st != CONVERGED:
                status = ST_STALLED
                break
            if e_min <= eg <= e_max:
                status = ST_CONVERGED
                break
        if it >= max_search:
            status = ST_MAX_SEARCH
            break
        # secant step in (ln P, ln E) toward e_goal
        lp = np.log(w / (2.0 * area)) if w > 0.0 else np.log(p_t)
        le = np.log(eg) if eg > 0.0 else np.log(e_goal) - 2.0 * expo
        slope = expo
        if have1 and lp != lp1:
            s2 = (le - le1) / (lp - lp1)
            if 0.5 * expo < s2 < 2.0 * expo:
                slope = s2
        lp1 = lp
        le1 = le
        have1 = True
        p_t = np.exp(lp + (np.log(e_goal) - le) / slope)
    wrapped = _wrap_core(pos, box)
    for i in range(n):
        positions[order[i], 0] = wrapped[i, 0]
        positions[order[i], 1] = wrapped[i, 1]
    return status, lam, e_last, w_last, res_last, it, nforce

