"""``jam()``: a jammed packing at a target energy per grain (checked wrapper).

``jam(n, energy, seed, **settings)`` places ``n`` disks uniformly at random in the
periodic box (from ``numpy.random.Generator(PCG64(SeedSequence(seed)))``), scales
the radii to ``phi_start`` and runs the O'Hern search of ``kernels.protocol`` with
the FIRE 2.0 minimiser of ``kernels.fire`` (or the conjugate-gradient minimiser of
``kernels.cg``) until the energy per disk ``E_G`` lies in
``[energy, energy (1 + window)]`` with the forces on non-rattlers balanced to
``force_tolerance`` (relative to the mean contact force). The result is a frozen
``Packing``; identical arguments give bit-identical arrays.
"""

from dataclasses import dataclass, field
import math
import numbers
from types import SimpleNamespace

import numpy as np

from kernels.barostat import BARO_SCALE, STAGE_STEP, _pressure_core
from kernels.cells import _candidate_pairs_core
from kernels.names import (CHOICES, MAX_POLYDISPERSITY, ROUTES, SIZE_DISTRIBUTIONS,  # noqa: F401 - ROUTES re-exported
                           protocol_problem)
from kernels.network import HALF_PLANE_TOL, _overlapping_core, _rattlers_core
from kernels.potential import ALPHA_RANGE, check_exponent, stress_from_bonds
from kernels.space import _as_box
from kernels.protocol import (CELL_NAMES, ENDGAME_NAMES, MINIMIZER_NAMES, SEARCH_NAMES,
                              STATUS_NAMES, SearchSettings, ohern_search)

DEFAULT_SPECIES = ((0.5, 1.4), (0.5, 1.0))

#: Default settings of ``jam`` (see its docstring for the meaning of each).
DEFAULTS = dict(
    box=(1.0, 1.0),
    species=DEFAULT_SPECIES,
    exponent=2.0,
    window=0.1,
    force_tolerance=1e-6,
    search_tolerance=1e-4,
    phi_start=0.86,
    max_search=200,
    max_steps=2_000_000,
    minimizer="fire",
    stop="force",
    energy_tolerance=1e-16,
    search="secant",
    delta=0.01,
    skin=0.3,
    route="ohern",
    sizes=None,
    endgame="none",
    cell="fixed",
)


#: Largest factor by which the secant search lowers the energy per minimisation.
ENERGY_STEP = 1e-1

STATUS_CODES = {name: code for code, name in enumerate(STATUS_NAMES)}


@dataclass(frozen=True, eq=False)
class Packing:
    """A packing produced by ``jam`` (arrays are float64 unless stated; read-only).

    Compared by identity (``eq=False``): compare arrays with ``tobytes()``."""

    positions: np.ndarray  # (n, 2), wrapped into [0, Lx) x [0, Ly) (kernels.space)
    radii: np.ndarray  # (n,)
    box: np.ndarray  # (2,) [Lx, Ly]; (3,) [Lx, Ly, xy] with cell "shear" (kernels.space)
    species: np.ndarray  # (n,) int32, species index (0 = first entry = A)
    energy: float  # E_G: total pair energy / n
    energy_nonrattler: float  # total pair energy / N_G (nan when N_G = 0)
    phi: float  # sum pi r^2 / (Lx Ly)
    pressure: float  # virial pressure (see kernels.potential)
    force_residual: float  # max |F_net| over non-rattlers / mean contact force
    iterations: int  # minimisations of the O'Hern search
    force_evaluations: int
    status: str  # "converged" or the bound that stopped the search
    exponent: float
    n_nonrattlers: int
    settings: dict = field(default_factory=dict, compare=False)
    factorizations: int = 0  # sparse Cholesky factorisations of the Newton endgame
    gamma: float = 0.0  # the cell's tilt factor xy (0 in a fixed, rectangular box)
    sigma_xy: float = 0.0  # residual shear stress (1/A) sum f r_x r_y / r, units of pressure

    @property
    def converged(self):
        return self.status == "converged"

    @property
    def status_code(self):
        """Integer code of ``status`` (``STATUS_CODES``), 0 for converged."""
        return STATUS_CODES[self.status]


def _is_int(x):
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def _positive_float(name, x, upper=None):
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a finite number > 0, got {x!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name}: expected a finite number > 0, got {x!r}")
    if upper is not None and not v < upper:
        raise ValueError(f"{name}: expected a number below {upper:g}, got {x!r}")
    return v


