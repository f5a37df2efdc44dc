"""Memory and time of one large packing: ``kernels.jam`` then ``kernels.analyze``.

    /usr/bin/time -v taskset -c 0 python benchmarks/bench_large.py            # N = 65536, E = 1e-6
    python benchmarks/bench_large.py --n 16384 --energy 1e-8 --json large.json

One packing (``--seed``, default 0) at ``--energy`` (default 1e-6) with the default
protocol, then one analysis with every observable and the default bins. Prints a
Markdown table: wall time of each phase (the first call of each includes compiling
or loading the numba kernels: compile time is measured separately on a tiny packing
first and reported on its own line), the peak resident set size of the process
after each phase (``resource.getrusage``, the same figure ``/usr/bin/time -v``
reports as "Maximum resident set size"), the packing's status, force residual,
iterations and force evaluations, and the analysis' N_G and identity check.
``--json FILE`` writes the same figures.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import time


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MB (Linux reports kB)."""
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if sys.platform != "darwin" else kb / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=65536, help="number of disks (default 65536)")
    ap.add_argument("--energy", type=float, default=1e-6, help="target E_G (default 1e-6)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--force-tolerance", type=float, default=None,
                    help="jam's force_tolerance (default: the kernels' default)")
    ap.add_argument("--json", metavar="FILE", help="write the measurements as JSON")
    args = ap.parse_args(argv)

    import numpy as np

    import kernels

    rows = []
    t0 = time.perf_counter()
    base_rss = peak_rss_mb()
    # compile (or load from the cache) every kernel on a tiny packing first
    p = kernels.jam(64, 1e-4, 0)
    kernels.analyze(p.positions, p.radii, p.box)
    rows.append(dict(phase="compile (N = 64 jam + analyze)", seconds=time.perf_counter() - t0,
                     peak_rss_mb=peak_rss_mb()))

    settings = {}
    if args.force_tolerance is not None:
        settings["force_tolerance"] = args.force_tolerance
    t0 = time.perf_counter()
    p = kernels.jam(args.n, args.energy, args.seed, **settings)
    t_jam = time.perf_counter() - t0
    rows.append(dict(phase=f"jam N = {args.n}, E = {args.energy:g}", seconds=t_jam,
                     peak_rss_mb=peak_rss_mb(), status=p.status, energy=p.energy,
                     force_residual=p.force_residual, iterations=p.iterations,
                     force_evaluations=p.force_evaluations, phi=p.phi))

    t0 = time.perf_counter()
    a = kernels.analyze(p.positions, p.radii, p.box)
    t_an = time.perf_counter() - t0
    rows.append(dict(phase="analyze (all observables)", seconds=t_an, peak_rss_mb=peak_rss_mb(),
                     N_G=a.scalars["N_G"], identities_ok=a.scalars["identities_ok"],
                     ordered_fraction=a.scalars["ordered_fraction"]))

    print(f"| phase | wall (s) | peak RSS (MB) | notes |")
    print("|---|---:|---:|---|")
    for r in rows:
        notes = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                          for k, v in r.items() if k not in ("phase", "seconds", "peak_rss_mb"))
        print(f"| {r['phase']} | {r['seconds']:.2f} | {r['peak_rss_mb']:.0f} | {notes} |")
    print(f"\npython {platform.python_version()}, numpy {np.__version__}, "
          f"interpreter at start: {base_rss:.0f} MB")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(dict(n=args.n, energy=args.energy, seed=args.seed, rows=rows,
                           platform=platform.platform()), fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
