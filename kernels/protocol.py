"""O'Hern grow/shrink search for a jammed packing at a target energy (numba core).

The protocol (O'Hern et al., PRE 68, 011306 (2003); Ramola & Chakraborty, section
"Simulation Protocol"): minimise the energy at fixed radii, then scale *all* radii by
a common factor -- grow when ``E_G < E_min``, shrink when ``E_G > E_max`` -- and
minimise again starting from the previous minimum, until ``E_min <= E_G <= E_max``
with ``E_max = E_min (1 + window)``. Positions are never reset.

Two rules choose the next scale factor; both only ever scale radii and relax
positions from the previous minimum, so they produce the same kind of packing:

* ``SEARCH_HALVING`` (the documented O'Hern rule): multiply the radii by
  ``(1 + Delta)`` or ``1 / (1 + Delta)`` and halve ``Delta`` at every reversal of
  direction.
* ``SEARCH_SECANT`` (default; about 3 times fewer minimisations at low energy, and
  somewhat fewer force evaluations, than halving): near jamming
  ``g = E_G^(1/alpha)`` is linear in the radius scale factor ``lambda`` (it vanishes
  at ``lambda_J``). After each jammed minimum (force-balanced, ``E_G > 0``) the line
  is refitted: through the two latest jammed minima when its slope agrees within a
  factor 5 with the one-point estimate ``lambda_J ~ lambda (1 - x)`` (``x`` the
  typical relative overlap), else through that estimate. The next ``lambda`` is
  where the line reaches ``g_goal``: the middle of the window, but never more than
  a factor ``energy_step`` (10) below the current energy, so that each minimisation
  starts close to its minimum. After a minimisation that fell below the window
  without a jammed minimum (an unjammed or collapsing packing) the radii grow by
  the line's step to the window, doubled at each consecutive such event. History
  matters near jamming (every minimisation can rearrange the packing and move
  ``lambda_J``), so the rule keeps no bracket from older states; every step is
  limited to a factor ``(1 + delta)``.

* ``SEARCH_PAPER`` (the paper's literal rule, "we reduce the step size Delta by
  half after every step of energy minimization"): the same factors ``(1 + Delta)``,
  but ``Delta`` halves after *every* minimisation, whatever the direction. The k-th
  rescaling uses ``delta0 / 2^(k-1)``, so the radii can move by at most a factor
  ``prod (1 + delta0 2^-k) ~ exp(2 delta0)`` (2 % for the default 0.01) either way
  from the start: the search is a bisection of that interval. When the jamming point
  of the (rearranging) packing lies outside it, the steps shrink below the float64
  resolution of the scale factor after about 50 minimisations and the search ends
  with ``max_search`` (or earlier at the ``max_search`` bound).

Minimiser (``minimizer``): FIRE 2.0 (``kernels.fire``) or Polak-Ribiere+ conjugate
gradients (``kernels.cg``). With ``cell`` shear, FIRE also relaxes the cell's tilt and aspect
ratio at fixed area in every minimisation (``kernels.cellrelax``): the search's radius steps
then act on a cell that follows the packing. With CG, ``e_tol > 0`` replaces the force tolerances of
every minimisation by the paper's energy-change rule (no polish step); the final force
residual is still returned.

Intermediate minimisations stop at the looser ``search_tolerance`` or as soon as
the energy falls below ``E_min / 2`` (FIRE hardly ever climbs back: the packing is
treated as below the window). When
a minimum lands in the window it is minimised further to ``force_tolerance``; the
search only ends once that fully converged minimum is inside the window.

Bounds: at most ``max_search`` minimisations, each of at most ``max_steps`` FIRE
steps. The status says which bound stopped the search (``STATUS_NAMES``); it is
``converged`` only for a force-balanced packing inside the window.

Jitted cores usable from other numba code: ``OHERN_CORES[(minimizer, endgame, cell)]``, one
per minimiser (each compiles only its own minimiser); ``ohern_search`` (Python) picks one
by the integer codes (see their docstrings).
"""

