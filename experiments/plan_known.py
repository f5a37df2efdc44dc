"""What the precision rounds could save with the parameters known (docs/PRECISION.md, "What the
rounds can save"): a finished store taken as the truth, its own errors as the targets.

    python experiments/plan_known.py data/paper-small.h5 [--pilot 4] [--floor 8] [--keys A_G_star_E beta_E psi_O_star]

The model of the errors (``campaign.precision.errormodel``, the rounds' own) is built from every
packing of the store and calibrated to its bootstrap errors, as a decision is; the targets are the
store's errors of ``--keys`` (``--scale`` times them: looser or tighter). Printed, in the store's
disk-force evaluations (its force evaluations times N_G, per cell the mean of its packings):

* the uniform grid the model says meets the targets (seeds per cell; at scale 1 near the store's own);
* the rounds' plan from a uniform pilot of ``--pilot`` (with every fit-range cell first brought to
  ``--floor`` packings, as the rounds did before 0.4) (``plan_greedy``, as a decision plans, all in
  one round): what the rounds
  would spend if their first decision already knew what the store knows;
* each as a share of the store's own work.

The gap between this plan and what a precision run spends is the cost of learning the parameters as
the rounds go; the gap between it and 1 is what any allocation of this estimator can save here.
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from campaign.precision import allocation, errormodel
from campaign.results.finished import load_finished
from campaign.results.reduce import Settings, reduce_table


def plans(table, keys, scale=1.0, pilot=4, floors=(0,), max_seeds=400):
    """The rows of the table printed by ``main`` for a reduction ``table`` of a finished campaign:
    ``(rows, goals, packings)``, each row ``(plan, seeds, share of the campaign's disk-force
    evaluations)``."""
    cells = errormodel.table_cells(table)
    index = cells.index()
    g, fin = table.grid, table.fin
    n = errormodel.cell_counts(table, cells)
    work = np.full(cells.C, np.nan)  # disk-force evaluations per packing
    for gc in range(g.C):
        c = index[(str(g.cv[gc]), int(g.cN[gc]), float(g.cE[gc]))]
        p = g.packings(gc)
        if len(p):
            work[c] = float(np.mean(fin.scalars["force_evaluations"][p])) * cells.N[c]
    work = allocation.fill_costs(np.where(work > 0, work, np.nan), cells)
    row = table.extrapolated["default"]
    goals = {k: scale * float(row[f"{k}_err"]) for k in keys}
    settings = {"target": goals, "pilot": pilot, "max_seeds": max_seeds, "budget": None}
    targets = allocation._targets(table, cells, settings)
    states = {}
    for t in targets:
        if id(t.law) not in states:
            states[id(t.law)] = t.law.state(n)
            t.law.anchor(states[id(t.law)])
        t.ratio = t.error / math.sqrt(t.variance(states[id(t.law)]))  # calibrated to the bootstrap
    relevant = cells.relevant(goals)
    store_work = float(np.sum(n * work))

    def meets(alloc):
        st = {}
        for t in targets:
            if id(t.law) not in st:
                st[id(t.law)] = t.law.state(alloc)
            if not t.variance(st[id(t.law)]) <= t.goal ** 2 * (1 + 1e-9):
                return False
        return True

    lo, hi = 1, max_seeds
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if meets(np.full(cells.C, float(mid))) else (mid, hi)
    rows = [("uniform, the seeds per cell that meet the targets", f"{hi} per cell",
             hi * float(np.sum(work)) / store_work)]
    for floor in floors:
        n0 = np.full(cells.C, float(pilot))
        base = np.where(relevant, np.maximum(n0, min(max_seeds, floor)), n0)
        st = {id(t.law): t.law.state(base) for t in targets}
        plan = allocation.plan_greedy(targets, cells, base, base.astype(np.int64), np.ones(cells.C), work, relevant,
                                      max_seeds, st)
        alloc = plan.prefix(plan.cost_to_met, base.astype(np.int64))
        total = float(np.sum(base * work)) + plan.cost_to_met
        rows.append((f"pilot {pilot}, " + (f"fit range to {floor} first, " if floor > pilot else "")
                     + "then the plan with the parameters known",
                     int(alloc.sum()), total / store_work))
    return rows, goals, int(n.sum())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store", nargs="+")
    ap.add_argument("--keys", nargs="+", default=["A_G_star_E", "beta_E", "psi_O_star"])
    ap.add_argument("--scale", type=float, default=1.0, help="targets: this times the store's errors")
    ap.add_argument("--pilot", type=int, default=4)
    ap.add_argument("--floor", type=int, nargs="+", default=[0],
                    help="packings every fit-range cell holds before the plan (the rounds before 0.4: 8)")
    ap.add_argument("--max-seeds", type=int, default=400)
    a = ap.parse_args(argv)

    table = reduce_table(load_finished(a.store), Settings(), per_size=False)
    rows, goals, packings = plans(table, a.keys, a.scale, a.pilot, a.floor, a.max_seeds)
    print(f"{', '.join(a.store)}: {packings} packings; targets {a.scale:g} x its errors: "
          + ", ".join(f"{k} {v:.3g}" for k, v in goals.items()))
    print("| plan | seeds | disk-force evaluations / the store's |\n|---|---|---|")
    for name, seeds, share in rows:
        print(f"| {name} | {seeds} | {share:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
