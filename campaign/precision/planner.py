"""A precision campaign's decisions from its packings: the planner a run asks (``Planner``, through
``campaign.run.rounds``), the same rounds without a store (``run_in_memory``, for the checks of
docs/PRECISION.md), and the plan before a pilot from the prior (``plan_from_prior``, for ``campaign
validate`` and ``campaign slurm``). The decisions themselves are ``campaign.precision.allocation``'s.
"""

from __future__ import annotations

import json
import math
from importlib import resources

import numpy as np

from campaign.plan import calibration
from campaign.plan import tasks as plan_tasks
from campaign.plan.targets import SHARED_FIT_CELLS, law_of
from campaign.storage.layout import SCHEMA
from campaign.results import fits
from campaign.results.finished import finished_from_arrays
from campaign.results.reduce import Settings, reduce_table
from campaign.precision.allocation import (State, Target, fill_costs, plan_greedy, smooth_costs, decide, pilot,
                                         seconds_per_disk_force_evaluation)
from campaign.precision.errormodel import Cells, LawModel, campaign_cells, cell_counts, param_index as _k
from campaign.storage.layout import DONE, PENDING

#: round 0 of a campaign the prior holds (``first_round``): the pilot and this share of the prior's plan
#: above it; the rest waits for the first decision, made on the campaign's own packings
PRIOR_SHARE = 0.65
#: the scalars a decision reads (the laws' quantities and abscissae, the cost, which packings are usable)
DECISION_SCALARS = ("E_G", "delta_Z", "A_G", "psi_O", "force_evaluations", "jam_status", "identities_ok")


