"""Precision targets against a uniform campaign, measured side by side (docs/PRECISION.md).

    python benchmarks/bench_precision.py                      # paper-small: uniform 20 seeds, then the rounds
    python benchmarks/bench_precision.py --uniform-store results/paper-small.h5 --json bench-precision.json
    python benchmarks/bench_precision.py --uniform-store data/paper-small.h5 --keys A_G_star_E   # one target
    python benchmarks/bench_precision.py --uniform-store data/paper-small.h5 --loose 2           # looser targets

The uniform campaign is `campaigns/paper-small.yaml` (N_G 64..1024, 13 energies, 20 seeds per cell). Its
reduction's errors of A_G_star_E, beta_E and psi_O_star become the targets of the same grid run with
`precision` (`--pilot`, `--max-seeds`; `--keys` asks for some of them only, `--loose F` for F times
them); both run here, one after the other, with `--workers` local
workers (`--uniform-store` reuses a finished uniform store and times it from its record). Printed:
packings, force evaluations, force evaluations times disks (what the rounds price a packing at),
core-seconds (the workers' task times), wall seconds and the workers' idle share, the row of each run
and whether they agree within their combined errors, and per decision and target the error the model
projected after the round against the one the next decision measured (``planner.projections``).
The rounds are also set against the uniform grid that meets the same targets: the fewest seeds per cell
whose reduction (the first that many seeds of every cell of the uniform store, reduced as `campaign
reduce` does) meets every target, and the work of those packings. (Not 20 / F^2 for targets F times
the 20 seeds' errors: the reducer leaves N_G 64 out of the extrapolation at some seed counts, and the
error jumps; on paper-small 5 seeds give A_G_star_E 0.0016, 6 give 0.0008.)
Force evaluations are deterministic; seconds depend on the machine and its load (run it on a quiet one).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from campaign.precision import planner

ROOT = Path(__file__).resolve().parents[1]
KEYS = ("A_G_star_E", "beta_E", "psi_O_star")


def campaign(*args, env=None):
    r = subprocess.run([sys.executable, "-m", "campaign", *args], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise SystemExit(f"campaign {' '.join(args)} failed:\n{r.stderr}")
    return r


def row(store, out):
    r = campaign("reduce", str(store), "--json", "--out", str(out))
    return json.loads(r.stdout)["extrapolated"]["default"]


def uniform_meeting(store, targets, most=20):
    """The fewest seeds per cell (2 .. ``most``) whose reduction of the uniform store's first seeds meets
    every target, with that reduction's errors; (None, {}) when none does."""
    for n in range(2, most + 1):
        row = planner.reduce_store_rows(store, lambda t: t["seed"] < n).extrapolated["default"]
        errs = {k: float(row[f"{k}_err"]) for k in targets}
        if all(errs[k] <= targets[k] for k in targets):
            return n, errs
    return None, {}


