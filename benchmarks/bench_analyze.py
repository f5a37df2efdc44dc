"""Cost of ``kernels.analyze`` per packing: scalars only, each observable, everything.

    python benchmarks/bench_analyze.py                       # N = 1024, 8192, 32768
    python benchmarks/bench_analyze.py --sizes 1024 --json out.json
    python benchmarks/bench_analyze.py --sizes 1024 8192 --source jam --response-only   # moduli, modes, gaps

The linear-response observables (``moduli``, ``modes``, ``gaps``: kernels.response) get a table
of their own: scalars plus each, median and minimum over ``--repeats`` calls (``modes``: over
``--mode-repeats``), with the method ``modes`` used (the dense spectrum up to
``kernels.response.DENSE_MODES_MAX`` non-rattlers, shift-invert beyond); ``--dense-sizes``
adds packings measured for ``modes`` only (default: 2048, the largest dense size).

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
    ap.add_argument("--mode-repeats", type=int, default=3, help="calls timed for modes (default 3)")
    ap.add_argument("--dense-sizes", type=int, nargs="*", default=[2048],
                    help="extra sizes measured for modes only (default: 2048, the largest dense one)")
    ap.add_argument("--response-only", action="store_true",
                    help="only the linear-response table (moduli, modes, gaps)")
    args = ap.parse_args(argv)

    from kernels.analysis import analyze
    from kernels.names import DEFAULT_OBSERVABLES, RESPONSE_OBSERVABLES

    singles = [name for name in DEFAULT_OBSERVABLES if name != "scalars"]
    rows = []
    t0 = time.perf_counter()
    pos, rad, box = make_packing(64, 0, "fire", 0.9, 0)
    analyze(pos, rad, box)
    first_call = time.perf_counter() - t0
    t0 = time.perf_counter()
    analyze(pos, rad, box, list(RESPONSE_OBSERVABLES))
    first_response = time.perf_counter() - t0
    response_rows = []
    for n in sorted(set(args.sizes) | set(args.dense_sizes)):
        pos, rad, box = load_packing(n, args.seed, args)
        base = analyze(pos, rad, box, ["scalars"])
        row = dict(N=n, N_G=base.scalars["N_G"], z_g_mean=base.scalars["z_g_mean"], E_G=base.scalars["E_G"])
        reps = {}
        if n in args.sizes:
            reps["scalars"] = args.repeats
            reps["moduli"] = args.repeats
            reps["gaps"] = args.repeats
        reps["modes"] = args.mode_repeats
        for name, r in reps.items():
            obs = ["scalars"] if name == "scalars" else ["scalars", name]
            row[f"{name}_ms"] = [1e3 * t for t in timed(lambda obs=obs: analyze(pos, rad, box, obs), r)]
        res = analyze(pos, rad, box, ["scalars", "moduli", "modes"])
        row.update(modes_dense=bool(res.scalars["modes_dense"]), n_modes=res.scalars["n_modes"],
                   moduli_ok=bool(res.scalars["moduli_ok"]), G=res.scalars["G"], B=res.scalars["B"])
        response_rows.append(row)
        print(f"N = {n}: response measured", file=sys.stderr, flush=True)
    if args.response_only:
        args.sizes = []
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

    if rows:
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
    print(f"\nlinear response (kernels.response), scalars plus one observable, ms, median / min of "
          f"{args.repeats} calls ({args.mode_repeats} for modes); first call incl. loading/compiling: "
          f"{first_response:.1f} s\n")
    print("| N | N_G | scalars | + moduli | + gaps | + modes | modes method |")
    print("|---:|---:|---:|---:|---:|---:|---|")

    def cell(r, name):
        return f"{r[name + '_ms'][1]:.2f} / {r[name + '_ms'][0]:.2f}" if name + "_ms" in r else "-"

    for r in response_rows:
        method = "dense" if r["modes_dense"] else f"shift-invert, lowest {r['n_modes']}"
        print(f"| {r['N']} | {r['N_G']} | {cell(r, 'scalars')} | {cell(r, 'moduli')} | {cell(r, 'gaps')} "
              f"| {cell(r, 'modes')} | {method} |")
    if args.json:
        meta = dict(python=platform.python_version(), machine=platform.machine(), processor=platform.processor(),
                    cpus=os.cpu_count(), numpy=np.__version__, first_call_seconds=first_call,
                    source=args.source, phi=args.phi, energy=args.energy, repeats=args.repeats)
        try:
            import numba

            meta["numba"] = numba.__version__
        except ImportError:  # pragma: no cover
            pass
        meta["first_response_call_seconds"] = first_response
        with open(args.json, "w") as fh:
            json.dump(dict(meta=meta, rows=rows, response=response_rows), fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
