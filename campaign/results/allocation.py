"""Where a campaign with precision targets spends its next seeds (docs/PRECISION.md).

After each round the campaign's finished packings are reduced with the reducer itself
(``campaign.results.reduce.reduce_table``: the table and its bootstrap errors as ``campaign reduce``
computes them). ``decide`` then compares each target's error with its goal and, while one is short,
gives the next round's seeds to the cells where a packing removes the most error per core-second.

**The model of the errors.** Each target is an entry of the ``N_G -> inf`` row of one law
``y = a_N + c_N x^beta`` (y: ``A_G`` or ``psi_O``; x: ``E_G`` or ``delta_Z``), the exponent shared by the
sizes and the intercepts extrapolated as ``a_N = a_inf + b / N``. Linearised about the fitted values,
the row is a weighted least-squares fit of the cell means with parameters
``theta = (a_inf, b, beta, c_N1 .. c_NG)``, so its covariance is the inverse of the Fisher information

    I(n) = sum over the cells c of the fit range  (n_c / s_c^2) J_c J_c^T,
    J_c = d(a_inf + b/N + c_N x_c^beta) / d theta = (1, 1/N, c_N x_c^beta ln x_c, x_c^beta e_N),

``n_c`` the cell's usable packings and ``s_c^2`` the variance between its packings of
``y - c_N beta x_c^(beta-1) x`` (the scatter of the abscissa carried through the law, as the
bootstrap carries it). A target's predicted variance is ``r^2 [I(n)^-1]_kk`` (k: ``a_inf`` or
``beta``), with ``r`` the ratio of the reducer's bootstrap error to the model's at the current
``n``, so that the prediction starts from the measured error and the model only says how it falls.
An intercept whose sizes scatter about the 1/N_G line more than their errors allow (p < 0.01) has
the reducer's error inflated by ``sqrt(chi^2/dof)``; that part does not fall with more seeds, and
the model keeps it as a floor.

**The allocation** is greedy on the marginal reduction of ``sum_T V_T / tau_T^2`` over the targets
not yet met, per core-second: the continuous optimum of a sum of variances at a given cost is
Neyman's allocation (``n_c`` proportional to ``|g_c| s_c / sqrt(cost_c)`` for a linear estimator
``sum g_c ybar_c``), which the greedy reaches step by step while the weights ``g_c`` change with
the allocation (the fit re-weights its cells as they fill, which a fixed Neyman allocation does not
see), and it stops giving a target seeds once the target is projected met. A round commits at most
as much as the campaign has spent so far (rounds double), so the model is re-estimated from the
new packings before it is trusted far; it also stops at ``max_seeds`` per cell and the budget. The
next round's first seeds (``early``) are the plan's continuation, a tenth of the round's cost, given
out while the round's last packings finish, so that no worker waits at a round's end.

Every decision is a function of stored, deterministic values (the packings' scalars and force
evaluations), never of wall times, so a campaign's tasks and store are the same bits however it
is run. Costs: a packing's force evaluations times its disks, times the calibration's seconds per
disk-force evaluation (``seconds_per_disk_force_evaluation``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from campaign.plan.precision import (DEFAULT_FIT_OVERLAP, FITS, in_fit_range, law_of)
from campaign.results import fits

#: a round commits at most this multiple of what the campaign has spent before it
ROUND_GROWTH = 1.0
#: the next round's early seeds: this share of the round's cost (the plan's continuation)
EARLY_SHARE = 0.1
#: a size whose intercept lies off the 1/N_G line by more than this many of its errors has a systematic
#: offset (a finite-size correction beyond 1/N_G) that the model keeps: more seeds at that size make the
#: reducer's sqrt(chi^2/dof) of the line larger, not its error smaller
SYSTEMATIC_SIGMA = 3.0
#: ... in a 1/N_G line whose chi^2 has a p-value below this (a few packings per cell make a size's
#: bootstrap error short, and one size in several lies 3 errors off now and then)
SYSTEMATIC_P = 0.001
#: a cell's seeds grow at most this many times in one round: the first rounds' model comes from a
#: few packings per cell, and a design it finds optimal (often a few cells) is taken a step at a
#: time, re-estimated before it is trusted with more
CELL_GROWTH = 4
#: a law whose data show no dependence of y on x at this p-value or above has no exponent to measure
NO_DEPENDENCE_P = 0.01
#: an undetermined target (no value from the reducer) is planned to this share of its goal
UNDETERMINED_GOAL = 0.5
#: a target with a value is planned to this share of its goal: the bootstrap error the next decision
#: sees scatters about the model's projection, and a plan that aims at the goal itself falls short
#: about half the time, each time by a little (a round for a few packings)
AIM = 1.0
#: a round gives out at least this share of what the campaign has spent (rounds of a few packings
#: cost a decision each and gain little)
MIN_ROUND = 0.05

ACTIONS = ("pilot", "continue", "met", "budget", "max_seeds", "unreachable")


def seconds_per_disk_force_evaluation() -> float:
    """Core-seconds per disk per force evaluation of a packing (the FIRE kernels' cost per step, with
    the search and the analysis around it spread over the steps), from the calibration in force."""
    from campaign.plan import calibration

    return calibration.active().disk_force_evaluation_seconds


# --------------------------------------------------------------------------- the campaign's cells

@dataclass
class Cells:
    """The cells of a campaign (variant, N, E) in the task table's order, each holding the tasks
    ``first + seed`` for seeds 0 .. ``seeds - 1``."""

    variant: list
    N: np.ndarray
    E: np.ndarray
    exponent: np.ndarray   # the variant's potential exponent
    first: np.ndarray      # index of the cell's seed 0
    seeds: int             # tasks per cell (max_seeds)

    @property
    def C(self) -> int:
        return len(self.variant)

    def key(self, c) -> tuple:
        return (self.variant[c], int(self.N[c]), float(self.E[c]))

    def index(self) -> dict:
        return {self.key(c): c for c in range(self.C)}

    def tasks_of(self, counts) -> np.ndarray:
        """Task indices of the first ``counts[c]`` seeds of every cell (bool mask, one per task)."""
        mask = np.zeros(self.C * self.seeds, bool)
        for c in range(self.C):
            mask[self.first[c]:self.first[c] + int(counts[c])] = True
        return mask

    def relevant(self, targets) -> np.ndarray:
        """The cells in the default fit range of a variant that has targets: where seeds can move
        the ``N_G -> inf`` row (every variant has every target)."""
        return np.asarray(in_fit_range(self.E, self.exponent), bool) if targets else np.zeros(self.C, bool)


def campaign_cells(spec, tasks) -> Cells:
    """The cells of a precision campaign's task table (canonical order: variant, N, E, seed)."""
    S = spec.precision.max_seeds if spec.precision is not None else len(spec.seeds)
    first = np.arange(0, len(tasks), S)
    t = [tasks[i] for i in first]
    return Cells(variant=[x.variant for x in t], N=np.array([x.N for x in t], np.int64),
                 E=np.array([x.E for x in t], float), exponent=np.array([x.exponent for x in t], float),
                 first=first, seeds=S)


