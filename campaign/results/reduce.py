"""The reducer: campaign file(s) -> a ``Reduction`` (the finite-size table, its fits, the sections).

Distributions, scaling fits, the finite-size table and the optional sections of ``SECTIONS``.

``reduce_campaign`` takes its steps in this order, each one's machinery in the module named:

1. the finished packings, and which of them are usable (``campaign.results.finished``, the one
   place that knows the store layout of docs/CONTRACTS.md; only rows with status 1 are used);
2. the cells (variant, N, E): counts and the notes on what is left out, the statistics of every
   scalar, P(A_G) (``campaign.results.cells``);
3. the physical system of each variant (``campaign.results.finished``);
4. the scaling fits per size over the fit range (``campaign.results.scaling``);
5. the N_G -> inf row (``campaign.results.finitesize``);
6. the histograms summed per cell (``campaign.results.cells``);
7. the sections of ``SECTIONS``, in that order (``campaign.results.sections``): the variants compared
   (``tradeoff``), the physical systems (``systems``), the linear response (``response``), the
   jamming point and the protocols compared (``protocols``).

Its result, a ``Reduction``, is written by ``campaign.report.writing`` and drawn by
``campaign.report.plots``. The output layout (``/reduced`` group and the tables) is documented
in docs/REDUCED.md.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from campaign.errors import UserError
from campaign.results import fits, protocols, response, systems, tradeoff
from campaign.results.cells import area_distributions, cell_table, count_notes, grid, histograms
from campaign.results.finitesize import extrapolate
from campaign.results.finished import ladder_variants, load_finished, variant_systems
from campaign.results.scaling import (DEFAULT_FIT_OVERLAP, fit_rule_name, fit_rule_text, is_default_range,
                                      scaling_fits)

#: The optional sections (``campaign.results.sections``), in the order they are computed and their
#: keys enter summary.json. A new statistic is a module ending in ``SECTION = Section(...)`` and its
#: line here (docs/DEVELOPMENT.md, "The house").
SECTIONS = (tradeoff.SECTION, systems.SECTION, response.SECTION, protocols.SECTION)

#: The outputs that list the sections in another order than ``SECTIONS``: the order each had before
#: the sections were a registry, kept so that every output stays byte for byte what it was. The
#: sections named come first, in this order; the others follow in the order of ``SECTIONS``.
ORDER = {"console": ("systems", "tradeoff"),               # campaign reduce's text after the table
         "reduced": ("tradeoff", "systems", "protocols"),  # the groups of /reduced
         "files": ("response", "protocols", "systems")}    # the files written after summary.json


def in_order(output: str) -> tuple:
    """The sections in the order ``output`` (a key of ``ORDER``, else ``SECTIONS``' order) lists them."""
    first = ORDER.get(output, ())
    return tuple(sorted(SECTIONS, key=lambda sec: first.index(sec.name) if sec.name in first else len(first)))


@dataclass
class Settings:
    min_packings: int = 3       # a cell with fewer finished packings is left out of the fits
    n_boot: int = 1000          # bootstrap resamples (packings within each cell)
    boot_seed: int = 20240917   # fixed: the same file gives the same errors
    area_bins: int = 30         # bins of the per-cell P(A_G) histogram
    sin_bins: int = 100         # bins of P(sin theta) on [0, 1]
    reference: str = "default"  # the variant the others are compared with (campaign.results.tradeoff)
    # The fit range of the scaling laws (docs/REDUCED.md, "The fit range"): the cells whose grid
    # energy lies in fit_energies = [lo, hi] and whose typical relative overlap
    # (alpha E_G / 2)^(1/alpha) is at most fit_overlap (alpha: the variant's exponent). The
    # default, DEFAULT_FIT_OVERLAP, is one distance from jamming for every potential, chosen by
    # experiments/fit_rules.py; fit_overlap = inf with the default fit_energies: every energy.
    fit_energies: tuple = (0.0, float("inf"))
    fit_overlap: float = DEFAULT_FIT_OVERLAP
    # a range asked for explicitly (the command line's --fit-all, --fit-energies, --fit-overlap):
    # a (variant, N) whose range holds fewer energies of the grid than a fit needs
    # (fits.MIN_CELLS) is refused (UserError); with the default range it only gets no fits
    strict_range: bool = False


def three_disk_peaks(system: dict) -> dict:
    """The exact three-disk peaks of a variant's system (``finished.variant_systems``): of its discrete
    radii; for a continuous size distribution only the equal-disk edge triangle
    (``alpha_e = sqrt(3)/4``, ``theta = pi/3``), the centre of the continuum of peaks a
    polydisperse packing smears out, and no ``alpha_v`` (its scale, the packing's largest
    radius, is itself random)."""
    if system["radii"]:
        alpha_e, theta, alpha_v = fits.three_disk_peaks(system["radii"])
    else:
        alpha_e, theta, alpha_v = np.array([math.sqrt(3) / 4]), np.array([math.pi / 3]), np.array([])
    return {"alpha_e": alpha_e, "theta": theta, "alpha_v": alpha_v}


@dataclass
class Reduction:
    cells: dict                  # column -> (C,) arrays
    distributions: dict          # name -> {"edges", "counts" (C, nb), "density" (C, nb)};
    #                              sin_theta (derived from contact_angle) has no counts
    self_averaging: dict         # name -> {"ratio_mean" (C, 2), "ratio_std" (C, 2)}
    area_hist: dict              # {"edges" (C, nb+1), "counts" (C, nb)}: a cell uses the
    #                              first ~sqrt(n) bins; unused edges are NaN, counts 0
    fits: list                   # records (dicts), one per (variant, N, quantity, abscissa)
    residuals: np.ndarray        # (F, C) normalised residuals, NaN where a cell was not used
    width_scaling: list          # records per (variant, E)
    rows: list                   # table rows per (variant, N)
    extrapolated: dict           # variant -> {key: value, key_err: ...}
    peaks: dict                  # variant -> {alpha_e, theta, alpha_v} (``three_disk_peaks``)
    notes: list                  # human-readable: what is missing, what was skipped
    meta: dict
    # section name -> its result (SECTIONS), also red.<name>: red.tradeoff (campaign.results.tradeoff's
    # records, summary.json's "variants"), red.systems, red.response, red.protocols (a Protocols)
    sections: dict = field(default_factory=dict)
    # (variant, quantity, abscissa) -> N_G -> what the law's fits took at that size: the cells' means,
    # the variance model's errors (the weights), the cells (Table.shared_in), or why it did not enter
    fit_inputs: dict = field(default_factory=dict)

    def __getattr__(self, name):
        """A section's result by its name (``red.tradeoff``): ``sections[name]``."""
        sections = self.__dict__.get("sections", {})
        if name in sections:
            return sections[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute or section {name!r}")

    def fit_rule(self) -> dict:
        """Which cells the scaling fits use: the range's name and sentence, whether it is the
        default, its window (docs/REDUCED.md, "The fit range")."""
        m = self.meta
        return {"name": m.get("fit_rule_name", ""), "text": m.get("fit_rule_text", ""),
                "default": bool(m.get("fit_default", False)),
                "fit_energies": list(m.get("fit_energies", (0.0, math.inf))),
                "fit_overlap": m.get("fit_overlap", math.inf)}

    def to_json(self):
        def clean(v):
            if isinstance(v, (float, np.floating)):
                return None if not np.isfinite(v) else float(v)
            if isinstance(v, (np.integer,)):
                return int(v)
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [clean(x) for x in v]
            return v

        out = {"fit_rule": self.fit_rule(), "rows": self.rows, "extrapolated": self.extrapolated}
        for sec in SECTIONS:
            out.update(sec.json(self.sections[sec.name]))
        return clean({**out, "status": {k: self.meta[k] for k in ("done", "pending", "failed", "total")},
                      "notes": self.notes})


@dataclass
class Table:
    """The reducer's steps 1-5 (the module docstring) on finished packings: what the finite-size
    table and its ``N_G -> inf`` row come from. ``shared_in``: (variant, quantity, abscissa) -> per
    N_G the inputs of the shared-exponent fit (cell means, errors, bootstrap replicas, the cells of
    ``grid`` they come from), or why the size did not enter."""

    everything: object           # campaign.results.finished.Finished: every finished packing
    good: np.ndarray             # which of them are usable
    reasons: dict
    fin: object                  # the usable ones
    grid: object                 # campaign.results.cells.Grid
    cells: dict
    notes: list
    systems: dict                # variant -> its system (finished.variant_systems)
    fit_records: list
    residuals: np.ndarray
    rows: list
    shared_in: dict
    extrapolated: dict
    shared_fits: dict = field(default_factory=dict)  # (variant, quantity, abscissa) -> (sizes, SharedFit, 1/N line)
    replica_weights: dict = field(default_factory=dict)  # cell -> (n_boot, packings): bootstrap.replica_weights


def reduce_table(everything, s: Settings, per_size=True) -> Table:
    """Steps 1-5 of ``reduce_campaign`` on the finished packings ``everything``
    (``campaign.results.finished.Finished``, from the store or built from arrays): the cells, their
    statistics, the scaling fits per size and the ``N_G -> inf`` row, with their bootstrap errors.
    The same function serves ``campaign reduce`` and the rounds of a campaign with precision
    targets (``campaign.precision.allocation``), so both see the same table and errors (those rounds
    need the ``N_G -> inf`` row only: ``per_size=False`` leaves the per-size fits out, which that
    row does not use)."""
    # statistics use the converged packings whose identities hold; the others are
    # counted per cell (n_excluded) and named in the notes
    good, reasons = everything.usable()
    fin = everything.subset(good)
    if len(fin.tasks["status"]) == 0:
        raise UserError(f"{fin.paths[0] if fin.paths else 'the store'}: the task table is empty")
    g = grid(everything, good, fin.tasks)  # cells are defined by every task, finished or not
    cells = cell_table(fin, g)
    notes = count_notes(fin, g, reasons)
    vsys = variant_systems(fin.attrs, variants=g.cv)
    fit_records, residuals, rows, shared_in, laws, weights = scaling_fits(fin, g, s, cells, notes,
                                                                 {v: d["exponent"] for v, d in vsys.items()},
                                                                 per_size, chains=ladder_variants(fin.attrs))
    shared_fits = {}
    extrapolated = extrapolate(rows, shared_in, laws, notes, shared_fits)
    return Table(everything=everything, good=good, reasons=reasons, fin=fin, grid=g, cells=cells, notes=notes,
                 systems=vsys, fit_records=fit_records, residuals=residuals, rows=rows, shared_in=shared_in,
                 extrapolated=extrapolated, shared_fits=shared_fits, replica_weights=weights)


def reduce_campaign(paths, settings: Settings | None = None, *, distributions=True) -> Reduction:
    """Reduce campaign file(s) (see the module docstring). ``distributions=False`` skips the
    histogram pass (scalars, fits and the table only)."""
    s = settings or Settings()
    t0 = time.perf_counter()
    everything = load_finished(paths)
    t_load = time.perf_counter() - t0
    tab = reduce_table(everything, s)
    fin, g, cells, notes, vsys = tab.fin, tab.grid, tab.cells, tab.notes, tab.systems
    fit_records, residuals, rows, extrapolated = tab.fit_records, tab.residuals, tab.rows, tab.extrapolated
    area_hist, width = area_distributions(fin, g, s, cells)
    t1 = time.perf_counter()
    dists, selfavg = histograms(fin, g, s) if distributions else ({}, {})
    t_hist = time.perf_counter() - t1
    sections = {sec.name: sec.compute(tab, s, dists) if sec.present(tab) else sec.empty() for sec in SECTIONS}
    meta = {"sources": fin.paths, "done": int(len(fin)), "excluded": int(g.n_excluded.sum()),
            "pending": int(g.n_pending.sum()), "failed": int(g.n_failed.sum()),
            "total": int(g.n_tasks.sum()), "n_boot": s.n_boot,
            "boot_seed": s.boot_seed, "min_packings": s.min_packings,
            "fit_energies": [float(x) for x in s.fit_energies], "fit_overlap": float(s.fit_overlap),
            "fit_default": is_default_range(s), "fit_rule_name": fit_rule_name(s),
            "fit_rule_text": fit_rule_text(s),
            "spec_hash": fin.attrs.get("spec_hash", ""), "name": fin.attrs.get("name", ""),
            "seconds": {"load": t_load, "histograms": t_hist,
                        "total": time.perf_counter() - t0}}
    return Reduction(cells=cells, distributions=dists, self_averaging=selfavg,
                     area_hist=area_hist, fits=fit_records, residuals=residuals,
                     width_scaling=width, rows=rows, extrapolated=extrapolated,
                     peaks={v: three_disk_peaks(vsys[v]) for v in sorted(set(g.cv))},
                     notes=notes, meta=meta, sections=sections, fit_inputs=tab.shared_in)