from typing import NamedTuple

import numpy as np
from numba import njit

from kernels.cellrelax import _fire_cell_core
from kernels.cg import _cg_core
from kernels.newton import PATTERN_SKIN, _fire_newton
from kernels.fire import _fire_core
from kernels.minimiser import _dt_for
from kernels import rules
from kernels.rules import (ABORT_FRACTION, AIM, BELOW, CONVERGED, DT_FACTOR,  # noqa: F401 (re-exported)
                           E_FIRST_GUESS, MAX_STEPS, SEARCH_HALVING, SEARCH_NAMES, SEARCH_PAPER,
                           SEARCH_SECANT)
from kernels.space import _wrap_core, remainder
from kernels.names import CELL_NAMES, ENDGAME_NAMES, MINIMIZER_NAMES, RUNNABLE


#: The search's next radius scale (``kernels.rules.search_step``, the rule the GPU block shares).
_search_step = njit(cache=True)(rules.search_step)
_search_targets = njit(cache=True, inline="always")(rules.search_targets)
_search_start = njit(cache=True, inline="always")(rules.search_start)

# the codes of the choices: their positions in kernels.names' tuples
MIN_FIRE = MINIMIZER_NAMES.index("fire")
MIN_CG = MINIMIZER_NAMES.index("cg")
ENDGAME_NONE = ENDGAME_NAMES.index("none")
ENDGAME_NEWTON = ENDGAME_NAMES.index("newton")
CELL_FIXED = CELL_NAMES.index("fixed")
CELL_SHEAR = CELL_NAMES.index("shear")

# status codes of the O'Hern search
ST_CONVERGED = 0
ST_MAX_SEARCH = 1
ST_MAX_STEPS = 2
ST_STALLED = 3
ST_TOO_DENSE = 4
STATUS_NAMES = ("converged", "max_search", "max_steps", "stalled", "too_dense")


# One minimisation at fixed radii, one jitted function per minimiser: the O'Hern search is
# compiled once per minimiser (``OHERN_CORES``), each entry calling only its own, so that a
# campaign compiles only the minimiser it uses (numba compiles every callee of a function,
# also those of branches it never takes). Same arguments and returns for all three: the
# minimiser's tuple (``kernels.fire._fire_core``) and the number of factorisations. Inlined
# (numba IR) into their entry: a separately compiled layer would optimise and generate the
# machine code of everything it calls once more. Which layers are inlined (here, in
# kernels.fire and kernels.newton) also moves the force loop (``_energy_forces_rows_scaled``)
# within each entry's machine code, and on the 2-core Xeon of the measurements its speed
# depends on that placement by 8-10 % (fast at 16 mod 32 bytes, slow at 0 mod 32): the
# present choice keeps every entry at the original speed; time a change to it.


@njit(cache=True, inline="always")
def _minimize_fire(positions, radii, box, alpha, tol, max_steps, skin, dt0, e_abort, e_tol, pskin):
    """One minimisation with FIRE 2.0 (``e_tol`` and ``pskin`` unused)."""
    r = _fire_core(positions, radii, box, alpha, tol, max_steps, skin, dt0, e_abort)
    return r[0], r[1], r[2], r[3], r[4], r[5], r[6], 0


@njit(cache=True, inline="always")
def _minimize_cg(positions, radii, box, alpha, tol, max_steps, skin, dt0, e_abort, e_tol, pskin):
    """One minimisation with conjugate gradients (``e_tol > 0``: the paper's energy-change
    rule). The line search starts at ``1 / k``, the step matching FIRE's ``dt0 = DT_FACTOR /
    sqrt(k)``. ``pskin`` unused."""
    r = _cg_core(positions, radii, box, alpha, tol, max_steps, skin, (dt0 / DT_FACTOR) ** 2,
                 e_abort, e_tol)
    return r[0], r[1], r[2], r[3], r[4], r[5], r[6], 0


