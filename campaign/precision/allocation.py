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
Where the reducer averages the line in 1/N_G with the parabola (four sizes or more), an intercept's
variance is the line's plus ``(v2 - v1) choice_variance(zeta)``: the parabola's excess variance times
the scatter of the Akaike weight's pull, at the z-score ``zeta`` of the 1/N_G^2 term, which grows like
the square root of the packings (``errormodel.LawModel.intercept_variance``; the choice is most of
paper-small's intercept errors, and packings at the sizes that pin the curvature shrink it). An
intercept the reducer finds limited by its sizes (the line through the last three fails) has its error
inflated by ``sqrt(chi^2/dof)``; that part does not fall with more seeds, and the model keeps it as a
floor.

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

from campaign.plan import calibration
from campaign.plan import tasks as plan_tasks
from campaign.plan.targets import law_of
from campaign.results import fits
from campaign.precision.errormodel import (NO_DEPENDENCE_P, Cells, LawModel, inverse, build_law,
                                         param_index as _k)

#: a round commits at most this multiple of what the campaign has spent before it
ROUND_GROWTH = 1.0
#: the next round's early seeds: this share of the round's cost (the plan's continuation)
EARLY_SHARE = 0.1
#: a cell's seeds grow at most this many times in one round: the first rounds' model comes from a
#: few packings per cell, and a design it finds optimal (often a few cells) is taken a step at a
#: time, re-estimated before it is trusted with more
CELL_GROWTH = 4
#: a target with a value is planned to this share of its goal. Aiming below it costs that much more every
#: time; aiming at it falls short about half the time, by a little, which a small last round makes up
AIM = 1.0
#: a round gives out at least this share of what the campaign has spent (rounds of a few packings
#: cost a decision each and gain little)
MIN_ROUND = 0.05

#: A target the reducer finds limited by its sizes ends the rounds when two decisions in a row find it so
#: with the line through the sizes kept at a p-value below this: the reducer's own flag (p < 0.05) is a
#: false alarm in one campaign in twenty, and two decisions share most of their packings; a real
#: crossover's p falls with every round (1e-19 on the test's 1/N_G^2 term)
LIMITED_P = 1e-3

ACTIONS = ("pilot", "continue", "met", "budget", "max_seeds", "unreachable", "limited")


def seconds_per_disk_force_evaluation() -> float:
    """Core-seconds per disk per force evaluation of a packing (the FIRE kernels' cost per step, with
    the search and the analysis around it spread over the steps), from the calibration in force."""
    return calibration.active().disk_force_evaluation_seconds


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
    limited: str = ""     # the reducer's paragraph when the sizes limit the value (``<key>_limited``)

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
        if self.plan_k == 0:  # the intercept: the line's, with the choice of the parabola where the reducer makes
            # it (the parabola takes up what lies off the line: the reducer inflates nothing there)
            infl = 1.0 if self.law.curved else self.law.inflation(st[1])
            return self.ratio ** 2 * self.law.intercept_variance(st) * infl
        return self.ratio ** 2 * float(st[0][self.plan_k, self.plan_k])


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
            limited, p = row.get(f"{key}_limited") or "", row.get(f"{key}_p")
            strong = isinstance(limited, str) and p is not None and np.isfinite(p) and p < LIMITED_P
            out.append(Target(v, key, float(goal), value, err, laws[(v, q, x)], limited=limited if strong else ""))
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


def pilot(cells: Cells, settings, first=None, how="") -> Decision:
    """Round 0: ``first`` seeds per cell (``planner.first_round``: designed from the prior where it holds
    the campaign), else ``pilot`` seeds in every cell; its early part: one more in the cells that can
    move a target (the fit range of the targets' laws)."""
    p, m = int(settings["pilot"]), int(settings["max_seeds"])
    allocated = np.full(cells.C, p, np.int64) if first is None else np.minimum(np.asarray(first, np.int64), m)
    early = allocated.copy()
    relevant = cells.relevant(settings["target"])
    early[relevant] = np.minimum(allocated[relevant] + 1, m)
    return Decision(0, "pilot", allocated, early, dict(settings),
                    message=(f"round 0: {int(allocated.sum())} seeds in {cells.C} cells, {how}" if how
                             else f"pilot: {p} seeds in each of {cells.C} cells"))


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
    cost = fill_costs(state.cost, cells)
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
                "out_of_reach": (t.variant, t.key) in doubt, "limited": bool(t.limited)}

    def decision(action, message, alloc=given, early=None, projected=None, round_cost=0.0, to_targets=np.nan):
        proj = projected or {}
        return Decision(k, action, alloc, alloc.copy() if early is None else early, dict(settings),
                        [record(t, proj.get(i, np.nan)) for i, t in enumerate(targets)], state.spent, committed,
                        round_cost, to_targets, message)

    # the model of each target, calibrated to the reducer's error at the present allocation
    states, model_met = {}, []
    for t in targets:
        if not t.law.ok:
            model_met.append(True)
            continue
        if id(t.law) not in states:
            states[id(t.law)] = t.law.state(n_now)
            t.law.anchor(states[id(t.law)])
        raw = t.variance(states[id(t.law)])  # ratio 1 here: the model's own error
        t.v_now = raw
        model_met.append(bool(np.isfinite(raw) and raw <= t.goal ** 2))
        if t.determined and t.v_now > 0:
            t.ratio = t.error / math.sqrt(raw)
    # stop when the reducer's errors are at their goals and so are the model's: a bootstrap error from
    # packings of a few rounds scatters by some per cent, and stopping on it alone would stop the
    # campaigns whose error came out low by chance, leaving their intervals short (the coverage checks)
    if all(t.met for t in targets) and all(model_met):
        return decision("met", "every target met: " + _errors_text(targets))
    for t, ok in zip(targets, model_met):
        if t.met and not ok:  # met by the reducer, not by the model: planned on the model's error
            t.ratio = 1.0
    # limited by its sizes: the 1/N_G models fail through the largest sizes, and the inflated error does
    # not fall with seeds; two decisions in a row (the first may be a few packings' chance)
    was = {(r["variant"], r["key"]) for r in (previous or {}).get("targets", []) if r.get("limited")}
    stuck = [t for t in targets if not t.met and t.limited and (t.variant, t.key) in was]
    if stuck:
        return decision("limited", " ".join(_limited_text(t) for t in stuck))
    # out of reach: with max_seeds in every cell of the fit range a target stays above its goal, by
    # the model alone (not scaled to the bootstrap's error, which a few packings per cell inflate
    # where the fit is far from linear: the model is what the fit reaches once its cells are full)
    n_max = np.maximum(np.where(relevant, m * frac, n_now), n_now)
    unreachable = []
    for t in targets:
        if t.met or not t.law.ok:
            continue
        v_max = best_case(t, n_max, n_now)
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
    full = plan_greedy(targets, cells, n_now, given, frac, cost, relevant, m, states)  # the whole way
    projected = dict(enumerate(full.final_variance))
    to_targets = full.cost_to_met
    # this round's part of it: the plan again with each cell's growth capped (CELL_GROWTH)
    plan = plan_greedy(targets, cells, n_now, given, frac, cost, relevant, m, states,
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
    met_cost = plan.cost_to_met if np.isfinite(plan.cost_to_met) else math.inf
    main = plan.prefix(min(ROUND_GROWTH * spent_all, room / (1.0 + EARLY_SHARE),
                           max(met_cost, MIN_ROUND * spent_all)), given)
    if np.array_equal(main, given) and plan.steps_total:  # at least the plan's first step
        if plan.costs[0] > room:
            return decision("budget", f"the budget left ({room / 3600:.3g} core-hours) does not pay for the next "
                            "step; " + _errors_text(targets) + _cost_text(to_targets), projected=projected,
                            to_targets=to_targets)
        main = plan.prefix(plan.costs[0], given)
    main_spend = float(np.sum((main - given) * cost))
    early = np.maximum(plan.prefix(main_spend + min(EARLY_SHARE * main_spend, room - main_spend), given),
                       main)
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


def best_case(t, n, n_now) -> float:
    """The smallest variance the model gives target ``t`` at usable packings ``n`` over the exponents
    its data do not exclude (``LawModel.plausible``), not scaled to the bootstrap and without the 1/N_G
    line's inflation (a size's offset from the line is judged from a few packings per cell, too often
    wrongly, to end a campaign on): a target out of reach for every plausible exponent is out of reach (a pilot's few
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
        keep = np.r_[0, 1, 3:J.shape[1]]  # each amplitude's error with the exponent held at beta
        now = inverse(t.law.info(n_now, J, s2)[np.ix_(keep, keep)])
        err = np.sqrt(np.maximum(np.diag(now)[2:2 + G], 0.0))
        sure = np.sign(coeffs) * np.maximum(np.abs(coeffs) - 2.0 * err, 0.0)
        J, s2 = t.law.at(beta, sure)
        v = float(t.law.state(n, J, s2)[0][t.plan_k, t.plan_k])
        if np.isfinite(v):
            best = min(best, v)
    return best


def smooth_costs(cost, n, cells, prior_n=4.0):
    """Each cell's cost per packing pulled toward a smooth law of its variant's cells (ln cost linear in
    ln N_G, the decades below 1e-3 and their square), weighted by its packings against ``prior_n``:
    packings scatter by a factor of 1.3-1.5 in cost, and the cells that came out cheap by chance
    would draw the seeds."""
    out = cost.copy()
    for v in set(cells.variant):
        mine = np.array([c for c in range(cells.C) if cells.variant[c] == v])
        L = np.maximum(0.0, np.log10(1e-3 / cells.E[mine]))
        X = np.column_stack([np.ones(len(mine)), np.log(cells.N[mine]), L, L * L])
        w = np.sqrt(np.maximum(n[mine], 0.0))
        if np.count_nonzero(w) < X.shape[1] + 1:
            continue
        coef, *_ = np.linalg.lstsq(X * w[:, None], np.log(cost[mine]) * w, rcond=None)
        pred = X @ coef
        out[mine] = np.exp((n[mine] * np.log(cost[mine]) + prior_n * pred) / (n[mine] + prior_n))
    return out


def fill_costs(cost, cells):
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


def plan_greedy(targets, cells, n_now, given, frac, cost, relevant, m, states, cap=None) -> _Plan:
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
    return _Plan(steps, np.array(costs), n_met, cost_to_met, final, targets, cost, n_now, frac, given)


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


def _limited_text(t) -> str:
    who = f" of variant {t.variant!r}" if t.variant != "default" else ""
    return (f"{t.key}{who} cannot reach its goal {t.goal:g} with more seeds (error {t.error:.2g}): {t.limited}.")


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
    else:
        why = "the fit range's cells cannot pin it closer"
    return (f"{t.key}{who} cannot reach its goal {t.goal:g}: its error is {now}, and with max_seeds ({m}) in every "
            f"cell of the fit range it would still be {at_max}: {why}.")
