"""Newton endgame of a minimisation at fixed radii (numba).

Near jamming FIRE (and CG) spend almost all their force evaluations relaxing the soft modes of
a contact network that hardly changes any more: from a force residual of 1e-2 to 1e-6 costs
10 000 - 90 000 evaluations at N = 1024 (docs/PRESSURE_ROUTE.md), while the network's own
linear algebra solves those modes at once. The endgame (``_fire_newton``) therefore runs FIRE
until the residual is below ``HANDOFF`` (the network has settled), then Newton's method
(``_newton_core``) on the Hessian of the contact network (``kernels.hessian``), factored by
the sparse Cholesky of ``kernels.sparse``:

* **Pattern.** The Hessian lives on a *pattern*, the pairs closer than their contact distance
  plus ``PATTERN_SKIN`` mean diameters (a Verlet list, also used for the forces); pairs out of
  contact are explicit zeros. The ordering and symbolic analysis are done once per pattern;
  every iteration refactors numerically on it. The pattern is rebuilt (a new symbolic
  analysis) once a disk has moved a quarter of the skin from where it was built, and no step
  moves a disk further than ``0.4`` skins from there, so no pair outside the pattern can come
  into contact.
* **Step.** ``(H + D) p = F``, ``F`` the net forces, ``D`` a diagonal shift relative to the
  mean contact stiffness ``k0``: ``mu k0`` on disks that carry load and ``RATTLER_SHIFT k0`` on
  the current rattlers (``kernels.network``'s rule), whose blocks are singular or indefinite
  (a disk with one compressed contact is unstable sideways). ``mu`` starts at ``MU_MIN`` (it
  also lifts the two translations off zero), grows tenfold (at least to ``MU_FAIL``) when the
  factorisation meets a pivot that is not positive (``kernels.sparse.PIVOT_REL``) and after a
  failed line search, and falls tenfold after a full step, never below ``MU_MIN``. A shifted
  matrix that still fails at ``MU_MAX`` ends the endgame (``FAILED``).
* **Step control.** The first trial step is cut so that no pair out of contact closes its gap
  by more than ``RATIO_OVERLAP`` typical overlaps ``x = (alpha E_G / 2)^(1/alpha)`` of a
  contact distance (a ratio test: new contacts enter the network a few at a time, at the
  overlaps they will have); the line search of ``kernels.linesearch`` (secant on the
  directional derivative, strong Wolfe with ``SIGMA``, Armijo or, below the energy's float64
  resolution, Hager and Zhang's approximate rule) may then lengthen or shorten it, up to the
  pattern's cap. **An accepted step never raises the computed energy by more than its float64
  resolution, and lowers it by at least ``C1 t |phi'(0)|`` wherever the fall is resolved.**
* **Start.** Newton starts only where the force residual is below ``HANDOFF`` and at least
  ``READY_FRACTION`` of the disks carry load (``NOT_READY`` otherwise, nothing moved).
* **Stopping.** The rattler-aware force residual of ``kernels.fire`` below ``tol``, at a
  certified minimum: the Hessian of the load-bearing network alone (rattlers and their
  contacts left out) plus ``mu k0`` must factor (``CONVERGED``), else the point is a saddle
  (``NOT_MINIMUM``), with ``mu = min(MU_CERT, CERT_PRESTRESS f / (k0 d))`` (``f`` the mean
  contact force, ``d`` the mean diameter). Shifted Newton converges to saddles as readily as
  to minima, and near jamming they are common: without this check minimisations of O'Hern
  searches at N = 1024 ended on saddles up to 3.6 times above the energy FIRE reached from the
  same start. A saddle's negative curvature is of the prestress's size ``f / d`` (about
  ``sqrt(E_G) k0``), so a fixed shift would accept the saddles of low energies: with
  ``MU_CERT k0`` alone, packings below E_G ~ 1e-12 ended on hypostatic saddles one or two
  contacts short. Also: the energy below the caller's abort
  level (``BELOW``); the residual not halved for ``STALL_ITERS`` iterations or ``FAILS_MAX``
  failed line searches in a row (``STALLED``); ``max_iter`` iterations (``MAX_STEPS``).

``_fire_newton`` tries Newton first and then after every ``PROBE_STEPS`` FIRE steps (FIRE's
velocities kept between turns unless Newton moved the packing) until one minimisation ends.
A saddle is left by FIRE from a small reproducible nudge (``NUDGE`` typical overlaps), and FIRE
alone finishes that minimisation: the negative curvature is weak, FIRE takes far longer than
one probe to leave the saddle, and Newton tried again lands on it again (one packing at
N = 512, E_G 1e-16 spent 6900 factorisations and 20 times FIRE's force evaluations so). FIRE is
the globally robust method, Newton the fast local one.

Jitted cores: ``_newton_core(...)`` and ``_fire_newton(...)`` (same calling convention and
return tuple as ``kernels.fire._fire_core``, plus the counts of factorisations, symbolic
analyses and Newton iterations).
"""

