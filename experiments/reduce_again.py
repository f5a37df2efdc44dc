"""A finished store's packings reduced again, in parts: the error of each target and the sizes the
reducer kept in its N_G -> inf extrapolation (docs/PRECISION.md, "One target, looser targets, a larger
round 0: where the rounds lose").

    python experiments/reduce_again.py seeds data/paper-small.h5 4 5 6 20   # the first n seeds of every cell
    python experiments/reduce_again.py decisions results/bench-precision/precision.h5   # each decision's packings

`seeds`: the first n seeds of every cell (of a precision campaign's store: at most n a cell).
`decisions`: a precision campaign's store, the packings each decision of its rounds reduced (the seeds
given out before it), as it reduced them (the reducer's defaults, the tasks' ids).
"""

from __future__ import annotations

import argparse
import json

import h5py
import numpy as np

from campaign.plan.parse import parse_spec
from campaign.plan.tasks import expand
from campaign.precision import errormodel, planner

KEYS = ("A_G_star_E", "beta_E", "psi_O_star")
ALL = "64 128 256 512 1024"


def line(label, table, packings) -> str:
    row = table.extrapolated.get("default", {})
    parts = []
    for k in KEYS:
        err, p, sizes = row.get(f"{k}_err"), row.get(f"{k}_p"), row.get(f"{k}_sizes") or ""
        err = float(err) if err is not None else np.nan
        p = float(p) if p is not None else np.nan
        parts.append(f"{err:.3g} | {p:.2g} | {'all' if sizes == ALL else sizes}")
    return f"| {label} | {packings} | " + " | ".join(parts) + " |"


def header() -> str:
    cols = " | ".join(f"{k} error | p | sizes" for k in KEYS)
    return f"| packings of | packings | {cols} |\n|---|---|" + "---|" * (3 * len(KEYS))


def decisions(path):
    with h5py.File(path, "r") as f:
        if "precision" not in f:
            raise SystemExit(f"{path}: not a precision campaign's store (no rounds recorded)")
        spec = parse_spec(f.attrs["spec_yaml"])
        recs = [json.loads(f["precision"][k][()].tobytes().decode()) for k in sorted(f["precision"])]
    cells = errormodel.campaign_cells(spec, expand(spec))
    print(header())
    for r in recs[:-1]:
        given = cells.tasks_of(np.asarray(r["allocated"]))  # a store's rows are its spec's tasks
        table = planner.reduce_store_rows(path, lambda t, given=given: given)
        print(line(f"decision {r['round'] + 1}", table, int(table.grid.n_done.sum())))


def seeds(path, counts):
    print(header())
    for n in counts:
        table = planner.reduce_store_rows(path, lambda t: t["seed"] < n)
        print(line(f"the first {n} seeds a cell", table, int(table.grid.n_done.sum())))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    s = sub.add_parser("seeds")
    s.add_argument("store")
    s.add_argument("n", type=int, nargs="+")
    d = sub.add_parser("decisions")
    d.add_argument("store")
    a = p.parse_args(argv)
    if a.what == "seeds":
        if min(a.n) < 2:
            p.error("seeds: at least 2 a cell")
        seeds(a.store, a.n)
    else:
        decisions(a.store)


if __name__ == "__main__":
    main()