def _positive_int(name, x):
    if not _is_int(x) or x < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {x!r}")
    return int(x)


def check_species(species):
    """Validate a size distribution: a sequence of ``(fraction, relative radius)``.

    Returns ``(fractions, relative_radii)`` as float64 arrays. Fractions must be
    positive and sum to 1 (to 1e-9); relative radii positive and finite.
    """
    try:
        rows = [tuple(row) for row in species]
    except TypeError:
        raise ValueError("species: expected a sequence of (fraction, relative radius) pairs, "
                         f"got {species!r}") from None
    if not rows or any(len(row) != 2 for row in rows):
        raise ValueError("species: expected a non-empty sequence of (fraction, relative radius) "
                         f"pairs, got {species!r}")
    try:
        arr = np.array(rows, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"species: expected numbers, got {species!r}") from None
    frac, rel = arr[:, 0], arr[:, 1]
    if not (np.all(np.isfinite(arr)) and np.all(frac > 0) and np.all(rel > 0)):
        raise ValueError("species: expected positive finite fractions and relative radii, "
                         f"got {species!r}")
    if abs(frac.sum() - 1.0) > 1e-9:
        raise ValueError(f"species: expected fractions summing to 1, got sum {frac.sum()!r}")
    return frac, rel


def species_counts(n, fractions):
    """Largest-remainder rounding of ``fractions * n`` (ties: the earlier species)."""
    exact = np.asarray(fractions, float) * n
    counts = np.floor(exact).astype(np.int64)
    rest = n - int(counts.sum())
    order = sorted(range(len(exact)), key=lambda k: (-(exact[k] - counts[k]), k))
    for k in order[:rest]:
        counts[k] += 1
    return counts


def check_sizes(sizes):
    """Validate a continuous size distribution ``(name, polydispersity)``; None passes."""
    if sizes is None:
        return None
    try:
        name, delta = sizes
    except (TypeError, ValueError):
        raise ValueError(f"sizes: expected None or (distribution, polydispersity), got {sizes!r}") from None
    if name not in SIZE_DISTRIBUTIONS:
        raise ValueError(f"sizes: expected a distribution among {list(SIZE_DISTRIBUTIONS)}, got {name!r}")
    d = _positive_float("sizes polydispersity", delta)
    if d > MAX_POLYDISPERSITY:
        raise ValueError(f"sizes: expected a polydispersity in (0, {MAX_POLYDISPERSITY:g}], got {delta!r}")
    return name, d


def relative_radii(rng, n, name, delta):
    """``n`` relative radii of mean 1 and standard deviation ``delta`` (the polydispersity
    ``sqrt(<R^2> - <R>^2) / <R>`` of the distribution, not of the sample).

    "uniform": flat on ``1 +- sqrt(3) delta``. "lognormal": ``exp(s Z - s^2 / 2)`` with
    ``s^2 = ln(1 + delta^2)``, ``Z`` standard normal (not truncated)."""
    if name == "uniform":
        half = math.sqrt(3.0) * delta
        return 1.0 - half + 2.0 * half * rng.random(n)
    s2 = math.log1p(delta * delta)
    return np.exp(math.sqrt(s2) * rng.standard_normal(n) - 0.5 * s2)


def _seed_sequence(seed):
    if isinstance(seed, np.random.SeedSequence):
        return seed
    if _is_int(seed) and seed >= 0:
        return np.random.SeedSequence(int(seed))
    if isinstance(seed, (list, tuple)) and seed and all(_is_int(s) and s >= 0 for s in seed):
        return np.random.SeedSequence([int(s) for s in seed])
    raise ValueError("seed: expected a non-negative int, a non-empty sequence of them or a "
                     f"numpy.random.SeedSequence, got {seed!r}")


def initial_state(n, seed, box, species, phi_start, sizes=None):
    """Random positions, radii at ``phi_start`` and species, in species order.

    With ``sizes = (distribution, polydispersity)`` the relative radii are drawn per disk
    (``relative_radii``, after the positions, from the same stream) and every disk is
    species 0; ``species`` is then not used."""
    b = np.asarray(box, dtype=np.float64)
    rng = np.random.Generator(np.random.PCG64(_seed_sequence(seed)))
    positions = rng.random((n, 2)) * b
    sizes = check_sizes(sizes)
    if sizes is None:
        frac, rel = check_species(species)
        counts = species_counts(n, frac)
        species_idx = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
        rel_r = rel[species_idx]
    else:
        rel_r = relative_radii(rng, n, *sizes)
        species_idx = np.zeros(n, dtype=np.int32)
    radii = rel_r * math.sqrt(phi_start * b[0] * b[1] / (math.pi * float(np.sum(rel_r ** 2))))
    return positions, radii, species_idx


