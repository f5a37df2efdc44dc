"""Are the rounds of a precision campaign honest? Synthetic campaigns with a known truth, run through
the rounds many times (docs/PRECISION.md, "Honest statistics").

    python experiments/precision_coverage.py --reps 200 --boot 200 --json coverage.json   # ~30 CPU-minutes
    python experiments/precision_coverage.py --reps 200 --scenario "like paper-small" --json coverage-c.json

Choosing where to sample from the data and stopping on the data's own error estimate can bias
both the row and its errors. Each repetition is a campaign on the paper-small grid (N_G 64..1024,
E_G 1e-15..1e-3) whose packings come from the generator of the fit-range test
(``experiments/fit_rules.py``: excess contacts drawn as whole numbers, ``Delta A_G = B Delta Z^beta_Z
(1 + k Delta Z^omega)``, the spread of A_G between packings paper-small's ``0.10 / sqrt(N_G)``), with
psi_O drawn alike (``Delta Psi_O = B_P Delta Z^beta_Z``, spread ``0.17 / sqrt(N_G)``) and force
evaluations from the calibrated cost model (``campaign.plan.tasks.cost``), run through
``campaign.precision.planner.run_in_memory`` (the decisions of a real run, on these packings) until
it stops. The truth: ``A_G* = 0.446``, ``Psi_O* = 0.369`` (no 1/N_G term) and ``beta_E =
beta_Z / (2 alpha) = 0.2625``. Per target: the median of (value - truth) / error, and the share of
1- and 2-sigma intervals that hold the truth (nominal 0.68, 0.95); beside it the same for a uniform
campaign of ``--uniform`` seeds per cell (the reducer alone, no rounds). ``--boot`` sets the
reducer's bootstrap in the rounds and the final reduction (the campaign's own: 1000).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fit_rules  # noqa: E402 - the generator of the fit-range test

from campaign.plan.parse import parse_spec  # noqa: E402
from campaign.plan.tasks import cost as task_cost, expand  # noqa: E402
from campaign.precision import errormodel, planner  # noqa: E402
from campaign.results.reduce import Settings  # noqa: E402

SPEC = """\
name: coverage
seed: 1
grid:
  N_G: [64, 128, 256, 512, 1024]
  E_G: {log_range: [1.0e-15, 1.0e-3], per_decade: 1}
precision:
  target: {%(target)s}
  pilot: %(pilot)d
  max_seeds: %(max)d
