"""Contact-network analysis of one configuration: ``analyze()`` and ``Analysis``.

``analyze(positions, radii, box, observables=None, bins=None, *, exponent=2.0,
species=None)`` measures everything ``docs/PHYSICS.md`` defines on one packing (any
configuration, including ones made by other programs) and checks every exact
identity of the contact network, reporting the result as flags, never raising on a
packing that fails them. Observables are chosen by name (``OBSERVABLES``); an
unrequested one is not computed. The scalars and identity checks are always
computed. Histograms are raw counts on fixed edges (``DEFAULT_BINS`` unless the
caller gives ``bins``), so they add up across packings.

The numerical work is in the jitted cores of ``kernels.network``,
``kernels.triangulate`` and ``kernels.observables``; this module checks inputs and
assembles the result.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kernels.cells import _candidate_pairs_core
from kernels.network import (
    _bond_order_core,
    _checked_config,
    _faces_core,
    _grain_pass_core,
    _overlapping_core,
    _pair_energy_core,
    _rattlers_core,
    _rotation_core,
)
from kernels.names import DEFAULT_OBSERVABLES
from kernels.potential import stress_from_bonds
from kernels.observables import (
    HISTOGRAMS,
    OBSERVABLES,
    _contact_points_core,
    _histogram_core,
    _radial_core,
    check_edges,
    is_uniform,
)
from kernels.response import RESPONSE_BINS, gaps_from_bonds, moduli_from_bonds, modes_from_bonds
from kernels.triangulate import _triangulate_faces_core


def _integer_edges(top):
    return np.arange(-0.5, top + 1.0, 1.0)


#: Default bin edges per histogram (a campaign may give its own).
DEFAULT_BINS = {
    "contact_angle": np.linspace(0.0, np.pi, 181),
    "contact_length": np.linspace(0.0, 8.0, 161),
    "z_g": _integer_edges(20),
    "z_v": _integer_edges(40),
    "alpha_e": np.linspace(0.0, 0.5, 201),
    "alpha_v": np.linspace(0.0, 4.0, 401),
    "fictitious_length": np.linspace(0.0, 3.0, 301),
    "radial_grains": np.linspace(0.0, 8.0, 401),
    "radial_contacts": np.linspace(0.0, 6.0, 301),
    # linear response (kernels.response): omega / sqrt(<k>), log-spaced gaps and forces
    "omega": RESPONSE_BINS["omega"].copy(),
    "gap": RESPONSE_BINS["gap"].copy(),
    "force": RESPONSE_BINS["force"].copy(),
    "force_extended": RESPONSE_BINS["force_extended"].copy(),
}
for _e in DEFAULT_BINS.values():
    _e.setflags(write=False)

#: Keys of ``Analysis.scalars`` every caller may rely on (docs/CONTRACTS.md).
SCALAR_KEYS = (
    "N", "N_G", "N_R", "E_G", "phi", "pressure", "A_G", "A_V", "N_C", "N_V", "N_F",
    "z_g_mean", "z_iso", "delta_Z", "psi_O", "psi_DO", "identities_ok",
)

#: Identity and degeneracy flags of ``Analysis.identities``.
IDENTITY_KEYS = (
    "network_nonempty",     # at least one grain survives rattler removal
    "area_tiling",          # A_G + A_V = 1 (fractions of the box area)
    "euler",                # N_C = 2 N_G + 2 N_V (torus, chi = 0)
    "fictitious_count",     # N_C - 3 N_V = 2 N_G - N_V (= number of fictitious contacts)
    "triangle_count",       # N_T = N_C - 2 N_V = 2 N_G
    "duality",              # 1/<z_g> + 1/<z_v> = 1/2
    "bounds",               # 3 <= z_g, <z_g> <= 6, N_V <= 2 N_G
    "void_sides",           # every z_v >= 3
    "contractible_faces",   # no face winds around the torus
    "no_collinear_contacts",  # no relative angle at 0 or pi, no two disks at one centre
    "semicircle",           # every relative angle < pi
)

#: A grain is *ordered* (crystal-like) when the bond-orientational order of its
#: contacts, ``|psi_6| = |(1/z_g) sum_c exp(6 i theta_gc)|``, exceeds this value
#: (scalar ``ordered_fraction``). Measured at N = 256 (kernels.jam, E_G = 1e-4 .. 1e-12):
#: 0.08-0.10 of the grains of the bidisperse 1:1.4 mixture pass it, 0.65-0.85 of a
#: monodisperse packing (crystallites), 1 of a triangular crystal.
ORDER_THRESHOLD = 0.9

#: Radii, box sides and coordinates must lie within these magnitudes: squared lengths
#: (contact tests, areas) then stay normal float64 numbers with room for overlaps of 1e-8
#: of a radius (at 1e-160 contacts vanish by underflow, at 1e-170 the box area is 0).
LENGTH_RANGE = (1e-100, 1e100)

#: Free cell parameters per ensemble (``cell``): each adds one contact to the isostatic count
#: ``N_C = 2 N_G - 1 + free`` (``docs/PHYSICS.md``): none in a fixed cell, tilt and aspect ratio in a
#: shear-stabilised one (``kernels.cellrelax``).
CELL_CONSTRAINTS = {"fixed": 0, "shear": 2}

#: Rounding allowance for the area identity A_G + A_V = 1 (fractions of the box area).
AREA_RTOL = 1e-9
#: Relative rounding allowance for the duality identity (relative to 1/2).
DUALITY_RTOL = 1e-12


@dataclass(frozen=True)
class Analysis:
    """Result of ``analyze``.

    ``scalars``: name -> int/float (``SCALAR_KEYS`` and more); ``identities``: name ->
    bool (``IDENTITY_KEYS``); ``histograms``: name -> int64 counts of the requested
    observables; ``bin_edges``: the edges they were counted on. ``contacts`` is the
    (m, 2) int64 array of all contacts ``i < j`` (sorted), ``rattler`` the (n,) mask
    of removed disks, ``z_g`` the (n,) contact count inside the network (0 for
    rattlers), ``z_v`` the side count of each void, ``observables`` the names computed.
    """

    scalars: dict
    identities: dict
    histograms: dict
    bin_edges: dict
    contacts: np.ndarray
    rattler: np.ndarray
    z_g: np.ndarray
    z_v: np.ndarray
    observables: tuple = field(default=())

    @property
    def ok(self) -> bool:
        return bool(self.scalars["identities_ok"])


def _check_observables(observables):
    if observables is None:
        return tuple(DEFAULT_OBSERVABLES)
    if isinstance(observables, str):
        observables = (observables,)
    names = []
    for name in observables:
        if name not in OBSERVABLES:
            raise ValueError(
                f"observables: unknown name {name!r}; expected some of {', '.join(OBSERVABLES)}"
            )
        if name not in names:
            names.append(name)
    if "scalars" not in names:
        names.insert(0, "scalars")
    return tuple(names)


def _check_bins(bins, wanted):
    bins = {} if bins is None else dict(bins)
    for name in bins:
        if name not in HISTOGRAMS:
            raise ValueError(f"bins: unknown histogram {name!r}; expected some of {', '.join(HISTOGRAMS)}")
    out = {}
    for name in wanted:
        edges = check_edges(name, bins.get(name, DEFAULT_BINS[name]))
        if name in ("radial_grains", "radial_contacts") and edges[-1] <= 0:
            raise ValueError(f"bins[{name!r}]: expected a positive largest edge, got {edges[-1]}")
        out[name] = edges
    return out


def _check_inputs(positions, radii, box, exponent, species):
    pos, rad, b = _checked_config(positions, radii, box)
    n = pos.shape[0]
    if n < 2:
        raise ValueError(f"positions: expected at least 2 disks, got {n}")
    lo, hi = LENGTH_RANGE
    sides = b[:2]
    if not (rad.min() >= lo and sides.min() >= lo and sides.max() <= hi and np.abs(pos).max() <= hi):
        raise ValueError(
            f"lengths: expected radii and box sides in [{lo:g}, {hi:g}] and coordinates of magnitude "
            f"at most {hi:g} (squared lengths must stay normal float64 numbers), got radii from "
            f"{rad.min():g}, box {b.tolist()}, largest |coordinate| {np.abs(pos).max():g}; rescale "
            "all lengths by one factor (the analysis is scale invariant)")
    if 4.0 * rad.max() >= sides.min():
        raise ValueError(
            f"radii: the largest diameter ({2 * rad.max():g}) must be below half the smaller box side "
            f"({sides.min() / 2:g}) for contacts to be unique under the minimum image"
        )
    a = float(exponent)
    if not (np.isfinite(a) and a > 1.0):
        raise ValueError(f"exponent: expected a finite number > 1, got {exponent!r}")
    if species is not None:
        sp = np.asarray(species)
        if sp.shape != (n,) or not np.issubdtype(sp.dtype, np.integer):
            raise ValueError(f"species: expected ({n},) integer labels, got shape {sp.shape} dtype {sp.dtype}")
    return pos, np.ascontiguousarray(rad), b, a


def analyze(positions, radii, box, observables=None, bins=None, *, exponent=2.0, species=None,
            angle_tolerance=1e-9, max_void_sides=4096, cell="fixed") -> Analysis:
    """Analyse the contact network of one configuration.

    Parameters
    ----------
    positions : (n, 2) centres (need not be wrapped into the box)
    radii : (n,) positive radii
    box : (Lx, Ly) periodic box sides, or a tilted cell (Lx, Ly, xy) (``kernels.space``)
    observables : names from ``OBSERVABLES`` (None: every contact-network observable,
        ``DEFAULT_OBSERVABLES``; the linear-response ones, ``moduli``, ``modes`` and ``gaps``,
        only when named); scalars are always computed
    bins : mapping histogram name -> increasing edges (missing: ``DEFAULT_BINS``)
    exponent : alpha of the pair potential (1/alpha)(1 - r/s)^alpha, for E_G and pressure
    species : optional (n,) integer labels (checked; not needed by the analysis)
    angle_tolerance : relative angles within ``angle_tolerance * pi`` of 0 or pi are
        flagged as collinear contacts
    max_void_sides : voids with more sides are not triangulated (and flagged)
    cell : the packing's ensemble, which sets its isostatic count: "fixed" (a fixed cell,
        ``N_C = 2 N_G - 1``) or "shear" (tilt and aspect ratio relaxed, ``N_C = 2 N_G + 1``;
        ``docs/PHYSICS.md``); ``z_iso`` and ``delta_Z`` use it
    """
    pos, rad, b, alpha = _check_inputs(positions, radii, box, exponent, species)
    if cell not in CELL_CONSTRAINTS:
        raise ValueError(f"cell: expected one of {list(CELL_CONSTRAINTS)}, got {cell!r}")
    names = _check_observables(observables)
    wanted = [h for name in names for h in OBSERVABLES[name]]
    edges = _check_bins(bins, wanted)
    if int(max_void_sides) != max_void_sides or max_void_sides < 3:
        raise ValueError(f"max_void_sides: expected an integer >= 3, got {max_void_sides!r}")
    tol = float(angle_tolerance)
    if not (np.isfinite(tol) and 0.0 <= tol < 0.5):
        raise ValueError(f"angle_tolerance: expected a number in [0, 0.5), got {angle_tolerance!r}")

    n = pos.shape[0]
    Lx, Ly = float(b[0]), float(b[1])
    box_area = Lx * Ly

    # --- contacts, energy, rattlers, rotation system, grain polygons, faces
    # network._contact_bonds_core written out: the kernels jam() has loaded already (one compilation)
    bi, bj, dx, dy = _overlapping_core(pos, rad, b, *_candidate_pairs_core(pos, rad, b, 0.0))
    energy, virial = _pair_energy_core(rad, bi, bj, dx, dy, alpha)
    rattler = _rattlers_core(n, bi, bj, dx, dy, tol * np.pi)
    offsets, src, dst, hdx, hdy, ang, twin, frac = _rotation_core(n, bi, bj, dx, dy, rattler, rad)
    theta, edge_area = _grain_pass_core(offsets, hdx, hdy, ang, frac)
    psi6 = _bond_order_core(offsets, ang, 6.0)
    face_of, fptr, fhe, sides, sx, sy, varea = _faces_core(offsets, src, dst, hdx, hdy, twin, frac)

    z_g = np.diff(offsets)
    N_G = int(n - rattler.sum())
    N_C = int(src.shape[0])
    N_V = int(sides.shape[0])
    area_G = float(edge_area.sum())
    area_V = float(varea.sum())
    A_G = area_G / box_area
    A_V = area_V / box_area
    E_G = energy / n
    contractible = np.hypot(sx, sy) < 0.25 * min(Lx, Ly)
    n_tri3 = int(np.count_nonzero(sides == 3))
    N_F = N_C - 3 * N_V
    N_T = N_C - 2 * N_V

    histograms = {}
    # --- fictitious contacts (per-void Delaunay)
    if "fictitious" in names:
        face_ok = contractible & (sides >= 3)
        fa, fb, flen, fface, triangles, done = _triangulate_faces_core(
            fptr, fhe, src, dst, hdx, hdy, rad, face_ok, int(max_void_sides))
        n_fict = int(fa.shape[0])
        n_tri = int(triangles.sum())
    else:
        flen = None
        n_fict = N_F
        n_tri = N_T

    nan = float("nan")
    z_mean = N_C / N_G if N_G else nan
    z_v_mean = N_C / N_V if N_V else nan
    # isostatic: N_C = 2 N_G - 1 contacts, plus one per free cell parameter
    z_iso = 4.0 + 2.0 * (CELL_CONSTRAINTS[cell] - 1) / N_G if N_G else nan
    two_pi = 2.0 * np.pi
    angle_eps = tol * np.pi
    near_zero = (theta <= angle_eps) | (theta >= two_pi - angle_eps)
    near_pi = np.abs(theta - np.pi) <= angle_eps

    flags = {}
    flags["network_nonempty"] = N_G > 0
    flags["area_tiling"] = bool(abs(A_G + A_V - 1.0) <= AREA_RTOL)
    flags["euler"] = N_C == 2 * N_G + 2 * N_V
    flags["fictitious_count"] = (N_C - 3 * N_V == 2 * N_G - N_V) and n_fict == N_F
    flags["triangle_count"] = N_T == 2 * N_G and n_tri == N_T
    if N_G and N_V:
        flags["duality"] = bool(abs(1.0 / z_mean + 1.0 / z_v_mean - 0.5) <= DUALITY_RTOL * 0.5)
    else:
        flags["duality"] = False
    flags["bounds"] = bool(N_G > 0 and np.all(z_g[~rattler] >= 3) and N_C <= 6 * N_G and N_V <= 2 * N_G)
    flags["void_sides"] = bool(np.all(sides >= 3))
    flags["contractible_faces"] = bool(np.all(contractible))
    coincident = bool(np.any((dx == 0.0) & (dy == 0.0)))
    flags["no_collinear_contacts"] = not (coincident or bool(np.any(near_zero | near_pi)))
    flags["semicircle"] = bool(np.all(theta < np.pi - angle_eps))
    identities_ok = all(flags.values())

    sigma_max = float(rad.max())
    scalars = {
        "N": int(n),
        "N_G": N_G,
        "N_R": int(n - N_G),
        "E_G": float(E_G),
        "E_G_nonrattler": float(energy / N_G) if N_G else nan,
        "phi": float(np.pi * np.sum(rad * rad) / box_area),
        "pressure": float(virial / (2.0 * box_area)),
        "A_G": A_G,
        "A_V": A_V,
        "area_G": area_G,
        "area_V": area_V,
        "N_C": N_C,
        "N_V": N_V,
        "N_F": int(N_F),
        "N_T": int(N_T),
        "z_g_mean": float(z_mean),
        "z_v_mean": float(z_v_mean),
        "z_iso": float(z_iso),
        "delta_Z": float(z_mean - z_iso),
        "psi_O": n_tri3 / N_V if N_V else nan,
        "psi_DO": N_F / N_V if N_V else nan,
        "ordered_fraction": (int(np.count_nonzero(psi6[~rattler] > ORDER_THRESHOLD)) / N_G
                             if N_G else nan),
        "sigma_max": sigma_max,
        "gamma": float(b[2]),
        "sigma_xy": stress_from_bonds(rad, bi, bj, dx, dy, alpha)[2] / box_area,
        "contacts_total": int(bi.shape[0]),
        "identities_ok": bool(identities_ok),
    }

    # --- histograms
    def count(name, values):
        e = edges[name]
        c = np.zeros(e.shape[0] - 1, dtype=np.int64)
        _histogram_core(np.ascontiguousarray(values, dtype=np.float64), e, is_uniform(e), c)
        histograms[name] = c

    if "contact_angles" in names:
        count("contact_angle", theta)
    if "contact_lengths" in names:
        rg = rad[src]
        length = frac * np.hypot(hdx, hdy)
        if E_G > 0:
            count("contact_length", (1.0 - length / rg) / np.sqrt(E_G))
        else:
            count("contact_length", np.empty(0))
    if "connectivity" in names:
        count("z_g", z_g[~rattler])
        count("z_v", sides)
    if "edge_triangles" in names:
        count("alpha_e", edge_area / rad[src] ** 2)
    if "void_areas" in names:
        count("alpha_v", varea / sigma_max**2)
    if "fictitious" in names:
        count("fictitious_length", flen - 1.0)
    if "radial_grains" in names or "radial_contacts" in names:
        scales, cls = np.unique(rad, return_inverse=True)
        cls = cls.astype(np.int64)
    if "radial_grains" in names:
        e = edges["radial_grains"]
        c = np.zeros(e.shape[0] - 1, dtype=np.int64)
        keep = ~rattler
        _radial_core(np.ascontiguousarray(pos[keep]), np.ascontiguousarray(cls[keep]),
                     np.full(N_G, -1, dtype=np.int64), scales, b, e, is_uniform(e), c)
        histograms["radial_grains"] = c
    if "radial_contacts" in names:
        e = edges["radial_contacts"]
        c = np.zeros(e.shape[0] - 1, dtype=np.int64)
        pts, ga, gb = _contact_points_core(src, dst, twin, hdx, hdy, frac, pos)
        _radial_core(pts, cls[ga], cls[gb], scales, b, e, is_uniform(e), c)
        histograms["radial_contacts"] = c

    # --- linear response (kernels.response): the non-rattler network's Hessian and forces
    if "moduli" in names:
        scalars.update(moduli_from_bonds(pos, rad, b, bi, bj, dx, dy, rattler, alpha))
    if "modes" in names:
        sm, histograms["omega"] = modes_from_bonds(pos, rad, b, bi, bj, dx, dy, rattler, alpha,
                                                   edges["omega"])
        scalars.update(sm)
    if "gaps" in names:
        sg, hg = gaps_from_bonds(pos, rad, b, bi, bj, dx, dy, rattler, z_g, alpha, edges)
        scalars.update(sg)
        histograms.update(hg)

    contacts = np.stack([bi, bj], axis=1) if bi.size else np.empty((0, 2), dtype=np.int64)
    return Analysis(
        scalars=scalars,
        identities=flags,
        histograms=histograms,
        bin_edges={k: edges[k].copy() for k in histograms},
        contacts=contacts,
        rattler=rattler,
        z_g=z_g,
        z_v=sides,
        observables=names,
    )