def _check_start(start, n, box, cell):
    """Copies of a starting configuration's positions, radii and species, checked, and the cell
    ``[Lx, Ly, xy]`` the search starts in: the start's own when it brings a tilted one (a
    shear-stabilised packing, ``cell`` shear only; its area must be the box's), else ``box``."""
    if isinstance(start, Packing):
        start = (start.positions, start.radii, start.species, start.box)
    try:
        pos, rad, spc, *own = start
        pos = np.array(pos, dtype=np.float64)
        rad = np.array(rad, dtype=np.float64)
        spc = np.array(spc, dtype=np.int32)
        own = np.array(own[0], dtype=np.float64) if len(own) == 1 else None
    except (TypeError, ValueError):
        raise ValueError("start: expected None, a Packing or (positions, radii, species[, box]) arrays, "
                         f"got {type(start).__name__}") from None
    if pos.shape != (n, 2) or rad.shape != (n,) or spc.shape != (n,):
        raise ValueError(f"start: expected positions ({n}, 2), radii ({n},) and species ({n},) for "
                         f"n={n}, got {pos.shape}, {rad.shape} and {spc.shape}")
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(rad)) and np.all(rad > 0)):
        raise ValueError("start: expected finite positions and positive finite radii")
    cell_box = np.array([box[0], box[1], 0.0])
    if own is not None and own.shape == (3,) and cell:
        area = box[0] * box[1]
        if not (np.all(np.isfinite(own)) and abs(own[0] * own[1] - area) <= 1e-12 * area):
            raise ValueError(f"start: expected a cell of area {area!r} (box {box.tolist()}), got "
                             f"{own.tolist()}")
        cell_box = _as_box(own)
    elif own is not None and not (own.shape in ((2,), (3,)) and np.array_equal(own[:2], box)
                                  and (own.shape == (2,) or own[2] == 0.0)):
        raise ValueError(f"start: expected a packing in the box {box.tolist()}, got one in "
                         f"{own.tolist()}")
    return pos, rad, spc, cell_box


def energy_floor(radii, box, exponent, force_tolerance):
    """Lowest E_G whose forces float64 can balance to ``force_tolerance``.

    A coordinate is known to ``delta_r = eps max(Lx, Ly)``, so a contact force
    ``f = x^(alpha-1)/s`` (relative overlap ``x``, contact distance ``s``) is known to
    ``delta_f / f = (alpha - 1) delta_r / (x s)``. With ``x = (alpha E_G / 2)^(1/alpha)``
    (about two contacts per disk) and the smallest ``s``, requiring ``delta_f / f <=
    force_tolerance`` gives ``E_G >= (2/alpha) x_min^alpha``. In a unit box with
    tolerance 1e-6 this allows 1e-16 up to N ~ 1500 (harmonic); measured: N = 4096 at
    1e-16 stalls near a residual of 5e-6.
    """
    eps = np.finfo(np.float64).eps
    s_min = 2.0 * float(np.min(radii))
    x_min = (exponent - 1.0) * eps * float(np.max(box)) / (s_min * force_tolerance)
    return 2.0 / exponent * x_min ** exponent


def _check_box(box):
    try:
        b = np.asarray(box, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"box: expected two positive lengths (Lx, Ly), got {box!r}") from None
    if b.shape != (2,) or not (np.all(np.isfinite(b)) and np.all(b > 0)):
        raise ValueError(f"box: expected two positive finite lengths (Lx, Ly), got {box!r}")
    return b


