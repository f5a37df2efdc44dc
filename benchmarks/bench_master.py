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

3. Scale (``--scale T``, e.g. 1000000): T synthetic tasks carrying every histogram with
   the kernels' default bin counts (about 2100 int64 counts, 17 KB a task), 2 local
   workers. Reported: the master's peak resident memory (``getrusage`` of the master
   itself, stored in the run record), tasks per second of the master loop and per second
   of master CPU (the machine is shared: the first is a lower bound, the second what the
   master alone could sustain), the store's size and the journal's largest size during the
   run, the time of ``campaign status``, the time and peak memory of ``campaign reduce``
   (from ``wait4``). Targets: master below 1 GB, >= 2000 tasks/s, status < 2 s, reduce
   < 5 min and < 4 GB.

    python benchmarks/bench_master.py [--tasks 20000] [--skip-quickstart] [--json FILE]
    nice -n 5 python benchmarks/bench_master.py --scale 1000000 --scale-only

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


def _timed_child(cmd, env, timeout=3600, usage_out=None):
    """Run ``cmd``; its wall seconds and peak resident memory (MB, from wait4). ``usage_out``
    (a dict) receives its CPU seconds, its own and its reaped children's (local workers)."""
    t0 = time.monotonic()
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(p.pid, 0)
    if usage_out is not None:
        usage_out["cpu_seconds"] = usage.ru_utime + usage.ru_stime
    wall = time.monotonic() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    err = p.stderr.read().decode(errors="replace")
    if p.returncode != 0:
        raise SystemExit(f"benchmark command failed ({p.returncode}): {' '.join(map(str, cmd))}\n{err}")
    return wall, usage.ru_maxrss / 1024.0


def scale(tmp: Path, n_tasks: int, workers: int = 2) -> dict:
    """``n_tasks`` synthetic tasks with every histogram at the kernels' default bin counts."""
    import threading

    seeds = max(1, n_tasks // 10)
    spec = tmp / "scale.yaml"
    spec.write_text(f"name: scale\nseed: 1\ngrid: {{N_G: [16], E_G: {{log_range: [1.0e-10, 1.0e-1], "
                    f"per_decade: 1}}, seeds: {seeds}}}\n")  # every observable: every histogram
    out = tmp / "scale.h5"
    journal = Path(str(out) + ".journal")
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", PYTHONPATH=str(ROOT))
    peak = {"journal": 0, "stop": False}

    def watch():
        while not peak["stop"]:
            try:
                peak["journal"] = max(peak["journal"], journal.stat().st_size)
            except OSError:
                pass
            time.sleep(0.05)

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    cpu = {}
    wall, _ = _timed_child([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet",
                            "--new", "--workers", str(workers)], env, usage_out=cpu)
    peak["stop"] = True
    th.join()
    with h5py.File(out, "r") as f:
        run = json.loads(f.attrs["runs"])[-1]
        bins = sum(f[f"histograms/{h}/counts"].shape[1] for h in f["histograms"])
    status_s = []
    for _ in range(3):
        status_s.append(_timed_child([sys.executable, "-m", "campaign", "status", str(out)], env))
    red_s, red_rss = _timed_child([sys.executable, "-m", "campaign", "reduce", str(out), "--out",
                                   str(tmp / "scale_reduced")], env)
    done = int(run["completed"])
    return {"benchmark": f"scale: {done} synthetic tasks, {bins} histogram bins each, {workers} local workers",
            "tasks": done, "bins": bins, "loop_seconds": float(run["seconds"]), "wall_seconds": wall,
            "tasks_per_second": done / float(run["seconds"]),
            "master_cpu_seconds": float(run["master_cpu_seconds"]),
            "tasks_per_master_cpu_second": done / float(run["master_cpu_seconds"]),
            "master_peak_rss_mb": float(run["master_peak_rss_mb"]),
            "cpu_ms_per_task_all": 1e3 * cpu["cpu_seconds"] / done,
            "cpu_ms_per_task_master": 1e3 * float(run["master_cpu_seconds"]) / done,
            "machine_share": cpu["cpu_seconds"] / wall,
            "file_mb": out.stat().st_size / 1e6, "journal_peak_mb": peak["journal"] / 1e6,
            "journal_end_mb": journal.stat().st_size / 1e6,
            "status_seconds": float(np.median([x[0] for x in status_s])),
            "status_peak_rss_mb": float(max(x[1] for x in status_s)),
            "reduce_seconds": red_s, "reduce_peak_rss_mb": red_rss}


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
    ap.add_argument("--scale", type=int, default=0, metavar="T",
                    help="also the scale benchmark with T tasks (e.g. 1000000)")
    ap.add_argument("--scale-only", action="store_true", help="only the scale benchmark")
    ap.add_argument("--tmp", default=None, help="directory for the benchmark's files (default: a temporary one)")
    ap.add_argument("--json", default=None, help="write the figures to this file")
    args = ap.parse_args(argv)
    os.environ.setdefault("NUMBA_CACHE_DIR", str(Path.home() / ".cache" / "jamming-campaign" / "numba"))
    results = []
    with tempfile.TemporaryDirectory(dir=args.tmp) as d:
        tmp = Path(d)
        if args.scale:
            results.append(scale(tmp, args.scale))
        if MPIEXEC.exists() and not args.scale_only:
            results.append(throughput(tmp, args.tasks, "mpi"))
        if not args.scale_only:
            results.append(throughput(tmp, args.tasks, "local"))
        if not args.skip_quickstart and not args.scale_only:
            # warm the numba cache so that neither timed run compiles
            _run([sys.executable, "-m", "campaign", "run", str(ROOT / "campaigns" / "ci.yaml"), "--out",
                  str(tmp / "warm.h5"), "--quiet", "--workers", "1"], dict(os.environ, PYTHONPATH=str(ROOT)))
            results.append(quickstart(tmp, args.repeats))
    print("| benchmark | figure | target |")
    print("|---|---|---|")
    for r in results:
        if "master_peak_rss_mb" in r:
            rows = [("master peak RSS", f"{r['master_peak_rss_mb']:,.0f} MB", "< 1 GB"),
                    ("tasks per second (master loop; shared cores: a lower bound)",
                     f"{r['tasks_per_second']:,.0f} ({r['tasks']} tasks in {r['loop_seconds']:.0f} s)", ">= 2000"),
                    ("tasks per second of master CPU", f"{r['tasks_per_master_cpu_second']:,.0f}", "-"),
                    ("CPU per task, master / master and workers (whole run)",
                     f"{r['cpu_ms_per_task_master']:.3f} ms / {r['cpu_ms_per_task_all']:.3f} ms "
                     f"(the run got {r['machine_share']:.2f} cores on average)", "-"),
                    ("store size", f"{r['file_mb']:,.0f} MB", "-"),
                    ("journal size, largest during the run / at the end",
                     f"{r['journal_peak_mb']:,.1f} MB / {r['journal_end_mb']:.3f} MB", "-"),
                    ("campaign status (median of 3)", f"{r['status_seconds']:.2f} s, {r['status_peak_rss_mb']:,.0f} MB",
                     "< 2 s"),
                    ("campaign reduce", f"{r['reduce_seconds']:.0f} s, {r['reduce_peak_rss_mb']:,.0f} MB",
                     "< 5 min, < 4 GB")]
            for name, fig, target in rows:
                print(f"| {r['benchmark']}: {name} | {fig} | {target} |")
        elif "tasks_per_second" in r:
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
