"""Precision targets in a spec: the ``precision`` section, what it may target and what a grid can
produce (docs/PRECISION.md).

A campaign with ``precision`` does not fix its seeds. It runs a pilot of ``pilot`` seeds in every
cell (variant, N_G, E_G), then rounds: after each, the reducer's ``N_G -> inf`` row and its errors
decide which cells get more seeds, until every target is met, the ``budget`` is spent, or the
cells that matter hold ``max_seeds``. Its task table is the grid with seeds ``0 .. max_seeds - 1``
in every cell; a round gives a cell its next integers. The allocation is decided by
``campaign.precision.allocation`` and recorded in the store; this module only reads the spec.

The reducer's fit range (its default and ``in_fit_range``, the one test of which cells a range
holds) and its table keys are defined here (the plan wing), so that a spec can be checked against
them before anything runs; the reducer (``campaign.results``) and the precision campaigns' model
(``campaign.precision``) use them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The default fit range of the scaling laws: typical relative overlaps up to 0.1%
#: (docs/REDUCED.md, "The fit range"), one distance from jamming for every potential, chosen by
#: experiments/fit_rules.py.
DEFAULT_FIT_OVERLAP = 0.001

#: (quantity, abscissa, intercept key, exponent key) of the four laws fitted per size; the
#: ``N_G -> inf`` row holds the intercept (extrapolated in 1/N_G) and the shared exponent of each.
FITS = (
    ("A_G", "E_G", "A_G_star_E", "beta_E"),
    ("A_G", "delta_Z", "A_G_star_Z", "beta_Z"),
    ("psi_O", "E_G", "psi_O_star", "psi_beta_E"),
    ("psi_O", "delta_Z", "psi_O_star_Z", "psi_beta_Z"),
)

#: Keys of a table row (each also with ``<key>_err``); the first five are the paper's. Every one of
#: them is an entry of the ``N_G -> inf`` row a precision target may name.
TABLE_KEYS = ("A_G_star_E", "beta_E", "A_G_star_Z", "beta_Z", "psi_O_star",
              "psi_O_star_Z", "psi_beta_E", "psi_beta_Z")

#: A size enters the ``N_G -> inf`` row's shared fit with at least this many cells in the fit range
#: (three positive abscissae: an intercept, an amplitude and the shared exponent)
SHARED_FIT_CELLS = 3

PRECISION_KEYS = ("target", "pilot", "max_seeds", "budget")
DEFAULT_PILOT = 6
DEFAULT_MAX_SEEDS = 400
#: fewer packings than this leave a cell out of the fits (``campaign reduce --min-packings``' default)
MIN_PILOT = 3
MAX_SEEDS_LIMIT = 1_000_000


def law_of(key: str):
    """``(quantity, abscissa, kind)`` of a table key, ``kind`` "intercept" or "exponent"."""
    for quantity, absc, ikey, bkey in FITS:
        if key == ikey:
            return quantity, absc, "intercept"
        if key == bkey:
            return quantity, absc, "exponent"
    raise KeyError(key)


def typical_overlap(E, alpha):
    """The typical relative overlap ``(alpha E_G / 2)^(1/alpha)`` of a packing at energy per
    grain ``E_G`` (two contacts per disk carrying it): the distance from jamming that is
    comparable across exponents, where ``E_G`` is not."""
    return (alpha * np.asarray(E, float) / 2.0) ** (1.0 / alpha)


def in_fit_range(E, alpha, overlap=DEFAULT_FIT_OVERLAP, energies=(0.0, math.inf)):
    """Whether each grid energy ``E`` lies in a fit range of a system of exponent ``alpha``: in
    ``energies`` = [lo, hi], and of typical overlap at most ``overlap`` (no bound when it is
    infinite), both to a relative 1e-9 (docs/REDUCED.md, "The fit range"). The defaults: the
    reducer's default range. The one test of the fit range: the reducer's scaling fits, its jamming
    point and a precision campaign's model all take their cells with it."""
    E = np.asarray(E, float)
    lo, hi = energies
    inside = (E >= lo * (1 - 1e-9)) & (E <= hi * (1 + 1e-9))
    if math.isfinite(overlap):
        inside &= typical_overlap(E, alpha) <= overlap * (1 + 1e-9)
    return inside


@dataclass(frozen=True)
class Precision:
    """A spec's ``precision`` section. ``targets``: (table key, standard error) pairs, sorted;
    ``budget``: core-hours as the cost model prices the packings (None: no budget)."""

    targets: tuple[tuple[str, float], ...]
    pilot: int = DEFAULT_PILOT
    max_seeds: int = DEFAULT_MAX_SEEDS
    budget: float | None = None

    @property
    def target(self) -> dict:
        return dict(self.targets)

    def canonical(self) -> dict:
        """What decides the task table (the pilot and the seed range). The targets and the budget
        are left out: a store's campaign can go on with tighter targets or a larger budget."""
        return {"pilot": self.pilot, "max_seeds": self.max_seeds}

    def settings(self) -> dict:
        """What a round's decision is made with, as it is recorded with the decision."""
        return {"target": dict(self.targets), "pilot": self.pilot, "max_seeds": self.max_seeds,
                "budget": self.budget}