def jam(n, energy, seed, start=None, **settings):
    """Jammed packing of ``n`` disks with ``E_G`` in ``[energy, energy (1 + window)]``.

    Parameters
    ----------
    n : int >= 2
        number of disks.
    energy : float > 0
        target energy per disk ``E_min`` (the window's lower edge), in units of the
        interaction scale.
    seed : int, sequence of ints or numpy.random.SeedSequence
        the initial positions come from ``Generator(PCG64(SeedSequence(seed)))``.
    start : None, a ``Packing`` or ``(positions, radii, species[, box])``
        None (default): random positions at ``phi_start``. Otherwise the search starts
        from these positions and radii (scale factor 1) instead: the *energy ladder*
        protocol, which reaches a lower energy by decompressing a packing made at a
        higher one. ``seed``, ``phi_start`` and ``species`` are then not used; the
        result's ``species`` are the starting ones. ``force_evaluations`` counts this
        search only. With ``cell`` "shear" a start in a tilted cell (a shear-stabilised
        packing, or a ``box`` ``[Lx, Ly, xy]`` of the same area) goes on in that cell.

    Settings (keyword; defaults in ``DEFAULTS``)
    --------------------------------------------
    box : (Lx, Ly), default (1, 1).
    species : sequence of (fraction, relative radius); default 50:50 with the first
        species (A) 1.4 times larger. Counts by largest-remainder rounding.
    sizes : None (default: ``species``) or ``(distribution, polydispersity)``, a continuous
        size distribution among ``SIZE_DISTRIBUTIONS`` ("uniform", "lognormal") with
        relative radii of mean 1 and standard deviation ``polydispersity`` (at most
        ``MAX_POLYDISPERSITY``), drawn from the seed's stream; every disk is species 0.
    exponent : alpha in [2, 3]; 2 harmonic, 2.5 Hertz.
    window : relative window width, ``E_max = energy (1 + window)``; default 0.1.
    force_tolerance : final bound on max |F_net| over non-rattlers / mean contact
        force; default 1e-6. At ``E_G = 1e-14`` this fixes contact overlaps to
        about 1e-6 of their size, far below what decides whether a pair touches, so
        the isostatic contact count is resolved; it stays above the float64 force
        noise down to ``E_G ~ 1e-16`` for N up to ~1500 in a unit box (see
        ``energy_floor``; lower energies are refused).
    search_tolerance : the (looser) tolerance of intermediate minimisations of the
        search; default 1e-4 (looser ones misjudge the energy near jamming and cost
        more iterations). The final minimum is always
        converged to ``force_tolerance``.
    phi_start : packing fraction of the random initial state; default 0.86, above
        jamming for the default mixture (phi_J ~ 0.84), so the search shrinks.
    max_search : bound on the minimisations of the search; default 200.
    max_steps : bound on FIRE steps (CG iterations) per minimisation; default 2,000,000.
    minimizer : "fire" (FIRE 2.0, default) or "cg" (Polak-Ribiere+ conjugate
        gradients, ``kernels.cg``; the paper's minimiser).
    stop : "force" (default): every minimisation stops on the force residual
        (``search_tolerance``, then ``force_tolerance`` in the window). "energy" (needs
        ``minimizer="cg"``): the paper's literal rule, a minimisation stops once one CG
        step changes the energy per disk by less than ``energy_tolerance``; the force
        residual is then only recorded, not bounded.
    energy_tolerance : the paper's tolerance for ``stop="energy"``; default 1e-16.
    search : "secant" (default), "halving" (plain O'Hern Delta halving at each
        reversal) or "paper" (Delta halved after every minimisation, the paper's
        literal rule); see ``kernels.protocol``.
    delta : first relative radius step Delta (and the largest step); default 0.01.
    skin : Verlet skin in units of the mean diameter; default 0.3.
    route : "ohern" (default: the grow/shrink search above) or "pressure": the
        positions relax together with the common radius scale toward a target
        pressure aimed from the energy, in stages of a factor 100 in energy, with
        secant corrections and a final polish at fixed radii (``kernels.barostat``).
        ``search`` and ``delta`` only apply to "ohern"; ``iterations`` counts the
        minimisations either way.
    endgame : "none" (default: FIRE alone) or "newton": every minimisation of the
        O'Hern search (FIRE, stop "force") hands over to Newton steps on the sparse
        Hessian of the contact network once FIRE has brought the force residual
        below 1e-2, and ends at a minimum whose rattler-free Hessian is positive
        definite (``kernels.newton``); ``Packing.factorizations`` counts the sparse
        Cholesky factorisations.
    cell : "fixed" (default: the rectangular ``box``) or "shear": every minimisation also
        relaxes the cell's tilt and aspect ratio at fixed area (``kernels.cellrelax``), so the
        packing ends force-balanced and with residual shear stresses below
        ``force_tolerance`` times its pressure: stable to every deformation of the cell (the
        shear-stabilised ensemble). FIRE on the O'Hern route only. ``Packing.box`` is then
        ``[Lx, Ly, xy]``; a ``start`` packing made so keeps its cell.

    Returns a ``Packing``; its ``status`` is "converged" or the bound that stopped
    the search ("max_search", "max_steps", "stalled", "too_dense").

    Raises ValueError naming the expected and received value for any bad argument,
    including a box too small for the disks (the largest contact distance plus the
    skin must stay below half the shorter box side) and an energy below what float64
    can resolve at this size and tolerance (``energy_floor``).
    """
    job = _prepare(n, energy, seed, start, settings)
    return _run(job)


