"""A line search on the directional derivative of the energy (numba), shared by the
conjugate-gradient minimiser (``kernels.cg``) and the Newton endgame (``kernels.newton``).

Along a direction ``d`` from ``x``, on ``phi(t) = E(x + t d)``: a bracketing secant search on
the *directional derivative* ``phi'(t) = -F(x + t d).d``. The potential is one-sided, so
``phi`` is piecewise smooth (C1 for alpha = 2: ``phi''`` jumps where a contact opens or
closes); ``phi'`` is nearly linear between such events and the secant step through two
derivatives is exact for a quadratic. A step ``t`` is accepted when

* ``|phi'(t)| <= sigma |phi'(0)|`` (strong Wolfe curvature condition), and
* ``phi(t) <= phi(0) + C1 t phi'(0)`` (Armijo), or, when the two energies differ by less than
  their float64 resolution ``e_res``, ``phi(t) <= phi(0) + e_res``.

The second branch is the "approximate Wolfe" idea of Hager and Zhang (SIAM J. Optim. 16, 170
(2005)): near a minimum at ``E_G ~ 1e-16`` energy differences between line search points are
far below rounding, while forces are still accurate, so the derivative decides. The
resolution of a computed total energy is ``e_res = E_ROUND eps max(Lx, Ly) sum_contacts |f|``
(``energy_resolution``): each pair energy inherits the rounding of its overlap, ``eps L`` from
coordinates of size ``L``, times its force.

A step that is still descending at the cap ``t_cap`` is taken (``at_cap``). Without an
acceptable step within ``LS_MAX`` evaluations, the longest step known to descend is taken if
it lowered the energy (also reported as ``at_cap``: not a Wolfe step); otherwise nothing is
accepted. The Verlet list is rebuilt at any trial point more than half the skin away from
the list's reference positions ``ref``.
"""

import numpy as np
from numba import njit

from kernels.minimiser import _verlet_rows
from kernels.potential import _energy_forces_rows

C1 = 1e-4  # Armijo parameter
LS_MAX = 30  # force evaluations per line search before it counts as failed
E_ROUND = 8.0  # e_res = E_ROUND * eps * max(Lx, Ly) * sum of contact forces
EPS = np.finfo(np.float64).eps


@njit(cache=True)
def energy_resolution(box, fsum):
    """Float64 resolution of a total energy whose contact forces sum to ``fsum``."""
    return E_ROUND * EPS * max(box[0], box[1]) * fsum


@njit(cache=True)
def _dot(a, b):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i, 0] * b[i, 0] + a[i, 1] * b[i, 1]
    return s


@njit(cache=True)
def _max_norm2(a):
    m = 0.0
    for i in range(a.shape[0]):
        v = a[i, 0] * a[i, 0] + a[i, 1] * a[i, 1]
        if v > m:
            m = v
    return m


@njit(cache=True)
def _max_disp2(a, b):
    m = 0.0
    for i in range(a.shape[0]):
        dx = a[i, 0] - b[i, 0]
        dy = a[i, 1] - b[i, 1]
        v = dx * dx + dy * dy
        if v > m:
            m = v
    return m


@njit(cache=True)
def _along(positions, t, d, out):
    """``out = positions + t d``: the trial point at step ``t`` of the line search."""
    for i in range(positions.shape[0]):
        out[i, 0] = positions[i, 0] + t * d[i, 0]
        out[i, 1] = positions[i, 1] + t * d[i, 1]


@njit(cache=True)
def _line_search(positions, d, t, t_cap, g0, energy, e_res, sigma, ref, radii, box, skin, alpha,
                 pi, pj, start, nbr, inv_s, trial, ftr):
    """Line search from ``positions`` along ``d`` (see the module docstring), first trial
    step ``t``, largest step ``t_cap``, ``g0 = phi'(0) < 0``, ``energy = phi(0)``. The trial
    point and its forces are left in ``trial`` and ``ftr``.

    Returns ``(accepted, at_cap, t, energy, virial, n_contacts, sum_contact_force,
    force_evaluations, pi, pj, start, nbr, inv_s)``: the accepted step's values and the
    (possibly rebuilt) Verlet list.
    """
    t_lo = 0.0
    g_lo = g0
    t_hi = -1.0
    g_hi = 0.0
    hi_secant = False
    t_last = 0.0
    g_last = g0
    accepted = False
    at_cap = False
    e_t = energy
    w_t = 0.0
    nc_t = 0
    fs_t = 0.0
    nforce = 0
    half2 = 0.25 * skin * skin
    for ls in range(LS_MAX):
        _along(positions, t, d, trial)
        if _max_disp2(trial, ref) > half2:
            pi, pj, start, nbr, inv_s = _verlet_rows(trial, radii, box, skin, radii, ref)
        e_t, w_t, nc_t, fs_t = _energy_forces_rows(trial, box, start, nbr, inv_s, alpha, ftr)
        nforce += 1
        g_t = -_dot(ftr, d)
        ok_energy = e_t <= energy + C1 * t * g0 or abs(e_t - energy) <= e_res
        if ok_energy and abs(g_t) <= sigma * (-g0):
            accepted = True
            break
        if ok_energy and g_t < 0.0 and t >= t_cap:
            # still descending at the largest step allowed: take it, then restart
            accepted = True
            at_cap = True
            break
        if g_t >= 0.0 or not ok_energy:
            t_hi = t
            g_hi = g_t
            # secant only across a sign change of phi'; a rise while phi' < 0 bisects
            hi_secant = g_t >= 0.0 and ok_energy
        else:
            t_lo = t
            g_lo = g_t
        if t_hi < 0.0:
            # no bracket yet: extrapolate with the secant of the last two derivatives
            t_new = 4.0 * t
            if g_t > g_last:
                t_sec = t - g_t * (t - t_last) / (g_t - g_last)
                t_new = min(max(t_sec, 1.05 * t), 10.0 * t)
            if t_new > t_cap:
                t_new = t_cap
        else:
            w = t_hi - t_lo
            t_new = t_lo + 0.5 * w
            if hi_secant and g_hi > g_lo:
                t_sec = t_lo - g_lo * w / (g_hi - g_lo)
                t_new = min(max(t_sec, t_lo + 0.01 * w), t_hi - 0.01 * w)
        t_last = t
        g_last = g_t
        t = t_new
    if not accepted and t_lo > 0.0:
        # fall back to the longest step known to descend, if it lowered the energy
        t = t_lo
        _along(positions, t, d, trial)
        if _max_disp2(trial, ref) > half2:
            pi, pj, start, nbr, inv_s = _verlet_rows(trial, radii, box, skin, radii, ref)
        e_t, w_t, nc_t, fs_t = _energy_forces_rows(trial, box, start, nbr, inv_s, alpha, ftr)
        nforce += 1
        if e_t <= energy + C1 * t * g0 or abs(e_t - energy) <= e_res:
            accepted = True
            at_cap = True  # not a Wolfe step: restart the directions
    return accepted, at_cap, t, e_t, w_t, nc_t, fs_t, nforce, pi, pj, start, nbr, inv_s
