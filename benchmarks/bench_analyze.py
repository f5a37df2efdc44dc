"""Cost of ``kernels.analyze`` per packing: scalars only, each observable, everything.

    python benchmarks/bench_analyze.py                       # N = 1024, 8192, 32768
    python benchmarks/bench_analyze.py --sizes 1024 --json out.json

Packings: by default FIRE-minimised bidisperse disks (ratio 1.4) at fixed packing
fraction ``--phi`` (0.85: just above jamming, <z_g> about 4.4, like the paper's
higher energies), which takes seconds; ``--source jam`` uses ``kernels.jam`` at
``--energy`` instead (minutes for N = 8192). ``--cache DIR`` keeps the packings as
.npz between runs. Times are wall-clock after compilation (the first call, which
includes loading or compiling the numba kernels, is reported separately): the
minimum and the median over ``--repeats`` calls, default bins.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import numpy as np


def make_packing(n, seed, source, phi, energy):
    if source == "jam":
        import kernels

        p = kernels.jam(n, energy, seed)
        return p.positions, p.radii, p.box
    from kernels.fire import minimize

    rng = np.random.default_rng([n, seed])
    rel = np.r_[np.full(n // 2, 1.4), np.ones(n - n // 2)]
    rad = rel * np.sqrt(phi / (np.pi * np.sum(rel**2)))
    box = np.ones(2)
    res = minimize(rng.random((n, 2)), rad, box, force_tolerance=1e-6, max_steps=2_000_000)
    return res.positions, rad, box


def load_packing(n, seed, args):
    if args.cache:
        tag = f"{args.source}_{n}_{seed}_" + (f"{args.energy:g}" if args.source == "jam" else f"{args.phi:g}")
        path = os.path.join(args.cache, f"packing_{tag}.npz")
        if os.path.exists(path):
            with np.load(path) as d:
                return d["positions"], d["radii"], d["box"]
    pos, rad, box = make_packing(n, seed, args.source, args.phi, args.energy)
    if args.cache:
        os.makedirs(args.cache, exist_ok=True)
        np.savez(path, positions=pos, radii=rad, box=box)
    return pos, rad, box


def timed(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), statistics.median(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 8192, 32768])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--source", choices=("fire", "jam"), default="fire")
    ap.add_argument("--phi", type=float, default=0.85)
    ap.add_argument("--energy", type=float, default=1e-6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", default=None, help="directory to keep packings in (.npz)")
    ap.add_argument("--json", default=None, metavar="FILE", help="also write the results as JSON")
    args = ap.parse_args(argv)

    from kernels.analysis import analyze
    from kernels.observables import OBSERVABLES

    singles = [name for name in OBSERVABLES if name != "scalars"]
    rows = []
    t0 = time.perf_counter()
    pos, rad, box = make_packing(64, 0, "fire", 0.9, 0)
    analyze(pos, rad, box)
    first_call = time.perf_counter() - t0
    for n in args.sizes:
        t0 = time.perf_counter()
        pos, rad, box = load_packing(n, args.seed, args)
        made = time.perf_counter() - t0
        res = analyze(pos, rad, box)
        row = dict(N=n, N_G=res.scalars["N_G"], N_C=res.scalars["N_C"], N_V=res.scalars["N_V"],
                   z_g_mean=res.scalars["z_g_mean"], E_G=res.scalars["E_G"],
                   identities_ok=res.scalars["identities_ok"], packing_seconds=made)
        row["scalars_ms"] = [1e3 * t for t in timed(lambda: analyze(pos, rad, box, ["scalars"]), args.repeats)]
        row["all_ms"] = [1e3 * t for t in timed(lambda: analyze(pos, rad, box), args.repeats)]
        row["each_ms"] = {
            name: 1e3 * timed(lambda name=name: analyze(pos, rad, box, [name]), args.repeats)[0]
            for name in singles
        }
        rows.append(row)
        print(f"N = {n}: packing in {made:.1f} s, analysed", file=sys.stderr, flush=True)

    print(f"\nkernels.analyze, cost per packing after compilation (first call incl. loading/compiling: "
          f"{first_call:.1f} s); min / median of {args.repeats} calls, default bins\n")
    print("| N | N_G | <z_g> | scalars only (ms) | all observables (ms) |")
    print("|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['N']} | {r['N_G']} | {r['z_g_mean']:.3f} | {r['scalars_ms'][0]:.2f} / {r['scalars_ms'][1]:.2f} "
              f"| {r['all_ms'][0]:.2f} / {r['all_ms'][1]:.2f} |")
    print("\nscalars plus one observable (ms, min):\n")
    print("| observable | " + " | ".join(f"N = {r['N']}" for r in rows) + " |")
    print("|---|" + "---:|" * len(rows))
    for name in singles:
        print(f"| {name} | " + " | ".join(f"{r['each_ms'][name]:.2f}" for r in rows) + " |")
    if args.json:
        meta = dict(python=platform.python_version(), machine=platform.machine(), processor=platform.processor(),
                    cpus=os.cpu_count(), numpy=np.__version__, first_call_seconds=first_call,
                    source=args.source, phi=args.phi, energy=args.energy, repeats=args.repeats)
        try:
            import numba

            meta["numba"] = numba.__version__
        except ImportError:  # pragma: no cover
            pass
        with open(args.json, "w") as fh:
            json.dump(dict(meta=meta, rows=rows), fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