import numpy as np
from numba import njit

from kernels.fire import _fire_run, _fire_state
from kernels.minimiser import _residual_alive, _verlet_rows
from kernels.hessian import _hessian_rows
from kernels.linesearch import _dot, _line_search, _max_disp2, _max_norm2, energy_resolution
from kernels.potential import _energy_forces_rows
from kernels.rules import BELOW, CONVERGED, MAX_STEPS, STALLED
from kernels.sparse import (CUTS, _adjacency, _nd_order, _numeric_core, _solve_core,
                            _symbolic_core)
from kernels.space import _wrap_inplace, near_image

FAILED = 4  # the shifted Hessian was not positive definite even at MU_MAX
NOT_READY = 5  # Newton did not start: the network is not rigid yet
NOT_MINIMUM = 6  # Newton converged to a saddle: FIRE's turn, from a nudge

HANDOFF = 1e-2  # FIRE runs until the force residual is below this, then Newton
PATTERN_SKIN = 0.02  # pairs within their contact distance plus this many mean diameters
MU_MIN = 1e-10  # smallest diagonal shift, relative to the mean contact stiffness
MU_CERT = 1e-6  # a minimum's rattler-free Hessian plus this shift must be positive definite,
CERT_PRESTRESS = 1e-3  # or this fraction of the prestress scale f / (k0 d) if that is smaller
NUDGE = 1e-2  # a saddle is left with random displacements of this many typical overlaps
MU_FAIL = 1e-6  # shift after a failed factorisation or line search (then tenfold per failure)
MU_MAX = 1e-1  # a factorisation failing at this shift ends the endgame
RATTLER_SHIFT = 1.0  # diagonal shift of the current rattlers, relative to k0
RATIO_OVERLAP = 1.0  # the first trial closes no gap by more than this many typical overlaps
SIGMA = 0.9  # curvature parameter of the Newton line search
T_SHORT = 0.5  # an accepted step shorter than this raises the shift by MU_UP
MU_UP = 10.0
T_MAX = 1.0  # the line search never lengthens the Newton step beyond this
STALL_ITERS = 60  # iterations without the residual halving that end Newton (STALLED)
FAILS_MAX = 3  # failed line searches in a row that end Newton (STALLED)
READY_FRACTION = 0.5  # Newton needs at least this fraction of the disks to carry load
PROBE_STEPS = 2000  # FIRE steps between two tries of Newton
NEWTON_ITERS = 200  # Newton iterations per attempt before falling back to FIRE


@njit(cache=True)
def _ratio_step(positions, box, start, nbr, inv_s, p, budget):
    """Largest ``t <= 1`` at which no listed pair out of contact closes its gap by more than
    ``budget`` times its contact distance along ``t p`` (to first order)."""
    n = positions.shape[0]
    Lx = box[0]
    Ly = box[1]
    tilt = box[2] * Ly
    hx = 0.5 * Lx
    hy = 0.5 * Ly
    t = 1.0
    for i in range(n):
        for k in range(start[i], start[i + 1]):
            j = nbr[k]
            dx = positions[j, 0] - positions[i, 0]
            dy = positions[j, 1] - positions[i, 1]
            dx, dy = near_image(dx, dy, Lx, Ly, tilt, hx, hy)
            r = np.sqrt(dx * dx + dy * dy)
            s = 1.0 / inv_s[k]
            gap = r - s
            if gap <= 0.0:
                continue
            rate = (dx * (p[j, 0] - p[i, 0]) + dy * (p[j, 1] - p[i, 1])) / r
            if rate < 0.0:
                tk = (gap + budget * s) / (-rate)
                if tk < t:
                    t = tk
    return t


