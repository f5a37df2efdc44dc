"""Linear response of a packing: elastic constants, vibrational modes, gaps and small forces.

Three observables of ``kernels.analyze`` (``moduli``, ``modes``, ``gaps``) computed on the
network of non-rattlers (the project's rattler rule, ``kernels.network``): rattlers and
their contacts are left out of every quantity below. Energies are in units of the
interaction scale (epsilon = 1), lengths in the configuration's units, masses 1.

Elastic constants (``moduli``)
------------------------------
Box and positions are deformed by ``F = I + eps``, ``eps = [[e1, e3/2], [e3/2, e2]]`` (``e3``
the engineering shear strain), then the positions relax: ``r_i -> F r_i + u_i``. For a
contact ``i -> j`` with minimum-image vector ``d = r_j - r_i`` the deformed vector is
``d' = F d + u_j - u_i``, linear in ``e`` and ``u``. With ``g_a = d d'/d e_a``
(``g_1 = (d_x, 0)``, ``g_2 = (0, d_y)``, ``g_3 = (d_y, d_x) / 2``) and the contact's block
``K = V'' n n^T + (V'/r)(I - n n^T)`` (``kernels.hessian``, the prestress ``V'/r`` included):

    A_ab   = sum_contacts g_a . K g_b                 (affine, Born term with the prestress)
    Xi_ja  = sum_contacts of j  (+/-) K g_a           (+ for j the end, - for the start of d)
    sigma_a = (1 / (Lx Ly)) sum_contacts V' n . g_a   (first derivative: the stress)

and the energy of the relaxed packing is ``U(e) = U0 + Lx Ly sigma . e + (Lx Ly / 2) e^T C e``
with

    C = (A - Xi^T H^+ Xi) / (Lx Ly),

``H`` the Hessian of the non-rattlers. ``d'`` being linear in ``e``, ``A`` has no other term.
Every contact adds ``+K g_a`` to one end and ``-K g_a`` to the other, so the columns of ``Xi``
sum to zero: they are orthogonal to the two translations, the null space of ``H``. The
solve therefore pins one disk (its two unknowns removed): ``H_rr u_r = Xi_r`` has a unique
solution, ``u`` differs from ``H^+ Xi`` by a translation only and ``Xi^T u = Xi^T H^+ Xi``
exactly, whichever disk is pinned (``pin``). One sparse Cholesky factorisation
(``kernels.sparse``) and three solves.

``C`` is the second derivative of the energy per area of the undeformed box, in Voigt
order (xx, yy, xy): ``c11, c22, c12, c66`` (``c66`` multiplies ``e3^2 / 2``) and the two
off-diagonal shear couplings ``c16, c26``. ``B = (c11 + c22 + 2 c12) / 4`` and ``G = (4 c66 +
c11 + c22 - 2 c12) / 8`` are JAX MD's angle averages. For a packing under pressure ``p`` the
stress-strain coefficients (the derivative of the Cauchy stress, equal to the second
derivative of the enthalpy ``U + p A``) differ by pressure terms:
``C_stress = C + p [[0, 1, 0], [1, 0, 0], [0, 0, -1/2]]`` (Voigt), so ``B_stress = B + p/2``
and ``G_stress = G - p/2`` (docs/RESPONSE.md).

A packing whose Hessian is not positive definite once a disk is pinned (an unstable or
floppy network, an unconverged minimum) fails the factorisation; a solve whose relative
backward error ``|H u - Xi| / (|H|_F |u| + |Xi|)`` exceeds ``MODULI_RESIDUAL`` is not trusted either: both give
NaN constants and ``moduli_ok = False`` (``moduli_status`` says which).

Vibrational modes (``modes``)
-----------------------------
Eigenvalues ``lambda`` of the rattler-free Hessian (unit masses), frequencies
``omega = sqrt(lambda)``; LAPACK and ARPACK run on one thread (``_one_blas_thread``). A mode is zero when ``|lambda| <= ZERO_MODE_REL <k>``, ``<k>`` the
mean contact stiffness ``V''`` of the network; ``lambda < -ZERO_MODE_REL <k>`` is an unstable
mode. Up to ``DENSE_MODES_MAX`` non-rattlers every eigenvalue is computed (dense,
``numpy.linalg.eigvalsh``) and the density of states is histogrammed as
``omega / sqrt(<k>)``; beyond, the lowest ``LOW_MODES`` eigenvalues come from shift-invert
Lanczos (``scipy.sparse.linalg.eigsh``) on the sparse factorisation of ``H + tau I``
(``tau = SHIFT_REL <k>``), and the density of states is not computed (its histogram stays
empty and ``modes_dense = False``).

Gaps and small forces (``gaps``)
--------------------------------
Gaps ``h = r / s - 1 >= 0`` between non-contacting pairs of non-rattlers (``s`` the contact
distance) up to ``GAP_MAX``, in log-spaced bins down to ``1e-16`` (float64 resolves ``h`` to
about ``eps L / s``, ``L`` the box side); the contact forces ``f / <f>`` of the network (all
contacts, and the *extended* ones: neither disk a buckler, a grain with exactly three
contacts) in log-spaced bins down to ``1e-12``.

Jitted cores: ``_response_blocks_core``, ``_moduli_core``, ``_block_matvec``,
``_dense_core``, ``_gaps_core``, ``_forces_core``. Wrappers: ``moduli``, ``modes``,
``gaps`` (checked, from positions), and ``moduli_from_bonds`` etc. used by
``kernels.analyze`` on the bonds it has already found.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from kernels import sparse
from kernels.cells import _candidate_pairs_core
from kernels.hessian import pair_block, pair_stiffness
from kernels.observables import _histogram_core, is_uniform
from kernels.sparse import (
    _adjacency,
    _nd_order,
    _numeric_core,
    _solve_core,
    _symbolic_core,
)
from kernels.space import _wrap_core, separation

#: Backward error ``|H u - Xi| / (|H|_F |u| + |Xi|)`` of a non-affine solve above which it is
#: not trusted (a stable Cholesky solve gives about 1e-16).
MODULI_RESIDUAL = 1e-9
#: Candidate cuts per split of the nested-dissection ordering of the moduli's solve: one
#: factorisation per packing, so the cheapest ordering wins (``kernels.sparse.analyse``).
MODULI_CUTS = 1
#: ``moduli_status`` codes.
MODULI_STATUS = {0: "ok", 1: "fewer than two non-rattlers", 2: "not positive definite",
                 3: "residual too large"}

#: Largest number of non-rattlers whose whole spectrum is computed (dense, about 5 s at
#: N_G = 2048 on one core; 0.4 s at 1024).
DENSE_MODES_MAX = 2048
#: Eigenvalues computed by shift-invert beyond ``DENSE_MODES_MAX``.
LOW_MODES = 16
#: Zero-mode threshold and shift of the shift-invert, relative to the mean contact stiffness.
ZERO_MODE_REL = 1e-10
SHIFT_REL = 1e-8

#: Largest gap ``h = r / s - 1`` counted (pairs closer than twice their contact distance).
GAP_MAX = 1.0

#: ``moduli`` scalars (docs/RESPONSE.md).
MODULI_KEYS = ("c11", "c22", "c12", "c66", "c16", "c26", "B", "G", "c_min",
               "c11_affine", "c22_affine", "c12_affine", "c66_affine", "B_affine", "G_affine",
               "stress_xx", "stress_yy", "stress_xy", "contact_distance",
               "moduli_ok", "moduli_status", "moduli_residual")
#: ``modes`` scalars.
MODES_KEYS = ("omega_min", "omega_scale", "n_zero_modes", "n_unstable_modes", "n_modes",
              "modes_dense", "modes_ok")
#: ``gaps`` scalars.
GAPS_KEYS = ("gap_min", "force_min", "buckler_fraction")


def _log_edges(lo_exp, hi_exp, per_decade):
    """``[0, 10^lo, ..., 10^hi]``: log-spaced edges with a first bin from 0."""
    k = (hi_exp - lo_exp) * per_decade
    return np.r_[0.0, np.logspace(lo_exp, hi_exp, k + 1)]


#: Default bins of the histograms of this module (``kernels.analysis.DEFAULT_BINS``).
RESPONSE_BINS = {
    "omega": np.linspace(0.0, 8.0, 321),            # omega / sqrt(<k>)
    "gap": _log_edges(-16, 0, 8),                    # h = r / s - 1, up to GAP_MAX
    "force": _log_edges(-12, 1, 8),                  # f / <f>
    "force_extended": _log_edges(-12, 1, 8),
}


# ------------------------------------------------------------------------------ blocks

@njit(cache=True)
def _response_blocks_core(radii, bi, bj, dx, dy, index, m, alpha):
    """Hessian blocks, mixed derivatives and affine term of the contacts among kept disks.

    ``index[i]`` is disk ``i``'s number among the ``m`` kept disks, -1 for a rattler; a bond
    ``(bi, bj)`` with displacement ``(dx, dy) = r_bj - r_bi`` counts when both ends are
    kept. Returns ``(pi, pj, offdiag, diag, xi, affine, dstress, ksum, ssum)``: the pairs in
    kept numbering (``pi < pj``) with their off-diagonal blocks ``-K`` (xx, xy, yy), the
    diagonal blocks (m, 3), ``Xi`` (2 m, 3), ``A`` (3, 3) and ``sum V' n . g_a`` (3,), the
    sum of ``V''`` and of the contact distances."""
    nb = bi.shape[0]
    cnt = 0
    for k in range(nb):
        if index[bi[k]] >= 0 and index[bj[k]] >= 0:
            cnt += 1
    pi = np.empty(cnt, dtype=np.int64)
    pj = np.empty(cnt, dtype=np.int64)
    off = np.empty((cnt, 3))
    diag = np.zeros((m, 3))
    xi = np.zeros((2 * m, 3))
    aff = np.zeros((3, 3))
    dstress = np.zeros(3)
    g = np.empty((3, 2))
    ksum = 0.0
    ssum = 0.0
    t = 0
    for k in range(nb):
        a = index[bi[k]]
        b = index[bj[k]]
        if a < 0 or b < 0:
            continue
        ddx = dx[k]
        ddy = dy[k]
        r = np.sqrt(ddx * ddx + ddy * ddy)
        s = radii[bi[k]] + radii[bj[k]]
        kxx, kxy, kyy, kpar, kperp = pair_block(ddx, ddy, r, 1.0 / s, alpha)
        nx = ddx / r
        ny = ddy / r
        pi[t] = a
        pj[t] = b
        off[t, 0] = -kxx
        off[t, 1] = -kxy
        off[t, 2] = -kyy
        diag[a, 0] += kxx
        diag[a, 1] += kxy
        diag[a, 2] += kyy
        diag[b, 0] += kxx
        diag[b, 1] += kxy
        diag[b, 2] += kyy
        g[0, 0] = ddx
        g[0, 1] = 0.0
        g[1, 0] = 0.0
        g[1, 1] = ddy
        g[2, 0] = 0.5 * ddy
        g[2, 1] = 0.5 * ddx
        vp = kperp * r  # V'(r)
        for c in range(3):
            kgx = kxx * g[c, 0] + kxy * g[c, 1]
            kgy = kxy * g[c, 0] + kyy * g[c, 1]
            xi[2 * b, c] += kgx
            xi[2 * b + 1, c] += kgy
            xi[2 * a, c] -= kgx
            xi[2 * a + 1, c] -= kgy
            for d in range(c, 3):
                aff[c, d] += g[d, 0] * kgx + g[d, 1] * kgy
            dstress[c] += vp * (nx * g[c, 0] + ny * g[c, 1])
        ksum += kpar
        ssum += s
        t += 1
    for c in range(3):
        for d in range(c):
            aff[c, d] = aff[d, c]
    return pi, pj, off, diag, xi, aff, dstress, ksum, ssum


@njit(cache=True)
def _block_matvec(diag, pi, pj, off, x):
    """``H x`` for the block matrix (diagonal blocks ``diag``, pairs ``(pi, pj)`` with
    blocks ``off``), ``x`` (2 m,) in the order ``x0, y0, x1, y1, ...``."""
    m = diag.shape[0]
    y = np.empty(2 * m)
    for v in range(m):
        y[2 * v] = diag[v, 0] * x[2 * v] + diag[v, 1] * x[2 * v + 1]
        y[2 * v + 1] = diag[v, 1] * x[2 * v] + diag[v, 2] * x[2 * v + 1]
    for k in range(pi.shape[0]):
        a = pi[k]
        b = pj[k]
        oxx = off[k, 0]
        oxy = off[k, 1]
        oyy = off[k, 2]
        y[2 * a] += oxx * x[2 * b] + oxy * x[2 * b + 1]
        y[2 * a + 1] += oxy * x[2 * b] + oyy * x[2 * b + 1]
        y[2 * b] += oxx * x[2 * a] + oxy * x[2 * a + 1]
        y[2 * b + 1] += oxy * x[2 * a] + oyy * x[2 * a + 1]
    return y


@njit(cache=True)
def _solve3_core(perm, sup_first, upd_ptr, upd_rows, l_ptr, lval, b):
    """``kernels.sparse._solve_core`` for three right-hand sides at once, ``b`` (2 n, 3) in
    the old numbering: the factor is read once, and each column sees the same operations in
    the same order as in a solve of its own (the same bits)."""
    n = perm.shape[0]
    nsup = sup_first.shape[0] - 1
    y = np.empty((2 * n, 3))
    for a in range(n):
        for c in range(3):
            y[2 * a, c] = b[2 * perm[a], c]
            y[2 * a + 1, c] = b[2 * perm[a] + 1, c]
    # forward: L y = b
    for s in range(nsup):
        f2 = 2 * sup_first[s]
        w = 2 * sup_first[s + 1] - f2
        lo = upd_ptr[s]
        nu = upd_ptr[s + 1] - lo
        m = w + 2 * nu
        base = l_ptr[s]
        for q in range(w):
            col = base + q * m
            d = lval[col + q]
            y0 = y[f2 + q, 0] / d
            y1 = y[f2 + q, 1] / d
            y2 = y[f2 + q, 2] / d
            y[f2 + q, 0] = y0
            y[f2 + q, 1] = y1
            y[f2 + q, 2] = y2
            for i in range(q + 1, w):
                li = lval[col + i]
                y[f2 + i, 0] -= li * y0
                y[f2 + i, 1] -= li * y1
                y[f2 + i, 2] -= li * y2
            for t in range(nu):
                r = 2 * upd_rows[lo + t]
                la = lval[col + w + 2 * t]
                lb = lval[col + w + 2 * t + 1]
                y[r, 0] -= la * y0
                y[r, 1] -= la * y1
                y[r, 2] -= la * y2
                y[r + 1, 0] -= lb * y0
                y[r + 1, 1] -= lb * y1
                y[r + 1, 2] -= lb * y2
    # backward: L^T x = y
    for s in range(nsup - 1, -1, -1):
        f2 = 2 * sup_first[s]
        w = 2 * sup_first[s + 1] - f2
        lo = upd_ptr[s]
        nu = upd_ptr[s + 1] - lo
        m = w + 2 * nu
        base = l_ptr[s]
        for q in range(w - 1, -1, -1):
            col = base + q * m
            t0 = y[f2 + q, 0]
            t1 = y[f2 + q, 1]
            t2 = y[f2 + q, 2]
            for i in range(q + 1, w):
                li = lval[col + i]
                t0 -= li * y[f2 + i, 0]
                t1 -= li * y[f2 + i, 1]
                t2 -= li * y[f2 + i, 2]
            for t in range(nu):
                r = 2 * upd_rows[lo + t]
                la = lval[col + w + 2 * t]
                lb = lval[col + w + 2 * t + 1]
                t0 -= la * y[r, 0]
                t1 -= la * y[r, 1]
                t2 -= la * y[r, 2]
                t0 -= lb * y[r + 1, 0]
                t1 -= lb * y[r + 1, 1]
                t2 -= lb * y[r + 1, 2]
            d = lval[col + q]
            y[f2 + q, 0] = t0 / d
            y[f2 + q, 1] = t1 / d
            y[f2 + q, 2] = t2 / d
    x = np.empty((2 * n, 3))
    for a in range(n):
        for c in range(3):
            x[2 * perm[a], c] = y[2 * a, c]
            x[2 * perm[a] + 1, c] = y[2 * a + 1, c]
    return x


@njit(cache=True)
def _pinned_core(pos, pi, pj, off, diag, pin):
    """The system without node ``pin``: its positions, pairs (renumbered), blocks."""
    m = diag.shape[0]
    keep = 0
    for k in range(pi.shape[0]):
        if pi[k] != pin and pj[k] != pin:
            keep += 1
    qi = np.empty(keep, dtype=np.int64)
    qj = np.empty(keep, dtype=np.int64)
    qoff = np.empty((keep, 3))
    t = 0
    for k in range(pi.shape[0]):
        a = pi[k]
        b = pj[k]
        if a == pin or b == pin:
            continue
        qi[t] = a - (a > pin)
        qj[t] = b - (b > pin)
        qoff[t, 0] = off[k, 0]
        qoff[t, 1] = off[k, 1]
        qoff[t, 2] = off[k, 2]
        t += 1
    qpos = np.empty((m - 1, 2))
    qdiag = np.empty((m - 1, 3))
    for v in range(m):
        if v == pin:
            continue
        w = v - (v > pin)
        qpos[w, 0] = pos[v, 0]
        qpos[w, 1] = pos[v, 1]
        qdiag[w, 0] = diag[v, 0]
        qdiag[w, 1] = diag[v, 1]
        qdiag[w, 2] = diag[v, 2]
    return qpos, qi, qj, qoff, qdiag


@njit(cache=True)
def _moduli_core(pos, box, pi, pj, off, diag, xi, pin, cuts):
    """Non-affine correction ``Xi^T H^+ Xi`` (3, 3) with node ``pin`` pinned, the largest
    backward error of the three solves, and a status (0 ok, 2 not positive definite).
    ``pos`` are the kept disks' wrapped positions (the ordering's geometry)."""
    m = diag.shape[0]
    corr = np.zeros((3, 3))
    # Xi's columns sum to zero up to rounding: project the translations out exactly
    # (Xi^T H^+ Xi = (P Xi)^T H^+ (P Xi)), so that the pinned rows hold as well
    xi = xi.copy()
    for c in range(3):
        for comp in range(2):
            mean = 0.0
            for v in range(m):
                mean += xi[2 * v + comp, c]
            mean /= m
            for v in range(m):
                xi[2 * v + comp, c] -= mean
    qpos, qi, qj, qoff, qdiag = _pinned_core(pos, pi, pj, off, diag, pin)
    n = m - 1
    start, nbr = _adjacency(n, qi, qj)
    order = _nd_order(qpos, box, start, nbr, cuts)
    (perm, iperm, sup_first, sup_parent, sup_nchild, upd_ptr, upd_rows, rel, l_ptr,
     pair_ptr, pair_idx, pair_col, pair_row, max_front, stack_size) = _symbolic_core(n, qi, qj, order)
    lval = np.empty(l_ptr[-1])
    bad = _numeric_core(perm, sup_first, sup_nchild, upd_ptr, upd_rows, rel, l_ptr, pair_ptr,
                        pair_idx, pair_col, pair_row, max_front, stack_size, qdiag, qoff, lval)
    if bad >= 0:
        return corr, np.inf, 2
    u = np.zeros((2 * m, 3))
    worst = 0.0
    hnorm = 0.0
    for v in range(m):
        hnorm += diag[v, 0] ** 2 + 2.0 * diag[v, 1] ** 2 + diag[v, 2] ** 2
    for k in range(pi.shape[0]):
        hnorm += 2.0 * (off[k, 0] ** 2 + 2.0 * off[k, 1] ** 2 + off[k, 2] ** 2)
    hnorm = np.sqrt(hnorm)
    rhs = np.empty((2 * n, 3))
    for v in range(m):
        if v == pin:
            continue
        w = v - (v > pin)
        for c in range(3):
            rhs[2 * w, c] = xi[2 * v, c]
            rhs[2 * w + 1, c] = xi[2 * v + 1, c]
    x = _solve3_core(perm, sup_first, upd_ptr, upd_rows, l_ptr, lval, rhs)
    for v in range(m):
        if v == pin:
            continue
        w = v - (v > pin)
        for c in range(3):
            u[2 * v, c] = x[2 * w, c]
            u[2 * v + 1, c] = x[2 * w + 1, c]
    for c in range(3):
        # normwise backward error of the whole system (the pinned rows included):
        # |H u - Xi| / (|H|_F |u| + |Xi|)
        hu = _block_matvec(diag, pi, pj, off, u[:, c].copy())
        num = 0.0
        nu = 0.0
        nxi = 0.0
        for q in range(2 * m):
            e = hu[q] - xi[q, c]
            num += e * e
            nu += u[q, c] * u[q, c]
            nxi += xi[q, c] * xi[q, c]
        den = hnorm * np.sqrt(nu) + np.sqrt(nxi)
        res = np.sqrt(num) / den if den > 0.0 else 0.0
        if not res <= worst:  # NaN propagates
            worst = res
    for c in range(3):
        for d in range(3):
            sacc = 0.0
            for q in range(2 * m):
                sacc += xi[q, c] * u[q, d]
            corr[c, d] = sacc
    for c in range(3):
        for d in range(c + 1, 3):
            avg = 0.5 * (corr[c, d] + corr[d, c])
            corr[c, d] = avg
            corr[d, c] = avg
    return corr, worst, 0


@njit(cache=True)
def _kept_index(rattler):
    """Number of every non-rattler among the non-rattlers (-1 for a rattler), and their count."""
    n = rattler.shape[0]
    index = np.full(n, -1, dtype=np.int64)
    m = 0
    for i in range(n):
        if not rattler[i]:
            index[i] = m
            m += 1
    return index, m


def _kept_positions(positions, box, rattler):
    return np.ascontiguousarray(_wrap_core(positions, box)[~rattler])


def _isotropic(c11, c22, c12, c66):
    return (c11 + c22 + 2.0 * c12) / 4.0, (4.0 * c66 + c11 + c22 - 2.0 * c12) / 8.0


def moduli_from_bonds(positions, radii, box, bi, bj, dx, dy, rattler, alpha, pin=0):
    """The ``moduli`` scalars (``MODULI_KEYS``) of a configuration whose contacts
    ``(bi, bj, dx, dy)`` and rattler mask are known (``kernels.analyze``'s inputs,
    positions as given). ``pin``: which non-rattler (in index order) is pinned."""
    nan = float("nan")
    area = float(box[0] * box[1])
    index, m = _kept_index(rattler)
    out = {k: nan for k in MODULI_KEYS}
    out.update(moduli_ok=False, moduli_status=1)
    if m < 2:
        return out
    pi, pj, off, diag, xi, aff, dstress, ksum, ssum = _response_blocks_core(
        radii, bi, bj, dx, dy, index, m, float(alpha))
    out["stress_xx"], out["stress_yy"], out["stress_xy"] = (float(v) / area for v in dstress)
    out["contact_distance"] = float(ssum / len(pi)) if len(pi) else nan
    ca = aff / area
    out["c11_affine"], out["c22_affine"] = float(ca[0, 0]), float(ca[1, 1])
    out["c12_affine"], out["c66_affine"] = float(ca[0, 1]), float(ca[2, 2])
    out["B_affine"], out["G_affine"] = (float(v) for v in _isotropic(ca[0, 0], ca[1, 1], ca[0, 1], ca[2, 2]))
    if not (0 <= pin < m):
        raise ValueError(f"pin: expected a non-rattler number in [0, {m}), got {pin!r}")
    pos = _kept_positions(positions, box, rattler)
    corr, res, status = _moduli_core(pos, box, pi, pj, off, diag, xi, int(pin), MODULI_CUTS)
    out["moduli_residual"] = float(res)
    if status == 0 and not res <= MODULI_RESIDUAL:
        status = 3
    out["moduli_status"] = int(status)
    if status != 0:
        return out
    c = (aff - corr) / area
    out.update(c11=float(c[0, 0]), c22=float(c[1, 1]), c12=float(c[0, 1]), c66=float(c[2, 2]),
               c16=float(c[0, 2]), c26=float(c[1, 2]), c_min=float(np.linalg.eigvalsh(c)[0]),
               moduli_ok=True)
    out["B"], out["G"] = (float(v) for v in _isotropic(c[0, 0], c[1, 1], c[0, 1], c[2, 2]))
    return out


# ------------------------------------------------------------------------------ modes

@njit(cache=True)
def _dense_core(m, pi, pj, off, diag):
    """The dense (2 m, 2 m) matrix of the blocks."""
    h = np.zeros((2 * m, 2 * m))
    for v in range(m):
        h[2 * v, 2 * v] = diag[v, 0]
        h[2 * v, 2 * v + 1] = diag[v, 1]
        h[2 * v + 1, 2 * v] = diag[v, 1]
        h[2 * v + 1, 2 * v + 1] = diag[v, 2]
    for k in range(pi.shape[0]):
        a = 2 * pi[k]
        b = 2 * pj[k]
        h[a, b] += off[k, 0]
        h[a, b + 1] += off[k, 1]
        h[a + 1, b] += off[k, 1]
        h[a + 1, b + 1] += off[k, 2]
        h[b, a] += off[k, 0]
        h[b, a + 1] += off[k, 1]
        h[b + 1, a] += off[k, 1]
        h[b + 1, a + 1] += off[k, 2]
    return h


_BLAS = []


def _one_blas_thread():
    """A context in which LAPACK and ARPACK use one thread (threadpoolctl): a campaign runs
    one packing per core, and a multithreaded BLAS on busy cores spins (a dense spectrum of
    1000 unknowns measured 12 s instead of 0.17 s on two loaded cores); one thread also keeps
    the eigenvalues' bits independent of the machine's core count."""
    if not _BLAS:
        import scipy.sparse.linalg  # noqa: F401 - load scipy's BLAS before looking for it
        from threadpoolctl import ThreadpoolController

        _BLAS.append(ThreadpoolController())
    return _BLAS[0].limit(limits=1, user_api="blas")


def _low_eigenvalues(pos, box, pi, pj, off, diag, k, tau):
    """The ``k`` eigenvalues nearest ``-tau`` by shift-invert Lanczos on the factorisation of
    ``H + tau I``; raises ``kernels.sparse.NotPositiveDefinite`` when that is not positive
    definite (an eigenvalue below ``-tau``)."""
    from scipy.sparse.linalg import LinearOperator, eigsh

    m = diag.shape[0]
    sym = sparse.analyse(pos, box, pi, pj, cuts=MODULI_CUTS)
    shifted = diag.copy()
    shifted[:, 0] += tau
    shifted[:, 2] += tau
    lval = sparse.factor(sym, shifted, off)
    args = (sym.perm, sym.sup_first, sym.upd_ptr, sym.upd_rows, sym.l_ptr, lval)

    def inv(b):
        return _solve_core(*args, np.ascontiguousarray(b, dtype=np.float64).ravel())

    def mv(x):
        return _block_matvec(diag, pi, pj, off, np.ascontiguousarray(x, dtype=np.float64).ravel())

    n = 2 * m
    hop = LinearOperator((n, n), matvec=mv, dtype=np.float64)
    op = LinearOperator((n, n), matvec=inv, dtype=np.float64)
    v0 = np.random.default_rng(0).standard_normal(n)  # a fixed start: the same result every call
    with _one_blas_thread():
        ev = eigsh(hop, k=k, sigma=-tau, which="LM", OPinv=op, v0=v0, return_eigenvectors=False)
    return np.sort(ev)


def modes_from_bonds(positions, radii, box, bi, bj, dx, dy, rattler, alpha, omega_edges,
                     dense_max=DENSE_MODES_MAX, low_modes=LOW_MODES):
    """``(scalars, omega counts)`` of the ``modes`` observable (see the module docstring)."""
    nan = float("nan")
    counts = np.zeros(len(omega_edges) - 1, dtype=np.int64)
    out = {k: nan for k in MODES_KEYS}
    out.update(modes_ok=False, modes_dense=False)
    index, m = _kept_index(rattler)
    if m < 2:
        return out, counts
    pi, pj, off, diag, _, _, _, ksum, _ = _response_blocks_core(radii, bi, bj, dx, dy, index, m,
                                                                float(alpha))
    kmean = ksum / len(pi) if len(pi) else 0.0
    if not kmean > 0.0:
        return out, counts
    out["omega_scale"] = float(np.sqrt(kmean))
    tol = ZERO_MODE_REL * kmean
    if m <= dense_max:
        h = _dense_core(m, pi, pj, off, diag)
        with _one_blas_thread():
            ev = np.linalg.eigvalsh(h)
        out["modes_dense"] = True
        pos_ev = ev[ev > tol]
        e = np.ascontiguousarray(omega_edges, dtype=np.float64)
        _histogram_core(np.sqrt(pos_ev) / np.sqrt(kmean), e, is_uniform(e), counts)
    else:
        k = int(min(low_modes, 2 * m - 2))
        try:
            ev = _low_eigenvalues(_kept_positions(positions, box, rattler), box, pi, pj, off, diag,
                                  k, SHIFT_REL * kmean)
        except sparse.NotPositiveDefinite:
            # an eigenvalue below -tau: unstable, how many is not known
            out.update(n_modes=0, n_unstable_modes=nan)
            return out, counts
    zero = np.abs(ev) <= tol
    unstable = ev < -tol
    above = ev[ev > tol]
    out.update(n_modes=int(len(ev)), n_zero_modes=int(zero.sum()), n_unstable_modes=int(unstable.sum()),
               omega_min=float(np.sqrt(above[0])) if len(above) else nan)
    out["modes_ok"] = bool(len(above) and not unstable.any())
    return out, counts


# ------------------------------------------------------------------------------ gaps, forces

@njit(cache=True)
def _gaps_core(positions, radii, box, rattler, hmax):
    """Gaps ``h = r / s - 1`` in ``[0, hmax]`` between non-contacting pairs of non-rattlers."""
    rmax = 0.0
    for i in range(radii.shape[0]):
        if radii[i] > rmax:
            rmax = radii[i]
    pi, pj = _candidate_pairs_core(positions, radii, box, hmax * 2.0 * rmax)
    out = np.empty(pi.shape[0])
    t = 0
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        if rattler[i] or rattler[j]:
            continue
        ddx, ddy = separation(positions[j, 0] - positions[i, 0], positions[j, 1] - positions[i, 1], box)
        s = radii[i] + radii[j]
        d2 = ddx * ddx + ddy * ddy
        if d2 < s * s:
            continue  # a contact
        h = np.sqrt(d2) / s - 1.0
        if h <= hmax:
            out[t] = h
            t += 1
    return out[:t].copy()


@njit(cache=True)
def _forces_core(radii, bi, bj, dx, dy, rattler, z, alpha):
    """Contact forces ``f = -V'`` of the contacts among non-rattlers, and whether each is
    *extended* (neither end has exactly three contacts, ``z``: contacts among non-rattlers)."""
    nb = bi.shape[0]
    f = np.empty(nb)
    ext = np.empty(nb, dtype=np.bool_)
    t = 0
    for k in range(nb):
        i = bi[k]
        j = bj[k]
        if rattler[i] or rattler[j]:
            continue
        r = np.sqrt(dx[k] * dx[k] + dy[k] * dy[k])
        s = radii[i] + radii[j]
        kpar, kperp = pair_stiffness(r, 1.0 / s, alpha)
        f[t] = -kperp * r
        ext[t] = z[i] != 3 and z[j] != 3
        t += 1
    return f[:t].copy(), ext[:t].copy()


def gaps_from_bonds(positions, radii, box, bi, bj, dx, dy, rattler, z_g, alpha, edges):
    """``(scalars, histograms)`` of the ``gaps`` observable: ``gap``, ``force`` and
    ``force_extended`` counted on ``edges[name]``."""
    nan = float("nan")
    h = _gaps_core(positions, radii, box, rattler, GAP_MAX)
    f, ext = _forces_core(radii, bi, bj, dx, dy, rattler, np.asarray(z_g, dtype=np.int64), float(alpha))
    fmean = float(f.mean()) if len(f) else nan
    rel = f / fmean if len(f) and fmean > 0 else np.empty(0)
    hists = {}
    for name, values in (("gap", h), ("force", rel), ("force_extended", rel[ext] if len(rel) else rel)):
        e = np.ascontiguousarray(edges[name], dtype=np.float64)
        c = np.zeros(len(e) - 1, dtype=np.int64)
        _histogram_core(np.ascontiguousarray(values, dtype=np.float64), e, is_uniform(e), c)
        hists[name] = c
    keep = ~np.asarray(rattler, bool)
    ng = int(keep.sum())
    scalars = {"gap_min": float(h.min()) if len(h) else nan,
               "force_min": float(rel.min()) if len(rel) else nan,
               "buckler_fraction": float(np.count_nonzero(np.asarray(z_g)[keep] == 3) / ng) if ng else nan}
    return scalars, hists


# ------------------------------------------------------------------------------ checked wrappers

def _network(positions, radii, box):
    from kernels.network import HALF_PLANE_TOL, _checked_config, _contact_bonds_core, _rattlers_core

    pos, rad, b = _checked_config(positions, radii, box)
    bi, bj, dx, dy = _contact_bonds_core(pos, rad, b)
    rattler = _rattlers_core(pos.shape[0], bi, bj, dx, dy, HALF_PLANE_TOL)
    return pos, rad, b, bi, bj, dx, dy, rattler


def moduli(positions, radii, box, exponent=2.0, *, pin=0):
    """Elastic constants of a configuration (the ``moduli`` scalars, ``MODULI_KEYS``)."""
    pos, rad, b, bi, bj, dx, dy, rattler = _network(positions, radii, box)
    return moduli_from_bonds(pos, rad, b, bi, bj, dx, dy, rattler, float(exponent), pin=pin)


def modes(positions, radii, box, exponent=2.0, *, edges=None, dense_max=DENSE_MODES_MAX,
          low_modes=LOW_MODES):
    """``(scalars, omega counts)`` of the ``modes`` observable of a configuration."""
    pos, rad, b, bi, bj, dx, dy, rattler = _network(positions, radii, box)
    e = RESPONSE_BINS["omega"] if edges is None else edges
    return modes_from_bonds(pos, rad, b, bi, bj, dx, dy, rattler, float(exponent), e,
                            dense_max=dense_max, low_modes=low_modes)


def gaps(positions, radii, box, exponent=2.0, *, edges=None):
    """``(scalars, histograms)`` of the ``gaps`` observable of a configuration (``edges``:
    histogram name -> bin edges, default ``RESPONSE_BINS``)."""
    from kernels.network import _rotation_core

    pos, rad, b, bi, bj, dx, dy, rattler = _network(positions, radii, box)
    offsets = _rotation_core(pos.shape[0], bi, bj, dx, dy, rattler, rad)[0]
    e = dict(RESPONSE_BINS, **(edges or {}))
    return gaps_from_bonds(pos, rad, b, bi, bj, dx, dy, rattler, np.diff(offsets), float(exponent), e)


__all__ = ["moduli", "modes", "gaps", "MODULI_KEYS", "MODES_KEYS", "GAPS_KEYS", "RESPONSE_BINS",
           "DENSE_MODES_MAX", "LOW_MODES", "GAP_MAX", "MODULI_RESIDUAL", "ZERO_MODE_REL"]