def parse(c, value, path, *, seeds_given: bool, N, variants, check_grid=True) -> Precision | None:
    """The ``precision`` mapping, checked (``c``: the spec's checker; errors are recorded there).
    ``seeds_given``: whether the grid fixes its seeds (refused with precision); ``N`` and
    ``variants``: the grid, to refuse targets its cells cannot produce (when ``check_grid``: the grid
    itself is sound)."""
    m = c.mapping(value, path, PRECISION_KEYS, ("target",))
    if m is None:
        return None
    ok = True
    targets = {}
    if "target" in m:
        t = c.mapping(m["target"], path + ("target",), TABLE_KEYS)
        if t is None:
            ok = False
        elif not t:
            c.err(path + ("target",), "no target: name at least one entry of the N_G -> inf row with the standard "
                                      f"error wanted, e.g. {{A_G_star_E: 5.0e-4}}; keys: {', '.join(TABLE_KEYS)}")
            ok = False
        else:
            for k, v in t.items():
                if k not in TABLE_KEYS:
                    ok = False
                    continue
                x = c.number(v, path + ("target", k), lo=0, lo_open=True)
                if x is None:
                    ok = False
                else:
                    targets[k] = x
    pilot = DEFAULT_PILOT
    if "pilot" in m:
        pilot = c.number(m["pilot"], path + ("pilot",), lo=MIN_PILOT, hi=MAX_SEEDS_LIMIT, integer=True)
        ok &= pilot is not None
    max_seeds = DEFAULT_MAX_SEEDS
    if "max_seeds" in m:
        max_seeds = c.number(m["max_seeds"], path + ("max_seeds",), lo=MIN_PILOT, hi=MAX_SEEDS_LIMIT, integer=True)
        ok &= max_seeds is not None
    if ok and max_seeds < pilot:
        c.err(path + ("max_seeds",), f"max_seeds ({max_seeds}) is below the pilot ({pilot}): the pilot runs "
                                     "that many seeds in every cell")
        ok = False
    budget = None
    if "budget" in m:
        budget = c.number(m["budget"], path + ("budget",), lo=0, lo_open=True)
        ok &= budget is not None
    if seeds_given:
        c.err(("grid", "seeds"), "a campaign with `precision` chooses its own seeds (the pilot, then rounds up to "
                                 "max_seeds, each cell's next integers): drop grid.seeds, or drop `precision` "
                                 "for a fixed number of seeds in every cell")
        ok = False
    if ok and check_grid:
        for v in variants:
            proto = dict(v.protocol)
            if proto.get("start") == "ladder":
                where = ("protocol", "start") if v.name == "default" else ("variants",)
                c.err(where, f"variant {v.name!r} is an energy ladder (start: ladder), whose packings at the "
                             "energies of one seed form a chain; precision targets give seeds to single cells. "
                             "Run the ladder with a fixed grid.seeds, or drop start: ladder")
                ok = False
    if ok and check_grid:
        for key in sorted(targets):
            for why in producible(key, N, variants):
                c.err(path + ("target", key), why)
                ok = False
    if not ok:
        return None
    return Precision(targets=tuple(sorted(targets.items())), pilot=pilot, max_seeds=max_seeds, budget=budget)


def producible(key, N, variants) -> list:
    """Why the grid cannot give the ``N_G -> inf`` entry ``key`` in some variant (empty when it can):
    it needs two sizes, each with ``SHARED_FIT_CELLS`` energies in the default fit range."""
    out = []
    for v in variants:
        alpha = v.system.exponent
        n_in = int(np.count_nonzero(in_fit_range(np.array(v.E, float), alpha)))
        e_max = 2.0 / alpha * DEFAULT_FIT_OVERLAP ** alpha
        if len(N) < 2:
            out.append(f"variant {v.name!r} has one size (N_G = {N[0]}): the N_G -> inf row extrapolates in 1/N_G "
                       f"and needs two sizes or more, so no seed count gives {key}")
        elif n_in < SHARED_FIT_CELLS:
            out.append(f"variant {v.name!r} has {n_in} energ{'y' if n_in == 1 else 'ies'} in the fit range "
                       f"(typical overlap <= {DEFAULT_FIT_OVERLAP:g}: E_G <= {e_max:.3g} at alpha = {alpha:g}); "
                       f"the shared fit behind {key} needs {SHARED_FIT_CELLS} per size, so no seed count gives it")
    return out


def describe(p: Precision) -> str:
    parts = [f"{k} {v:g}" for k, v in p.targets]
    extra = f", budget {p.budget:g} core-hours" if p.budget is not None else ""
    return (f"targets {', '.join(parts)} (standard errors of the N_G -> inf row); pilot {p.pilot} seeds per cell, "
            f"at most {p.max_seeds}{extra}")