# --------------------------------------------------------------------------- the model of one law

@dataclass
class LawModel:
    """One variant's law ``y = a_N + c_N x^beta``, linearised about a fit (the module docstring):
    the cells it fits (indices into ``Cells``, and the size of each), their means, the reducer's
    weights and their packings, the point fit, and at any exponent the design vectors and the
    per-packing variances (``at``) from which the Fisher information follows."""

    variant: str
    quantity: str
    abscissa: str
    sizes: list
    cells: np.ndarray = field(default_factory=lambda: np.zeros(0, int))   # campaign cells in the fit
    size_of: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # index into sizes
    xbar: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ybar: np.ndarray = field(default_factory=lambda: np.zeros(0))
    yerr: np.ndarray = field(default_factory=lambda: np.zeros(0))          # the reducer's weights 1/yerr^2
    packings: list = field(default_factory=list)                           # per cell (x, y) of its packings
    beta: float = np.nan
    sys2: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per size: its intercept's systematic
    #                         squared offset from the 1/N_G line (seeds do not remove it: the reducer's
    #                         sqrt(chi^2/dof) grows as the sizes' errors shrink)
    dof: int = 0            # degrees of freedom of the 1/N_G line (sizes - 2)
    ok: bool = True
    why: str = ""
    J: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))         # at the point fit
    s2: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def free(self, J) -> np.ndarray:
        """The design vectors with a free intercept per size (``theta = (beta, a_N1 .. a_NG, c_N1 ..
        c_NG)``: the shared fit before the 1/N_G line), for the sizes' intercept errors."""
        G = len(self.sizes)
        F = np.zeros((len(J), 1 + 2 * G))
        F[:, 0] = J[:, 2]
        F[np.arange(len(J)), 1 + self.size_of] = 1.0
        F[:, 1 + G:] = J[:, 3:]
        return F

    def state(self, n, J=None, s2=None):
        """The inverses of the Fisher information at ``n`` (joint, and with free intercepts)."""
        J = self.J if J is None else J
        s2 = self.s2 if s2 is None else s2
        w = np.asarray(n, float)[self.cells] / s2
        F = self.free(J)
        return [_inverse((J * w[:, None]).T @ J), _inverse((F * w[:, None]).T @ F), J, F, s2]

    def add(self, st, i, dn):
        """``st`` with ``dn`` more usable packings in the law's cell ``i`` (rank-one updates)."""
        inv, invf, J, F, s2 = st
        w = dn / s2[i]
        out = [inv, invf]
        for k, (A_, v) in enumerate(((inv, J[i]), (invf, F[i]))):
            Av = A_ @ v
            q = float(v @ Av)
            if np.all(np.isfinite(Av)) and np.isfinite(q):
                out[k] = A_ - np.outer(Av, Av) * (w / (1.0 + w * q))
        return [out[0], out[1], J, F, s2]

    def inflation(self, invf) -> float:
        """The reducer's sqrt(chi^2/dof) of the 1/N_G line, squared, expected at the sizes' intercept
        errors of ``invf``: ``max(1, (dof + sum sys2 / sigma_N^2) / dof)``."""
        if self.dof <= 0 or not np.any(self.sys2 > 0):
            return 1.0
        G = len(self.sizes)
        var = np.diag(invf)[1:1 + G]
        chi2 = self.dof + float(np.sum(np.where(var > 0, self.sys2 / np.maximum(var, 1e-300), 0.0)))
        return max(1.0, chi2 / self.dof)

    def refit(self, beta):
        """The amplitudes c_N and chi^2 of the reducer's weighted fit with the exponent held at ``beta``."""
        G = len(self.sizes)
        coeffs, chi2 = np.zeros(G), 0.0
        for gi in range(G):
            m = self.size_of == gi
            x, y, w = self.xbar[m], self.ybar[m], 1.0 / self.yerr[m] ** 2
            f = np.where(x > 0, x, 0.0) ** beta
            a, c, ch = fits._solve_linear(f[None], y[None], w)
            coeffs[gi], chi2 = float(c[0]), chi2 + float(ch[0])
        return coeffs, chi2

    def at(self, beta, coeffs):
        """Design vectors (K, 3 + G) and per-packing residual variances (K,) at an exponent and its
        amplitudes; cells whose packings show no spread are left out (weight 0)."""
        G = len(self.sizes)
        K = len(self.cells)
        J, s2 = np.zeros((K, 3 + G)), np.full(K, np.inf)
        for i in range(K):
            gi, xc = int(self.size_of[i]), float(self.xbar[i])
            xv, yv = self.packings[i]
            cN = coeffs[gi]
            if xc > 0:
                xb = xc ** beta
                resid, dbeta = yv - cN * beta * xc ** (beta - 1.0) * xv, cN * xb * math.log(xc)
            else:  # an isostatic cell (every Delta Z = 0): a point at the intercept
                resid, xb, dbeta = yv, 0.0, 0.0
            var = float(np.var(resid, ddof=1)) if len(resid) >= 2 else np.nan
            if not (np.isfinite(var) and var > 0):
                var = float(np.var(yv, ddof=1)) if len(yv) >= 2 else np.nan
            if np.isfinite(var) and var > 0:
                s2[i] = var
            J[i, 0], J[i, 1], J[i, 2], J[i, 3 + gi] = 1.0, 1.0 / self.sizes[gi], dbeta, xb
        return J, s2

    def info(self, n, J=None, s2=None) -> np.ndarray:
        """Fisher information at usable packings ``n`` per campaign cell."""
        J = self.J if J is None else J
        s2 = self.s2 if s2 is None else s2
        w = np.asarray(n, float)[self.cells] / s2
        return (J * w[:, None]).T @ J

    def inverse(self, n, J=None, s2=None) -> np.ndarray:
        return _inverse(self.info(n, J, s2))

    def dependence_p(self) -> float:
        """The p-value of "y does not depend on x" against the best power law (the reducer's weighted
        chi^2 of a constant per size less the fit's, as a chi^2 of G + 1 degrees of freedom: the
        amplitudes and the exponent)."""
        const = 0.0
        for gi in range(len(self.sizes)):
            m = self.size_of == gi
            y, w = self.ybar[m], 1.0 / self.yerr[m] ** 2
            const += float(np.sum(w * (y - np.sum(w * y) / np.sum(w)) ** 2))
        best = min(ch for _, _, ch in self._profile())
        return fits.chi2_p_value(max(const - best, 0.0), len(self.sizes) + 1)

    def _profile(self, points=60):
        grid = np.linspace(fits.BETA_BOUNDS[0], fits.BETA_BOUNDS[1], points)
        return [(b, *self.refit(b)) for b in np.append(grid, self.beta)]

    def plausible(self, spread=9.0, points=60):
        """Exponents of the search range the data do not exclude (the reducer's weighted chi^2 within
        ``spread`` of its minimum: three standard deviations of a profile), with their amplitudes."""
        fitted = self._profile(points)
        best = min(ch for _, _, ch in fitted)
        return [(b, c) for b, c, ch in fitted if ch <= best + spread]