def measure(store, seeds=None):
    """The work of the store's finished packings (with ``seeds``, of its first that many seeds per cell)."""
    with h5py.File(store, "r") as f:
        done = f["tasks/status"][:] == 1
        if seeds is not None:
            done &= f["tasks/seed"][:] < seeds  # a uniform grid's seeds per cell are 0, 1, 2, ...
        fe = f["scalars/force_evaluations"][:][done]
        N = f["tasks/N"][:][done]
        wall = f["tasks/wall"][:][done]
        runs = json.loads(f.attrs["runs"])
    seconds = sum(float(r.get("seconds") or 0.0) for r in runs) if seeds is None else float("nan")
    slots = sum(float(r.get("seconds") or 0.0) * int(r.get("workers") or 1) for r in runs)
    return {"packings": int(done.sum()), "force_evaluations": float(fe.sum()), "fe_x_N": float((fe * N).sum()),
            "core_seconds": float(wall.sum()), "wall_seconds": seconds,
            "idle": 1.0 - float(wall.sum()) / slots if slots > 0 and seeds is None else float("nan")}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--pilot", type=int, default=4)
    p.add_argument("--max-seeds", type=int, default=400)
    p.add_argument("--uniform-store", help="a finished store of campaigns/paper-small.yaml (else run it)")
    p.add_argument("--precision-store", help="a finished store of the rounds (made by this script with the same "
                   "options): measured again, not run")
    p.add_argument("--dir", default="results/bench-precision")
    p.add_argument("--keys", nargs="+", choices=KEYS, default=list(KEYS), help="the targets asked for")
    p.add_argument("--loose", type=float, default=1.0, help="targets this many times the uniform run's errors")
    p.add_argument("--json")
    a = p.parse_args(argv)
    if not a.loose >= 1.0:
        p.error(f"--loose: expected a factor of at least 1, got {a.loose}")
    d = Path(a.dir)
    d.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, NUMBA_CACHE_DIR=os.environ.get("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache")))
    uniform_spec = ROOT / "campaigns" / "paper-small.yaml"
    uni = Path(a.uniform_store) if a.uniform_store else d / "uniform.h5"
    if not a.uniform_store:
        t0 = time.time()
        campaign("run", str(uniform_spec), "--out", str(uni), "--workers", str(a.workers), "--quiet", "--new", env=env)
        print(f"uniform: {time.time() - t0:.0f} s", file=sys.stderr)
    u_row = row(uni, d / "uniform_reduced")
    targets = {k: a.loose * float(u_row[f"{k}_err"]) for k in a.keys}
    text = uniform_spec.read_text().replace("  seeds: 20\n", "")
    text = text.replace("name: paper-small\n", "name: paper-small-precision\n")
    text += ("precision:\n  target: {" + ", ".join(f"{k}: {v:.6g}" for k, v in targets.items()) + "}\n"
             f"  pilot: {a.pilot}\n  max_seeds: {a.max_seeds}\n")
    spec = d / "precision.yaml"
    spec.write_text(text)
    ada = Path(a.precision_store) if a.precision_store else d / "precision.h5"
    if a.precision_store:
        with h5py.File(ada, "r") as f:
            if "precision" not in f or f.attrs["spec_yaml"].strip() != text.strip():
                raise SystemExit(f"{ada}: not the rounds of these options (its spec is not {spec})")
    else:
        t0 = time.time()
        campaign("run", str(spec), "--out", str(ada), "--workers", str(a.workers), "--quiet", "--new", env=env)
        print(f"precision: {time.time() - t0:.0f} s", file=sys.stderr)
    a_row = row(ada, d / "precision_reduced")
    with h5py.File(ada, "r") as f:
        g = f["precision"]
        recs = [json.loads(g[k][()].tobytes().decode()) for k in sorted(g)]
    mu, ma = measure(uni), measure(ada)
    runs = [("uniform, 20 seeds", mu)]
    n_meet, meet_errs = uniform_meeting(uni, targets)
    if n_meet is not None and n_meet < 20:
        runs.append((f"uniform, {n_meet} seeds (the fewest that meet the targets)", measure(uni, n_meet)))
    runs.append(("precision targets", ma))
    print(f"targets ({a.loose:g} x the uniform run's errors): {targets}; pilot {a.pilot}, max_seeds {a.max_seeds}, "
          f"{a.workers} workers; the rounds ended: {recs[-1]['action']} after round {recs[-1]['round'] - 1}; "
          f"the fewest uniform seeds per cell that meet them: {n_meet} (errors {meet_errs})")
    print("| | packings | force evaluations | force evaluations x N | core-seconds | wall seconds | idle |")
    print("|---|---|---|---|---|---|---|")
    for label, m in runs:
        print(f"| {label} | {m['packings']} | {m['force_evaluations']:.4g} | {m['fe_x_N']:.4g} | "
              f"{m['core_seconds']:.0f} | {m['wall_seconds']:.0f} | {100 * m['idle']:.1f}% |")
    for label, m in runs[:-1]:
        print(f"| ratio to {label.split(' (')[0]} | {ma['packings'] / m['packings']:.2f} | "
              f"{ma['force_evaluations'] / m['force_evaluations']:.2f} | {ma['fe_x_N'] / m['fe_x_N']:.2f} | "
              f"{ma['core_seconds'] / m['core_seconds']:.2f} | |  |")
    print("| key | uniform | precision | difference / combined error | goal met |")
    print("|---|---|---|---|---|")
    agree = {}
    for k in a.keys:
        x, ex, y, ey = u_row[k], u_row[f"{k}_err"], a_row[k], a_row[f"{k}_err"]
        z = (y - x) / np.hypot(ex, ey)
        agree[k] = float(z)
        print(f"| {k} | {x:.6g} +- {ex:.2g} | {y:.6g} +- {ey:.2g} | {z:+.2f} | {'yes' if ey <= targets[k] else 'no'} |")
    proj = planner.projections(recs)
    print("\nEach decision's projection after its round against the error the next decision measured:\n")
    print(planner.projections_markdown(proj))
    if a.json:
        Path(a.json).write_text(json.dumps({"targets": targets, "loose": a.loose, "uniform_meeting": [n_meet, meet_errs], "runs": dict(runs[:-1]), "precision": ma, "projections": proj, "rows": {
            "uniform": {k: [u_row[k], u_row[f"{k}_err"]] for k in a.keys},
            "precision": {k: [a_row[k], a_row[f"{k}_err"]] for k in a.keys}}, "agreement": agree,
            "rounds": [{"round": x["round"], "action": x["action"], "message": x["message"]} for x in recs]}, indent=1))


if __name__ == "__main__":
    main()
