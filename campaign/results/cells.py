"""The reducer's cells, one per (variant, N, E) of the task table, and what it computes per
cell: the counts (done, excluded, pending, failed) and the notes on them, the mean, standard
deviation and standard error of every scalar, P(A_G) with its best Gaussian and the width
scaling sigma(A_G) ~ N^-gamma, and the one pass over the histograms (summed distributions,
self-averaging, P(sin theta)). Works on the ``Finished`` packings of
``campaign.results.finished``; ``s`` is the reducer's ``Settings`` (``campaign.results.reduce``,
which imports this module). docs/REDUCED.md describes the outputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.results import fits
from campaign.storage.layout import FAILED, PENDING

#: Histograms whose self-averaging is not tested: radial pair counts are not per-object
#: variables; gaps and forces are counted on log-spaced bins for their small-value tails.
SELF_AVERAGING_SKIP = ("radial_grains", "radial_contacts", "gap", "force", "force_extended")


def _cell_index(variant, N, E):
    """Unique (variant, N, E) keys sorted by variant, N, then E; and each row's cell."""
    vnames, vcode = np.unique(np.asarray(variant, dtype=str), return_inverse=True)
    order = np.lexsort((E, N, vcode))
    key = np.stack([vcode[order], N[order]], axis=1)
    new = np.ones(len(order), bool)
    new[1:] = (np.any(key[1:] != key[:-1], axis=1)) | (E[order][1:] != E[order][:-1])
    cell_sorted = np.cumsum(new) - 1
    cell = np.empty(len(order), np.int64)
    cell[order] = cell_sorted
    first = order[new]
    return cell, vnames[vcode[first]], N[first], E[first]


def _group_stats(values, cell, C):
    """Count, mean, sample std and standard error per cell, ignoring NaN."""
    ok = np.isfinite(values)
    c = cell[ok]
    v = values[ok]
    n = np.bincount(c, minlength=C).astype(float)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        mean = np.bincount(c, weights=v, minlength=C) / n
        d = v - mean[c]
        # a cell with fewer than two values has no spread (0 / -1 would give a finite -0.0)
        var = np.where(n >= 2, np.bincount(c, weights=d * d, minlength=C) / np.maximum(n - 1, 1), np.nan)
        std = np.sqrt(var)
        sem = std / np.sqrt(n)
    return n, mean, std, sem


@dataclass
class Grid:
    """The cells of a reduction, (variant, N, E) for every task finished or not, and where
    each usable packing falls (``cell``; ``order``/``bounds``: the packings sorted by cell)."""

    cv: np.ndarray
    cN: np.ndarray
    cE: np.ndarray
    cell: np.ndarray
    n_done: np.ndarray
    n_excluded: np.ndarray
    n_failed: np.ndarray
    n_pending: np.ndarray
    order: np.ndarray
    bounds: np.ndarray

    @property
    def C(self):
        return len(self.cv)

    @property
    def n_tasks(self):
        return self.n_done + self.n_excluded + self.n_failed + self.n_pending

    def packings(self, i):
        """Rows (into the usable packings) of cell ``i``."""
        return self.order[self.bounds[i]:self.bounds[i + 1]]


def grid(everything, good, tasks) -> Grid:
    """The cells of every task of ``tasks`` (finished or not), counted, and where each usable
    packing (``good``: mask over the finished packings ``everything``) falls."""
    cell_all, cv, cN, cE = _cell_index(tasks["variant"], tasks["N"].astype(np.int64),
                                       tasks["E"].astype(float))
    C = len(cv)
    lookup = {(v, int(n), float(e)): i for i, (v, n, e) in enumerate(zip(cv, cN, cE))}
    cell_everything = np.array([lookup[(v, int(n), float(e))] for v, n, e
                                in zip(everything.variant, everything.N, everything.E)],
                               dtype=np.int64)
    cell = cell_everything[good]
    st = tasks["status"]
    counted = tasks["counted"]
    order = np.argsort(cell, kind="stable")
    return Grid(cv=cv, cN=cN, cE=cE, cell=cell,
                n_done=np.bincount(cell, minlength=C),
                n_excluded=np.bincount(cell_everything[~good], minlength=C),
                n_failed=np.bincount(cell_all[counted & (st == FAILED)], minlength=C),
                n_pending=np.bincount(cell_all[counted & (st == PENDING)], minlength=C),
                order=order, bounds=np.searchsorted(cell[order], np.arange(C + 1)))


def cell_table(fin, g: Grid) -> dict:
    """Counts, and mean, standard deviation and standard error of every scalar, per cell."""
    cells = {"variant": g.cv, "N": g.cN, "E": g.cE, "n_packings": g.n_done, "n_excluded": g.n_excluded,
             "n_pending": g.n_pending, "n_failed": g.n_failed, "n_tasks": g.n_tasks}
    for name, v in fin.scalars.items():
        _, mean, std, sem = _group_stats(v, g.cell, g.C)
        cells[f"mean_{name}"] = mean
        cells[f"std_{name}"] = std
        cells[f"sem_{name}"] = sem
    return cells