def _inverse(I) -> np.ndarray:
    """The inverse of a Fisher information; a parameter the data do not inform at all (an amplitude of
    zero leaves the exponent's column zero) gets an infinite variance and the others the inverse of
    the rest."""
    diag = np.diag(I).copy()
    live = diag > 1e-300 * max(1.0, float(np.max(np.abs(diag), initial=0.0)))
    out = np.zeros_like(I)
    out[~live, ~live] = np.inf
    if not live.any():
        return out
    sub = I[np.ix_(live, live)]
    d = np.sqrt(np.diag(sub))
    scaled = sub / np.outer(d, d)
    try:
        inv = np.linalg.inv(scaled)
        if not np.all(np.isfinite(inv)):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(scaled, rcond=1e-13)
    inv = inv / np.outer(d, d)
    bad = ~(np.diag(inv) > 0)  # a direction the data leave free (numerically singular)
    inv[bad, bad] = np.inf
    out[np.ix_(live, live)] = inv
    return out


def _k(kind):
    return 0 if kind == "intercept" else 2


def build_law(table, cells: Cells, variant, quantity, absc) -> LawModel:
    """The model of one variant's law from its reduction ``table`` (``reduce.Table``): the sizes
    that entered the shared fit, their cells, the point fit and each cell's packings."""
    per_n = table.shared_in.get((variant, quantity, absc), {})
    sizes = sorted(n for n, d in per_n.items() if not isinstance(d, str))
    index = cells.index()
    g = table.grid
    if len(sizes) < 2:
        return LawModel(variant, quantity, absc, sizes, ok=False,
                        why=f"{len(sizes)} size(s) in the shared fit of {quantity} against {absc}; the N_G -> inf "
                            "row needs two")
    xs, ys, yerrs = [per_n[n][0] for n in sizes], [per_n[n][1] for n in sizes], [per_n[n][2] for n in sizes]
    f = fits.fit_shared_exponent(xs, ys, yerrs)
    beta = float(f.exponent)
    if not (f.ok and np.isfinite(beta)):
        return LawModel(variant, quantity, absc, sizes, ok=False, why=f"no fit of {quantity} against {absc}")
    cell_ids, size_of, xbar, ybar, yerr, packs = [], [], [], [], [], []
    for gi, n in enumerate(sizes):
        x, y, ye, _, _, gcells = per_n[n]
        for xc, yc, ec, gc in zip(x, y, ye, gcells):
            c = index.get((str(g.cv[gc]), int(g.cN[gc]), float(g.cE[gc])))
            if c is None:
                continue
            p = g.packings(gc)
            yv, xv = table.fin.scalars[quantity][p], table.fin.scalars[absc][p]
            good = np.isfinite(yv) & np.isfinite(xv)
            cell_ids.append(c)
            size_of.append(gi)
            xbar.append(xc)
            ybar.append(yc)
            yerr.append(ec)
            packs.append((xv[good], yv[good]))
    law = LawModel(variant, quantity, absc, sizes, np.array(cell_ids, int), np.array(size_of, int), np.array(xbar),
                   np.array(ybar), np.array(yerr), packs, beta, dof=max(0, len(sizes) - 2))
    law.J, law.s2 = law.at(beta, np.asarray(f.coeffs, float))
    got = table.shared_fits.get((variant, quantity, absc))
    law.sys2 = np.zeros(len(sizes))
    if got is not None and law.dof > 0:
        fsizes, sf, line = got
        if list(fsizes) == list(sizes) and np.isfinite(line.value) and np.isfinite(line.slope):
            resid = np.asarray(sf.intercepts) - (line.value + line.slope / np.asarray(sizes, float))
            err = np.asarray(sf.intercept_errs, float)
            # a size off the line by more than SYSTEMATIC_SIGMA of its error, in a line that fails its
            # chi^2 test (p < SYSTEMATIC_P): its offset is taken as real
            chi2 = float(line.chi2_dof) * law.dof if np.isfinite(line.chi2_dof) else 0.0
            if fits.chi2_p_value(chi2, law.dof) < SYSTEMATIC_P:
                law.sys2 = np.where(np.abs(resid) > SYSTEMATIC_SIGMA * err, resid ** 2 - err ** 2, 0.0)
    return law


