"""What the store's checksums cost (docs/STORE.md, "Checksums, verify and repair").

Every figure compares a store written with checksums (fletcher32 on every chunk, crc32 on every
configuration and failure record) with one written without (``CAMPAIGN_NO_CHECKSUMS=1``, as
stores before them), measured side by side in one run: the two are alternated ``--repeats``
times and the ratios of the medians reported, so that a shared, loaded machine slows both alike.

Since the block checksums (a uint64 of the values of each block of rows, checked by the readers),
"with checksums" includes them: written by the master, checked by every read below.

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
    from campaign.plan.spec import parse_spec

    seeds = max(1, n_tasks // 10)
    return parse_spec(f"name: cks\nseed: 1\ngrid: {{N_G: [16], E_G: {{log_range: [1.0e-10, 1.0e-1], per_decade: 1}}, "
                      f"seeds: {seeds}}}\n")


def write_store(path, n_tasks, checksums):
    """Seconds of CPU the store path takes for n_tasks finished tasks; the file written."""
    from campaign.storage.store import Store
    from campaign.plan.tasks import expand
    from campaign.run.worker import SyntheticTask, run_task

    if checksums:
        os.environ.pop("CAMPAIGN_NO_CHECKSUMS", None)
    else:
        os.environ["CAMPAIGN_NO_CHECKSUMS"] = "1"
    try:
        spec = _spec(n_tasks)
        tasks = expand(spec)
        fn = SyntheticTask()
        ctx = {"task_function": "synthetic", "observables": list(spec.observables), "histograms": list(spec.histograms),
               "bins": {}, "configurations": False}
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
    res = {"tasks": args.tasks, "repeats": args.repeats, "on": {"write": [], "read": [], "verify": []},
           "off": {"write": [], "read": [], "verify": []}}
    with tempfile.TemporaryDirectory(dir=args.tmp) as d:
        paths = {"on": Path(d) / "on.h5", "off": Path(d) / "off.h5"}
        for k in range(args.repeats):
            for key in (("on", "off") if k % 2 == 0 else ("off", "on")):
                res[key]["write"].append(write_store(paths[key], args.tasks, key == "on"))
            for key in (("on", "off") if k % 2 == 0 else ("off", "on")):
                res[key]["read"].append(read_blocks(paths[key]))
                res[key]["verify"].append(verify_seconds(paths[key]))
        for key in ("on", "off"):
            res[key]["file_bytes"] = paths[key].stat().st_size
        res["crc"] = crc_rate()
        if args.scale:
            import bench_master

            res["scale"] = {"on": [], "off": []}
            for k in range(args.repeats if args.scale <= 100000 else 1):
                for key in (("on", "off") if k % 2 == 0 else ("off", "on")):
                    if key == "off":
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
    med = {key: {m: float(np.median(res[key][m])) for m in ("write", "read", "verify")} for key in ("on", "off")}
    n = args.tasks
    print(f"| {n} synthetic tasks, every histogram at the default bins; medians of {args.repeats} alternated pairs "
          "| with checksums | without | ratio |")
    print("|---|---|---|---|")
    rows = [("store path, CPU per task (record, blocks, journal, close)", "write", 1e3 / n, "ms"),
            ("reading every block back, per task", "read", 1e3 / n, "ms"),
            ("campaign verify's whole scan, per task", "verify", 1e3 / n, "ms")]
    for label, m, scale, unit in rows:
        on, off = med["on"][m] * scale, med["off"][m] * scale
        print(f"| {label} | {on:.3f} {unit} | {off:.3f} {unit} | {on / off:.3f} |")
    on, off = res["on"]["file_bytes"], res["off"]["file_bytes"]
    print(f"| file size, per task | {on / n:.1f} B | {off / n:.1f} B | {on / off:.4f} |")
    for size, c in res["crc"].items():
        print(f"| crc32 of a configuration, N = {size} ({c['bytes'] / 1024:.0f} KiB) | {c['microseconds']:.1f} us "
              f"| - | - |")
    if args.scale:
        sc = res["scale"]
        keys = [("master_peak_rss_mb", "master peak RSS, MB"), ("tasks_per_second", "tasks per second, master loop"),
                ("tasks_per_master_cpu_second", "tasks per second of master CPU"), ("file_mb", "store size, MB"),
                ("status_seconds", "campaign status, s"), ("reduce_seconds", "campaign reduce, s"),
                ("verify_seconds", "campaign verify (whole scan), s"),
                ("reduce_peak_rss_mb", "campaign reduce peak RSS, MB")]
        print(f"\n| scale: {args.scale} tasks (bench_master.py), medians | with checksums | without | ratio |")
        print("|---|---|---|---|")
        for k, label in keys:
            a = float(np.median([r[k] for r in sc["on"]]))
            b = float(np.median([r[k] for r in sc["off"]]))
            print(f"| {label} | {a:,.2f} | {b:,.2f} | {a / b:.3f} |")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
