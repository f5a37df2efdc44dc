"""GPU workers against the CPU kernels (docs/GPU.md), side by side in one run on one machine.

1. FIRE steps: microseconds per FIRE step per packing for N_G in ``--sizes`` and batches of
   ``--batches`` packings (one thread block each): the kernel alone (arrays on the device before
   the clock), steps ``--steps`` to ``2 --steps`` of the first minimisation of random starts at
   E_G = 1e-12 (two launches bounded at ``max_search 1``, their difference: past the first steps,
   which rebuild the lists at every step; list rebuilds and the residual checks every 100 steps
   included), divided by steps x packings. The CPU kernel's step on one core
   (``kernels.fire._fire_core``, same starts, same steps) beside it, and the ratio
   (``kernels.gpu.batch.time_steps``).
2. Whole packings at ``--full`` (N_G, E_G) cells: ``--full-batch`` packings (seeds 0, 1, ...) in
   one launch, the wall time to the last one, hence packings per hour of the GPU; the CPU's
   packings per hour on all of this machine's cores from the CPU step time measured with all
   cores busy (each core minimising its own packing) and the packings' mean force evaluations
   (same protocol: equal in the mean, docs/GPU.md), and with ``--cpu-full`` also from whole CPU
   packings of the same seeds on all cores (long at N_G 8192: 3-11 minutes each).

    python benchmarks/bench_gpu.py [--sizes 1024 4096 8192] [--batches 1 32 132 264 528]
        [--steps 1000] [--full 8192:1e-12 8192:1e-15] [--full-batch 132] [--cpu-full]
        [--threads 256] [--backend auto|cuda|emulate] [--check] [--json FILE]

``--check`` first runs the kernel and its CPU emulation on the same inputs (8 packings at N_G 256,
E_G 1e-6 and at N_G 1024, E_G 1e-10; the emulation one packing per core meanwhile) and reports
how far their positions part.

docs/GPU.md has the figures of one H200 and the command (164 s with ``--sizes 1024 4096 8192
--batches 1 132 264 --steps 500 --full 4096:1e-12``; the defaults' whole packings at N_G 8192
take longer: a batch of 132 at E_G 1e-12 did not finish in 150 s there).
Without a GPU, ``--backend emulate`` runs the same block on the CPU (tiny sizes only: it shows that
the script works, not how fast a GPU is).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _gpu_batch(n, energies, seeds, backend, threads, **kw):
    from kernels.gpu import jam_batch

    t0 = time.perf_counter()
    out = jam_batch(n, energies, seeds, backend=backend, threads=threads, **kw)
    return time.perf_counter() - t0, out


def _cpu_steps(args):
    """Seconds per FIRE step of the CPU kernel on the first minimisation of a random start."""
    n, seed, steps = args
    from kernels.fire import _fire_core
    from kernels.minimiser import default_timestep
    from kernels.jamming import DEFAULTS, initial_state

    pos, rad, _ = initial_state(n, np.random.SeedSequence(seed), (1.0, 1.0), DEFAULTS["species"], 0.86)
    box = np.array([1.0, 1.0, 0.0])
    dt = default_timestep(rad, 2.0, 1e-8)
    skin = 0.3 * 2 * float(np.mean(rad))
    _fire_core(pos.copy(), rad, box, 2.0, 1e-6, 10, skin, dt, 0.0)  # compiled before the clock
    t0 = time.perf_counter()
    r = _fire_core(pos, rad, box, 2.0, 1e-6, steps, skin, dt, 0.0)
    return (time.perf_counter() - t0) / max(1, r[1])


def _warm():
    """A pool process compiles the CPU kernels before any clock starts."""
    import kernels

    kernels.jam(16, 1e-3, 0)
    _cpu_steps((16, 0, 10))


def _warm_done(_):
    return 0


def _cpu_packing(args):
    n, e, seed = args
    import kernels

    t0 = time.perf_counter()
    p = kernels.jam(n, e, seed)
    return time.perf_counter() - t0, p.force_evaluations, p.status


def _emulated(args):
    n, e, seed, threads = args
    return _gpu_batch(n, [e], [seed], "emulate", threads)[1][0]


def check_kernel(backend, threads):
    """The kernel against the emulation on the same inputs: positions to round-off (the GPU
    compiler fuses multiply-adds; the emulation does not), the same course of the search. The
    emulation runs one packing per core while the GPU runs its batches."""
    cells = ((256, 1e-6), (1024, 1e-10))
    seeds = list(range(8))
    jobs = [(n, e, s, threads) for n, e in cells for s in seeds]
    with mp.get_context("spawn").Pool(min(len(jobs), os.cpu_count() or 1)) as pool:
        pending = pool.map_async(_emulated, jobs)
        gpus = []
        for n, e in cells:
            wall, got = _gpu_batch(n, [e] * len(seeds), seeds, backend, threads)
            gpus.append(got)
            print(f"  the kernel: {len(seeds)} packings at N_G {n}, E_G {e:g} in {wall:.1f} s (the first "
                  "launch compiles)", flush=True)
        emus = pending.get()
    rows = []
    for k, (n, e) in enumerate(cells):
        for s, g, m in zip(seeds, gpus[k], emus[k * len(seeds):(k + 1) * len(seeds)]):
            d = float(np.max(np.abs(((g.positions - m.positions) + 0.5) % 1.0 - 0.5)))
            rows.append({"N": n, "E": e, "seed": s, "max_position_difference": d,
                         "gpu_status": g.status, "emulation_status": m.status,
                         "gpu_force_evaluations": g.force_evaluations,
                         "emulation_force_evaluations": m.force_evaluations,
                         "gpu_energy": g.energy, "emulation_energy": m.energy,
                         "bitwise_equal": g.positions.tobytes() == m.positions.tobytes()})
        same = [r for r in rows if r["N"] == n]
        print(f"  N_G {n} E_G {e:g}: {sum(r['bitwise_equal'] for r in same)}/8 bitwise equal, largest position "
              f"difference {max(r['max_position_difference'] for r in same):.2e}, force evaluations equal in "
              f"{sum(r['gpu_force_evaluations'] == r['emulation_force_evaluations'] for r in same)}/8", flush=True)
    return rows


def step_table(sizes, batches, steps, backend, threads):
    from kernels.gpu.batch import time_steps

    rows = []
    for n in sizes:
        for b in batches:
            gpu, cpu = time_steps(n, b, steps, backend, threads)
            rows.append({"N": n, "batch": b, "us_per_step_per_packing": 1e6 * gpu, "cpu_us_per_step": 1e6 * cpu,
                         "cores_per_gpu": cpu / gpu})
            print(f"  N_G {n:6d}  batch {b:4d}  {1e6 * gpu:9.2f} us/step/packing   CPU core {1e6 * cpu:9.1f} us/step"
                  f"   ratio {cpu / gpu:7.1f}", flush=True)
    return rows


def full_table(cells, batch, backend, threads, cpu_full):
    rows = []
    cores = os.cpu_count() or 1
    for n, e in cells:
        seeds = list(range(batch))
        wall, out = _gpu_batch(n, [e] * batch, seeds, backend, threads)
        ok = [p for p in out if not isinstance(p, Exception) and p.status == "converged"]
        evals = float(np.mean([p.force_evaluations for p in ok])) if ok else float("nan")
        with mp.get_context("spawn").Pool(cores, initializer=_warm) as pool:
            per_step = float(np.median(pool.map(_cpu_steps, [(n, s, 1000) for s in range(cores)])))
        cpu_hour = cores * 3600.0 / (evals * per_step)
        row = {"N": n, "E": e, "batch": batch, "gpu_wall_s": wall, "converged": len(ok),
               "gpu_packings_per_hour": 3600.0 * len(ok) / wall, "mean_force_evaluations": evals,
               "cpu_cores": cores, "cpu_us_per_step_all_cores": 1e6 * per_step,
               "cpu_packings_per_hour_from_steps": cpu_hour}
        if cpu_full:
            with mp.get_context("spawn").Pool(cores, initializer=_warm) as pool:
                pool.map(_warm_done, range(cores))
                t0 = time.perf_counter()
                got = pool.map(_cpu_packing, [(n, e, s) for s in seeds[:cores]])
            row["cpu_packings_per_hour_measured"] = 3600.0 * len(got) / (time.perf_counter() - t0)
            row["cpu_mean_force_evaluations"] = float(np.mean([g[1] for g in got]))
        row["gpu_over_cpu_cores"] = row["gpu_packings_per_hour"] / (cpu_hour / cores)
        rows.append(row)
        print(f"  N_G {n} E_G {e:g}: GPU {row['gpu_packings_per_hour']:.0f} packings/h ({len(ok)}/{batch} "
              f"converged in {wall:.0f} s, {evals:.3g} force evaluations each); CPU {cores} cores "
              f"{cpu_hour:.1f} packings/h from {1e6 * per_step:.0f} us/step"
              + (f", measured {row['cpu_packings_per_hour_measured']:.1f}" if cpu_full else "")
              + f"; one GPU = {row['gpu_over_cpu_cores']:.0f} CPU cores", flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[1024, 4096, 8192])
    ap.add_argument("--batches", type=int, nargs="*", default=[1, 32, 132, 264, 528])
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--full", nargs="*", default=["8192:1e-12", "8192:1e-15"], metavar="N:E")
    ap.add_argument("--full-batch", type=int, default=132)
    ap.add_argument("--cpu-full", action="store_true")
    ap.add_argument("--threads", type=int, default=256)
    ap.add_argument("--backend", default="auto", choices=("auto", "cuda", "emulate"))
    ap.add_argument("--check", action="store_true",
                    help="first compare the kernel with the emulation on the same inputs (N_G 256, 1024)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    from kernels.gpu import describe, resolve_backend

    backend = resolve_backend(a.backend)
    device = describe(backend)
    print(f"bench_gpu: {device}, {a.threads} threads per block; CPU: {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores", flush=True)
    t0 = time.perf_counter()
    check = []
    if a.check:
        print("the kernel against its CPU emulation, same inputs:", flush=True)
        check = check_kernel(backend, a.threads)
    print(f"FIRE steps (the kernel alone, steps {a.steps}-{2 * a.steps} of the first minimisation from random "
          "starts at E_G 1e-12):", flush=True)
    steps = step_table(a.sizes, a.batches, a.steps, backend, a.threads)
    cells = [(int(c.split(":")[0]), float(c.split(":")[1])) for c in a.full]
    print("whole packings:", flush=True)
    full = full_table(cells, a.full_batch, backend, a.threads, a.cpu_full)
    print(f"bench_gpu: {time.perf_counter() - t0:.0f} s", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps({"device": device, "threads": a.threads, "cpu_cores": os.cpu_count(),
                                            "check": check, "steps": steps, "full": full}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
