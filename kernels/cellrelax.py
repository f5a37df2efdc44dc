"""FIRE 2.0 on the disks and the cell's shape at fixed area: shear-stabilised minima (numba).

The cell ``box = [Lx, Ly, xy]`` (``kernels.space``) has two shape degrees of freedom at fixed
area ``A = Lx Ly``: simple shear (the tilt ``xy``) and pure shear (the aspect ratio). Both are
moved by a deformation of the whole configuration, fractional coordinates fixed,

    F = [[e^eps, gamma], [0, e^-eps]]      r -> F r,  (Lx, Ly, xy Ly) -> (e^eps Lx, A / Lx', e^eps xy Ly + gamma Ly),

whose generalised forces are (``docs/PHYSICS.md``; ``S_ab = sum over contacts f r_a r_b / r``, the
stress tensor times the area)

    -dU/dgamma = S_xy = A sigma_xy,      -dU/deps = S_xx - S_yy = A (sigma_xx - sigma_yy).

FIRE moves ``q = (sqrt(A) gamma, sqrt(A) eps)`` with the forces ``(S_xy, S_xx - S_yy) / sqrt(A)``
beside the disks (unit masses): the cell's stiffness along ``q`` is then of the order of the
shear modulus, below the stiffest contact's, so FIRE's time step stays stable. Each step's
change of ``q`` is applied at once as a deformation ``F`` of the positions, of the Verlet
list's reference positions (so that the list's displacement test sees only non-affine motion)
and of the cell; ``Ly = A / Lx`` keeps the area exact. A tilt beyond ``|xy| > 1/2`` is reduced
by a lattice change (``xy -> xy - round(xy)``, the same lattice). The Verlet list is rebuilt
once twice the largest non-affine displacement plus the strain since the last build times the
list's range could exceed the skin.

Converged when the largest net force on any disk, rattlers included, is below ``tol`` times
the mean contact force (``kernels.fire`` leaves rattlers out of its residual; here a rattler
left overlapping would carry stress that the cell balances, up to 1e-3 of the pressure, measured,
which the cell would no longer balance once the rattler leaves its contacts) and the cell's
residual stress ``max(|sigma_xy|, |sigma_xx - sigma_yy| / 2) / p`` is below ``tol`` too. Stops with
``STALLED`` when the cell's shorter side would leave no room for the list's range (twice
``2 r_max + skin`` must stay below ``min(Lx, Ly)``).

Jitted cores: ``_stress_rows`` (forces, energy, virial and ``S``), ``_fire_cell_core`` (the
minimiser, same arguments and returns as ``kernels.fire._fire_core`` with ``box`` updated in
place).
"""

import numpy as np
from numba import njit

from kernels.fire import _fire_adapt, _fire_kick, _fire_mix_move, _fire_power, _fire_retreat
from kernels.minimiser import _verlet_rows
from kernels.potential import pair_energy_force_inv
from kernels.rules import (A_START, BELOW, CONVERGED, DT_MAX_FACTOR, DT_MIN_FACTOR, MAX_STEPS,
                           N_NEG_MAX, STALLED)
from kernels.space import _wrap_inplace, near_image


@njit(cache=True)
def _stress_rows(positions, box, start, nbr, inv_s, alpha, forces, stress):
    """``kernels.potential._energy_forces_rows`` that also sums the stress tensor times the
    area into ``stress`` = ``[S_xx, S_yy, S_xy]`` (``S_ab = sum f r_a r_b / r``). A copy of that
    loop, not a switch inside it: the fixed cell's force loop stays as it was (its speed depends
    on its machine code, ``kernels.protocol``)."""
    n = positions.shape[0]
    Lx = box[0]
    Ly = box[1]
    tilt = box[2] * Ly
    hx = 0.5 * Lx
    hy = 0.5 * Ly
    for i in range(n):
        forces[i, 0] = 0.0
        forces[i, 1] = 0.0
    energy = 0.0
    virial = 0.0
    ncontact = 0
    fsum = 0.0
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    for i in range(n):
        xi = positions[i, 0]
        yi = positions[i, 1]
        fxi = 0.0
        fyi = 0.0
        for k in range(start[i], start[i + 1]):
            j = nbr[k]
            dx = positions[j, 0] - xi
            dy = positions[j, 1] - yi
            dx, dy = near_image(dx, dy, Lx, Ly, tilt, hx, hy)
            d2 = dx * dx + dy * dy
            q = inv_s[k]
            if d2 * q * q >= 1.0:
                continue
            r = np.sqrt(d2)
            v, f = pair_energy_force_inv(r, q, alpha)
            energy += v
            virial += r * f
            ncontact += 1
            fsum += f
            if r > 0.0:
                fr = f / r
                fx = fr * dx
                fy = fr * dy
                sxx += fx * dx
                syy += fy * dy
                sxy += fx * dy
                fxi -= fx
                fyi -= fy
                forces[j, 0] += fx
                forces[j, 1] += fy
        forces[i, 0] += fxi
        forces[i, 1] += fyi
    stress[0] = sxx
    stress[1] = syy
    stress[2] = sxy
    return energy, virial, ncontact, fsum