@njit(cache=True)
def _shifted(diag0, alive, mu, k0, diag):
    """``diag = diag0 + D``: ``mu k0`` on the disks that carry load, ``RATTLER_SHIFT k0`` on
    the rattlers (whose blocks are singular or indefinite)."""
    for v in range(diag0.shape[0]):
        sh = (mu if alive[v] else RATTLER_SHIFT) * k0
        diag[v, 0] = diag0[v, 0] + sh
        diag[v, 1] = diag0[v, 1]
        diag[v, 2] = diag0[v, 2] + sh


@njit(cache=True)
def _newton_core(positions, radii, box, alpha, tol, max_iter, pskin, e_abort):
    """Newton's method at fixed radii from ``positions`` (overwritten, wrapped at the end);
    see the module docstring.

    ``tol``: force-residual tolerance; ``max_iter``: bound on Newton iterations; ``pskin``:
    the pattern's skin (absolute length); ``e_abort``: ``BELOW`` once the total energy is
    below it (0 disables). Starts only where the network is ready (else ``NOT_READY`` with
    the positions unchanged) and ends ``CONVERGED`` only at a certified minimum (else
    ``NOT_MINIMUM``). Returns ``(status, iterations, force_evaluations, energy, virial,
    residual, n_contacts, factorisations, symbolic_analyses)``.
    """
    n = positions.shape[0]
    frc = np.empty((n, 2))
    ftr = np.empty((n, 2))
    trial = np.empty((n, 2))
    scratch = np.empty((n, 2))
    ref = np.empty((n, 2))
    step = np.empty((n, 2))
    diag = np.empty((n, 3))
    diag0 = np.empty((n, 3))
    ncon = np.empty(n, dtype=np.int64)
    everyone = np.ones(n, dtype=np.bool_)
    dbar = 2.0 * np.mean(radii)  # the typical contact distance, for the prestress scale
    mu = MU_MIN
    it = 0
    nforce = 0
    nfact = 0
    nsym = 0
    fails = 0
    best = np.inf
    best_it = 0
    status = MAX_STEPS
    residual = np.inf
    rebuild = True
    analysed = False
    # typed placeholders, set at the first rebuild
    pi = np.empty(0, dtype=np.int64)
    pj = np.empty(0, dtype=np.int64)
    start = np.zeros(n + 1, dtype=np.int64)
    nbr = np.empty(0, dtype=np.int32)
    inv_s = np.empty(0)
    off = np.empty((0, 3))
    lval = np.empty(0)
    energy = 0.0
    virial = 0.0
    nc = 0
    fsum = 0.0
    perm = np.arange(n)
    sup_first = np.zeros(2, dtype=np.int64)
    sup_nchild = np.zeros(1, dtype=np.int64)
    upd_ptr = np.zeros(2, dtype=np.int64)
    upd_rows = np.empty(0, dtype=np.int64)
    rel = np.empty(0, dtype=np.int64)
    l_ptr = np.zeros(2, dtype=np.int64)
    pair_ptr = np.zeros(2, dtype=np.int64)
    pair_idx = np.empty(0, dtype=np.int64)
    pair_col = np.empty(0, dtype=np.int64)
    pair_row = np.empty(0, dtype=np.int64)
    max_front = 0
    stack_size = 0
    while True:
        if rebuild:
            _wrap_inplace(positions, box)
            pi, pj, start, nbr, inv_s = _verlet_rows(positions, radii, box, pskin, radii, ref)
            off = np.empty((pi.shape[0], 3))
            analysed = False
            energy, virial, nc, fsum = _energy_forces_rows(positions, box, start, nbr, inv_s,
                                                           alpha, frc)
            nforce += 1
            rebuild = False
        if e_abort > 0.0 and energy < e_abort:
            status = BELOW
            residual = -1.0
            break
        if nc == 0:
            status = CONVERGED
            residual = 0.0
            break
        residual, ng, mean_f, alive = _residual_alive(positions, radii, box, pi, pj, alpha,
                                                      scratch)
        if it == 0 and (ng < READY_FRACTION * n or residual >= HANDOFF):
            status = NOT_READY  # no rigid backbone yet, or far from a minimum
            break
        if not analysed:
            astart, anbr = _adjacency(n, pi, pj)
            order = _nd_order(positions, box, astart, anbr, CUTS)
            (perm, _iperm, sup_first, _sup_parent, sup_nchild, upd_ptr, upd_rows, rel, l_ptr,
             pair_ptr, pair_idx, pair_col, pair_row, max_front,
             stack_size) = _symbolic_core(n, pi, pj, order)
            lval = np.empty(l_ptr[l_ptr.shape[0] - 1])
            nsym += 1
            analysed = True
        ncont, ksum = _hessian_rows(positions, box, start, nbr, inv_s, alpha, everyone, diag0,
                                    off, ncon)
        k0 = ksum / ncont if ncont > 0 else 1.0
        if residual < tol:
            # a minimum only if the load-bearing network's own Hessian (rattlers and their
            # contacts left out), shifted by a thousandth of the prestress's scale (at most
            # MU_CERT), is positive definite: a saddle's instability is of the prestress's size
            _hessian_rows(positions, box, start, nbr, inv_s, alpha, alive, diag0, off, ncon)
            _shifted(diag0, alive, min(MU_CERT, CERT_PRESTRESS * mean_f / (k0 * dbar)), k0,
                     diag)
            bad = _numeric_core(perm, sup_first, sup_nchild, upd_ptr, upd_rows, rel, l_ptr,
                                pair_ptr, pair_idx, pair_col, pair_row, max_front, stack_size,
                                diag, off, lval)
            nfact += 1
            status = CONVERGED if bad < 0 else NOT_MINIMUM
            break
        if residual < 0.5 * best:
            best = residual
            best_it = it
        elif it - best_it >= STALL_ITERS:
            status = STALLED
            break
        if it >= max_iter:
            status = MAX_STEPS
            break
        it += 1
        # ---- the Newton step: (H + D) p = F, raising the shift until H + D factors
        ok = False
        while True:
            _shifted(diag0, alive, mu, k0, diag)
            bad = _numeric_core(perm, sup_first, sup_nchild, upd_ptr, upd_rows, rel, l_ptr,
                                pair_ptr, pair_idx, pair_col, pair_row, max_front, stack_size,
                                diag, off, lval)
            nfact += 1
            if bad < 0:
                ok = True
                break
            mu = max(10.0 * mu, MU_FAIL)
            if mu > MU_MAX:
                break
        if not ok:
            status = FAILED
            break
        x = _solve_core(perm, sup_first, upd_ptr, upd_rows, l_ptr, lval, frc.ravel())
        for i in range(n):
            step[i, 0] = x[2 * i]
            step[i, 1] = x[2 * i + 1]
        g0 = -_dot(frc, step)
        dmax = np.sqrt(_max_norm2(step))
        if not (g0 < 0.0) or dmax == 0.0:
            # not a descent direction (rounding in a nearly singular system): shift more
            mu = max(10.0 * mu, MU_FAIL)
            fails += 1
            if fails >= FAILS_MAX:
                status = STALLED
                break
            continue
        t_cap = min(T_MAX, (0.4 * pskin - np.sqrt(_max_disp2(positions, ref))) / dmax)
        x_typ = (0.5 * alpha * max(energy, 0.0) / n) ** (1.0 / alpha)
        t0 = min(1.0, t_cap, _ratio_step(positions, box, start, nbr, inv_s, step,
                                         RATIO_OVERLAP * x_typ))
        accepted, at_cap, t, e_t, w_t, nc_t, fs_t, nf, pi, pj, start, nbr, inv_s = _line_search(
            positions, step, t0, t_cap, g0, energy, energy_resolution(box, fsum), SIGMA, ref,
            radii, box, pskin, alpha, pi, pj, start, nbr, inv_s, trial, ftr)
        nforce += nf
        if not accepted:
            fails += 1
            mu = max(10.0 * mu, MU_FAIL)
            if fails >= FAILS_MAX:
                status = STALLED
                break
            continue
        fails = 0
        for i in range(n):
            positions[i, 0] = trial[i, 0]
            positions[i, 1] = trial[i, 1]
            frc[i, 0] = ftr[i, 0]
            frc[i, 1] = ftr[i, 1]
        energy = e_t
        virial = w_t
        nc = nc_t
        fsum = fs_t
        if t == 1.0:
            mu = max(0.1 * mu, MU_MIN)
        elif t < T_SHORT:
            # the quadratic model held over a fraction of the step only: a shorter step next
            mu = max(MU_UP * mu, MU_FAIL)
        if _max_disp2(positions, ref) > 0.0625 * pskin * pskin:
            rebuild = True
    # the energy, virial and contacts at the final positions
    energy, virial, nc, fsum = _energy_forces_rows(positions, box, start, nbr, inv_s, alpha, frc)
    nforce += 1
    _wrap_inplace(positions, box)
    return status, it, nforce, energy, virial, residual, nc, nfact, nsym


