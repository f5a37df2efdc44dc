"""One-sided power-law pair potential: energy, forces, pressure (numba).

For two disks with radii ``r_i``, ``r_j`` at centre distance ``r`` and contact
distance ``s = r_i + r_j``::

    V(r) = (1/alpha) (1 - r/s)^alpha        r < s
    V(r) = 0                                r >= s

``alpha = 2`` is the harmonic spring of the paper, ``alpha = 2.5`` Hertz. The
supported range is ``2 <= alpha <= 3`` (``ALPHA_RANGE``): the force
``-dV/dr = (1/s)(1 - r/s)^(alpha - 1)`` is then continuous and vanishes at contact.
Energies are in units of the interaction scale (epsilon = 1), lengths in box units.

The potential is written once, as a function of distance, in ``pair_energy_force_inv``
(taking ``1/s``, which the loops precompute per pair); every loop calls it.

Pressure convention (virial, two dimensions, box area ``A = Lx Ly``)::

    P = -(1 / (2 A)) sum_pairs r dV/dr = (1 / (2 A)) sum_pairs r |f|

positive for a compressed packing.

Jitted cores, usable from other numba code:

* ``pair_energy_force(r, s, alpha) -> (V, f)`` with ``f = -dV/dr`` (>= 0, repulsive).
* ``_energy_forces_core(positions, box, pi, pj, inv_s, alpha, forces)``: loops over
  the candidate pairs ``(pi, pj)`` with ``inv_s = 1/(r_i + r_j)`` per pair
  (``_pair_inv_sigma(radii, pi, pj)``) (any superset of the overlapping pairs, e.g. a
  Verlet list), writes the net forces into ``forces`` (n, 2) and returns
  ``(energy, virial, n_contacts, sum_contact_force)`` where ``energy`` is the total
  pair energy, ``virial = sum r f`` and the last two describe the overlapping pairs.

* ``_energy_forces_rows(positions, box, start, nbr, inv_s, alpha, forces)``: the same
  over a CSR Verlet list (``_rows_from_pairs``); the FIRE loop uses it.

Checked wrappers (all pairs found with ``kernels.cells``): ``pair_potential``,
``energy``, ``forces``, ``pressure``.
"""

import math

import numpy as np
from numba import njit

from kernels.cells import _as_radii, _candidate_pairs_core
from kernels.space import _as_box, _as_positions, _wrap_core, near_image

ALPHA_RANGE = (2.0, 3.0)


def pair_energy_force_py(r, inv_s, alpha):
    """Pair energy ``V`` and repulsive force ``f = -dV/dr`` at distance ``r``, given
    ``inv_s = 1/s``. This is the one definition of the potential: plain Python on scalars,
    compiled here for the CPU (``pair_energy_force_inv``) and by ``kernels.gpu.block`` for the
    GPU."""
    x = 1.0 - r * inv_s
    if x <= 0.0:
        return 0.0, 0.0
    if alpha == 2.0:
        return 0.5 * x * x, x * inv_s
    if alpha == 2.5:
        xs = x * math.sqrt(x)
        return 0.4 * x * xs, xs * inv_s
    xa1 = x ** (alpha - 1.0)
    return x * xa1 / alpha, xa1 * inv_s


pair_energy_force_inv = njit(cache=True, inline="always")(pair_energy_force_py)


@njit(cache=True, inline="always")
def pair_energy_force(r, s, alpha):
    """Pair energy ``V`` and repulsive force magnitude ``f = -dV/dr`` at distance ``r``."""
    return pair_energy_force_inv(r, 1.0 / s, alpha)


@njit(cache=True)
def _pair_inv_sigma(radii, pi, pj):
    """``1 / (radii[i] + radii[j])`` for every listed pair."""
    out = np.empty(pi.shape[0])
    for k in range(pi.shape[0]):
        out[k] = 1.0 / (radii[pi[k]] + radii[pj[k]])
    return out


@njit(cache=True)
def _energy_forces_core(positions, box, pi, pj, inv_s, alpha, forces):
    """Net forces (written into ``forces``), total energy, virial and contact stats.

    ``inv_s[k] = 1 / (r_i + r_j)`` for pair ``k`` (see ``_pair_inv_sigma``).
    Precondition: ``y`` lies in ``[-Ly/4, 5Ly/4)`` (wrapped positions, ``kernels.space``, that
    have since moved less than a quarter box), so one shift by ``b`` reduces ``dy``; ``dx`` is
    then reduced by as many shifts ``a`` as it takes (one in a rectangular box).
    """
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
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        dx = positions[j, 0] - positions[i, 0]
        dy = positions[j, 1] - positions[i, 1]
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
            forces[i, 0] -= fx
            forces[i, 1] -= fy
            forces[j, 0] += fx
            forces[j, 1] += fy
    return energy, virial, ncontact, fsum


@njit(cache=True)
def _energy_forces_rows(positions, box, start, nbr, inv_s, alpha, forces):
    """``_energy_forces_core`` over a Verlet list in row (CSR) form.

    Row ``i`` holds the neighbours ``j > i`` in ``nbr[start[i]:start[i + 1]]`` (int32,
    half the memory traffic of int64 pair arrays) with ``inv_s`` aligned to ``nbr``;
    the force on ``i`` is accumulated in registers. Same sums, same precondition on
    coordinates as ``_energy_forces_core``; only the summation order differs.
    """
    return _energy_forces_rows_scaled(positions, box, start, nbr, inv_s, 1.0, alpha, forces)