def _prepare(n, energy, seed, start, settings):
    """The checked inputs of one search (``jam``'s arguments; ValueError on any bad one) as a
    ``SimpleNamespace``: the options, the codes of the minimiser, search rule, endgame and
    cell, the start (positions, radii at scale 1, species, the cell ``[Lx, Ly, xy]``) and the
    bounds. ``kernels.gpu`` prepares its packings with it too."""
    unknown = sorted(set(settings) - set(DEFAULTS))
    if unknown:
        raise ValueError(f"settings: expected names among {sorted(DEFAULTS)}, got {unknown}")
    opt = dict(DEFAULTS)
    opt.update(settings)

    if not _is_int(n) or n < 2:
        raise ValueError(f"n: expected an integer >= 2, got {n!r}")
    e_min = _positive_float("energy", energy)
    box = _check_box(opt["box"])
    alpha = check_exponent(opt["exponent"])
    window = _positive_float("window", opt["window"])
    tol = _positive_float("force_tolerance", opt["force_tolerance"], upper=1.0)
    search_tol = _positive_float("search_tolerance", opt["search_tolerance"], upper=1.0)
    search_tol = max(search_tol, tol)
    phi_start = _positive_float("phi_start", opt["phi_start"], upper=1.0)
    max_search = _positive_int("max_search", opt["max_search"])
    max_steps = _positive_int("max_steps", opt["max_steps"])
    for key, names in CHOICES.items():
        if opt[key] not in names:
            raise ValueError(f"{key}: expected one of {list(names)}, got {opt[key]!r}")
    problem = protocol_problem(opt)  # the combinations the kernels run (kernels.names.RUNNABLE)
    if problem is not None:
        raise ValueError(f"{problem[0]}: {problem[1]}")
    minimizer = MINIMIZER_NAMES.index(opt["minimizer"])
    endgame = ENDGAME_NAMES.index(opt["endgame"])
    cell = CELL_NAMES.index(opt["cell"])
    e_tol = _positive_float("energy_tolerance", opt["energy_tolerance"])
    if opt["stop"] == "force":
        e_tol = 0.0
    if opt["search"] not in SEARCH_NAMES:
        raise ValueError(f"search: expected one of {list(SEARCH_NAMES)}, got {opt['search']!r}")
    rule = SEARCH_NAMES.index(opt["search"])
    delta = _positive_float("delta", opt["delta"], upper=1.0)
    skin = _positive_float("skin", opt["skin"], upper=1.0)
    # the kernels' cell [Lx, Ly, xy] (kernels.space): a shear-stabilised start keeps its own
    if start is None:
        positions, radii0, species_idx = initial_state(n, _seed_sequence(seed), box, opt["species"],
                                                       phi_start, opt["sizes"])
        cell_box = np.array([box[0], box[1], 0.0])
    else:
        positions, radii0, species_idx, cell_box = _check_start(start, n, box, cell)
    # the nearest image must be the only one in range: 2 r_max (1 + skin) < L/2
    max_radius = float(cell_box[:2].min()) / (4.0 * (1.0 + skin))
    if radii0.max() * (1.0 + delta) ** 2 > max_radius:
        raise ValueError(
            f"box: expected a box large enough for {n} disks at phi_start={phi_start:g} "
            f"(largest radius below {max_radius:.4g} = min(Lx, Ly) / (4 (1 + skin)) with room to "
            f"grow), got box {box.tolist()} with largest radius {radii0.max():.4g}")

    e_floor = energy_floor(radii0, cell_box[:2], alpha, tol)
    if e_min < e_floor:
        raise ValueError(
            f"energy: expected at least {e_floor:.3g} for n={n}, exponent={alpha:g}, "
            f"force_tolerance={tol:g} in box {box.tolist()} (below it float64 rounding of the "
            f"positions exceeds force_tolerance times the contact forces), got {energy!r}; "
            "use a larger force_tolerance, a larger energy or a smaller n")

    return SimpleNamespace(n=n, e_min=e_min, box=box, alpha=alpha, window=window, tol=tol,
                           search_tol=search_tol, max_search=max_search, max_steps=max_steps,
                           minimizer=minimizer, e_tol=e_tol, rule=rule, endgame=endgame, cell=cell,
                           delta=delta, skin=skin, positions=positions, radii0=radii0,
                           species=species_idx, cell_box=cell_box, max_radius=max_radius, opt=opt,
                           start=start)