observables: [scalars]
"""
TRUTH = {"A_G_star_E": fit_rules.A_STAR, "psi_O_star": 0.369}
SD_P0 = 0.17          # psi_O's spread between packings times sqrt(N_G) (paper-small: 0.15-0.19)
B_P = 0.30            # Delta Psi_O = B_P Delta Z_true^beta_Z (paper-small at N_G 1024, 1e-5: 0.07 at Delta Z 0.28)
DISK_SECONDS = 1e-7
#: ``--sizes``: the intercepts' finite-size terms ``b / N_G + c / N_G^2`` (A_G, psi_O): none (the
#: intercepts the same at every size), or paper-small's, the parabola in 1/N_G through its sizes'
#: intercepts against E_G (generalised least squares with their bootstrap covariance, data/paper-small.h5:
#: A_G b = -0.82, c = 25, the 1/N_G^2 term at 2.0 of its error; psi_O b = -0.48, c = -33, at 0.8)
SIZES = {"none": ((0.0, 0.0), (0.0, 0.0)), "paper-small": ((-0.817, 24.96), (-0.479, -33.2))}


def draw_factory(spec, tasks, rep, scenario, sizes="none"):
    sc = fit_rules.SCENARIOS[scenario]
    (ba, ca), (bp, cp) = SIZES[sizes]
    alpha = 2.0

    def draw(rows):
        out = {k: np.empty(len(rows)) for k in ("E_G", "delta_Z", "A_G", "psi_O", "force_evaluations")}
        for j, r in enumerate(rows):
            t = tasks[r]
            rng = np.random.default_rng([rep, r, 20261128])
            E_G = t.E * (1 + 0.1 * rng.random())
            delta = (alpha * E_G / 2) ** (1 / alpha)
            zt = fit_rules.Z0 * delta ** 0.5
            m = t.N * zt / 2
            trials = max(math.ceil(m / fit_rules.Z_P), 1)
            dz = 2.0 / t.N * rng.binomial(trials, m / trials)
            corr = 1 + sc["k"] * zt ** sc["omega"]
            out["E_G"][j], out["delta_Z"][j] = E_G, dz
            out["A_G"][j] = (fit_rules.A_STAR + ba / t.N + ca / t.N ** 2 + fit_rules.B_COEFF * zt ** sc["beta_Z"] * corr
                             + fit_rules.SD_A0 / math.sqrt(t.N) * rng.normal())
            out["psi_O"][j] = TRUTH["psi_O_star"] + bp / t.N + cp / t.N ** 2 + B_P * zt ** sc["beta_Z"] * corr + SD_P0 / math.sqrt(t.N) * rng.normal()
            sec = task_cost(t.N, t.E) * math.exp(0.3 * rng.normal())
            out["force_evaluations"][j] = max(1.0, sec / (DISK_SECONDS * t.N))
        out["jam_status"], out["identities_ok"] = np.zeros(len(rows)), np.ones(len(rows))
        return out
    return draw


def one(job):
    rep, text, scenario, boot, uniform, sizes, model, knobs, first = job
    from campaign.precision import allocation

    for name, value in knobs:  # --set: the rounds' constants (allocation.ROUND_GROWTH, CELL_GROWTH, ...)
        setattr(allocation, name, value)
    if model == "line":  # the rounds' model before 0.4: an intercept's error is the line's alone
        errormodel.LawModel.intercept_variance = lambda self, st: float(st[0][0, 0])
    spec = parse_spec(text)
    tasks = expand(spec)
    cells = errormodel.campaign_cells(spec, tasks)
    draw = draw_factory(spec, tasks, rep, scenario, sizes)
    settings = Settings(n_boot=boot)
    t0 = time.perf_counter()
    round0 = planner.first_round(spec, tasks) if first == "prior" else None
    recs, table = planner.run_in_memory(cells, spec.precision.settings(), draw, reducer=settings,
                                  attrs={"schema": "jamming-campaign/1", "spec_yaml": text}, disk_seconds=DISK_SECONDS,
                                  first=round0)
    row = table.extrapolated["default"]
    counts = np.array(recs[-1]["early"])
    rows = np.flatnonzero(cells.tasks_of(counts))
    d = draw(rows)
    out = {"rep": rep, "rounds": len(recs) - 1, "action": recs[-1]["action"], "packings": int(counts.sum()),
           "cost": float(np.sum(d["force_evaluations"] * cells.N[rows // cells.seeds])),
           "seconds": time.perf_counter() - t0,
           "adaptive": {k: [row[k], row[f"{k}_err"]] for k in ("A_G_star_E", "beta_E", "psi_O_star")},
           "projections": [{k: r[k] for k in ("decision", "key", "ratio")} for r in planner.projections(recs)]}
    if uniform:
        u = np.full(cells.C, uniform)
        rows = np.flatnonzero(cells.tasks_of(u))
        d = draw(rows)
        tab = planner.reduce_rows(cells, {"schema": "jamming-campaign/1", "spec_yaml": text}, rows,
                            np.ones(len(rows), np.int8), d, settings=settings)
        r2 = tab.extrapolated["default"]
        out["uniform"] = {k: [r2[k], r2[f"{k}_err"]] for k in ("A_G_star_E", "beta_E", "psi_O_star")}
        out["uniform_cost"] = float(np.sum(d["force_evaluations"] * cells.N[rows // cells.seeds]))
    return out


def summarise(results, truth, label):
    lines = []
    for k in ("A_G_star_E", "beta_E", "psi_O_star"):
        vals = np.array([r[label][k] for r in results if label in r], float)
        ok = np.all(np.isfinite(vals), axis=1)
        v, e = vals[ok, 0], vals[ok, 1]
        z = (v - truth[k]) / e
        lines.append({"key": k, "n": int(ok.sum()), "missing": int((~ok).sum()), "median_bias_in_errors": float(np.median(z)),
                      "mean_bias": float(np.mean(v - truth[k])), "median_error": float(np.median(e)),
                      "spread": float(np.std(v, ddof=1)) if len(v) > 1 else float("nan"),
                      "cover_1sigma": float(np.mean(np.abs(z) <= 1)), "cover_2sigma": float(np.mean(np.abs(z) <= 2))})
    return lines


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--reps", type=int, default=200)
    p.add_argument("--boot", type=int, default=200)
    p.add_argument("--scenario", default="none", choices=sorted(fit_rules.SCENARIOS))
    p.add_argument("--targets", type=float, nargs=3, default=(5e-4, 0.02, 1e-3), metavar=("A", "BETA", "PSI"),
                   help="the targets of A_G_star_E, beta_E, psi_O_star (0: not asked for)")
    p.add_argument("--pilot", type=int, default=4)
    p.add_argument("--max-seeds", type=int, default=200)
    p.add_argument("--uniform", type=int, default=20, help="seeds per cell of the uniform control (0: none)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--sizes", default="none", choices=sorted(SIZES),
                   help="the intercepts' finite-size terms (SIZES): none, or paper-small's line and 1/N_G^2 term")
    p.add_argument("--model", default="choice", choices=("choice", "line"),
                   help="the rounds' model of an intercept's error: the reducer's average of line and parabola "
                        "(default), or the line alone (before 0.4)")
    p.add_argument("--first", default="prior", choices=("prior", "pilot"),
                   help="round 0: designed from the prior as a run does (planner.first_round), or the uniform pilot")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a constant of campaign.precision.allocation for the rounds (e.g. MIN_FIT_PACKINGS=4, ROUND_GROWTH=2)")
    p.add_argument("--json")
    a = p.parse_args(argv)
    knobs = []
    for item in a.set:
        name, _, value = item.partition("=")
        from campaign.precision import allocation

        if not name.isupper() or not hasattr(allocation, name):
            p.error(f"--set {item}: no constant {name} in campaign.precision.allocation")
        knobs.append((name, type(getattr(allocation, name))(float(value))))
    if not any(a.targets):
        p.error("--targets: at least one target above 0 (0: not asked for)")
    target = ", ".join(f"{k}: {v:g}" for k, v in zip(("A_G_star_E", "beta_E", "psi_O_star"), a.targets) if v > 0)
    text = SPEC % {"target": target, "pilot": a.pilot, "max": a.max_seeds}
    sc = fit_rules.SCENARIOS[a.scenario]
    truth = dict(TRUTH, beta_E=sc["beta_Z"] / 4.0)
    jobs = [(rep, text, a.scenario, a.boot, a.uniform, a.sizes, a.model, knobs, a.first) for rep in range(a.reps)]
    t0 = time.time()
    with ProcessPoolExecutor(a.workers) as ex:
        results = list(ex.map(one, jobs))
    summary = {"scenario": a.scenario, "sizes": a.sizes, "model": a.model, "set": dict(knobs), "first": a.first, "targets": dict(zip(("A_G_star_E", "beta_E", "psi_O_star"), a.targets)),
               "truth": truth, "reps": a.reps, "boot": a.boot, "pilot": a.pilot, "max_seeds": a.max_seeds,
               "adaptive": summarise(results, truth, "adaptive"),
               "uniform": summarise(results, truth, "uniform") if a.uniform else [],
               "rounds_median": float(np.median([r["rounds"] for r in results])),
               "actions": {x: sum(r["action"] == x for r in results) for x in {r["action"] for r in results}},
               "cost_ratio_median": (float(np.median([r["cost"] / r["uniform_cost"] for r in results]))
                                     if a.uniform else None),
               "seconds": time.time() - t0}
    print(f"scenario {a.scenario!r}, sizes {a.sizes!r}, model {a.model!r}, first round {a.first!r}, "
          f"set {dict(knobs)}, {a.reps} campaigns (bootstrap {a.boot}); targets {summary['targets']}; "
          f"truth {truth}")
    print(f"ended: {summary['actions']}; rounds (median) {summary['rounds_median']:g}; cost against {a.uniform} "
          f"uniform seeds (median ratio, fe x N): {summary['cost_ratio_median']}")
    print("| run | key | median (value - truth) / error | 1 sigma | 2 sigma | median error | spread | no value |")
    print("|---|---|---|---|---|---|---|---|")
    for label in ("adaptive", "uniform"):
        for s in summary[label]:
            print(f"| {label} | {s['key']} | {s['median_bias_in_errors']:+.2f} | {s['cover_1sigma']:.2f} | "
                  f"{s['cover_2sigma']:.2f} | {s['median_error']:.2g} | {s['spread']:.2g} | {s['missing']} |")
    print("\nachieved / projected error, each decision's round (median and 10%-90% over the campaigns' decisions):\n")
    print("| key | decisions | median | 10% | 90% |\n|---|---|---|---|---|")
    for k in ("A_G_star_E", "beta_E", "psi_O_star"):
        q = np.array([p["ratio"] for r in results for p in r["projections"] if p["key"] == k and np.isfinite(p["ratio"])])
        if len(q):
            print(f"| {k} | {len(q)} | {np.median(q):.2f} | {np.quantile(q, 0.1):.2f} | {np.quantile(q, 0.9):.2f} |")
    if a.json:
        Path(a.json).write_text(json.dumps({"summary": summary, "results": results}, indent=1))


if __name__ == "__main__":
    main()