# --------------------------------------------------------------------------- targets

@dataclass
class Target:
    variant: str
    key: str
    goal: float
    value: float          # the reducer's, at the decision
    error: float          # the reducer's bootstrap error (NaN: no value)
    law: LawModel | None = None
    ratio: float = 1.0    # reducer's error / the model's
    v_now: float = np.nan  # the model's variance at the current allocation

    @property
    def met(self) -> bool:
        return bool(np.isfinite(self.error) and self.error <= self.goal)

    @property
    def kind(self) -> str:
        return law_of(self.key)[2]

    @property
    def determined(self) -> bool:
        return bool(np.isfinite(self.error))

    @property
    def plan_k(self) -> int:
        """The parameter the plan watches: the target's own (``a_inf`` or ``beta``), or, while the
        reducer gives no value, its law's exponent, whose bootstrap reaching a search bound is what
        leaves the row without a value."""
        return _k(self.kind) if self.determined else 2

    @property
    def aim(self) -> float:
        """The error the plan aims for: ``AIM`` of the goal; while the reducer gives no value, an
        exponent error a third of the exponent's distance to the nearer search bound (its bootstrap
        then stays inside the range, so the row gets a value), or the goal if that is smaller."""
        if self.determined:
            return AIM * self.goal
        lo, hi = fits.BETA_BOUNDS
        room = max(min(self.law.beta - lo, hi - self.law.beta), 1e-3) / 3.0 if self.law.ok else self.goal
        return min(room, AIM * self.goal) if self.kind == "exponent" else room

    def variance(self, st) -> float:
        """Predicted variance of the reducer's error (of the parameter ``plan_k``) at the model state
        ``st`` (``LawModel.state``): the joint fit's, times the 1/N_G line's expected inflation for an
        intercept, times ``ratio^2``."""
        inv, invf = st[0], st[1]
        v = float(inv[self.plan_k, self.plan_k])
        infl = self.law.inflation(invf) if self.plan_k == 0 else 1.0
        return self.ratio ** 2 * v * infl


def _targets(table, cells, settings) -> list:
    out = []
    variants = sorted(set(cells.variant), key=cells.variant.index)
    laws = {}
    for v in variants:
        row = table.extrapolated.get(v, {})
        for key, goal in settings["target"].items():
            q, x, kind = law_of(key)
            if (v, q, x) not in laws:
                laws[(v, q, x)] = build_law(table, cells, v, q, x)
            value, err = row.get(key, np.nan), row.get(f"{key}_err", np.nan)
            value = float(value) if value is not None else np.nan
            err = float(err) if err is not None and np.isfinite(value) else np.nan
            out.append(Target(v, key, float(goal), value, err, laws[(v, q, x)]))
    return out


# --------------------------------------------------------------------------- the decision

@dataclass
class Decision:
    """One round's decision, as recorded in the store (``to_record``)."""

    round: int
    action: str                      # one of ACTIONS
    allocated: np.ndarray            # seeds per cell through this round
    early: np.ndarray                # seeds per cell through the next round's early part (>= allocated)
    settings: dict                   # the precision settings it was made with
    targets: list = field(default_factory=list)   # per target: variant, key, goal, value, error, projected
    spent: float = 0.0               # cost units (core-seconds) of the packings finished before it
    committed: float = 0.0           # estimated cost of the seeds given out and not finished
    round_cost: float = 0.0          # estimated cost of this round's new seeds (early ones included)
    to_targets: float = np.nan       # estimated cost of the plan that meets every target (from here)
    message: str = ""

    def to_record(self, cells: Cells) -> dict:
        def num(x):
            return None if x is None or not np.isfinite(x) else float(x)

        return {"round": int(self.round), "action": self.action,
                "allocated": [int(a) for a in self.allocated], "early": [int(a) for a in self.early],
                "cells": [[cells.variant[c], int(cells.N[c]), float(cells.E[c])] for c in range(cells.C)],
                "settings": self.settings,
                "targets": [{k: (num(v) if isinstance(v, float) else v) for k, v in t.items()} for t in self.targets],
                "spent_core_hours": num(self.spent / 3600.0), "committed_core_hours": num(self.committed / 3600.0),
                "round_core_hours": num(self.round_cost / 3600.0),
                "to_targets_core_hours": num(self.to_targets / 3600.0), "message": self.message}


def pilot(cells: Cells, settings) -> Decision:
    """Round 0: ``pilot`` seeds in every cell; its early part: one more in the cells that can move
    a target (the fit range of the targets' laws)."""
    p, m = int(settings["pilot"]), int(settings["max_seeds"])
    allocated = np.full(cells.C, p, np.int64)
    early = allocated.copy()
    early[cells.relevant(settings["target"])] = min(p + 1, m)
    return Decision(0, "pilot", allocated, early, dict(settings),
                    message=f"pilot: {p} seeds in each of {cells.C} cells")


@dataclass
class State:
    """What a decision starts from, per campaign cell: seeds given out (the early part of the round
    being decided included), of them finished (done or failed) before it, the usable packings among
    those, and the measured cost per packing (core-seconds; NaN: none finished)."""

    given: np.ndarray
    final: np.ndarray
    usable: np.ndarray
    cost: np.ndarray
    spent: float


