"""What every minimiser shares (FIRE, CG, the Newton endgame, the pressure route, the shear
cell): the convergence test on the force residual of the non-rattlers, the Verlet rows and their
bookkeeping, the starting time step, the checks of a minimiser's inputs and its result.

Convergence is relative, never absolute: the *force residual* is

    max over non-rattlers |F_net| / mean over non-rattler contacts |f_contact|

where rattlers are found by iteratively removing disks with fewer than 3 contacts or with all
contacts in a closed half-plane (``_nonrattler_mask_core``; the one implementation is
``kernels.network._rattlers_core``): neither can balance repulsive forces, so they carry no load
in a force-balanced packing. A packing without any contact has nothing to balance: its residual
is 0. The minimisers check the cheap bound ``max over all disks |F_net| / mean |f_contact|`` at
every step and this residual every ``rules.CHECK_EVERY`` steps and before declaring convergence.

Forces come from Verlet rows with a skin (``_verlet_rows``, built by ``kernels.cells``), rebuilt
when a disk has moved more than half the skin since the last build.

Jitted cores, usable from other numba code:

* ``_nonrattler_mask_core(n, ci, cj, dx, dy) -> bool (n,)`` from contact pairs (``ci < cj``) and
  their displacements ``r_cj - r_ci``.
* ``_contacts_core(positions, radii, box, pi, pj) -> (ci, cj, dx, dy)``: the overlapping pairs
  among the candidates.
* ``_residual_core(positions, radii, box, pi, pj, alpha, forces) -> (residual, n_nonrattlers,
  mean_contact_force)``; ``forces`` is scratch (n, 2). ``_residual_alive`` adds the mask.
* ``_verlet_rows(positions, radii, box, skin, sigma_radii, ref)``.
* ``_dt_for(radii, alpha, e_per_disk)``: the starting time step (``rules.dt_from_diameter``).

Checked: ``nonrattlers(...)``, ``default_timestep(...)``; ``_checked_minimize_inputs`` and
``fire_result`` for the minimisers' wrappers.
"""

from dataclasses import dataclass

import numpy as np
from numba import njit

from kernels import rules
from kernels.cells import _as_radii, _candidate_pairs_core
from kernels.network import HALF_PLANE_TOL, _overlapping_core, _rattlers_core
from kernels.potential import (_energy_forces_core, _pair_inv_sigma, _rows_from_pairs, check_exponent,
                               pair_energy_force)
from kernels.rules import STATUS_NAMES
from kernels.space import _as_box, _as_positions, _wrap_core, separation

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


@dataclass(frozen=True)
class FireResult:
    positions: np.ndarray  # wrapped into the box
    energy: float  # total pair energy
    pressure: float
    residual: float
    steps: int
    force_evaluations: int
    status: str


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
