"""GPU workers against the CPU kernels and a lean FIRE kernel (docs/GPU.md), side by side in one
run on one machine: where a GPU packing's time goes.

1. ``--check``: the kernel and its CPU emulation on the same inputs (8 packings at N_G 256, E_G
   1e-6 and 8 at N_G 1024, 1e-10; the emulation one packing per core meanwhile): how many end
   with the same bits; and a search stopped every 2000 steps and resumed on the GPU against
   the same search uninterrupted (N_G 256).
2. FIRE steps, per N_G (``--sizes``), threads per block (``--threads``) and packings resident
   (``--batches``): the kernel alone (arrays on the device before the clock), the steps
   ``--steps`` to ``2 --steps`` of the first minimisation of random starts at E_G 1e-12 (two
   launches bounded there, their difference: past the first steps, which rebuild the lists at
   every step), in microseconds per step per packing and per *block step* (the time one
   resident block takes for one step: per packing times the packings resident at once), with
   the kernel's registers per thread, spills and the blocks an SM holds; a CPU core's step on
   the same starts beside it (``kernels.gpu.batch.time_steps``). ``--jammed FILE.npz`` (arrays
   ``x``, ``rad``: a jammed packing in the unit box) times the same steps from that packing,
   each copy perturbed by 0.05 of the smallest radius (the lean kernel's workload: lists
   rebuilt rarely).
3. ``--cell N:E``: a whole cell of ``--cell-batch`` packings (seeds 0, 1, ...) in one launch,
   most expensive first: the wall to the last packing, packings per hour, and the GPU's busy
   fraction from the packings' device clocks (block-seconds over resident slots x the span
   from the first block's start to the last one's end).
4. ``--full N:E``: whole packings per hour of the GPU against the host's cores (the CPU's from
   its step time with all cores busy and the packings' mean force evaluations, or measured
   with ``--cpu-full``): how many cores one GPU is worth.
5. ``--campaign SPEC``: ``campaign run SPEC --gpus 1`` (a spec with ``device: gpu`` tasks) into a
   fresh store: wall, packings per hour and the busy fraction (``campaign status --json``).
6. ``--baseline PATH``: the lean FIRE kernel (``lean_fire.py``: FIRE steps only, harmonic, fixed
   rows of 16 slots) at the same N_G and batches in the same run, as the yardstick.

    python benchmarks/bench_gpu.py [--sizes 1024 4096 8192 16384] [--threads 256 512 1024]
        [--batches 1 132 264] [--registers 64 128] [--steps 500] [--jammed big_8192.npz] [--cell 8192:1e-9]
        [--cell-batch 264] [--full 8192:1e-9] [--cpu-full] [--campaign SPEC]
        [--baseline lean_fire.py] [--check] [--backend auto|cuda|emulate] [--json FILE]

``--json`` writes ``device`` (``cuda:<name>``), ``steps`` rows (``N``, ``batch``, ``threads``,
``us_per_step_per_packing``, ``us_per_block_step``, ``registers``, ``blocks_per_sm`` ...), the
``cells``, ``full``, ``campaign`` (``spec``, ``wall_s``, ``packings``, ``busy_fraction``) and
``baseline`` records. Without a GPU, ``--backend emulate`` runs the same block on the CPU (tiny
sizes only: it shows that the script works, not how fast a GPU is). The figures of a GPU and
the command that made them: docs/GPU.md.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import re
import subprocess
import sys
import tempfile
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
    n, e, seed, threads, budget = args
    if budget is None:
        return _gpu_batch(n, [e], [seed], "emulate", threads)[1][0]
    return _resumed(n, e, seed, "emulate", threads, budget)


def _resumed(n, e, seed, backend, threads, budget):
    """A search stopped every ``budget`` FIRE steps and resumed until it ends."""
    from kernels.gpu import Suspended

    back = None
    while True:
        got = _gpu_batch(n, [e], [seed], backend, threads, budget=budget, resume=[back])[1][0]
        if not isinstance(got, Suspended):
            return got
        back = got


def _same(a, b):
    return a.positions.tobytes() == b.positions.tobytes() and a.force_evaluations == b.force_evaluations


def check_kernel(backend, threads):
    """The kernel against the emulation on the same inputs, and a resumed search against an
    uninterrupted one on the GPU. The emulation runs one packing per core meanwhile."""
    cells = ((256, 1e-6), (1024, 1e-10))
    seeds = list(range(8))
    jobs = [(n, e, s, threads, None) for n, e in cells for s in seeds]
    with mp.get_context("spawn").Pool(min(len(jobs), os.cpu_count() or 1)) as pool:
        pending = pool.map_async(_emulated, jobs)
        gpus = []
        for n, e in cells:
            wall, got = _gpu_batch(n, [e] * len(seeds), seeds, backend, threads)
            gpus.append(got)
            print(f"  the kernel: {len(seeds)} packings at N_G {n}, E_G {e:g} in {wall:.1f} s (the first "
                  "launch compiles)", flush=True)
        t0 = time.time()
        whole = _gpu_batch(256, [1e-6], [0], backend, threads)[1][0]
        t1 = time.time()
        part = _resumed(256, 1e-6, 0, backend, threads, 2000)
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
    clock = whole.settings["device_clock"]
    resumed = {"N": 256, "E": 1e-6, "budget": 2000, "launches": part.settings["device_clock"]["launches"],
               "bitwise_equal": _same(whole, part),
               # the store's busy fraction takes the device clock for epoch seconds: is it?
               "device_clock_in_host_window": bool(t0 - 1.0 <= clock["start"] <= clock["end"] <= t1 + 1.0),
               "device_start_minus_host_start_s": clock["start"] - t0}
    print(f"  stop and go on the GPU (N_G 256, every 2000 steps, {resumed['launches']} launches): "
          f"{'the same bits' if resumed['bitwise_equal'] else 'OTHER BITS'} as uninterrupted; the device clock "
          f"{'reads' if resumed['device_clock_in_host_window'] else 'does NOT read'} epoch seconds (start - host "
          f"{resumed['device_start_minus_host_start_s']:+.3f} s)", flush=True)
    return {"packings": rows, "resumed": resumed}


def _jammed_starts(path, batch):
    """``batch`` copies of a jammed packing, each perturbed by 0.05 of the smallest radius."""
    d = np.load(path)
    x, rad = np.asarray(d["x"], float) % 1.0, np.asarray(d["rad"], float)
    rng = np.random.default_rng(1)
    species = (rad < rad.mean()).astype(np.int32)
    return len(rad), [((x + 0.05 * rad.min() * rng.standard_normal(x.shape)) % 1.0, rad, species)
                      for _ in range(batch)]


def step_table(sizes, threads, batches, steps, backend, jammed, bounds):
    from kernels.gpu.batch import time_steps

    rows = []
    plans = [(n, None) for n in sizes] + ([("jammed", jammed)] if jammed else [])
    for size, path in plans:
        for nt, regs, b in ((nt, regs, b) for nt in threads for regs in bounds for b in batches):
            n, starts = (size, None) if path is None else _jammed_starts(path, b)
            first = nt == threads[0] and regs == bounds[0] and b == batches[0]
            r = time_steps(n, b, steps, backend, nt, starts=starts, cpu=first, registers=regs)
            occ = r["occupancy"]
            row = {"N": n, "start": "jammed" if starts else "random", "batch": b, "threads": nt,
                   "max_registers": regs, "us_per_step_per_packing": 1e6 * r["gpu"],
                   "us_per_block_step": 1e6 * r["block_step"], "cpu_us_per_step": 1e6 * r["cpu"], **occ}
            rows.append(row)
            print(f"  N_G {n:6d} {row['start']:7s} {nt:5d} thr {regs:4d} regs  batch {b:4d}  "
                  f"{row['us_per_step_per_packing']:9.3f} us/step/packing  {row['us_per_block_step']:8.1f} us/block "
                  f"step  {occ['registers']:3d} regs {occ['local_bytes']:4d} B local  {occ['blocks_per_sm']} blocks/SM"
                  + (f"   CPU core {row['cpu_us_per_step']:8.1f} us/step" if np.isfinite(r["cpu"]) else ""),
                  flush=True)
    return rows


def busy(packings, slots):
    """The GPU's busy fraction over ``packings`` (their device clocks): block-seconds over
    ``slots`` x the span from the first start to the last end."""
    clocks = [p.settings["device_clock"] for p in packings]
    span = max(c["end"] for c in clocks) - min(c["start"] for c in clocks)
    return sum(c["seconds"] for c in clocks) / (slots * span), span


def cell_table(cells, batch, backend, threads):
    from kernels.gpu.batch import finish_batch, occupancy, start_batch

    rows = []
    for n, e in cells:
        t0 = time.perf_counter()
        handle = start_batch(n, [e] * batch, list(range(batch)), backend=backend, threads=threads)
        out = finish_batch(handle)
        wall = time.perf_counter() - t0
        occ = occupancy(handle)
        ok = [p for p in out if not isinstance(p, Exception) and p.status == "converged"]
        frac, span = busy([p for p in out if not isinstance(p, Exception)], occ["slots"])
        secs = [p.settings["device_clock"]["seconds"] for p in ok]
        row = {"N": n, "E": e, "batch": batch, "threads": threads, "wall_s": wall, "span_s": span,
               "converged": len(ok), "packings_per_hour": 3600.0 * len(ok) / wall, "busy_fraction": frac,
               "slots": occ["slots"], "packing_seconds_mean": float(np.mean(secs)) if secs else float("nan"),
               "packing_seconds_max": float(np.max(secs)) if secs else float("nan")}
        rows.append(row)
        print(f"  cell N_G {n} E_G {e:g}: {len(ok)}/{batch} converged in {wall:.0f} s, "
              f"{row['packings_per_hour']:.0f} packings/h, busy {frac:.1%} of {occ['slots']} slots, "
              f"packings {row['packing_seconds_mean']:.1f} s on average, slowest {row['packing_seconds_max']:.1f} s",
              flush=True)
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


def run_campaign(spec, extra):
    """``campaign run SPEC --gpus 1`` into a fresh store; wall, packings and busy fraction."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "c.h5"
        cmd = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--gpus", "1", "--quiet",
               *extra]
        t0 = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            print(r.stderr[-3000:], file=sys.stderr)
            return {"spec": str(spec), "wall_s": wall, "returncode": r.returncode}
        st = subprocess.run([sys.executable, "-m", "campaign", "status", str(out), "--json"],
                            capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
        info = json.loads(st.stdout) if st.returncode == 0 else {}
    done = int(info.get("done") or 0)
    fracs = [d.get("busy_fraction") for d in (info.get("gpu_busy") or {}).values()]
    row = {"spec": str(spec), "wall_s": wall, "packings": done, "packings_per_hour": 3600.0 * done / wall,
           "busy_fraction": fracs[0] if fracs else None, "gpu_busy": info.get("gpu_busy")}
    print(f"  campaign {spec}: {done} packings in {wall:.0f} s ({row['packings_per_hour']:.0f}/h), busy "
          f"fraction {row['busy_fraction']}", flush=True)
    return row


def run_baseline(path, sizes, batches, threads, jammed):
    """The lean FIRE kernel at the same sizes (from a jammed packing where given) and batches."""
    rows = []
    for nt in threads:
        src = [str(jammed)] if jammed else [str(n) for n in sizes]
        for s in src:
            r = subprocess.run([sys.executable, str(path), s, *map(str, batches), "--steps", "2000", "--tpb", str(nt)],
                               capture_output=True, text=True)
            for ln in r.stdout.splitlines():
                m = re.search(r"N=(\d+) B=(\d+) TPB=(\d+).*?([\d.]+) us per batch step, ([\d.]+) us per packing-step", ln)
                if m:
                    rows.append({"N": int(m.group(1)), "batch": int(m.group(2)), "threads": int(m.group(3)),
                                 "us_per_block_step": float(m.group(4)), "us_per_step_per_packing": float(m.group(5))})
                    print(f"  lean FIRE N {m.group(1)} B {m.group(2)} TPB {m.group(3)}: {m.group(4)} us per batch step, "
                          f"{m.group(5)} us per packing-step", flush=True)
            if r.returncode != 0:
                print(r.stderr[-2000:], file=sys.stderr)
    return rows


def _cells(items):
    return [(int(c.split(":")[0]), float(c.split(":")[1])) for c in items]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[1024, 4096, 8192, 16384])
    ap.add_argument("--threads", type=int, nargs="*", default=[256, 512, 1024])
    ap.add_argument("--batches", type=int, nargs="*", default=[1, 132, 264])
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--registers", type=int, nargs="*", default=[64, 128],
                    help="bounds on the kernel's registers per thread to time (never changes results)")
    ap.add_argument("--jammed", default=None, metavar="FILE.npz")
    ap.add_argument("--cell", nargs="*", default=[], metavar="N:E")
    ap.add_argument("--cell-batch", type=int, default=264)
    ap.add_argument("--full", nargs="*", default=[], metavar="N:E")
    ap.add_argument("--full-batch", type=int, default=132)
    ap.add_argument("--cpu-full", action="store_true")
    ap.add_argument("--campaign", default=None, metavar="SPEC")
    ap.add_argument("--campaign-args", nargs="*", default=[])
    ap.add_argument("--baseline", default=None, metavar="lean_fire.py")
    ap.add_argument("--backend", default="auto", choices=("auto", "cuda", "emulate"))
    ap.add_argument("--check", action="store_true",
                    help="first compare the kernel with the emulation on the same inputs (N_G 256, 1024)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    from kernels.gpu import describe, resolve_backend

    backend = resolve_backend(a.backend)
    device = describe(backend)
    print(f"bench_gpu: {device}; CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores",
          flush=True)
    t0 = time.perf_counter()
    record = {"device": device, "cpu_cores": os.cpu_count()}

    def save():
        if a.json:
            Path(a.json).write_text(json.dumps(record, indent=1, default=float))

    if a.check:
        print("the kernel against its CPU emulation, same inputs:", flush=True)
        record["check"] = check_kernel(backend, a.threads[0])
        save()
    if a.baseline:
        print("the lean FIRE kernel (the yardstick):", flush=True)
        record["baseline"] = run_baseline(a.baseline, a.sizes, a.batches, a.threads, a.jammed)
        save()
    if a.sizes or a.jammed:
        print(f"FIRE steps (the kernel alone, steps {a.steps}-{2 * a.steps} of the first minimisation):", flush=True)
        record["steps"] = step_table(a.sizes, a.threads, a.batches, a.steps, backend, a.jammed, a.registers)
        save()
    if a.cell:
        print("whole cells (one launch, most expensive first):", flush=True)
        record["cells"] = cell_table(_cells(a.cell), a.cell_batch, backend, a.threads[0])
        save()
    if a.full:
        print("whole packings against the host's cores:", flush=True)
        record["full"] = full_table(_cells(a.full), a.full_batch, backend, a.threads[0], a.cpu_full)
        save()
    if a.campaign:
        print("a campaign with --gpus 1:", flush=True)
        record["campaign"] = run_campaign(a.campaign, a.campaign_args)
        save()
    print(f"bench_gpu: {time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
