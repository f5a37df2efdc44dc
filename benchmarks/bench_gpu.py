"""GPU workers against the CPU kernels and a lean FIRE kernel (docs/GPU.md), side by side in one
run on one machine: where a GPU packing's time goes.

1. ``--check``: the kernel and its CPU emulation on the same inputs (``--check-seeds`` packings
   per ``--check-cells`` cell; default 8 at N_G 256, E_G 1e-6 and 8 at N_G 1024, 1e-10; the
   emulation one packing per core meanwhile): how many end with the same bits; and the first
   cell's first packing stopped every ``--check-budget`` steps (default 2000) and resumed on the
   GPU against the same packing uninterrupted.
2. FIRE steps, per N_G (``--sizes``), threads per block (``--threads``), bound on the registers
   per thread (``--registers``) and packings resident (``--batches``): the kernel alone (arrays
   on the device before the clock), the steps ``--steps`` to ``2 --steps`` of the first
   minimisation of random starts at E_G 1e-12 (two launches bounded there, their difference:
   past the first steps, which rebuild the lists at every step), in microseconds per step per
   packing and per *block step* (the time one resident block takes for one step: per packing
   times the packings resident at once), with the kernel's registers per thread, spills and the
   blocks an SM holds; a CPU core's step on the same starts beside it
   (``kernels.gpu.batch.time_steps``). Each threads x registers kernel is compiled once (a bound
   that comes to the same kernel as an earlier one, 128 registers at 1024 threads, is left out)
   and timed at every batch. The defaults are the question the targets ask (docs/GPU.md): N_G
   8192 at 512 and 1024 threads, 64 and 128 registers, a block alone and 132 and 264 packings
   (one and two blocks per SM of an H100 or H200). ``--jammed FILE.npz`` (arrays ``x``,
   ``rad``: a jammed packing in the unit box) times the same steps from that packing, each copy
   perturbed by 0.05 of the smallest radius (the lean kernel's workload: lists rebuilt rarely).
3. ``--cell N:E``: a whole cell of ``--cell-batch`` packings (seeds 0, 1, ...) in one launch,
   most expensive first: the wall to the last packing, packings per hour, and the GPU's busy
   fraction from the packings' device clocks (block-seconds over resident slots x the span
   from the first block's start to the last one's end).
4. ``--full N:E``: whole packings per hour of the GPU against the host's cores (the CPU's from
   its step time with all cores busy and the packings' mean force evaluations, or measured
   with ``--cpu-full``): how many cores one GPU is worth.
5. ``--campaign SPEC``: ``campaign run SPEC --gpus 1`` (a spec with ``device: gpu`` tasks) into
   ``--campaign-store`` (default: a fresh store in a temporary folder), with ``--time-limit``,
   ``--margin`` and ``--grace`` passed on (stop and go: a run that reaches its limit keeps its
   suspended packings in the store and exits 0; the same command on the same store goes on from
   them) and ``--backend`` as the GPU worker's (``CAMPAIGN_GPU_BACKEND``, unless ``auto``):
   wall, packings per hour, the busy fraction (``campaign status --json``) and the lower bound
   on the device's time for the store's finished packings; its progress every
   ``--campaign-poll`` seconds.
6. ``--baseline PATH``: the lean FIRE kernel (``lean_fire.py``: FIRE steps only, harmonic, fixed
   rows of 16 slots) at the same N_G and batches in the same run, as the yardstick, at
   ``--baseline-threads`` (default 512).

    python benchmarks/bench_gpu.py [--sizes 8192] [--threads 512 1024] [--registers 64 128]
        [--batches 1 132 264] [--steps 500] [--jammed big_8192.npz] [--cell 8192:1e-9]
        [--cell-batch 264] [--full 8192:1e-9] [--cpu-full] [--campaign SPEC]
        [--campaign-store FILE] [--time-limit T] [--margin S] [--grace S] [--baseline lean_fire.py]
        [--baseline-threads 512] [--check] [--check-cells 256:1e-6 1024:1e-10]
        [--backend auto|cuda|emulate] [--json FILE] [--jsonl FILE]

``--json`` writes the whole record, rewritten after every measurement: ``device``
(``cuda:<name>``; ``cuda-simulator`` or ``emulation`` without a GPU), ``steps`` rows (``N``,
``start``, ``batch``, ``threads``, ``max_registers`` the bound asked for, ``registers`` the
kernel's, ``us_per_step_per_packing``, ``us_per_block_step``, ``cpu_us_per_step``,
``local_bytes``, ``blocks_per_sm``, ``slots`` ...), ``check``, ``cells``, ``full``, ``campaign``
(``spec``, ``store``, ``wall_s``, ``packings``, ``busy_fraction``, ``lower_bound_s`` =
max(the longest packing's device time, block-seconds / resident slots) ...) and ``baseline``
(``N``, ``batch``, ``threads``, ``us_per_block_step``, ``us_per_step_per_packing``).
``--jsonl`` appends every measurement as it is made, one JSON object a line (``kind``: ``start``,
``check_packing``, ``check_resumed``, ``baseline``, ``step``, ``cell``, ``full``,
``campaign_progress``, ``campaign``, ``stopped``, ``end``; then the row's fields), flushed at
once: a run killed by a time limit leaves what it measured. SIGTERM (``timeout``'s signal) ends
a run with a ``stopped`` line; a campaign under way is stopped first (one SIGTERM: its running
packings are collected for ``--grace`` seconds, the store stays resumable) and its record
written. Without a GPU, ``--backend emulate`` runs the same block on the CPU, and
``NUMBA_ENABLE_CUDASIM=1`` the kernel under numba's CUDA simulator (tiny sizes only: it shows
that the script works, not how fast a GPU is). The figures of a GPU and the command that made
them: docs/GPU.md; the session that runs this on a GPU: ``benchmarks/gpu_session.sh``.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import platform
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


class Stopped(Exception):
    """SIGTERM or SIGINT came (``timeout``'s signal): what was measured is already written."""


_STOPPING = []


def _stop(signum, frame):
    """The first SIGTERM or SIGINT stops the run; the same signal again (the process group's and
    the one passed on by gpu_session.sh) changes nothing."""
    if _STOPPING:
        return
    _STOPPING.append(signum)
    raise Stopped(signal.Signals(signum).name)


class Record:
    """The run's record: ``--json`` (the whole, rewritten after every measurement) and
    ``--jsonl`` (one line per measurement, appended and flushed as it is made)."""

    def __init__(self, json_path=None, jsonl_path=None):
        self.data = {}
        self.json_path = Path(json_path) if json_path else None
        self.lines = open(jsonl_path, "a", encoding="utf-8") if jsonl_path else None  # noqa: SIM115
        self.t0 = time.perf_counter()

    def line(self, kind, row):
        """One measurement: a line of its own now."""
        if self.lines is not None:
            self.lines.write(json.dumps({"kind": kind, "elapsed_s": round(time.perf_counter() - self.t0, 3), **row},
                                        default=_plain) + "\n")
            self.lines.flush()

    def add(self, section, kind, row):
        """A row of ``section`` (a list in the record) and its line."""
        self.data.setdefault(section, []).append(row)
        self.line(kind, row)
        self.save()

    def set(self, section, kind, value):
        self.data[section] = value
        self.line(kind, value if isinstance(value, dict) else {"value": value})
        self.save()

    def save(self):
        if self.json_path is not None:
            tmp = self.json_path.with_name(self.json_path.name + ".tmp")
            tmp.write_text(json.dumps(self.data, indent=1, default=_plain))
            os.replace(tmp, self.json_path)


def _plain(x):
    """numpy scalars and the like as JSON (NaN stays NaN: Python's json writes it)."""
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, (set, tuple)):
        return list(x)
    return str(x)


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