@njit(cache=True)
def _deform(positions, ref, box, area, dg, de):
    """Apply ``F = [[e^de, dg], [0, e^-de]]`` to ``positions``, ``ref`` and the cell (area kept
    exact, the tilt offset reduced to ``|xy Ly| <= Lx / 2``)."""
    ex = np.exp(de)
    ey = np.exp(-de)
    for i in range(positions.shape[0]):
        positions[i, 0] = ex * positions[i, 0] + dg * positions[i, 1]
        positions[i, 1] = ey * positions[i, 1]
        ref[i, 0] = ex * ref[i, 0] + dg * ref[i, 1]
        ref[i, 1] = ey * ref[i, 1]
    tilt = ex * box[2] * box[1] + dg * box[1]
    box[0] = ex * box[0]
    box[1] = area / box[0]
    if abs(tilt) > 0.5 * box[0]:  # b -> b - m a: the same lattice
        tilt -= box[0] * np.floor(tilt / box[0] + 0.5)
    box[2] = tilt / box[1]


@njit(cache=True)
def _strain_since(box, ref_box):
    """A bound on how much the deformation from ``ref_box`` to ``box`` changes a separation,
    relative to its length: the Frobenius norm of ``H H_ref^-1 - I`` (``H`` upper triangular)."""
    a = box[0] / ref_box[0]
    d = box[1] / ref_box[1]
    b = (box[2] * box[1] - a * ref_box[2] * ref_box[1]) / ref_box[1]
    return np.sqrt((a - 1.0) ** 2 + (d - 1.0) ** 2 + b * b)


@njit(cache=True)
def _cell_residual(stress, virial):
    """``max(|sigma_xy|, |sigma_xx - sigma_yy| / 2) / p`` (0 without contacts)."""
    if virial <= 0.0:
        return 0.0
    return max(abs(stress[2]), 0.5 * abs(stress[0] - stress[1])) * 2.0 / virial


@njit(cache=True)
def _fire_cell_core(positions, radii, box, alpha, tol, max_steps, skin, dt0, e_abort):
    """Minimise the energy in the positions and the cell's shape at fixed area, in place
    (``positions`` and ``box``). Arguments and returned tuple as ``kernels.fire._fire_core``;
    the residual returned is the larger of the force residual and the cell's."""
    n = positions.shape[0]
    area = box[0] * box[1]
    lam = np.sqrt(area)
    dt_max = DT_MAX_FACTOR * dt0
    dt_min = DT_MIN_FACTOR * dt0
    dt = dt0
    a = A_START
    n_pos = 0
    n_neg = 0
    rmax = 0.0
    for i in range(n):
        rmax = max(rmax, radii[i])
    reach = 2.0 * rmax + skin
    vel = np.zeros((n, 2))
    frc = np.empty((n, 2))
    stress = np.zeros(3)
    cv = np.zeros(2)  # the cell's velocities along q
    cf = np.zeros(2)  # and forces
    _wrap_inplace(positions, box)
    ref = np.empty((n, 2))
    ref_box = box.copy()
    pi, pj, start, nbr, inv_s = _verlet_rows(positions, radii, box, skin, radii, ref)
    energy, virial, nc, fsum = _stress_rows(positions, box, start, nbr, inv_s, alpha, frc, stress)
    nforce = 1
    status = MAX_STEPS
    residual = np.inf
    step = 0
    while True:
        if e_abort > 0.0 and energy < e_abort:
            status = BELOW
            residual = -1.0
            break
        if nc == 0:
            status = CONVERGED
            residual = 0.0
            break
        cf[0] = stress[2] / lam
        cf[1] = (stress[0] - stress[1]) / lam
        fmax2, ff, p = _fire_power(frc, vel, cf[0] * cf[0] + cf[1] * cf[1],
                                   cf[0] * cv[0] + cf[1] * cv[1])
        mean_f = fsum / nc
        # every disk force-balanced, rattlers too: a rattler left overlapping carries stress that
        # the cell would balance, and once it leaves its contacts the cell would not be
        residual = max(np.sqrt(fmax2) / mean_f if mean_f > 0.0 else 0.0,
                       _cell_residual(stress, virial))
        if residual < tol:
            status = CONVERGED
            break
        if step >= max_steps:
            break
        if min(box[0], box[1]) <= 2.0 * reach:
            status = STALLED
            break
        step += 1
        n_pos, n_neg, dt, a = _fire_adapt(p, step, n_pos, n_neg, dt, a, dt_min, dt_max)
        if p <= 0.0:
            if n_neg > N_NEG_MAX:
                status = STALLED
                break
            # half a step back, the cell with the disks
            _fire_retreat(positions, vel, dt)
            _deform(positions, ref, box, area, -0.5 * dt * cv[0] / lam, -0.5 * dt * cv[1] / lam)
            cv[0] = 0.0
            cv[1] = 0.0
        cv[0] += dt * cf[0]
        cv[1] += dt * cf[1]
        vv = _fire_kick(vel, frc, dt, cv[0] * cv[0] + cv[1] * cv[1])
        mix = a * np.sqrt(vv / ff) if ff > 0.0 else 0.0
        disp2 = _fire_mix_move(positions, vel, frc, a, mix, dt, ref)
        cv[0] = (1.0 - a) * cv[0] + mix * cf[0]
        cv[1] = (1.0 - a) * cv[1] + mix * cf[1]
        _deform(positions, ref, box, area, dt * cv[0] / lam, dt * cv[1] / lam)
        if 2.0 * np.sqrt(disp2) + 2.0 * _strain_since(box, ref_box) * reach > skin:
            _wrap_inplace(positions, box)
            pi, pj, start, nbr, inv_s = _verlet_rows(positions, radii, box, skin, radii, ref)
            ref_box[:] = box
        energy, virial, nc, fsum = _stress_rows(positions, box, start, nbr, inv_s, alpha, frc,
                                                stress)
        nforce += 1
    return status, step, nforce, energy, virial, residual, nc
