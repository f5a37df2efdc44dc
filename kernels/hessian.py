"""The Hessian of a packing's contact network, as 2 x 2 blocks on a pair list (numba).

For a contact between disks ``i`` and ``j`` at distance ``r`` with unit vector ``n`` from ``i``
to ``j`` and the pair potential ``V(r)`` of ``kernels.potential``, the block

    K = V''(r) n n^T + (V'(r) / r) (I - n n^T)

is the second derivative of ``V`` with respect to the position of ``j`` (and of ``i``); the
Hessian of the total energy has ``+K`` on the diagonal blocks of ``i`` and ``j`` and ``-K`` on
the off-diagonal block ``(i, j)``. ``V'' = ((alpha - 1) / s^2) x^(alpha - 2)`` is the
stiffness along the contact and ``V' / r = -f / r < 0`` (``f`` the repulsive force) the
tension of a compressed contact, which softens the transverse direction; ``x = 1 - r / s`` is
the relative overlap and ``s`` the contact distance. Pairs that do not overlap contribute
nothing (their blocks are explicit zeros, so one pair list, a Verlet list, serves while
contacts come and go). Unit masses: the eigenvalues are squared frequencies.

Blocks are symmetric and stored as ``(xx, xy, yy)``: ``diag`` (n, 3) per disk and
``offdiag`` (npair, 3) per listed pair, the layout ``kernels.sparse`` factors.

Rattlers and translations are the caller's business: the Newton endgame (``kernels.newton``)
shifts the diagonal; ``hessian(..., rattlers=False)`` drops the rattlers (the project's rule,
``kernels.network``) and their pairs, leaving the two translations as zero modes.

Jitted core: ``_hessian_rows(positions, box, start, nbr, inv_s, alpha, keep, diag, offdiag, ncon)`` over a
CSR pair list (the layout of ``kernels.potential._energy_forces_rows``, with the same minimum
image and contact test as the force loop), returning the number of contacts and the sum of
their ``V''``. Checked wrapper: ``hessian(...) -> HessianBlocks`` and ``HessianBlocks.dense()``.
"""

from dataclasses import dataclass

import numpy as np
from numba import njit

from kernels.cells import _as_radii, _candidate_pairs_core
from kernels.potential import _pair_inv_sigma, _rows_from_pairs, check_exponent
from kernels.space import _as_box, _as_positions, _wrap_core, near_image


@njit(cache=True, inline="always")
def pair_stiffness(r, inv_s, alpha):
    """``(V''(r), V'(r) / r)`` of a pair at distance ``r`` with ``inv_s = 1 / s``; zeros when
    the disks do not overlap."""
    x = 1.0 - r * inv_s
    if x <= 0.0:
        return 0.0, 0.0
    if alpha == 2.0:
        return inv_s * inv_s, -x * inv_s / r
    xa2 = x ** (alpha - 2.0)
    return (alpha - 1.0) * xa2 * inv_s * inv_s, -xa2 * x * inv_s / r


@njit(cache=True, inline="always")
def pair_block(dx, dy, r, inv_s, alpha):
    """The 2x2 Hessian block ``K = V'' n n^T + (V'/r)(I - n n^T)`` of a pair at separation
    ``(dx, dy)``, ``r`` its length: ``(kxx, kxy, kyy, V'', V'/r)``."""
    kpar, kperp = pair_stiffness(r, inv_s, alpha)
    nx = dx / r
    ny = dy / r
    kxx = kpar * nx * nx + kperp * (1.0 - nx * nx)
    kxy = (kpar - kperp) * nx * ny
    kyy = kpar * ny * ny + kperp * (1.0 - ny * ny)
    return kxx, kxy, kyy, kpar, kperp