def check_kernel(backend, threads, cells, nseeds, budget, rec):
    """The kernel against the emulation on the same inputs, and a resumed search against an
    uninterrupted one on the GPU (the first cell's first packing, from its batch). The emulation
    runs one packing per core meanwhile."""
    seeds = list(range(nseeds))
    jobs = [(n, e, s, threads, None) for n, e in cells for s in seeds]
    with mp.get_context("spawn").Pool(min(len(jobs), os.cpu_count() or 1)) as pool:
        pending = pool.map_async(_emulated, jobs)
        gpus = []
        for k, (n, e) in enumerate(cells):
            t0 = time.time()
            wall, got = _gpu_batch(n, [e] * len(seeds), seeds, backend, threads)
            if k == 0:
                window = (t0, time.time())
            gpus.append(got)
            print(f"  the kernel: {len(seeds)} packings at N_G {n}, E_G {e:g} in {wall:.1f} s (the first "
                  "launch compiles)", flush=True)
        n0, e0 = cells[0]
        whole = gpus[0][0]
        part = _resumed(n0, e0, seeds[0], backend, threads, budget)
        emus = pending.get()
    for k, (n, e) in enumerate(cells):
        rows = []
        for s, g, m in zip(seeds, gpus[k], emus[k * len(seeds):(k + 1) * len(seeds)]):
            d = float(np.max(np.abs(((g.positions - m.positions) + 0.5) % 1.0 - 0.5)))
            row = {"N": n, "E": e, "seed": s, "threads": threads, "max_position_difference": d,
                   "gpu_status": g.status, "emulation_status": m.status,
                   "gpu_force_evaluations": g.force_evaluations,
                   "emulation_force_evaluations": m.force_evaluations,
                   "gpu_energy": g.energy, "emulation_energy": m.energy,
                   "bitwise_equal": g.positions.tobytes() == m.positions.tobytes()}
            rows.append(row)
            rec.line("check_packing", row)
        print(f"  N_G {n} E_G {e:g}: {sum(r['bitwise_equal'] for r in rows)}/{len(rows)} bitwise equal, largest "
              f"position difference {max(r['max_position_difference'] for r in rows):.2e}, force evaluations "
              f"equal in {sum(r['gpu_force_evaluations'] == r['emulation_force_evaluations'] for r in rows)}"
              f"/{len(rows)}", flush=True)
        rec.data.setdefault("check", {}).setdefault("packings", []).extend(rows)
    clock = whole.settings["device_clock"]
    t0, t1 = window
    resumed = {"N": n0, "E": e0, "seed": seeds[0], "budget": budget,
               "launches": part.settings["device_clock"]["launches"], "bitwise_equal": _same(whole, part),
               # the store's busy fraction takes the device clock for epoch seconds: is it?
               "device_clock_in_host_window": bool(t0 - 1.0 <= clock["start"] <= clock["end"] <= t1 + 1.0),
               "device_start_minus_host_start_s": clock["start"] - t0}
    rec.data["check"]["resumed"] = resumed
    rec.line("check_resumed", resumed)
    rec.save()
    print(f"  stop and go on the GPU (N_G {n0}, every {budget} steps, {resumed['launches']} launches): "
          f"{'the same bits' if resumed['bitwise_equal'] else 'OTHER BITS'} as uninterrupted; the device clock "
          f"{'reads' if resumed['device_clock_in_host_window'] else 'does NOT read'} epoch seconds (start - host "
          f"{resumed['device_start_minus_host_start_s']:+.3f} s)", flush=True)