def _run(job):
    """Run the prepared search on the CPU and make its ``Packing``."""
    n, positions, radii0, cell_box, alpha = job.n, job.positions, job.radii0, job.cell_box, job.alpha
    if job.opt["route"] == "pressure":
        status, scale, e_tot, virial, residual, iterations, nforce = _pressure_core(
            positions, radii0, cell_box, alpha, job.e_min, job.window, job.tol, job.search_tol,
            job.max_search, job.max_steps, job.skin, job.max_radius, STAGE_STEP, BARO_SCALE, False)
        nfact = 0
    else:
        settings = SearchSettings(alpha, job.e_min, job.window, job.tol, job.search_tol, job.max_search,
                                  job.max_steps, job.skin, job.delta, job.rule, job.max_radius,
                                  ENERGY_STEP, job.e_tol)
        status, scale, e_tot, virial, residual, iterations, nforce, nfact = ohern_search(
            positions, radii0, cell_box, settings, job.minimizer, job.endgame, job.cell)
    return _packing(job, STATUS_NAMES[status], scale, e_tot, virial, residual, iterations, nforce,
                    nfact)


def _packing(job, status, scale, e_tot, virial, residual, iterations, nforce, nfact, device=None):
    """The ``Packing`` of a finished search of ``job`` (positions minimised in place in
    ``job.positions``, the cell in ``job.cell_box``): radii at ``scale``, the rattler count,
    the residual shear stress. ``device``: recorded in the settings when not the CPU's."""
    n, positions, cell_box, alpha = job.n, job.positions, job.cell_box, job.alpha
    box = cell_box if job.cell else job.box
    species_idx = job.species
    opt = job.opt
    radii = job.radii0 * scale
    area = float(cell_box[0] * cell_box[1])
    pi, pj = _candidate_pairs_core(positions, radii, cell_box, 0.0)
    # kernels.minimiser._nonrattler_mask_core written out: its kernels are loaded already (the search
    # calls them), while its wrappers, inlined into their jitted callers, would be compiled anew
    ci, cj, cdx, cdy = _overlapping_core(positions, radii, cell_box, pi, pj)
    n_g = int(np.count_nonzero(~_rattlers_core(n, ci, cj, cdx, cdy, HALF_PLANE_TOL)))
    sxy = stress_from_bonds(radii, ci, cj, cdx, cdy, alpha)[2] / area
    for arr in (positions, radii, box, species_idx):
        arr.flags.writeable = False
    return Packing(
        positions=positions, radii=radii, box=box, species=species_idx,
        gamma=float(cell_box[2]), sigma_xy=float(sxy),
        energy=e_tot / n, energy_nonrattler=e_tot / n_g if n_g else math.nan,
        phi=float(math.pi * np.sum(radii ** 2) / area), pressure=virial / (2.0 * area),
        force_residual=float(residual), iterations=int(iterations),
        force_evaluations=int(nforce), status=status, exponent=alpha,
        n_nonrattlers=n_g, factorizations=int(nfact),
        settings=dict(opt, box=tuple(box.tolist()), exponent=alpha, energy=job.e_min, n=n,
                      start="random" if job.start is None else "packing",
                      **({} if device is None else {"device": device})),
    )


__all__ = ["jam", "Packing", "DEFAULTS", "ROUTES", "STATUS_CODES", "ALPHA_RANGE", "species_counts",
           "energy_floor", "SIZE_DISTRIBUTIONS", "MAX_POLYDISPERSITY", "check_sizes", "relative_radii",
           "initial_state", "check_species"]