@njit(cache=True)
def _hessian_rows(positions, box, start, nbr, inv_s, alpha, keep, diag, offdiag, ncon):
    """Fill ``diag`` (n, 3) and ``offdiag`` (len(nbr), 3) with the Hessian blocks of the pairs
    of the CSR list ``(start, nbr)`` (row ``i`` holds neighbours ``j > i``, aligned with
    ``inv_s``), and ``ncon`` (n,) with each disk's number of contacts. Only contacts between
    two disks with ``keep`` count (all True: the whole Hessian; the non-rattlers: the
    rattler-free one). Same precondition on coordinates as the force loop. Returns
    ``(n_contacts, sum of V'')``."""
    n = positions.shape[0]
    Lx = box[0]
    Ly = box[1]
    tilt = box[2] * Ly
    hx = 0.5 * Lx
    hy = 0.5 * Ly
    for i in range(n):
        diag[i, 0] = 0.0
        diag[i, 1] = 0.0
        diag[i, 2] = 0.0
        ncon[i] = 0
    ncontact = 0
    ksum = 0.0
    for i in range(n):
        xi = positions[i, 0]
        yi = positions[i, 1]
        for k in range(start[i], start[i + 1]):
            j = nbr[k]
            dx = positions[j, 0] - xi
            dy = positions[j, 1] - yi
            dx, dy = near_image(dx, dy, Lx, Ly, tilt, hx, hy)
            d2 = dx * dx + dy * dy
            q = inv_s[k]
            if d2 * q * q >= 1.0 or not (keep[i] and keep[j]):
                offdiag[k, 0] = 0.0
                offdiag[k, 1] = 0.0
                offdiag[k, 2] = 0.0
                continue
            kxx, kxy, kyy, kpar, _ = pair_block(dx, dy, np.sqrt(d2), q, alpha)
            offdiag[k, 0] = -kxx
            offdiag[k, 1] = -kxy
            offdiag[k, 2] = -kyy
            diag[i, 0] += kxx
            diag[i, 1] += kxy
            diag[i, 2] += kyy
            diag[j, 0] += kxx
            diag[j, 1] += kxy
            diag[j, 2] += kyy
            ncon[i] += 1
            ncon[j] += 1
            ncontact += 1
            ksum += kpar
    return ncontact, ksum


@dataclass(frozen=True)
class HessianBlocks:
    """Hessian of a contact network in block form (see the module docstring).

    ``nodes`` are the disks kept (all, or the non-rattlers), in increasing order; ``pairs_i``
    and ``pairs_j`` index into ``nodes`` (``i < j``), one entry per contact."""

    nodes: np.ndarray
    pairs_i: np.ndarray
    pairs_j: np.ndarray
    diag: np.ndarray
    offdiag: np.ndarray

    def dense(self):
        """The (2 m, 2 m) dense matrix, unknowns ``x0, y0, x1, y1, ...`` over ``nodes``."""
        from kernels.sparse import to_dense

        return to_dense(len(self.nodes), self.pairs_i, self.pairs_j, self.diag, self.offdiag)


def hessian(positions, radii, box, exponent=2.0, *, rattlers=True):
    """Hessian of the total pair energy at ``positions`` (checked wrapper).

    ``rattlers=True`` keeps every disk; ``False`` drops the rattlers (``kernels.network``'s
    rule, iterated) and their contacts. Returns ``HessianBlocks`` with one pair per contact.
    """
    b = _as_box(box)
    pos = _wrap_core(_as_positions(positions), b)
    rad = _as_radii(radii, pos.shape[0])
    a = check_exponent(exponent)
    n = pos.shape[0]
    pi, pj = _candidate_pairs_core(pos, rad, b, 0.0)
    start, nbr = _rows_from_pairs(n, pi, pj)
    diag = np.empty((n, 3))
    off = np.empty((pi.shape[0], 3))
    _hessian_rows(pos, b, start, nbr, _pair_inv_sigma(rad, pi, pj), a, np.ones(n, np.bool_),
                  diag, off, np.empty(n, np.int64))
    contact = np.any(off != 0.0, axis=1)
    keep = np.ones(n, dtype=bool)
    if not rattlers:
        from kernels.minimiser import nonrattlers

        keep = nonrattlers(pos, rad, b)
        contact &= keep[pi] & keep[pj]
        # the diagonal of the kept disks from their kept contacts only
        diag = np.zeros((n, 3))
        np.add.at(diag, pi[contact], -off[contact])
        np.add.at(diag, pj[contact], -off[contact])
    index = np.cumsum(keep) - 1
    return HessianBlocks(nodes=np.flatnonzero(keep), pairs_i=index[pi[contact]],
                         pairs_j=index[pj[contact]], diag=diag[keep], offdiag=off[contact])


__all__ = ["pair_stiffness", "hessian", "HessianBlocks"]