def _jammed_starts(path, batch):
    """``batch`` copies of a jammed packing, each perturbed by 0.05 of the smallest radius."""
    d = np.load(path)
    x, rad = np.asarray(d["x"], float) % 1.0, np.asarray(d["rad"], float)
    rng = np.random.default_rng(1)
    species = (rad < rad.mean()).astype(np.int32)
    return len(rad), [((x + 0.05 * rad.min() * rng.standard_normal(x.shape)) % 1.0, rad, species)
                      for _ in range(batch)]


def kernels_to_time(threads, bounds, backend):
    """The (threads, register bound) pairs to time, each kernel once: on a GPU a bound that
    comes to the bound of an earlier pair (``kernels.gpu.device.register_bound``: 128
    registers at 1024 threads are 64) is the same kernel and left out."""
    if backend != "cuda":
        return [(nt, regs) for nt in threads for regs in bounds]
    from kernels.gpu.device import register_bound

    out, seen = [], set()
    for nt in threads:
        for regs in bounds:
            key = (nt, register_bound(nt, regs))
            if key not in seen:
                seen.add(key)
                out.append((nt, regs))
    return out


def step_table(sizes, threads, batches, steps, backend, jammed, bounds, rec):
    from kernels.gpu.batch import time_steps

    plans = [(n, None) for n in sizes] + ([("jammed", jammed)] if jammed else [])
    pairs = kernels_to_time(threads, bounds, backend)
    left = [(nt, regs) for nt in threads for regs in bounds if (nt, regs) not in pairs]
    if left:
        print(f"  (the same kernel as an earlier bound, not timed again: {left})", flush=True)
    for size, path in plans:
        for (nt, regs), b in ((pair, b) for pair in pairs for b in batches):
            n, starts = (size, None) if path is None else _jammed_starts(path, b)
            first = (nt, regs) == pairs[0] and b == batches[0]
            r = time_steps(n, b, steps, backend, nt, starts=starts, cpu=first, registers=regs)
            occ = r["occupancy"]
            row = {"N": n, "start": "jammed" if starts else "random", "batch": b, "threads": nt,
                   "max_registers": regs, "us_per_step_per_packing": 1e6 * r["gpu"],
                   "us_per_block_step": 1e6 * r["block_step"], "cpu_us_per_step": 1e6 * r["cpu"], **occ}
            rec.add("steps", "step", row)
            print(f"  N_G {n:6d} {row['start']:7s} {nt:5d} thr {regs:4d} regs  batch {b:4d}  "
                  f"{row['us_per_step_per_packing']:9.3f} us/step/packing  {row['us_per_block_step']:8.1f} us/block "
                  f"step  {occ['registers']:3d} regs {occ['local_bytes']:4d} B local  {occ['blocks_per_sm']} blocks/SM"
                  + (f"   CPU core {row['cpu_us_per_step']:8.1f} us/step" if np.isfinite(r["cpu"]) else ""),
                  flush=True)


