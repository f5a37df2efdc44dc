"""Cost of ``campaign reduce`` on a synthetic campaign file.

    python benchmarks/bench_reduce.py                      # 100 000 packings, 1000 resamples
    python benchmarks/bench_reduce.py --packings 10000 --json out.json

The file (tests/synthetic_store.py: 5 sizes x 13 energies, every histogram of
docs/CONTRACTS.md with about 1450 bins per packing in all) is written to a
temporary directory first; its writing is not timed. The reduction is timed
end to end as the command runs it: reading, cell statistics, the histogram pass
with the self-averaging moments, bootstrap fits and extrapolation, and writing
the tables and the reduced HDF5 file. Target: at most 30 s for 100 000 packings.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from synthetic_store import SyntheticCampaign, write_store  # noqa: E402

from campaign.results import reduce as R  # noqa: E402
from campaign.report.writing import write_outputs  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--packings", type=int, default=100_000)
    ap.add_argument("--boot", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=1, help="timed reductions (best is reported)")
    ap.add_argument("--no-histograms", action="store_true",
                    help="a file with scalars only (isolates the fits' cost)")
    ap.add_argument("--keep", metavar="FILE", help="write the synthetic file here and keep it")
    ap.add_argument("--json", metavar="FILE", help="write the results as JSON")
    a = ap.parse_args(argv)

    N = (64, 128, 256, 512, 1024)
    E = tuple(10.0 ** -np.arange(3, 16))
    seeds = max(2, int(np.ceil(a.packings / (len(N) * len(E)))))
    camp = SyntheticCampaign(N=N, E=E, seeds=seeds,
                             histograms=() if a.no_histograms else SyntheticCampaign().histograms)
    tmp = None
    if a.keep:
        path = Path(a.keep)
    else:
        tmp = tempfile.TemporaryDirectory()
        path = Path(tmp.name) / "bench.h5"
    t0 = time.perf_counter()
    write_store(path, camp)
    t_write = time.perf_counter() - t0
    size = os.path.getsize(path)
    out = path.with_name(path.stem + "_reduced")
    times, red = [], None
    for _ in range(a.repeat):
        t0 = time.perf_counter()
        red = R.reduce_campaign(path, R.Settings(n_boot=a.boot))
        write_outputs(red, out)
        times.append(time.perf_counter() - t0)
    res = {
        "packings": camp.n_tasks, "cells": len(N) * len(E), "bootstrap": a.boot,
        "histogram_bins": int(sum(len(v["edges"]) - 1 for k, v in red.distributions.items()
                                  if k != "sin_theta")),
        "file_MB": round(size / 1e6, 1), "write_file_s": round(t_write, 2),
        "reduce_s": round(min(times), 2),
        "of_which_histograms_s": round(red.meta["seconds"]["histograms"], 2),
        "of_which_load_s": round(red.meta["seconds"]["load"], 2),
        "target_s": 30.0, "python": platform.python_version(), "machine": platform.machine(),
        "cpus": os.cpu_count(),
    }
    rows = [("packings", res["packings"]), ("(N, E) cells", res["cells"]),
            ("bootstrap resamples", res["bootstrap"]), ("histogram bins / packing",
                                                        res["histogram_bins"]),
            ("file size (MB)", res["file_MB"]), ("reduce, end to end (s)", res["reduce_s"]),
            ("  histogram pass (s)", res["of_which_histograms_s"]),
            ("  reading tasks and scalars (s)", res["of_which_load_s"]),
            ("target (s)", res["target_s"])]
    w = max(len(k) for k, _ in rows)
    print("| quantity" + " " * (w - 8) + " | value |")
    print("|" + "-" * (w + 2) + "|-------|")
    for k, v in rows:
        print(f"| {k:<{w}} | {v} |")
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1) + "\n")
    if tmp:
        tmp.cleanup()
    return 0 if res["reduce_s"] <= res["target_s"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