@njit(cache=True)
def _energy_forces_rows_scaled(positions, box, start, nbr, inv_s, scale, alpha, forces):
    """``_energy_forces_rows`` with every contact distance divided by ``scale``
    (``1/s = inv_s[k] * scale``): all radii scaled by ``1 / scale`` without rebuilding
    ``inv_s`` (the pressure route's radius degree of freedom). ``scale = 1`` gives the
    same bits as unscaled radii."""
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
            q = inv_s[k] * scale
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
                fxi -= fx
                fyi -= fy
                forces[j, 0] += fx
                forces[j, 1] += fy
        forces[i, 0] += fxi
        forces[i, 1] += fyi
    return energy, virial, ncontact, fsum


@njit(cache=True)
def _rows_from_pairs(n, pi, pj):
    """CSR form ``(start int64 (n+1), nbr int32)`` of pairs sorted by ``pi``."""
    start = np.zeros(n + 1, dtype=np.int64)
    for k in range(pi.shape[0]):
        start[pi[k] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    nbr = pj.astype(np.int32)
    return start, nbr


@njit(cache=True)
def _pair_array_core(r, s, alpha):
    v = np.empty(r.shape[0])
    f = np.empty(r.shape[0])
    for k in range(r.shape[0]):
        v[k], f[k] = pair_energy_force(r[k], s[k], alpha)
    return v, f


def stress_from_bonds(radii, bi, bj, dx, dy, exponent):
    """The stress tensor times the area, ``(S_xx, S_yy, S_xy)`` with ``S_ab = sum f r_a r_b / r``
    over the bonds ``(bi, bj)`` of separations ``(dx, dy)`` (``f > 0`` repulsive): ``sigma =
    S / A``, the pressure is ``(S_xx + S_yy) / (2 A)`` (``docs/PHYSICS.md``)."""
    dx = np.asarray(dx, dtype=np.float64)
    dy = np.asarray(dy, dtype=np.float64)
    r = np.hypot(dx, dy)
    f = _pair_array_core(r, np.ascontiguousarray(radii[bi] + radii[bj]), float(exponent))[1]
    fr = np.divide(f, r, out=np.zeros_like(f), where=r > 0)
    return float(np.sum(fr * dx * dx)), float(np.sum(fr * dy * dy)), float(np.sum(fr * dx * dy))


def check_exponent(exponent):
    """Return ``exponent`` as a float in ``ALPHA_RANGE`` or raise ValueError."""
    try:
        a = float(exponent)
    except (TypeError, ValueError):
        raise ValueError(f"exponent: expected a number in [2, 3], got {exponent!r}") from None
    if not (ALPHA_RANGE[0] <= a <= ALPHA_RANGE[1]):
        raise ValueError(f"exponent: expected a number in [{ALPHA_RANGE[0]:g}, "
                         f"{ALPHA_RANGE[1]:g}], got {exponent!r}")
    return a


def pair_potential(r, s, exponent=2.0):
    """``(V, f)`` arrays for distances ``r`` and contact distances ``s`` (broadcast)."""
    a = check_exponent(exponent)
    r, s = np.broadcast_arrays(np.asarray(r, float), np.asarray(s, float))
    if not (np.all(np.isfinite(r)) and np.all(r >= 0)):
        raise ValueError("r: expected finite distances >= 0")
    if not (np.all(np.isfinite(s)) and np.all(s > 0)):
        raise ValueError("s: expected finite contact distances > 0")
    shape = r.shape
    v, f = _pair_array_core(np.ascontiguousarray(r.ravel()), np.ascontiguousarray(s.ravel()), a)
    return v.reshape(shape), f.reshape(shape)


def _evaluate(positions, radii, box, exponent):
    b = _as_box(box)
    pos = _wrap_core(_as_positions(positions), b)
    rad = _as_radii(radii, pos.shape[0])
    a = check_exponent(exponent)
    pi, pj = _candidate_pairs_core(pos, rad, b, 0.0)
    forces = np.empty_like(pos)
    e, w, nc, fs = _energy_forces_core(pos, b, pi, pj, _pair_inv_sigma(rad, pi, pj), a, forces)
    return e, w, forces, b


def energy(positions, radii, box, exponent=2.0):
    """Total pair energy (sum over pairs of V; divide by n for E_G)."""
    return _evaluate(positions, radii, box, exponent)[0]


def forces(positions, radii, box, exponent=2.0):
    """Net force on every disk, (n, 2) array: minus the gradient of ``energy``."""
    return _evaluate(positions, radii, box, exponent)[2]


def pressure(positions, radii, box, exponent=2.0):
    """Virial pressure ``P = (1/(2 Lx Ly)) sum_pairs r f`` (see module docstring)."""
    e, w, f, b = _evaluate(positions, radii, box, exponent)
    return w / (2.0 * b[0] * b[1])