def busy(packings, slots):
    """The GPU's busy fraction over ``packings`` (their device clocks): block-seconds over
    ``slots`` x the span from the first start to the last end."""
    clocks = [p.settings["device_clock"] for p in packings]
    span = max(c["end"] for c in clocks) - min(c["start"] for c in clocks)
    return sum(c["seconds"] for c in clocks) / (slots * span), span


def cell_table(cells, batch, backend, threads, rec):
    from kernels.gpu.batch import finish_batch, occupancy, start_batch

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
        rec.add("cells", "cell", row)
        print(f"  cell N_G {n} E_G {e:g}: {len(ok)}/{batch} converged in {wall:.0f} s, "
              f"{row['packings_per_hour']:.0f} packings/h, busy {frac:.1%} of {occ['slots']} slots, "
              f"packings {row['packing_seconds_mean']:.1f} s on average, slowest {row['packing_seconds_max']:.1f} s",
              flush=True)


def full_table(cells, batch, backend, threads, cpu_full, rec):
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
        rec.add("full", "full", row)
        print(f"  N_G {n} E_G {e:g}: GPU {row['gpu_packings_per_hour']:.0f} packings/h ({len(ok)}/{batch} "
              f"converged in {wall:.0f} s, {evals:.3g} force evaluations each); CPU {cores} cores "
              f"{cpu_hour:.1f} packings/h from {1e6 * per_step:.0f} us/step"
              + (f", measured {row['cpu_packings_per_hour_measured']:.1f}" if cpu_full else "")
              + f"; one GPU = {row['gpu_over_cpu_cores']:.0f} CPU cores", flush=True)