def reduce_rows(cells: Cells, attrs, rows, status, scalars, ids=None, settings=None):
    """The reducer's table (``reduce_table``, the default settings unless ``settings``) of the task
    rows ``rows`` of a campaign with cells ``cells``: their status and scalars (per row)."""
    c = (np.asarray(rows) // cells.seeds).astype(np.int64)
    seed = np.asarray(rows) - cells.first[c]
    fin = finished_from_arrays(attrs=attrs, variant=[cells.variant[i] for i in c], N=cells.N[c], E=cells.E[c],
                               ids=[f"{i}" for i in rows] if ids is None else ids, seed=seed, status=status,
                               scalars=scalars)
    return reduce_table(fin, settings or Settings(), per_size=False)


def reduce_store_rows(path, pick, settings=None):
    """The reducer's table (``reduce_table``, the default settings unless ``settings``) of the finished
    packings among some task rows of a store: ``pick(columns)`` gives a bool mask over its rows from the
    task table's columns
    (``status``, ``seed``, ``N``, ``E``: the first seeds of a uniform store, the rows a decision of the
    rounds reduced). Only the scalars a decision reads (``DECISION_SCALARS``), no histograms: for the
    experiments that reduce a store's packings again (benchmarks/bench_precision.py,
    experiments/reduce_again.py)."""
    import h5py

    with h5py.File(path, "r") as f:
        cols = {k: f[f"tasks/{k}"][:] for k in ("status", "seed", "N", "E")}
        variant, ids = [x.decode() for x in f["tasks/variant"][:]], [x.decode() for x in f["tasks/id"][:]]
        scalars = {k: f[f"scalars/{k}"][:] for k in DECISION_SCALARS if k in f["scalars"]}
        attrs = {k: f.attrs[k] for k in ("schema", "spec_yaml", "name", "spec_hash") if k in f.attrs}
    r = np.flatnonzero(np.asarray(pick(cols), bool))
    fin = finished_from_arrays(attrs=attrs, variant=[variant[i] for i in r], N=cols["N"][r], E=cols["E"][r],
                               ids=[ids[i] for i in r], seed=cols["seed"][r], status=cols["status"][r],
                               scalars={k: x[r] for k, x in scalars.items()})
    return reduce_table(fin, settings or Settings(), per_size=False)


def cell_state(cells: Cells, table, rows, status, fe, given, disk_seconds) -> State:
    """The per-cell counts and costs of a decision (``State``): the task rows reduced (``rows``,
    their ``status`` and force evaluations ``fe``) and the seeds given out per cell."""
    C = cells.C
    cell_of = (np.asarray(rows) // cells.seeds).astype(np.int64)
    final = np.bincount(cell_of[status != PENDING], minlength=C)
    usable = cell_counts(table, cells)
    unit = np.asarray(fe, float) * cells.N[cell_of] * disk_seconds
    ok = (status == DONE) & np.isfinite(unit) & (unit > 0)
    n_ok = np.bincount(cell_of[ok], minlength=C)
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = np.where(n_ok > 0, np.bincount(cell_of[ok], weights=unit[ok], minlength=C) / np.maximum(n_ok, 1),
                        np.nan)
    cost = smooth_costs(fill_costs(cost, cells), n_ok, cells)
    # spent: every finished packing's force evaluations (one without them at its cell's mean)
    spent = float(np.sum(unit[ok]) + np.sum(cost[cell_of[(status != PENDING) & ~ok]]))
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
        self.spec, self.tasks = spec, tasks
        self.cells = campaign_cells(spec, tasks)
        self.settings = spec.precision.settings()
        self.attrs = {"spec_yaml": spec.text, "name": spec.name, "spec_hash": spec.hash, "schema": SCHEMA}
        self.disk_seconds = seconds_per_disk_force_evaluation()

    def pilot(self) -> dict:
        counts, how = first_round(self.spec, self.tasks)
        return pilot(self.cells, self.settings, counts, how).to_record(self.cells)

    def snapshot(self, store, through, names=DECISION_SCALARS) -> dict:
        """The rows of the tasks ``through`` (per-cell counts) of ``store``: their status and the
        scalars a decision reads. Read in the master's thread (the store is not thread-safe); the
        decision itself (``decide_snapshot``) may run beside it."""
        store.flush(force=True)  # every finished row into the file (and its scalars' datasets made)
        present = [n for n in names if n in store.scalar_names]
        cols = store.columns(["tasks/status"] + [f"scalars/{n}" for n in present])
        rows = np.flatnonzero(self.cells.tasks_of(through))
        return {"rows": rows, "status": np.asarray(cols["tasks/status"])[rows],
                "scalars": {n: np.asarray(cols[f"scalars/{n}"])[rows] for n in present}}

    def table(self, snap):
        """The reducer's table of a snapshot's finished packings."""
        return reduce_rows(self.cells, self.attrs, snap["rows"], snap["status"], snap["scalars"],
                           ids=[self.tasks[i].id for i in snap["rows"]])

    def decide_snapshot(self, k, snap, given, settings=None, previous=None) -> dict:
        """Decision ``k`` (its record) from the snapshot of the rounds before it."""
        settings = self.settings if settings is None else settings
        table = self.table(snap)
        fe = snap["scalars"].get("force_evaluations", np.full(len(snap["rows"]), np.nan))
        state = cell_state(self.cells, table, snap["rows"], snap["status"], fe, given, self.disk_seconds)
        return decide(k, table, self.cells, state, settings, previous).to_record(self.cells)

    def decide(self, k, store, given, through, settings=None, previous=None) -> dict:
        return self.decide_snapshot(k, self.snapshot(store, through), given, settings, previous)

    def report(self, store, given) -> str:
        """The errors of every finished packing of the campaign (the last round's early seeds
        included), as ``campaign reduce`` gives them: one line per variant."""
        return _report(self.table(self.snapshot(store, given)), self.settings["target"])


# --------------------------------------------------------------------------- where the error went

def projections(records) -> list:
    """What each decision projected and what the next one measured: per ``continue`` decision ``k``
    followed by a decision, per target, ``{"decision": k, "variant", "key", "goal", "error"}`` (the
    reducer's error at decision ``k``), ``"projected"`` (the model's error after round ``k``) and
    ``"achieved"`` (the reducer's error at decision ``k + 1``, from the packings of rounds ``0 .. k``),
    ``"ratio"`` achieved / projected, and ``"round_core_hours"`` (the round's priced cost). The gap
    between the plan and the rounds, decision by decision. A target without a value at decision ``k``
    is planned on its law's exponent: its ``projected`` is that exponent's error, and its ratio NaN."""
    out = []
    recs = sorted(records, key=lambda r: r["round"])
    for rec, nxt in zip(recs, recs[1:]):
        if rec["action"] != "continue":
            continue
        after = {(t["variant"], t["key"]): t for t in nxt.get("targets", [])}
        for t in rec.get("targets", []):
            got = after.get((t["variant"], t["key"]), {}).get("error")
            proj = t.get("projected")
            num = [x if x is not None else np.nan for x in (t.get("error"), proj, got)]
            out.append({"decision": int(rec["round"]), "variant": t["variant"], "key": t["key"], "goal": t["goal"],
                        "error": num[0], "projected": num[1], "achieved": num[2],
                        "ratio": (num[2] / num[1] if np.isfinite(num[0]) and np.isfinite(num[1]) and num[1] > 0
                                  else np.nan),
                        "round_core_hours": rec.get("round_core_hours")})
    return out


def projections_markdown(rows) -> str:
    """``projections`` as a markdown table (one line per decision and target)."""
    def g(x):
        return "-" if x is None or not np.isfinite(x) else f"{x:.3g}"

    lines = ["| decision | target | goal | error | projected after the round | achieved | achieved / projected "
             "| round core-hours |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        who = r["key"] if r["variant"] == "default" else f"{r['key']} ({r['variant']})"
        proj = g(r["projected"]) + (" (its exponent's)" if not np.isfinite(r["error"]) and np.isfinite(r["projected"])
                                    else "")
        lines.append(f"| {r['decision']} | {who} | {r['goal']:g} | {g(r['error'])} | {proj} | "
                     f"{g(r['achieved'])} | {g(r['ratio'])} | {g(r['round_core_hours'])} |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- a campaign in memory

def run_in_memory(cells: Cells, settings, draw, *, attrs=None, reducer=None, disk_seconds=None, log=None,
                  first=None):
    """A precision campaign's rounds without a store or workers: ``draw(rows) -> {scalar: values}``
    makes the packings of task rows (``cells.first[c] + seed``; a pure function of the row, as a
    packing is of its task). For the checks of docs/PRECISION.md (synthetic truths, many repeats).
    ``first``: round 0 as ``first_round`` gives it (its seeds per cell and how they were chosen; default
    the uniform pilot). Returns ``(records,
    table)``: every decision's record and the reduction of every packing run."""
    disk_seconds = seconds_per_disk_force_evaluation() if disk_seconds is None else disk_seconds
    T = cells.C * cells.seeds
    status = np.zeros(T, np.int8)
    data = {}
    attrs = attrs or {"schema": "jamming-campaign/1"}

    def run(mask):
        todo = np.flatnonzero(mask & (status == PENDING))
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

    rec = pilot(cells, settings, *(first or (None, ""))).to_record(cells)
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


# --------------------------------------------------------------------------- before the pilot: the prior

def load_prior():
    """The packaged prior (``campaign/plan/precision_prior.json``, written by experiments/precision_prior.py
    from paper-small): per cell (N_G, E_G) the packings' means and covariances."""
    return json.loads(resources.files("campaign").joinpath("plan", "precision_prior.json").read_text())


def _prior_cell(prior, N, E):
    """Means and covariance (of ``prior['names']``) at (N, E): the prior's own cell, or at a size it
    does not hold the means extrapolated linearly in 1/N_G over its sizes at that energy and the
    covariance of its nearest size scaled by that size over N (the spread between packings falls
    like 1/sqrt(N_G)). None when the prior has no cell at that energy."""
    same = [c for c in prior["cells"] if abs(c["E"] / E - 1) < 1e-9]
    if not same:
        return None
    exact = [c for c in same if c["N"] == N]
    if exact:
        return np.array(exact[0]["mean"]), np.array(exact[0]["cov"])
    Ns = np.array([c["N"] for c in same], float)
    means = np.array([c["mean"] for c in same])
    X = np.column_stack([np.ones(len(Ns)), 1.0 / Ns])
    coef, *_ = np.linalg.lstsq(X, means, rcond=None)
    mean = coef[0] + coef[1] / N
    mean[0] = means[:, 0].mean()  # E_G: where in the window a packing lands, whatever N
    mean[1] = max(mean[1], 0.0)   # Delta Z >= 0
    near = same[int(np.argmin(np.abs(np.log(Ns / N))))]
    return mean, np.array(near["cov"]) * near["N"] / N


def plan_from_prior(spec, tasks, prior=None, cal=None) -> dict:
    """What reaching a precision spec's targets would cost, planned before its pilot from the prior
    (``load_prior``): the model of the errors built on the prior's cells as if the pilot had run with
    their means and spreads, and the greedy plan from the pilot to the targets, priced per packing by
    the calibrated cost model in force (``campaign.plan.tasks.cost``). ``{"ok": False, "why": ...}``
    where the prior does not hold the campaign's system or energies; else the pilot's cost, the
    plan's (and its seeds per cell, ``allocation``), the errors projected, and what a uniform campaign would
    need for the same errors. ``cal``: the calibration that prices the packings (default: the one in force)."""
    prior = load_prior() if prior is None else prior
    settings = spec.precision.settings()
    cells = campaign_cells(spec, tasks)
    names = list(prior["names"])
    for v in spec.variants:
        if v.system.canonical() != prior["system"]:
            return {"ok": False, "why": f"variant {v.name!r} is another system ({v.system.label()}) than the prior's "
                                        "(paper-small's): its spreads are not known before its pilot"}
    stats = []
    for c in range(cells.C):
        got = _prior_cell(prior, int(cells.N[c]), float(cells.E[c]))
        if got is None:
            have = ", ".join(sorted({f"{x['E']:g}" for x in prior["cells"]}, key=float))
            return {"ok": False, "why": f"the prior holds no cell at E_G = {cells.E[c]:g} (it has {have})"}
        stats.append(got)
    pilot_n = int(settings["pilot"])
    m = int(settings["max_seeds"])
    relevant = cells.relevant(settings["target"])
    price = plan_tasks.cost if cal is None else cal.seconds
    cost = np.array([price(int(cells.N[c]), float(cells.E[c]), dict(tasks[cells.first[c]].protocol),
                           float(cells.exponent[c])) for c in range(cells.C)])
    n0 = np.full(cells.C, float(pilot_n))
    targets, laws = [], {}
    for v in sorted(set(cells.variant), key=cells.variant.index):
        for key, goal in settings["target"].items():
            q, x, kind = law_of(key)
            if (v, q, x) not in laws:
                laws[(v, q, x)] = _prior_law(cells, stats, names, v, q, x, pilot_n)
            targets.append(Target(v, key, float(goal), np.nan, np.nan, laws[(v, q, x)]))
    for t in targets:
        if not t.law.ok:
            return {"ok": False, "why": t.law.why}
    states = {id(law): law.state(n0) for law in laws.values()}
    for t in targets:
        t.v_now = float(states[id(t.law)][0][_k(t.kind), _k(t.kind)])
        t.error = math.sqrt(t.v_now)  # the model's error at the pilot: a determined target, ratio 1
    pilot_cost = float(np.sum(n0 * cost))
    n_max = np.where(relevant, float(m), n0)
    at_max = {t.key: math.sqrt(t.variance(t.law.state(n_max))) for t in targets}
    out = {"ok": True, "pilot_seconds": pilot_cost, "pilot_errors": {t.key: t.error for t in targets},
           "max_seeds_errors": at_max, "reachable": all(at_max[t.key] <= t.goal for t in targets)}
    if out["reachable"]:
        plan = plan_greedy(targets, cells, n0, n0.astype(np.int64), np.ones(cells.C), cost, relevant, m, states)
        out["plan_seconds"] = float(plan.cost_to_met)
        out["total_seconds"] = pilot_cost + out["plan_seconds"]
        alloc = plan.prefix(plan.cost_to_met, n0.astype(np.int64))
        out["packings"] = int(alloc.sum())
        out["allocation"] = [int(a) for a in alloc]
    # a uniform campaign (every cell the same seeds) that meets the same targets
    lo, hi = pilot_n, m
    if all(math.sqrt(t.variance(t.law.state(np.full(cells.C, float(hi))))) <= t.goal for t in targets):
        while hi - lo > 1:
            mid = (lo + hi) // 2
            n = np.full(cells.C, float(mid))
            if all(math.sqrt(t.variance(t.law.state(n))) <= t.goal for t in targets):
                hi = mid
            else:
                lo = mid
        out["uniform_seeds"] = hi
        out["uniform_seconds"] = float(hi * np.sum(cost))
    return out


def first_round(spec, tasks, prior=None):
    """Round 0's seeds per cell and how they were chosen (a sentence): where the prior
    (``plan_from_prior``) holds the campaign's system and energies and its plan reaches the targets,
    the pilot plus ``PRIOR_SHARE`` of that plan above it, so that the first decision is made on packings
    already where the model wants them (one pooled spread per quantity and size is what the model
    needs, not a measurement of every cell); else the uniform pilot. Priced by the packaged calibration
    whatever calibration is in force, so that round 0 is the same on every machine."""
    cells = campaign_cells(spec, tasks)
    p = int(spec.precision.pilot)
    counts = np.full(cells.C, p, np.int64)
    got = plan_from_prior(spec, tasks, prior, cal=calibration.packaged())
    if not got["ok"]:
        return counts, f"a uniform pilot of {p} seeds per cell ({got['why']})"
    if not got["reachable"] or "allocation" not in got:
        return counts, (f"a uniform pilot of {p} seeds per cell (by the prior the targets are not reached within "
                        "max_seeds: the pilot decides)")
    alloc = np.asarray(got["allocation"], float)
    counts = np.maximum(counts, np.floor(p + PRIOR_SHARE * (alloc - p) + 1e-9)).astype(np.int64)
    return counts, f"designed from the prior, paper-small's packings: {PRIOR_SHARE:.0%} of its plan above a pilot of {p}"


def _prior_law(cells, stats, names, variant, quantity, absc, pilot_n) -> LawModel:
    """A ``LawModel`` of one variant's law on the prior's cells (``_prior_cell``), the sizes with
    ``SHARED_FIT_CELLS`` cells of a positive mean abscissa in the fit range, fitted to their means."""
    iq, ix = names.index(quantity), names.index(absc)
    in_range = cells.relevant({"x": 1})
    by_size = {}
    for c in range(cells.C):
        if cells.variant[c] != variant or not in_range[c]:
            continue
        mean, cov = stats[c]
        if mean[ix] < 0 or not cov[iq, iq] > 0:
            continue
        by_size.setdefault(int(cells.N[c]), []).append(c)
    sizes = sorted(n for n, cs in by_size.items() if sum(stats[c][0][ix] > 0 for c in cs) >= SHARED_FIT_CELLS)
    if len(sizes) < 2:
        return LawModel(variant, quantity, absc, sizes, ok=False,
                        why=f"the prior gives {len(sizes)} size(s) with {SHARED_FIT_CELLS} cells of a positive mean "
                            f"{absc} in the fit range; the N_G -> inf row needs two")
    ids, size_of, xbar, ybar, yerr, mom = [], [], [], [], [], []
    for gi, n in enumerate(sizes):
        for c in by_size[n]:
            mean, cov = stats[c]
            ids.append(c)
            size_of.append(gi)
            xbar.append(mean[ix])
            ybar.append(mean[iq])
            yerr.append(math.sqrt(cov[iq, iq] / pilot_n))
            mom.append((cov[ix, ix], cov[iq, iq], cov[ix, iq]))
    law = LawModel(variant, quantity, absc, sizes, np.array(ids), np.array(size_of), np.array(xbar), np.array(ybar),
                   np.array(yerr), np.array(mom), dof=max(0, len(sizes) - 2))
    xs = [law.xbar[law.size_of == g] for g in range(len(sizes))]
    ys = [law.ybar[law.size_of == g] for g in range(len(sizes))]
    es = [law.yerr[law.size_of == g] for g in range(len(sizes))]
    f = fits.fit_shared_exponent(xs, ys, es)
    law.beta = float(f.exponent)
    law.sys2 = np.zeros(len(sizes))
    law.J, law.s2 = law.at(law.beta, np.asarray(f.coeffs, float))
    if len(sizes) >= 4:  # the reducer will average line and parabola: the prior's 1/N_G^2 coefficient
        law.z2 = 0.0
        st = law.state(np.full(cells.C, float(pilot_n)))
        G = len(sizes)
        cov = st[1][1:1 + G, 1:1 + G]
        if np.all(np.isfinite(cov)):
            Ninv = 1.0 / np.asarray(sizes, float)
            X = np.column_stack([np.ones(G), Ninv, Ninv ** 2])
            W = np.linalg.pinv(cov)
            law.c2 = float((np.linalg.pinv(X.T @ W @ X) @ X.T @ W @ np.asarray(f.intercepts, float))[2] ** 2)
    return law