def count_notes(fin, g: Grid, reasons) -> list:
    """What the reduction leaves out: unknown layout, unusable, pending and failed packings."""
    notes = []
    cv, cN, cE = g.cv, g.cN, g.cE
    schema = str(fin.attrs.get("schema", ""))
    if not schema.startswith("jamming-campaign/"):
        notes.append(f"{fin.paths[0]}: unknown store schema {schema!r} (expected "
                     "jamming-campaign/1); reading it as that layout")
    if len(fin) == 0:
        notes.append("no finished packings yet: nothing to fit")
    if g.n_excluded.sum():
        why = ", ".join(f"{int(m.sum())} with {r}" for r, m in reasons.items() if m.any())
        notes.append(f"{int(g.n_excluded.sum())} finished packing(s) left out of the statistics ({why}); "
                     "the cells' n_excluded counts them")
        for i in np.flatnonzero(g.n_excluded > 0):
            notes.append(f"  {cv[i]} N={cN[i]} E={cE[i]:.3g}: {g.n_excluded[i]} of "
                         f"{g.n_done[i] + g.n_excluded[i]} finished left out")
    pend_total, fail_total = int(g.n_pending.sum()), int(g.n_failed.sum())
    if pend_total or fail_total:
        notes.append(f"{len(fin)} packings done, {pend_total} pending, {fail_total} failed: "
                     "the reduction uses the finished ones only")
        for i in np.flatnonzero((g.n_pending + g.n_failed) > 0):
            notes.append(f"  {cv[i]} N={cN[i]} E={cE[i]:.3g}: {g.n_done[i]} done, "
                         f"{g.n_pending[i]} pending, {g.n_failed[i]} failed")
        errs = fin.tasks["error"][(fin.tasks["status"] == FAILED)]
        if len(errs):
            first = next((e for e in errs if e), "")
            if first:
                notes.append(f"  first failure: {first.splitlines()[-1] if first else ''}")
    return notes


def area_distributions(fin, g: Grid, s, cells):
    """P(A_G) per cell: its best Gaussian (added to ``cells``) and a histogram of about
    sqrt(n) bins; and the width scaling sigma(A_G) ~ N^-gamma per (variant, E)."""
    C = g.C
    A = fin.scalars.get("A_G", np.full(len(fin), np.nan))
    gm = np.full((C, 4), np.nan)
    a_edges = np.full((C, s.area_bins + 1), np.nan)
    a_counts = np.zeros((C, s.area_bins), np.int64)
    for i in range(C):
        v = A[g.packings(i)]
        v = v[np.isfinite(v)]
        if v.size >= 2:
            gm[i] = fits.gaussian_mle(v)
            lo, hi = v.min(), v.max()
            if hi <= lo:
                hi = lo + abs(lo) * 1e-9 + 1e-300
            nb = int(min(s.area_bins, max(4, round(np.sqrt(v.size)))))  # ~sqrt(n) bins
            a_edges[i, :nb + 1] = np.linspace(lo, hi, nb + 1)
            a_counts[i, :nb] = np.histogram(v, a_edges[i, :nb + 1])[0]
    cells.update(A_G_gauss_mean=gm[:, 0], A_G_gauss_sigma=gm[:, 1], A_G_gauss_mean_err=gm[:, 2],
                 A_G_gauss_sigma_err=gm[:, 3])
    width = []
    cv, cN, cE = g.cv, g.cN, g.cE
    for v in np.unique(cv):
        for e in np.unique(cE[cv == v]):
            sel = np.flatnonzero((cv == v) & (cE == e) & (g.n_done >= s.min_packings))
            r = fits.fit_width_scaling(cN[sel], gm[sel, 1], gm[sel, 3])
            width.append({"variant": v, "E": float(e), "gamma": r.value, "gamma_err": r.err,
                          "log_prefactor": r.slope, "chi2_dof": r.chi2_dof,
                          "n_sizes": r.n_points, "message": r.message})
    return {"edges": a_edges, "counts": a_counts}, width


def histograms(fin, g: Grid, s):
    """One pass over every histogram: summed and normalised counts per cell, the
    self-averaging ratios, and P(sin theta)."""
    C, cell = g.C, g.cell
    dists, selfavg = {}, {}
    for name, edges in sorted(fin.edges.items()):
        nb = len(edges) - 1
        centres = 0.5 * (edges[1:] + edges[:-1])
        counts = np.zeros((C, nb), np.int64)
        want_m = name not in SELF_AVERAGING_SKIP
        mom = np.full((len(fin), 2), np.nan) if want_m else None
        for pos, block in fin.histogram_blocks(name):
            cb = cell[pos]
            o = np.argsort(cb, kind="stable")
            cbs = cb[o]
            starts = np.flatnonzero(np.r_[True, cbs[1:] != cbs[:-1]])
            counts[cbs[starts]] += np.add.reduceat(block[o], starts, axis=0)
            if want_m:
                bf = block.astype(float)
                tot = bf.sum(axis=1)
                with np.errstate(invalid="ignore", divide="ignore"):
                    mom[pos, 0] = bf @ centres / tot
                    mom[pos, 1] = bf @ (centres * centres) / tot
        widths = np.diff(edges)
        with np.errstate(invalid="ignore", divide="ignore"):
            density = counts / counts.sum(axis=1, keepdims=True) / widths
        dists[name] = {"edges": edges, "counts": counts, "density": density}
        if want_m:
            tot = counts.sum(axis=1).astype(float)
            with np.errstate(invalid="ignore", divide="ignore"):
                ens = np.stack([counts @ centres / tot, counts @ (centres**2) / tot], axis=1)
                ratio = mom / ens[cell]
            rm = np.full((C, 2), np.nan)
            rs = np.full((C, 2), np.nan)
            for k in range(2):
                _, rm[:, k], rs[:, k], _ = _group_stats(ratio[:, k], cell, C)
            selfavg[name] = {"ratio_mean": rm, "ratio_std": rs, "ensemble_moments": ens}
    if "contact_angle" in dists:
        se = np.linspace(0.0, 1.0, s.sin_bins + 1)
        d = dists["contact_angle"]
        dens = np.full((C, s.sin_bins), np.nan)
        has = d["counts"].sum(axis=1) > 0
        if has.any():
            dens[has] = fits.sin_theta_density(d["counts"][has], d["edges"], se)
        dists["sin_theta"] = {"edges": se, "density": dens}
    return dists, selfavg