def _status(store):
    """``campaign status --json`` of a store, or None where it cannot be read (yet)."""
    if not Path(store).exists():
        return None
    r = subprocess.run([sys.executable, "-m", "campaign", "status", str(store), "--json"], capture_output=True,
                       text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    try:
        return json.loads(r.stdout) if r.returncode == 0 else None
    except ValueError:
        return None


def device_time(store) -> dict:
    """The device time of a store's finished GPU packings (``scalars/device_seconds``, their
    block-seconds, and ``device_slots``): the longest packing's, their sum, the resident slots,
    and ``lower_bound_s`` = max(longest, sum / slots): no device holding ``slots`` blocks at once
    makes them in less wall time."""
    import h5py

    out = {"finished_gpu_packings": 0, "longest_packing_s": None, "block_seconds": None, "slots": None,
           "lower_bound_s": None}
    with h5py.File(store, "r", locking=False) as f:
        if "scalars/device_seconds" not in f:
            return out
        done = np.asarray(f["tasks/status"][:]) == 1
        secs = np.asarray(f["scalars/device_seconds"][:], np.float64)[done]
        slots = (np.asarray(f["scalars/device_slots"][:], np.float64)[done] if "scalars/device_slots" in f
                 else np.ones_like(secs))
    keep = np.isfinite(secs)
    if not keep.any():
        return out
    secs = secs[keep]
    good = slots[keep][np.isfinite(slots[keep])]
    k = float(max(1.0, good.max())) if good.size else 1.0
    out.update(finished_gpu_packings=int(keep.sum()), longest_packing_s=float(secs.max()),
               block_seconds=float(secs.sum()), slots=int(k),
               lower_bound_s=float(max(secs.max(), secs.sum() / k)))
    return out


def _seconds(limit):
    """A ``--time-limit`` as seconds where it is a number (else as given: ``[D-]HH:MM:SS``)."""
    try:
        return float(limit)
    except (TypeError, ValueError):
        return limit


def _die_with_parent():
    """In the campaign's process, before it runs: SIGTERM when this process dies (Linux), so that a
    killed benchmark does not leave a campaign writing its store behind it."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except Exception:  # noqa: BLE001 - elsewhere the campaign's own --time-limit ends it
        pass
    # a new session: a signal to this benchmark's process group (timeout's) does not reach the
    # campaign directly; the benchmark passes one SIGTERM on (a second would abandon its packings)
    os.setsid()


def run_campaign(spec, extra, store, time_limit, margin, grace, poll, backend, rec):
    """``campaign run SPEC --gpus 1`` into ``store`` (None: a fresh one in a temporary folder),
    with ``--time-limit``/``--margin`` when given, ``--grace`` and the GPU worker's ``backend``
    (``CAMPAIGN_GPU_BACKEND``, unless ``auto``); the run's progress every ``poll`` seconds
    (``campaign_progress`` lines) and at its end the record: wall, packings, busy fraction,
    lower bound on the device's time."""
    tmp = None
    if store is None:
        tmp = tempfile.TemporaryDirectory()
        store = Path(tmp.name) / "c.h5"
    store = Path(store).resolve()
    store.parent.mkdir(parents=True, exist_ok=True)
    before = _status(store)
    cmd = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(store), "--gpus", "1", "--quiet",
           "--grace", str(grace)]
    if time_limit is not None:
        cmd += ["--time-limit", str(time_limit), "--margin", str(margin)]
    cmd += list(extra)
    print("  " + " ".join(cmd[1:]), flush=True)
    t0 = time.perf_counter()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    if backend != "auto":
        env["CAMPAIGN_GPU_BACKEND"] = backend
    proc = subprocess.Popen(cmd, env=env, preexec_fn=_die_with_parent)
    interrupted = None
    try:
        while True:
            try:
                proc.wait(timeout=poll)
                break
            except subprocess.TimeoutExpired:
                st = _status(store)
                if st is not None:
                    rec.line("campaign_progress", {"store": str(store), "wall_s": time.perf_counter() - t0,
                                                   "done": st.get("done"), "failed": st.get("failed"),
                                                   "running": st.get("running"), "tasks": st.get("tasks"),
                                                   "suspended": (st.get("suspended") or {}).get("tasks")})
    except Stopped as why:
        interrupted = str(why)
        print(f"  {interrupted}: the campaign is stopped (its running packings collected, the store resumable)",
              flush=True)
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=grace + 20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    wall = time.perf_counter() - t0
    info = _status(store) or {}
    done = int(info.get("done") or 0)
    done_before = int((before or {}).get("done") or 0)
    fracs = [d.get("busy_fraction") for d in (info.get("gpu_busy") or {}).values()]
    row = {"spec": str(spec), "store": str(store), "returncode": proc.returncode, "interrupted": interrupted,
           "resumed": before is not None, "time_limit_s": _seconds(time_limit), "margin_s": margin if time_limit else None,
           "wall_s": wall, "packings": done, "tasks": info.get("tasks"), "failed": info.get("failed"),
           "pending": info.get("remaining"), "suspended": (info.get("suspended") or {}).get("tasks"),
           "packings_this_run": done - done_before, "packings_per_hour": 3600.0 * (done - done_before) / wall,
           "busy_fraction": fracs[0] if fracs else None, "gpu_busy": info.get("gpu_busy"),
           **(device_time(store) if store.exists() else {})}
    rec.set("campaign", "campaign", row)
    left = (row["tasks"] or 0) - done - (row["failed"] or 0)
    print(f"  campaign {spec}: {done} of {row['tasks']} packings in the store ({row['packings_this_run']} in this run's "
          f"{wall:.0f} s), {left} left{' (resume: the same command on the same store)' if left else ''}; busy "
          f"fraction {row['busy_fraction']}, device time at least {row.get('lower_bound_s')} s; exit {proc.returncode}",
          flush=True)
    if tmp is not None:
        tmp.cleanup()
    if interrupted:
        raise Stopped(interrupted)
    return row


