"""What the store's checksums cost (docs/STORE.md, "Checksums, verify and repair").

Every figure compares three stores written side by side in one run: with every checksum (the
block checksums, a uint64 of the values of each block of rows, written by the master and checked
by every read below; fletcher32 on every chunk; crc32 on every configuration and failure record),
with all but the block checksums (the stores of 0.2.7, read as such: "before"), and without any
(``CAMPAIGN_NO_CHECKSUMS=1``). The three are alternated ``--repeats`` times and the ratios of the
medians reported, so that a shared, loaded machine slows them alike: "with / before" is what the
block checksums cost, "with / without" what every checksum costs.

1. Writing: the master's store path alone (``Store.record`` and the block writes, journal
   included), in this process, for ``--tasks`` synthetic tasks carrying every histogram at the
   kernels' default bin counts (the 10^6-packing benchmark's tasks); CPU seconds of this process.
2. Reading: every block of every per-task dataset read back in slabs (as ``campaign reduce`` and
   ``campaign verify`` read them); and ``campaign verify``'s whole scan of the checksummed store.
3. Configurations: CRC-32 of a packing's positions, radii, box and species (N = 1024 and 8192).
4. With ``--scale T``: ``benchmarks/bench_master.py``'s scale benchmark (T tasks, 2 local workers,
   ``campaign status`` and ``campaign reduce`` after it, and here ``campaign verify``'s scan) with
   and without checksums, alternated (``--repeats`` pairs up to 10^5 tasks, one pair beyond).

    python benchmarks/bench_checksums.py [--tasks 20000] [--repeats 3] [--scale 100000] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _spec(n_tasks):
    from campaign.plan.parse import parse_spec

    seeds = max(1, n_tasks // 10)
    return parse_spec(f"name: cks\nseed: 1\ngrid: {{N_G: [16], E_G: {{log_range: [1.0e-10, 1.0e-1], per_decade: 1}}, "
                      f"seeds: {seeds}}}\n")


def write_store(path, n_tasks, mode):
    """Seconds of CPU the store path takes for n_tasks finished tasks, the store written with every
    checksum (``mode`` "with"), without the block checksums ("before") or without any ("without")."""
    from campaign.storage import checksums as cks
    from campaign.storage.store import Store
    from campaign.plan.tasks import expand
    from campaign.run.worker import SyntheticTask, run_task

    saved = cks.create_sums, cks.create_fill_sums
    if mode == "without":
        os.environ["CAMPAIGN_NO_CHECKSUMS"] = "1"
    else:
        os.environ.pop("CAMPAIGN_NO_CHECKSUMS", None)
    if mode == "before":  # a store without /checksums: its writer and readers skip the block checksums
        cks.create_sums = cks.create_fill_sums = lambda *a, **k: None
    try:
        spec = _spec(n_tasks)
        tasks = expand(spec)
        fn = SyntheticTask()
        ctx = dict(spec.worker_context(), task_function="synthetic", bins={}, configurations=False)
        edges = fn.histogram_edges(ctx)
        ctx["edges"] = edges
        pool = [run_task(fn, dict(t.payload(), attempt=1), ctx, rank=1) for t in tasks[:64]]
        for p in Path(path).parent.glob(Path(path).name + "*"):
            p.unlink()
        t0 = time.process_time()
        st = Store(path, spec, tasks, edges, log=lambda m: None)
        for i in range(len(tasks)):
            st.record(i, dict(pool[i % len(pool)], id=tasks[i].id), attempts=1)
        st.close()
        return time.process_time() - t0
    finally:
        os.environ.pop("CAMPAIGN_NO_CHECKSUMS", None)
        cks.create_sums, cks.create_fill_sums = saved


def read_blocks(path):
    """Wall seconds to read every block of every per-task dataset, in slabs of at most 16 MB, as the
    readers open the store (``open_checked``: each block read is checked against its block checksum
    when the store has them; a store without reads as before)."""
    from campaign.storage.checksums import open_checked

    t0 = time.perf_counter()
    with open_checked(path) as f:
        names = [f"tasks/{n}" for n in ("id", "variant", "N", "E", "seed", "status", "attempts", "wall", "rank",
                                        "host", "error")]
        names += [f"scalars/{n}" for n in f["scalars"]] + [f"histograms/{h}/counts" for h in f["histograms"]]
        for n in names:
            ds = f[n]
            rowbytes = ds.dtype.itemsize * (ds.shape[1] if ds.ndim == 2 else 1)
            step = max(256, (16 << 20) // rowbytes // 256 * 256)
            for lo in range(0, ds.shape[0], step):
                ds[lo:lo + step]
    return time.perf_counter() - t0


def verify_seconds(path):
    from campaign.storage.integrity import scan

    t0 = time.perf_counter()
    r = scan(path)
    assert r.ok, [d.how for d in r.damage]
    return time.perf_counter() - t0


def crc_rate():
    from campaign.storage.checksums import config_crc

    out = {}
    for n in (1024, 8192):
        rng = np.random.default_rng(1)
        conf = {"positions": rng.random((n, 2)), "radii": rng.random(n), "box": np.ones(2),
                "species": np.zeros(n, np.int32)}
        reps = 2000 if n == 1024 else 300
        t0 = time.perf_counter()
        for _ in range(reps):
            config_crc(conf)
        dt = (time.perf_counter() - t0) / reps
        out[n] = {"microseconds": 1e6 * dt, "bytes": sum(a.nbytes for a in conf.values())}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", type=int, default=20000, help="synthetic tasks of the write and read benchmarks")
    ap.add_argument("--repeats", type=int, default=3, help="alternated pairs (medians)")
    ap.add_argument("--scale", type=int, default=0, metavar="T", help="also bench_master's scale benchmark, T tasks")
    ap.add_argument("--tmp", default=None, help="directory for the files (default: a temporary one)")
    ap.add_argument("--json", default=None, help="write the figures to this file")
    args = ap.parse_args(argv)
    modes = ("with", "before", "without")
    res = {"tasks": args.tasks, "repeats": args.repeats,
           **{m: {"write": [], "read": [], "verify": []} for m in modes}}
    with tempfile.TemporaryDirectory(dir=args.tmp) as d:
        paths = {m: Path(d) / f"{m}.h5" for m in modes}
        for k in range(args.repeats):
            order = modes[k % 3:] + modes[:k % 3]
            for key in order:
                res[key]["write"].append(write_store(paths[key], args.tasks, key))
            for key in order:
                res[key]["read"].append(read_blocks(paths[key]))
                res[key]["verify"].append(verify_seconds(paths[key]))
        for key in modes:
            res[key]["file_bytes"] = paths[key].stat().st_size
        res["crc"] = crc_rate()
        if args.scale:
            import bench_master

            res["scale"] = {"with": [], "without": []}
            for k in range(args.repeats if args.scale <= 100000 else 1):
                for key in (("with", "without") if k % 2 == 0 else ("without", "with")):
                    if key == "without":
                        os.environ["CAMPAIGN_NO_CHECKSUMS"] = "1"
                    try:
                        tmp = Path(d) / f"scale-{key}-{k}"
                        tmp.mkdir()
                        got = bench_master.scale(tmp, args.scale)
                        got["verify_seconds"] = verify_seconds(tmp / "scale.h5")
                        res["scale"][key].append(got)
                        for p in tmp.iterdir():
                            p.unlink() if p.is_file() else None
                    finally:
                        os.environ.pop("CAMPAIGN_NO_CHECKSUMS", None)
    med = {key: {m: float(np.median(res[key][m])) for m in ("write", "read", "verify")} for key in modes}
    n = args.tasks
    print(f"| {n} synthetic tasks, every histogram at the default bins; medians of {args.repeats} alternated "
          "triples | with every checksum | before (no block checksums) | without any | with / before | with / without |")
    print("|---|---|---|---|---|---|")
    rows = [("store path, CPU per task (record, blocks, journal, close)", "write"),
            ("reading every block back, per task", "read"),
            ("campaign verify's whole scan, per task", "verify")]
    for label, m in rows:
        a, b, c = (med[key][m] * 1e3 / n for key in modes)
        print(f"| {label} | {a:.3f} ms | {b:.3f} ms | {c:.3f} ms | {a / b:.3f} | {a / c:.3f} |")
    a, b, c = (res[key]["file_bytes"] for key in modes)
    print(f"| file size, per task | {a / n:.1f} B | {b / n:.1f} B | {c / n:.1f} B | {a / b:.4f} | {a / c:.4f} |")
    for size, c in res["crc"].items():
        print(f"| crc32 of a configuration, N = {size} ({c['bytes'] / 1024:.0f} KiB) | {c['microseconds']:.1f} us "
              f"| - | - | - | - |")
    if args.scale:
        sc = res["scale"]
        keys = [("master_peak_rss_mb", "master peak RSS, MB"), ("tasks_per_second", "tasks per second, master loop"),
                ("tasks_per_master_cpu_second", "tasks per second of master CPU"), ("file_mb", "store size, MB"),
                ("status_seconds", "campaign status, s"), ("reduce_seconds", "campaign reduce, s"),
                ("verify_seconds", "campaign verify (whole scan), s"),
                ("reduce_peak_rss_mb", "campaign reduce peak RSS, MB")]
        print(f"\n| scale: {args.scale} tasks (bench_master.py), medians | with every checksum | without any | ratio |")
        print("|---|---|---|---|")
        for k, label in keys:
            a = float(np.median([r[k] for r in sc["with"]]))
            b = float(np.median([r[k] for r in sc["without"]]))
            print(f"| {label} | {a:,.2f} | {b:,.2f} | {a / b:.3f} |")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
