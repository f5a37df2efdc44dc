"""Benchmarks of the campaign engine.

1. Master throughput: trivial (synthetic, scalars-only) tasks through the real
   master loop, journal and HDF5 store, under ``mpiexec -n 3`` (2 workers) and
   with 2 local worker processes. Target: >= 2000 tasks/s through MPI.
2. Parallel efficiency of ``campaigns/quickstart.yaml`` (the real kernels) with 1
   and 2 local workers: T1 / (2 T2), on the master loop's time (the numba cache
   is warmed first and workers load it before the clock starts, so neither run
   pays for compilation). Target: >= 0.9. Also printed: the fraction of T2 the
   workers spent inside tasks, which separates the engine's overhead from a busy
   machine (on a shared machine the efficiency measures the machine, not us).

    python benchmarks/bench_master.py [--tasks 20000] [--skip-quickstart] [--json FILE]

Prints a Markdown table; ``--json FILE`` writes the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = Path(sys.executable).parent / "mpiexec"


def _run(cmd, env, timeout=3600):
    t0 = time.monotonic()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    wall = time.monotonic() - t0
    if r.returncode != 0:
        raise SystemExit(f"benchmark command failed ({r.returncode}): {' '.join(map(str, cmd))}\n{r.stderr}")
    return wall


def _loop_seconds(path, details=False):
    with h5py.File(path, "r") as f:
        run = json.loads(f.attrs["runs"])[-1]
        done = int((f["tasks/status"][:] == 1).sum())
        busy = float(f["tasks/wall"][:][f["tasks/status"][:] == 1].sum())
    if details:
        return float(run["seconds"]), done, float(run.get("master_cpu_seconds", "nan")), busy
    return float(run["seconds"]), done


def throughput(tmp: Path, n_tasks: int, launcher: str) -> dict:
    seeds = max(1, n_tasks // 10)
    spec = tmp / f"trivial-{launcher}.yaml"
    spec.write_text(f"name: trivial\nseed: 1\ngrid: {{N_G: [16], E_G: {{log_range: [1.0e-10, 1.0e-1], "
                    f"per_decade: 1}}, seeds: {seeds}}}\nobservables: [scalars]\n")
    out = tmp / f"trivial-{launcher}.h5"
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", PYTHONPATH=str(ROOT))
    base = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet", "--new"]
    if launcher == "mpi":
        cmd = [str(MPIEXEC), "-n", "3"] + base
    else:
        cmd = base + ["--workers", "2"]
    wall = _run(cmd, env)
    loop, done, cpu, _ = _loop_seconds(out, details=True)
    return {"benchmark": f"master throughput, trivial tasks, {launcher}, 2 workers", "tasks": done,
            "loop_seconds": loop, "wall_seconds": wall, "tasks_per_second": done / loop,
            "master_cpu_seconds": cpu, "tasks_per_master_cpu_second": done / cpu}


def quickstart(tmp: Path, repeats: int) -> dict:
    """T1 and T2 alternated ``repeats`` times.

    Each adjacent pair gives an efficiency T1 / (2 T2) measured side by side, so slow drifts of
    a shared machine hit both of its runs alike; the headline is the median over pairs, and the
    ratio of the median times is reported beside it.
    """
    spec = ROOT / "campaigns" / "quickstart.yaml"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("CAMPAIGN_TASK_FUNCTION", None)
    res = {1: [], 2: []}
    for _ in range(repeats):
        for k in (1, 2):
            out = tmp / f"quickstart-{k}.h5"
            cmd = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet", "--new",
                   "--workers", str(k)]
            wall = _run(cmd, env)
            loop, done, _, busy = _loop_seconds(out, details=True)
            res[k].append({"loop_seconds": loop, "wall_seconds": wall, "tasks": done, "busy": busy / (k * loop)})
    med = {k: float(np.median([r["loop_seconds"] for r in res[k]])) for k in res}
    pairs = [a["loop_seconds"] / (2 * b["loop_seconds"]) for a, b in zip(res[1], res[2])]
    return {"benchmark": "parallel efficiency, campaigns/quickstart.yaml, 1 vs 2 local workers",
            "tasks": res[1][0]["tasks"], "repeats": repeats, "T1_seconds": med[1], "T2_seconds": med[2],
            "efficiency": float(np.median(pairs)), "efficiency_of_medians": med[1] / (2 * med[2]),
            "efficiency_per_pair": pairs,
            "worker_busy_fraction_2": float(np.median([r["busy"] for r in res[2]])), "runs": res}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", type=int, default=20000, help="trivial tasks for the throughput runs")
    ap.add_argument("--skip-quickstart", action="store_true", help="only the throughput runs")
    ap.add_argument("--repeats", type=int, default=3, help="alternated 1- and 2-worker quickstart runs (median)")
    ap.add_argument("--json", default=None, help="write the figures to this file")
    args = ap.parse_args(argv)
    os.environ.setdefault("NUMBA_CACHE_DIR", str(Path.home() / ".cache" / "jamming-campaign" / "numba"))
    results = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if MPIEXEC.exists():
            results.append(throughput(tmp, args.tasks, "mpi"))
        results.append(throughput(tmp, args.tasks, "local"))
        if not args.skip_quickstart:
            # warm the numba cache so that neither timed run compiles
            _run([sys.executable, "-m", "campaign", "run", str(ROOT / "campaigns" / "ci.yaml"), "--out",
                  str(tmp / "warm.h5"), "--quiet", "--workers", "1"], dict(os.environ, PYTHONPATH=str(ROOT)))
            results.append(quickstart(tmp, args.repeats))
    print("| benchmark | figure | target |")
    print("|---|---|---|")
    for r in results:
        if "tasks_per_second" in r:
            target = ">= 2000/s" if "mpi" in r["benchmark"] else "-"
            print(f"| {r['benchmark']} | {r['tasks_per_second']:,.0f} tasks/s ({r['tasks']} tasks in "
                  f"{r['loop_seconds']:.2f} s; {r['tasks_per_master_cpu_second']:,.0f} per second of master "
                  f"CPU) | {target} |")
        else:
            spread = ", ".join(f"{e:.2f}" for e in r["efficiency_per_pair"])
            print(f"| {r['benchmark']} | {r['efficiency']:.2f} (median over {r['repeats']} alternated pairs: "
                  f"{spread}; median T1 = {r['T1_seconds']:.1f} s, median T2 = {r['T2_seconds']:.1f} s, "
                  f"ratio of medians {r['efficiency_of_medians']:.2f}; "
                  f"{r['tasks']} packings; workers busy {100 * r['worker_busy_fraction_2']:.0f}% of T2) | >= 0.9 |")
    if args.json:
        Path(args.json).write_text(json.dumps({"results": results, "python": sys.version.split()[0],
                                               "cpus": os.cpu_count()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