def run_baseline(path, sizes, batches, threads, jammed, steps, rec):
    """The lean FIRE kernel at the same sizes (from a jammed packing where given) and batches."""
    for nt in threads:
        src = [str(jammed)] if jammed else [str(n) for n in sizes]
        for s in src:
            r = subprocess.run([sys.executable, str(path), s, *map(str, batches), "--steps", str(steps),
                                "--tpb", str(nt)], capture_output=True, text=True)
            got = 0
            for ln in r.stdout.splitlines():
                m = re.search(r"N=(\d+) B=(\d+) TPB=(\d+).*?([\d.]+) us per batch step, ([\d.]+) us per packing-step", ln)
                if m:
                    got += 1
                    rec.add("baseline", "baseline", {
                        "N": int(m.group(1)), "batch": int(m.group(2)), "threads": int(m.group(3)), "steps": steps,
                        "us_per_block_step": float(m.group(4)), "us_per_step_per_packing": float(m.group(5))})
                    print(f"  lean FIRE N {m.group(1)} B {m.group(2)} TPB {m.group(3)}: {m.group(4)} us per batch step, "
                          f"{m.group(5)} us per packing-step", flush=True)
            if r.returncode != 0 or not got:
                print(r.stderr[-2000:], file=sys.stderr)
                rec.line("baseline_failed", {"source": s, "threads": nt, "returncode": r.returncode,
                                             "stderr": r.stderr[-2000:]})