def decide(k: int, table, cells: Cells, state: State, settings, previous=None) -> Decision:
    """The decision after round ``k - 1``: stop (every target met, the budget spent, ``max_seeds``
    reached, a target out of reach) or the seeds of round ``k`` and the early part of round ``k + 1``.
    ``table``: the reduction of the packings of rounds ``0 .. k - 1``; ``state``: the cells' counts;
    ``previous``: the record of decision ``k - 1``. A target is out of reach when two decisions in
    a row find it so (the first, after the pilot's few packings per cell, may be a poor fit's)."""
    targets = _targets(table, cells, settings)
    m = int(settings["max_seeds"])
    given = state.given.astype(np.int64)
    relevant = cells.relevant(settings["target"])
    frac = np.clip(np.where(state.final > 0, state.usable / np.maximum(state.final, 1), 1.0), 0.05, 1.0)
    cost = _fill_costs(state.cost, cells)
    unfinished = np.maximum(given - state.final, 0)
    committed = float(np.sum(unfinished * cost))
    spent_all = state.spent + committed
    n_now = state.usable + unfinished * frac           # usable packings once the given seeds finish
    budget = settings.get("budget")
    room = math.inf if budget is None else float(budget) * 3600.0 - spent_all

    doubt = set()

    def record(t, projected=np.nan):
        return {"variant": t.variant, "key": t.key, "goal": t.goal, "value": t.value, "error": t.error,
                "met": t.met, "projected": float(np.sqrt(projected)) if np.isfinite(projected) else np.nan,
                "out_of_reach": (t.variant, t.key) in doubt}

    def decision(action, message, alloc=given, early=None, projected=None, round_cost=0.0, to_targets=np.nan):
        proj = projected or {}
        return Decision(k, action, alloc, alloc.copy() if early is None else early, dict(settings),
                        [record(t, proj.get(i, np.nan)) for i, t in enumerate(targets)], state.spent, committed,
                        round_cost, to_targets, message)

    if all(t.met for t in targets):
        return decision("met", "every target met: " + _errors_text(targets))
    # the model of each target, calibrated to the reducer's error at the present allocation
    states = {}
    for t in targets:
        if not t.law.ok:
            continue
        if id(t.law) not in states:
            states[id(t.law)] = t.law.state(n_now)
        t.v_now = float(states[id(t.law)][0][t.plan_k, t.plan_k])
        if t.determined and t.v_now > 0:
            t.ratio = t.error / math.sqrt(t.variance(states[id(t.law)]))   # variance() with ratio 1 here
    # out of reach: with max_seeds in every cell of the fit range a target stays above its goal, by
    # the model alone (not scaled to the bootstrap's error, which a few packings per cell inflate
    # where the fit is far from linear: the model is what the fit reaches once its cells are full)
    n_max = np.maximum(np.where(relevant, m * frac, n_now), n_now)
    unreachable = []
    for t in targets:
        if t.met or not t.law.ok:
            continue
        v_max = _best_case(t, n_max, n_now)
        # the goal, or while the reducer gives no value, the exponent error that gives it one
        if not (np.isfinite(v_max) and v_max <= (t.goal if t.determined else t.aim) ** 2):
            unreachable.append((t, v_max))
    seen = {(r["variant"], r["key"]) for r in (previous or {}).get("targets", []) if r.get("out_of_reach")}
    if unreachable and all((t.variant, t.key) in seen for t, _ in unreachable):
        return decision("unreachable", " ".join(_unreachable_text(t, v, m) for t, v in unreachable))
    doubt = {(t.variant, t.key) for t, _ in unreachable}
    if any(not t.law.ok and not t.met for t in targets):
        # a target without a model yet (too few sizes or cells with a value): the fit range doubled
        grow = np.where(relevant, np.minimum(m, 2 * given), given)
        missing = "; ".join(sorted({t.law.why for t in targets if not t.law.ok}))
        if np.array_equal(grow, given):
            return decision("max_seeds", f"max_seeds ({m}) in every cell of the fit range, and still {missing}")
        round_cost = float(np.sum((grow - given) * cost))
        if round_cost > room:
            return decision("budget", f"the budget left ({max(room, 0) / 3600:.3g} core-hours) does not pay "
                            f"for the next round ({round_cost / 3600:.3g}); {missing}")
        return decision("continue", f"round {k}: no model yet ({missing}): the fit range's seeds doubled",
                        grow, grow.copy(), round_cost=round_cost)
    full = _greedy(targets, cells, n_now, given, frac, cost, relevant, m, states)  # the whole way
    projected = dict(enumerate(full.final_variance))
    to_targets = full.cost_to_met
    # this round's part of it: the plan again with each cell's growth capped (CELL_GROWTH)
    plan = _greedy(targets, cells, n_now, given, frac, cost, relevant, m, states,
                   cap=np.maximum(given * CELL_GROWTH, given + 1))
    if plan.n_met == 0:
        # the model has every target where it should be, the reducer not (a bootstrap at a bound, an
        # error the model underrates): half as many seeds again in the fit range of the targets short
        short = np.zeros(cells.C, bool)
        for t in targets:
            if not t.met and t.law.ok:
                short[t.law.cells] = True
        grow = np.where(short, np.minimum(m, given + np.maximum(1, given // 2)), given)
        round_cost = float(np.sum((grow - given) * cost))
        if np.array_equal(grow, given):
            return decision("max_seeds", f"max_seeds ({m}) in every cell of the fit range; " + _errors_text(targets))
        if round_cost > room:
            return decision("budget", f"the budget left ({max(room, 0) / 3600:.3g} core-hours) does not pay "
                            f"for the next round ({round_cost / 3600:.3g}); " + _errors_text(targets))
        return decision("continue", f"round {k}: the model has every target met where the reducer has not; the fit "
                        f"range of the targets short grows by half: " + _errors_text(targets),
                        grow, grow.copy(), round_cost=round_cost)
    if plan.steps_total == 0:
        return decision("max_seeds", f"max_seeds ({m}) in every cell of the fit range; " + _errors_text(targets),
                        projected=projected)
    if room <= 0:
        return decision("budget", f"budget spent ({spent_all / 3600:.3g} of {budget:g} core-hours); "
                        + _errors_text(targets) + _cost_text(to_targets), projected=projected, to_targets=to_targets)
    met_cost = plan.cost_to_met if np.isfinite(plan.cost_to_met) else math.inf
    main = plan.prefix(min(ROUND_GROWTH * spent_all, room / (1.0 + EARLY_SHARE),
                           max(met_cost, MIN_ROUND * spent_all)), given)
    if np.array_equal(main, given):  # at least the plan's first step
        if plan.costs[0] > room:
            return decision("budget", f"the budget left ({room / 3600:.3g} core-hours) does not pay for the next "
                            "step; " + _errors_text(targets) + _cost_text(to_targets), projected=projected,
                            to_targets=to_targets)
        main = plan.prefix(plan.costs[0], given)
    main_spend = float(np.sum((main - given) * cost))
    early = np.maximum(plan.prefix(main_spend + min(EARLY_SHARE * main_spend, room - main_spend), given), main)
    if np.array_equal(early, main):  # at least the plan's next step, where the budget allows
        after = plan.costs[plan.costs > main_spend * (1 + 1e-12)]
        if len(after) and after[0] <= room:
            early = np.maximum(plan.prefix(after[0], given), main)
    round_cost = float(np.sum((early - given) * cost))
    msg = (f"round {k}: {int(np.sum(main - given))} seeds in {int(np.count_nonzero(main > given))} cells "
           f"(and {int(np.sum(early - main))} early seeds of round {k + 1}); " + _errors_text(targets)
           + _cost_text(to_targets))
    if doubt:
        msg += ("; out of reach by the model so far, to be confirmed by the next decision: "
                + ", ".join(k for _, k in sorted(doubt)))
    return decision("continue", msg, main, early, plan.variance_at(main), round_cost, to_targets)


def _best_case(t, n, n_now) -> float:
    """The smallest variance the model gives target ``t`` at usable packings ``n`` over the exponents
    its data do not exclude (``LawModel.plausible``), the 1/N_G line's inflation included, not scaled
    to the bootstrap: a target out of reach for every plausible exponent is out of reach (a pilot's few
    packings per cell can put the point fit far from the truth, which the best case does not trust).
    Each size's amplitude counts only as far as the packings ``n_now`` resolve it from zero (its fit
    less two standard errors, the exponent held): an amplitude the data cannot tell from noise
    measures no exponent, however many packings the model is given; and a target that waits on its
    law's exponent is out of reach while the data show no dependence of y on x at all
    (p > ``NO_DEPENDENCE_P``)."""
    if t.plan_k == 2 and not (t.law.dependence_p() <= NO_DEPENDENCE_P):
        return math.inf
    best = math.inf
    G = len(t.law.sizes)
    for beta, coeffs in t.law.plausible():
        J, s2 = t.law.at(beta, coeffs)
        keep = np.r_[0, 1, 3:3 + G]  # each amplitude's error with the exponent held at beta
        now = _inverse(t.law.info(n_now, J, s2)[np.ix_(keep, keep)])
        err = np.sqrt(np.maximum(np.diag(now)[2:], 0.0))
        sure = np.sign(coeffs) * np.maximum(np.abs(coeffs) - 2.0 * err, 0.0)
        J, s2 = t.law.at(beta, sure)
        st = t.law.state(n, J, s2)
        v = float(st[0][t.plan_k, t.plan_k]) * (t.law.inflation(st[1]) if t.plan_k == 0 else 1.0)
        if np.isfinite(v):
            best = min(best, v)
    return best


def _fill_costs(cost, cells):
    """A cell without a finished packing takes the cost of its variant's cells at the nearest size
    and energy that have one (scaled by N), else the calibrated model's price."""
    cost = np.asarray(cost, float).copy()
    have = np.isfinite(cost) & (cost > 0)
    if have.all():
        return cost
    for c in np.flatnonzero(~have):
        same = [d for d in np.flatnonzero(have) if cells.variant[d] == cells.variant[c]]
        if same:
            d = min(same, key=lambda d: (abs(math.log(cells.N[d] / cells.N[c])), abs(math.log(cells.E[d] / cells.E[c]))))
            cost[c] = cost[d] * cells.N[c] / cells.N[d]
        else:
            from campaign.plan import tasks as plan_tasks

            cost[c] = plan_tasks.cost(int(cells.N[c]), float(cells.E[c]), None, float(cells.exponent[c]))
    return cost


@dataclass
class _Plan:
    """The greedy sequence of (cell, seeds) steps from the current allocation, with the cumulative
    cost after each and the variances at the end."""

    steps: list
    costs: np.ndarray
    n_met: int               # steps up to the point every target is projected met (len(steps) if never)
    cost_to_met: float
    final_variance: list
    first_step_cost: float
    targets: list
    cells_cost: np.ndarray
    n0: np.ndarray
    frac: np.ndarray
    given: np.ndarray

    @property
    def steps_total(self):
        return len(self.steps)

    def prefix(self, budget, given):
        """Seeds per cell after the steps whose cumulative cost is within ``budget``."""
        out = given.copy()
        for (c, d), cum in zip(self.steps, self.costs):
            if cum > budget * (1 + 1e-12):
                break
            out[c] += d
        return out

    def variance_at(self, alloc):
        n = self.n0 + (alloc - self.given) * self.frac
        out = {}
        cache = {}
        for i, t in enumerate(self.targets):
            if not t.law.ok:
                continue
            lid = id(t.law)
            if lid not in cache:
                cache[lid] = t.law.state(n)
            out[i] = t.variance(cache[lid])
        return out


def _greedy(targets, cells, n_now, given, frac, cost, relevant, m, states, cap=None) -> _Plan:
    """Add seeds where ``sum over the targets short of their aim of V_T / aim_T^2`` falls fastest per
    core-second, until every target is projected met; then on (all targets weighted) until
    ``EARLY_SHARE`` more than that is planned, or every cell of the fit range holds ``m`` (or ``cap``,
    per cell)."""
    laws = {}
    for t in targets:
        if t.law.ok:
            laws.setdefault(id(t.law), t.law)
    st = {lid: list(states[lid]) for lid in laws}
    where = {lid: {int(c): i for i, c in enumerate(law.cells)} for lid, law in laws.items()}
    top = np.full(cells.C, m) if cap is None else np.minimum(m, cap)
    alloc = given.copy()
    steps, costs, cum = [], [], 0.0
    n_met, cost_to_met = None, math.nan
    live = [t for t in targets if t.law.ok]
    var = {id(t): t.variance(st[id(t.law)]) for t in live}
    cand = np.flatnonzero(relevant)
    limit = None
    for _ in range(200000):
        short = [t for t in live if var[id(t)] > t.aim ** 2 * (1 + 1e-12)]
        if not short and n_met is None:
            n_met, cost_to_met = len(steps), cum
            limit = cum * (1 + EARLY_SHARE) + 1e-9
        if limit is not None and cum >= limit:
            break
        weigh = short if short else live
        best, best_gain, best_d = -1, 0.0, 0
        for c in cand:
            if alloc[c] >= top[c]:
                continue
            d = int(min(top[c] - alloc[c], max(1, alloc[c] // 8)))
            dn = d * frac[c]
            gain, trial = 0.0, {}
            for t in weigh:
                lid = id(t.law)
                i = where[lid].get(int(c))
                if i is None:
                    continue
                if lid not in trial:
                    trial[lid] = t.law.add(st[lid], i, dn)
                gain += max(0.0, var[id(t)] - t.variance(trial[lid])) / t.aim ** 2
            score = gain / (d * cost[c])
            if score > best_gain:
                best, best_gain, best_d = c, score, d
        if best < 0:
            break
        c, d = int(best), best_d
        for lid, law in laws.items():
            i = where[lid].get(c)
            if i is not None:
                st[lid] = law.add(st[lid], i, d * frac[c])
        for t in live:
            var[id(t)] = t.variance(st[id(t.law)])
        alloc[c] += d
        cum += d * cost[c]
        steps.append((c, d))
        costs.append(cum)
    if n_met is None:
        n_met = len(steps)
    final = [var.get(id(t), np.nan) if t.law.ok else np.nan for t in targets]
    first = costs[0] if costs else 0.0
    return _Plan(steps, np.array(costs), n_met, cost_to_met, final, first, targets, cost, n_now, frac, given)


def _errors_text(targets) -> str:
    parts = []
    for t in targets:
        err = f"{t.error:.2g}" if np.isfinite(t.error) else "no value"
        who = f" ({t.variant})" if t.variant != "default" else ""
        parts.append(f"{t.key}{who} {err} (goal {t.goal:g})")
    return "errors " + ", ".join(parts)


def _cost_text(seconds) -> str:
    if not np.isfinite(seconds):
        return ""
    return f"; reaching every target: about {seconds / 3600:.3g} more core-hours"


def _unreachable_text(t, v_max, m) -> str:
    who = f" of variant {t.variant!r}" if t.variant != "default" else ""
    now = f"{t.error:.2g}" if np.isfinite(t.error) else "no value yet"
    at_max = f"{math.sqrt(v_max):.2g}" if np.isfinite(v_max) else "undetermined"
    if t.plan_k == 2:
        if not t.determined:
            at_max = (f"undetermined: its exponent's error would still be {math.sqrt(v_max):.2g}, too close to a bound "
                      "of the exponent's search for its bootstrap to stay inside" if np.isfinite(v_max) else
                      "undetermined")
        why = ("the data show no dependence of the quantity on the abscissa that would fix the exponent "
               "(its amplitude is not told apart from zero)" if not np.isfinite(v_max) or v_max > 100 * t.goal ** 2
               else "the fit range's cells cannot pin the exponent closer")
    elif t.law.dof > 0 and np.any(t.law.sys2 > 0):
        off = [n for n, d in zip(t.law.sizes, t.law.sys2) if d > 0]
        why = (f"N_G = {', '.join(map(str, off))} lie off the 1/N_G line by more than their errors allow (a "
               "finite-size correction beyond 1/N_G): more seeds raise the reducer's sqrt(chi^2/dof) of the line "
               "as they lower its error, a floor no seed count passes")
    else:
        why = "the fit range's cells cannot pin it closer"
    return (f"{t.key}{who} cannot reach its goal {t.goal:g}: its error is {now}, and with max_seeds ({m}) in every "
            f"cell of the fit range it would still be {at_max}: {why}.")


__all__ = ["ACTIONS", "Cells", "Decision", "DEFAULT_FIT_OVERLAP", "FITS", "State", "campaign_cells", "decide",
           "pilot", "seconds_per_disk_force_evaluation"]


# --------------------------------------------------------------------------- the planner of a run

#: the scalars a decision reads (the laws' quantities and abscissae, the cost, which packings are usable)
DECISION_SCALARS = ("E_G", "delta_Z", "A_G", "psi_O", "force_evaluations", "jam_status", "identities_ok")


def reduce_rows(cells: Cells, attrs, rows, status, scalars, ids=None, settings=None):
    """The reducer's table (``reduce_table``, the default settings unless ``settings``) of the task
    rows ``rows`` of a campaign with cells ``cells``: their status and scalars (per row)."""
    from campaign.results.reading import finished_from_arrays
    from campaign.results.reduce import Settings, reduce_table

    c = (np.asarray(rows) // cells.seeds).astype(np.int64)
    seed = np.asarray(rows) - cells.first[c]
    fin = finished_from_arrays(attrs=attrs, variant=[cells.variant[i] for i in c], N=cells.N[c], E=cells.E[c],
                               ids=[f"{i}" for i in rows] if ids is None else ids, seed=seed, status=status,
                               scalars=scalars)
    return reduce_table(fin, settings or Settings(), per_size=False)


def cell_state(cells: Cells, table, rows, status, fe, given, disk_seconds) -> State:
    """The per-cell counts and costs of a decision (``State``): the task rows reduced (``rows``,
    their ``status`` and force evaluations ``fe``) and the seeds given out per cell."""
    C = cells.C
    cell_of = (np.asarray(rows) // cells.seeds).astype(np.int64)
    final = np.bincount(cell_of[status != 0], minlength=C)
    index = cells.index()
    usable = np.zeros(C)
    g = table.grid
    for gc in range(g.C):
        c = index.get((str(g.cv[gc]), int(g.cN[gc]), float(g.cE[gc])))
        if c is not None:
            usable[c] = g.n_done[gc]
    unit = np.asarray(fe, float) * cells.N[cell_of] * disk_seconds
    ok = (status == 1) & np.isfinite(unit) & (unit > 0)
    n_ok = np.bincount(cell_of[ok], minlength=C)
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = np.where(n_ok > 0, np.bincount(cell_of[ok], weights=unit[ok], minlength=C) / np.maximum(n_ok, 1),
                        np.nan)
    cost = _fill_costs(cost, cells)
    # spent: every finished packing's force evaluations (one without them at its cell's mean)
    spent = float(np.sum(unit[ok]) + np.sum(cost[cell_of[(status != 0) & ~ok]]))
    return State(given=np.asarray(given, np.int64), final=final, usable=usable, cost=cost, spent=spent)


def _report(table, goals) -> str:
    out = []
    for v, row in table.extrapolated.items():
        parts = []
        for key, goal in goals.items():
            value, err = row.get(key, np.nan), row.get(f"{key}_err", np.nan)
            txt = (f"{key} = {value:.6g} +- {err:.2g}" if np.isfinite(value) and np.isfinite(err)
                   else f"{key}: no value")
            parts.append(txt + f" (goal {goal:g}{', met' if np.isfinite(err) and err <= goal else ''})")
        out.append(("" if v == "default" else f"{v}: ") + "; ".join(parts))
    return "\n".join(out)


class Planner:
    """The decisions of one precision campaign (``campaign.run.rounds`` asks them): the pilot, and
    each later round from the store's packings of the rounds before it, reduced as ``campaign
    reduce`` reduces them (``reduce_table`` with the default settings)."""

    def __init__(self, spec, tasks):
        from campaign.storage.storefile import SCHEMA

        self.spec, self.tasks = spec, tasks
        self.cells = campaign_cells(spec, tasks)
        self.settings = spec.precision.settings()
        self.attrs = {"spec_yaml": spec.text, "name": spec.name, "spec_hash": spec.hash, "schema": SCHEMA}
        self.disk_seconds = seconds_per_disk_force_evaluation()

    def pilot(self) -> dict:
        return pilot(self.cells, self.settings).to_record(self.cells)

    def table(self, store, through, names=DECISION_SCALARS):
        """The reduction of the finished packings among the tasks ``through`` (per-cell counts) of
        ``store``, and those rows' columns: ``(Table, rows, status, scalars)``."""
        store.flush(force=True)  # every finished row into the file (and its scalars' datasets made)
        present = [n for n in names if n in store.scalar_names]
        cols = store.columns(["tasks/status"] + [f"scalars/{n}" for n in present])
        rows = np.flatnonzero(self.cells.tasks_of(through))
        status = np.asarray(cols["tasks/status"])[rows]
        scalars = {n: np.asarray(cols[f"scalars/{n}"])[rows] for n in present}
        table = reduce_rows(self.cells, self.attrs, rows, status, scalars, ids=[self.tasks[i].id for i in rows])
        return table, rows, status, scalars

    def decide(self, k, store, given, through, settings=None, previous=None) -> dict:
        settings = self.settings if settings is None else settings
        table, rows, status, scalars = self.table(store, through)
        fe = scalars.get("force_evaluations", np.full(len(rows), np.nan))
        state = cell_state(self.cells, table, rows, status, fe, given, self.disk_seconds)
        return decide(k, table, self.cells, state, settings, previous).to_record(self.cells)

    def report(self, store, given) -> str:
        """The errors of every finished packing of the campaign (the last round's early seeds
        included), as ``campaign reduce`` gives them: one line per variant."""
        return _report(self.table(store, given)[0], self.settings["target"])


# --------------------------------------------------------------------------- a campaign in memory

def run_in_memory(cells: Cells, settings, draw, *, attrs=None, reducer=None, disk_seconds=1e-7, log=None):
    """A precision campaign's rounds without a store or workers: ``draw(rows) -> {scalar: values}``
    makes the packings of task rows (``cells.first[c] + seed``; a pure function of the row, as a
    packing is of its task). For the checks of docs/PRECISION.md (synthetic truths, many repeats).
    Returns ``(records, table)``: every decision's record and the reduction of every packing run."""
    T = cells.C * cells.seeds
    status = np.zeros(T, np.int8)
    data = {}
    attrs = attrs or {"schema": "jamming-campaign/1"}

    def run(mask):
        todo = np.flatnonzero(mask & (status == 0))
        if len(todo):
            got = draw(todo)
            for k, v in got.items():
                data.setdefault(k, np.full(T, np.nan))[todo] = v
            status[todo] = 1

    def reduce(counts):
        rows = np.flatnonzero(cells.tasks_of(counts))
        table = reduce_rows(cells, attrs, rows, status[rows], {k: v[rows] for k, v in data.items()},
                            settings=reducer)
        return table, rows

    rec = pilot(cells, settings).to_record(cells)
    records = [rec]
    while True:
        run(cells.tasks_of(rec["early"]))
        if rec["action"] not in ("pilot", "continue"):
            break
        table, rows = reduce(rec["allocated"])
        fe = data.get("force_evaluations", np.full(T, np.nan))[rows]
        state = cell_state(cells, table, rows, status[rows], fe, rec["early"], disk_seconds)
        rec = decide(len(records), table, cells, state, settings, rec).to_record(cells)
        records.append(rec)
        if log is not None:
            log(rec["message"])
    return records, reduce(rec["early"])[0]