@njit(cache=True, inline="always")
def _fire_newton(positions, radii, box, alpha, tol, max_steps, skin, dt0, e_abort, pskin):
    """FIRE, interrupted every ``PROBE_STEPS`` steps (and before it starts) to try Newton,
    which takes over wherever the network is ready and finishes at a certified minimum (see
    the module docstring). Arguments as ``kernels.fire._fire_core`` plus the pattern skin
    ``pskin``; ``max_steps`` bounds the FIRE steps of all turns together. Returns
    ``_fire_core``'s tuple ``(status, steps, force_evaluations, energy, virial, residual,
    n_contacts)`` followed by the counts of factorisations, symbolic analyses and Newton
    iterations."""
    n = positions.shape[0]
    mean_d = 2.0 * np.mean(radii)
    vel = np.zeros((n, 2))
    state = _fire_state(dt0)
    nudges = 0
    nfact = 0
    nsym = 0
    nit = 0
    steps = 0
    nforce = 0
    st = MAX_STEPS
    e = 0.0
    w = 0.0
    res = np.inf
    nc = 0
    newton = True  # until Newton lands on a saddle: then FIRE finishes the minimisation
    while newton:
        nst, it, nf, e2, w2, res2, nc2, fa, sy = _newton_core(positions, radii, box, alpha, tol,
                                                              NEWTON_ITERS, pskin, e_abort)
        nforce += nf
        nfact += fa
        nsym += sy
        nit += it
        if nst == CONVERGED or nst == BELOW:
            st, e, w, res, nc = nst, e2, w2, res2, nc2
            break
        if nst != NOT_READY:
            # Newton moved the packing and stopped short: FIRE starts afresh from there
            vel[:] = 0.0
            state = _fire_state(dt0)
        if nst == NOT_MINIMUM:
            # at a saddle the forces balance: a small, reproducible nudge lets FIRE roll off;
            # its negative curvature is of the prestress's size, so FIRE needs far longer than
            # a probe to leave it, and Newton, tried again, would land on it again
            newton = False
            nudges += 1
            amp = NUDGE * (0.5 * alpha * max(e2, 0.0) / n) ** (1.0 / alpha) * mean_d
            seed = np.uint64(nudges)
            for i in range(n):
                for c in range(2):
                    seed = seed * np.uint64(6364136223846793005) + np.uint64(1442695040888963407)
                    positions[i, c] += amp * (np.float64(seed >> np.uint64(11)) * 2.0 ** -53 - 0.5)
        if steps >= max_steps:
            st = MAX_STEPS
            break
        st, s2, nf, e, w, res, nc = _fire_run(positions, radii, box, alpha, tol,
                                              min(PROBE_STEPS, max_steps - steps), skin, e_abort,
                                              vel, state)
        steps += s2
        nforce += nf
        if st != MAX_STEPS:
            break  # converged, below the abort level or stalled
    if not newton and st == MAX_STEPS and steps < max_steps:
        st, s2, nf, e, w, res, nc = _fire_run(positions, radii, box, alpha, tol,
                                              max_steps - steps, skin, e_abort, vel, state)
        steps += s2
        nforce += nf
    return st, steps, nforce, e, w, res, nc, nfact, nsym, nit


__all__ = ["FAILED", "NOT_READY", "NOT_MINIMUM", "HANDOFF", "PATTERN_SKIN"]