def _cells(items):
    return [(int(c.split(":")[0]), float(c.split(":")[1])) for c in items]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[8192])
    ap.add_argument("--threads", type=int, nargs="*", default=[512, 1024])
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
    ap.add_argument("--campaign-store", default=None, metavar="FILE",
                    help="the campaign's store (default: a fresh one in a temporary folder); the same command on "
                         "the same store resumes it")
    ap.add_argument("--time-limit", default=None, metavar="SECONDS", help="campaign run --time-limit")
    ap.add_argument("--margin", type=float, default=60.0, help="campaign run --margin (with --time-limit)")
    ap.add_argument("--grace", type=float, default=20.0,
                    help="campaign run --grace: seconds its running packings get after a SIGTERM")
    ap.add_argument("--campaign-poll", type=float, default=30.0, metavar="SECONDS",
                    help="seconds between two progress lines of the campaign")
    ap.add_argument("--campaign-args", nargs="*", default=[])
    ap.add_argument("--baseline", default=None, metavar="lean_fire.py")
    ap.add_argument("--baseline-threads", type=int, nargs="*", default=[512])
    ap.add_argument("--baseline-steps", type=int, default=2000)
    ap.add_argument("--backend", default="auto", choices=("auto", "cuda", "emulate"))
    ap.add_argument("--check", action="store_true",
                    help="first compare the kernel with the emulation on the same inputs (--check-cells)")
    ap.add_argument("--check-cells", nargs="*", default=["256:1e-6", "1024:1e-10"], metavar="N:E")
    ap.add_argument("--check-seeds", type=int, default=8)
    ap.add_argument("--check-budget", type=int, default=2000, metavar="STEPS")
    ap.add_argument("--json", default=None)
    ap.add_argument("--jsonl", default=None)
    a = ap.parse_args(argv)
    rec = Record(a.json, a.jsonl)
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    try:
        return _run(a, rec)
    except Stopped as why:
        rec.line("stopped", {"signal": str(why)})
        print(f"bench_gpu: stopped by {why} after {time.perf_counter() - rec.t0:.0f} s; what was measured is in "
              f"{a.jsonl or a.json or 'the lines above'}", flush=True)
        return 143 if str(why) == "SIGTERM" else 130


def _run(a, rec) -> int:
    from kernels.gpu import describe, resolve_backend

    backend = resolve_backend(a.backend)
    device = describe(backend)
    print(f"bench_gpu: {device}; CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores",
          flush=True)
    rec.data.update(device=device, cpu_cores=os.cpu_count())
    rec.line("start", {"device": device, "backend": backend, "cpu_cores": os.cpu_count(), "argv": sys.argv[1:]})
    rec.save()
    if a.check:
        print("the kernel against its CPU emulation, same inputs:", flush=True)
        check_kernel(backend, a.threads[0], _cells(a.check_cells), a.check_seeds, a.check_budget, rec)
    if a.baseline:
        print(f"the lean FIRE kernel (the yardstick) at {a.baseline_threads} threads:", flush=True)
        run_baseline(a.baseline, a.sizes, a.batches, a.baseline_threads, a.jammed, a.baseline_steps, rec)
    if a.sizes or a.jammed:
        print(f"FIRE steps (the kernel alone, steps {a.steps}-{2 * a.steps} of the first minimisation):", flush=True)
        step_table(a.sizes, a.threads, a.batches, a.steps, backend, a.jammed, a.registers, rec)
    if a.cell:
        print("whole cells (one launch, most expensive first):", flush=True)
        cell_table(_cells(a.cell), a.cell_batch, backend, a.threads[0], rec)
    if a.full:
        print("whole packings against the host's cores:", flush=True)
        full_table(_cells(a.full), a.full_batch, backend, a.threads[0], a.cpu_full, rec)
    code = 0
    if a.campaign:
        print("a campaign with --gpus 1:", flush=True)
        row = run_campaign(a.campaign, a.campaign_args, a.campaign_store, a.time_limit, a.margin, a.grace,
                           a.campaign_poll, a.backend, rec)
        code = 0 if row["returncode"] == 0 else 1  # (0 also for a run stopped by its --time-limit: resumable)
    seconds = time.perf_counter() - rec.t0
    rec.line("end", {"seconds": seconds, "exit": code})
    print(f"bench_gpu: {seconds:.0f} s", flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