@njit(cache=True, inline="always")
def _minimize_newton(positions, radii, box, alpha, tol, max_steps, skin, dt0, e_abort, e_tol,
                     pskin):
    """One minimisation with FIRE handing over to Newton's method on the contact network
    (``kernels.newton``, pattern skin ``pskin``; ``e_tol`` unused)."""
    r = _fire_newton(positions, radii, box, alpha, tol, max_steps, skin, dt0, e_abort, pskin)
    return r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7]


@njit(cache=True, inline="always")
def _minimize_fire_cell(positions, radii, box, alpha, tol, max_steps, skin, dt0, e_abort, e_tol,
                        pskin):
    """One minimisation with FIRE 2.0 on the disks and the cell's shape at fixed area
    (``kernels.cellrelax``; ``box`` updated in place; ``e_tol`` and ``pskin`` unused)."""
    r = _fire_cell_core(positions, radii, box, alpha, tol, max_steps, skin, dt0, e_abort)
    return r[0], r[1], r[2], r[3], r[4], r[5], r[6], 0


@njit(cache=True)
def _spatial_order(positions, box, cell):
    """Permutation sorting disks by cell (row-major cells about ``cell`` wide, then
    index): neighbours in space become neighbours in memory. Deterministic.

    A counting sort by cell, stable in the index: the permutation ``np.argsort`` gives for
    the (distinct) keys ``cell * n + index``, without compiling a sort."""
    n = positions.shape[0]
    nx = max(1, int(box[0] / cell))
    ny = max(1, int(box[1] / cell))
    key = np.empty(n, dtype=np.int64)
    for i in range(n):
        x = remainder(positions[i, 0], box[0])
        y = remainder(positions[i, 1], box[1])
        cx = min(int(x / box[0] * nx), nx - 1)
        cy = min(int(y / box[1] * ny), ny - 1)
        # serpentine rows keep consecutive cells adjacent
        if cy % 2 == 1:
            cx = nx - 1 - cx
        key[i] = cy * nx + cx
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(n):
        start[key[i] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        order[start[key[i]]] = i
        start[key[i]] += 1
    return order


@njit(inline="always")
def _ohern_search(minimize, positions, radii0, box, alpha, e_min, window, tol, search_tol,
                  max_search, max_steps, skin_factor, delta0, rule, max_radius, energy_step, e_tol):
    """Run the O'Hern search in place with the minimiser ``minimize`` (one of
    ``_minimize_fire``, ``_minimize_cg``, ``_minimize_newton``). Inlined (numba IR) into
    each entry of ``OHERN_CORES``, which fixes ``minimize``: only that entry and its
    minimiser are compiled, and each entry is cached on its own.

    ``positions`` (n, 2): initial positions, overwritten by the final ones (wrapped).
    ``radii0``: radii at scale factor 1. ``e_min``: target E_G (per disk, window lower
    edge). ``tol``/``search_tol``: final and intermediate force tolerances.
    ``skin_factor``: Verlet skin in units of the mean diameter. ``delta0``: first
    relative radius step (and the largest step of the secant rule). ``rule``:
    ``SEARCH_HALVING`` or ``SEARCH_SECANT``. ``max_radius``: the largest radius
    allowed (stops with ``too_dense`` beyond it). ``energy_step``: the secant rule
    lowers the energy by at most this factor per minimisation. ``e_tol`` > 0 (CG only):
    every minimisation stops on the energy-change rule instead of the force tolerances (no
    polish).

    Returns ``(status, scale, energy_total, virial, residual, iterations,
    force_evaluations, factorisations)``; the final radii are ``scale * radii0``. Internally the disks
    are renumbered by position after the first minimisation (``_spatial_order``) and
    the result is written back in the caller's order.
    """
    n = positions.shape[0]
    e_max, inv_a, g_target, x_per_g = _search_targets(e_min, window, alpha)
    mean_d = 0.0
    rmax0 = 0.0
    for i in range(n):
        mean_d += 2.0 * radii0[i]
        if radii0[i] > rmax0:
            rmax0 = radii0[i]
    mean_d /= n

    scale = 1.0
    # work on a copy in spatial (cell) order for memory locality; see _spatial_order
    order = np.arange(n)
    pos = positions.copy()
    rad0 = radii0.copy()
    radii = radii0.copy()
    # the rules' state; secant: the latest two jammed minima (E > 0) on the current branch and
    # the slope d E^(1/alpha) / d scale of the linear model
    delta, last_dir, s1, g1, s2, g2, slope, n_below = _search_start(delta0)
    it = 0
    nforce = 0
    nfact = 0
    status = ST_MAX_SEARCH
    e_last = 0.0
    w_last = 0.0
    res_last = np.inf
    e_guess = max(e_min, E_FIRST_GUESS)
    abort = ABORT_FRACTION * e_min * n
    while True:
        it += 1
        for i in range(n):
            radii[i] = scale * rad0[i]
        skin = skin_factor * mean_d * scale
        pskin = PATTERN_SKIN * mean_d * scale
        dt0 = _dt_for(radii, alpha, e_guess)
        st, steps, nf, e, w, res, nc, fa = minimize(pos, radii, box, alpha, search_tol, max_steps,
                                                    skin, dt0, abort, e_tol, pskin)
        nforce += nf
        nfact += fa
        if it == 1:
            # the random start has relaxed: reorder the disks by cell
            perm = _spatial_order(pos, box, mean_d)
            pos = pos[perm].copy()
            rad0 = rad0[perm].copy()
            radii = radii[perm].copy()
            order = order[perm].copy()
        if st == CONVERGED and e_min <= e / n <= e_max and search_tol > tol and e_tol == 0.0:
            # polish to the final tolerance at the same radii
            st, steps, nf, e, w, res, nc, fa = minimize(pos, radii, box, alpha, tol, max_steps,
                                                        skin, dt0, abort, 0.0, pskin)
            nforce += nf
            nfact += fa
        e_last = e
        w_last = w
        res_last = res
        eg = e / n
        if st == CONVERGED and eg > 0.0:
            e_guess = eg
        if st == MAX_STEPS:
            status = ST_MAX_STEPS
            break
        if st != CONVERGED and st != BELOW:
            status = ST_STALLED
            break
        if st == CONVERGED and e_min <= eg <= e_max:
            status = ST_CONVERGED
            break
        if it >= max_search:
            status = ST_MAX_SEARCH
            break
        new, delta, last_dir, s1, g1, s2, g2, slope, n_below = _search_step(
            rule, st == CONVERGED and eg > 0.0, st == BELOW or eg < e_min, eg, scale, delta, last_dir,
            s1, g1, s2, g2, slope, n_below, delta0, g_target, x_per_g, inv_a, energy_step)
        if new == scale:
            # the step is below floating-point resolution of the scale factor
            status = ST_MAX_SEARCH
            break
        if new * rmax0 > max_radius:
            status = ST_TOO_DENSE
            break
        scale = new
    wrapped = _wrap_core(pos, box)
    for i in range(n):
        positions[order[i], 0] = wrapped[i, 0]
        positions[order[i], 1] = wrapped[i, 1]
    return status, scale, e_last, w_last, res_last, it, nforce, nfact


@njit(cache=True)
def _ohern_fire(positions, radii0, box, alpha, e_min, window, tol, search_tol, max_search,
                max_steps, skin_factor, delta0, rule, max_radius, energy_step, e_tol):
    """``_ohern_search`` with FIRE 2.0."""
    return _ohern_search(_minimize_fire, positions, radii0, box, alpha, e_min, window, tol,
                         search_tol, max_search, max_steps, skin_factor, delta0, rule, max_radius,
                         energy_step, e_tol)


@njit(cache=True)
def _ohern_cg(positions, radii0, box, alpha, e_min, window, tol, search_tol, max_search,
              max_steps, skin_factor, delta0, rule, max_radius, energy_step, e_tol):
    """``_ohern_search`` with conjugate gradients."""
    return _ohern_search(_minimize_cg, positions, radii0, box, alpha, e_min, window, tol,
                         search_tol, max_search, max_steps, skin_factor, delta0, rule, max_radius,
                         energy_step, e_tol)


@njit(cache=True)
def _ohern_newton(positions, radii0, box, alpha, e_min, window, tol, search_tol, max_search,
                  max_steps, skin_factor, delta0, rule, max_radius, energy_step, e_tol):
    """``_ohern_search`` with FIRE and the Newton endgame."""
    return _ohern_search(_minimize_newton, positions, radii0, box, alpha, e_min, window, tol,
                         search_tol, max_search, max_steps, skin_factor, delta0, rule, max_radius,
                         energy_step, e_tol)


@njit(cache=True)
def _ohern_fire_cell(positions, radii0, box, alpha, e_min, window, tol, search_tol, max_search,
                     max_steps, skin_factor, delta0, rule, max_radius, energy_step, e_tol):
    """``_ohern_search`` with FIRE 2.0 on the disks and the cell's shape (``box`` is updated)."""
    return _ohern_search(_minimize_fire_cell, positions, radii0, box, alpha, e_min, window, tol,
                         search_tol, max_search, max_steps, skin_factor, delta0, rule, max_radius,
                         energy_step, e_tol)


#: The jitted O'Hern search per ``(minimizer, endgame, cell)`` code triple (``MIN_*``,
#: ``ENDGAME_*``, ``CELL_*``); arguments ``(positions, radii0, box, *SearchSettings)``.
OHERN_CORES = {
    (MIN_FIRE, ENDGAME_NONE, CELL_FIXED): _ohern_fire,
    (MIN_CG, ENDGAME_NONE, CELL_FIXED): _ohern_cg,
    (MIN_FIRE, ENDGAME_NEWTON, CELL_FIXED): _ohern_newton,
    (MIN_FIRE, ENDGAME_NONE, CELL_SHEAR): _ohern_fire_cell,
}


if set(OHERN_CORES) != {(MINIMIZER_NAMES.index(m), ENDGAME_NAMES.index(e), CELL_NAMES.index(c))
                         for route, m, _, e, c in RUNNABLE if route == "ohern"}:
    raise ImportError("kernels.protocol.OHERN_CORES and kernels.names.RUNNABLE name different searches")


class SearchSettings(NamedTuple):
    """The settings of one O'Hern search: the jitted searches' arguments after ``(positions,
    radii0, box)``, in their order (``_ohern_search`` says what each is)."""
    alpha: float
    e_min: float
    window: float
    tol: float
    search_tol: float
    max_search: int
    max_steps: int
    skin_factor: float
    delta0: float
    rule: int
    max_radius: float
    energy_step: float
    e_tol: float


def ohern_search(positions, radii0, box, settings, minimizer, endgame=ENDGAME_NONE, cell=CELL_FIXED):
    """The O'Hern search (``_ohern_search``) with ``settings`` (a ``SearchSettings``),
    ``minimizer`` (``MIN_FIRE`` or ``MIN_CG``), ``endgame`` (``ENDGAME_NONE`` or
    ``ENDGAME_NEWTON``, FIRE only) and ``cell`` (``CELL_FIXED``, or ``CELL_SHEAR`` with FIRE
    alone: ``box`` = [Lx, Ly, xy] is relaxed and updated): calls the jitted entry of
    ``OHERN_CORES`` for that triple, which compiles (or loads from the numba cache) only that
    minimiser. Returns ``_ohern_search``'s tuple."""
    try:
        core = OHERN_CORES[(int(minimizer), int(endgame), int(cell))]
    except KeyError:
        raise ValueError(f"minimizer {minimizer!r} with endgame {endgame!r} and cell {cell!r}: "
                         f"expected one of {sorted(OHERN_CORES)}") from None
    return core(positions, radii0, box, *settings)
