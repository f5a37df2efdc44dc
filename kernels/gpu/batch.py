"""Batches of packings, one thread block each: on a GPU (numba.cuda) or its CPU emulation.

``jam_batch(n, energies, seeds, **settings)`` prepares each packing as ``kernels.jam`` does
(same checks, same random start from the seed), sorts each start by cell once (memory
locality), runs the whole O'Hern search of every packing in its own block
(``kernels.gpu.block``) and returns one ``Packing`` per packing, in the caller's disk order.

Backends (``backend=`` or ``CAMPAIGN_GPU_BACKEND``; default ``auto``):

* ``cuda``: one kernel launch for the batch, one block of ``threads`` threads per packing
  (``numba-cuda``, the ``gpu`` extra). Under ``NUMBA_ENABLE_CUDASIM=1`` numba's CUDA simulator
  runs the same kernel on the CPU, one Python thread per GPU thread (tiny N only).
* ``emulate``: the block's phases compiled with ``numba.njit`` and looped over the threads
  (``kernels.gpu.block``): the GPU's arithmetic in the GPU's order, at about the speed of the
  CPU kernels; what the tests run whole packings with.
* ``auto``: ``cuda`` when a CUDA device (or the simulator) is available, else ``emulate``.

Capacities (refused with a ``BlockOverflow`` result for that packing, never a wrong list): at
most ``MAXNB`` neighbours within contact plus the skin per disk, and at most the cell
capacity per cell of the list's grid.
"""

from functools import lru_cache
import math
import os

import numpy as np

from kernels.gpu.block import (N_FL, N_IV, N_OUT, N_PARAMS, O_ENERGY, O_FORCE_EVALS, O_ITERATIONS,
                               O_RESIDUAL, O_SCALE, O_STATUS, O_STEPS, O_VIRIAL, P_ALPHA, P_DELTA, P_E_MIN,
                               P_ENERGY_STEP, P_LX, P_LY, P_MAX_RADIUS, P_MAX_SEARCH, P_MAX_STEPS,
                               P_MEAN_D, P_NCX, P_NCY, P_RMAX, P_RULE, P_SEARCH_TOL, P_SIN_TOL, P_SKIN,
                               P_TOL, P_WINDOW, P_XY, R0, ROWS, ST_OVERFLOW, X, Y, make_block)

MAXNB = 32  # neighbour slots per disk (within r_i + r_j + skin: about 10-14 in a dense packing)
CELL_CAP = 48  # slots per cell of the list's grid (about 2-3 disks per cell on average)
DEFAULT_THREADS = 256
BACKENDS = ("auto", "cuda", "emulate")


class BlockOverflow(RuntimeError):
    """A packing whose neighbour row or cell outgrew its slots (returned, not raised, in its
    place in ``jam_batch``'s list)."""


def _device():
    """``kernels.gpu.device`` (numba-cuda), or None where it cannot be imported."""
    try:
        from kernels.gpu import device
    except Exception:  # noqa: BLE001 - no numba-cuda, or a build that does not load: no GPU
        return None
    return device


def cuda_available() -> bool:
    """Whether a CUDA device (or numba's CUDA simulator) can run the kernel."""
    dev = _device()
    try:
        return dev is not None and dev.available()
    except Exception:  # noqa: BLE001 - no driver: no GPU
        return False


def simulated() -> bool:
    """Whether numba's CUDA simulator stands in for the GPU (``NUMBA_ENABLE_CUDASIM=1``)."""
    from numba import config

    return bool(config.ENABLE_CUDASIM)


def resolve_backend(backend=None) -> str:
    """``cuda`` or ``emulate`` for ``backend`` (None: ``CAMPAIGN_GPU_BACKEND``, else auto)."""
    name = backend or os.environ.get("CAMPAIGN_GPU_BACKEND") or "auto"
    if name not in BACKENDS:
        raise ValueError(f"backend: expected one of {list(BACKENDS)}, got {name!r}")
    if name == "auto":
        return "cuda" if cuda_available() else "emulate"
    if name == "cuda" and not cuda_available():
        raise ValueError("backend: 'cuda' needs a CUDA device and numba-cuda (pip install "
                         "'jamming-campaign[gpu]'), or NUMBA_ENABLE_CUDASIM=1 for the simulator; "
                         "none is available here")
    return name


def describe(backend) -> str:
    """What runs the blocks: ``cuda:<device name>``, ``cuda-simulator`` or ``emulation``."""
    if resolve_backend(backend) == "emulate":
        return "emulation"
    return _device().name()


def _noop():
    pass


def _slot_add(cells, c):
    old = cells[0, c]
    cells[0, c] = old + 1
    return old


@lru_cache(maxsize=None)
def emulated_block():
    """The block's phases compiled for the CPU (``make_block``'s namespace)."""
    from numba import njit

    return make_block(njit, njit(_noop), njit(_slot_add))


@lru_cache(maxsize=None)
def _emulator():
    """A loop over a batch's packings with the block compiled for the CPU."""
    from numba import njit

    ohern = emulated_block().ohern

    @njit
    def run(nt, fl, nbr, ninv, iv, cells, prm, out):
        red = np.zeros((ROWS, nt))
        for b in range(fl.shape[0]):
            ohern(0, nt, nt, fl[b], nbr[b], ninv[b], iv[b], cells[b], red, prm[b], out[b])

    return run


def threads_for(n, threads=None) -> int:
    """Threads per block: ``threads`` (default ``DEFAULT_THREADS``), a power of two, at most the
    power of two at or above ``n`` and at least 1."""
    nt = DEFAULT_THREADS if threads is None else int(threads)
    if nt < 1 or nt & (nt - 1):
        raise ValueError(f"threads: expected a power of two >= 1, got {threads!r}")
    return max(1, min(nt, 1 << max(0, (n - 1).bit_length())))


def _grid(job, n):
    """Cells allocated along x and y (those of the starting radii, finer by the search's
    largest first shrink) and their capacity."""
    from kernels.cells import _cell_grid

    box = job.cell_box
    skin = job.skin * 2.0 * float(np.mean(job.radii0))
    cutoff = (2.0 * float(job.radii0.max()) + skin) / (1.0 + job.delta) ** 2
    ncx, ncy = (int(v) for v in _cell_grid(box, cutoff, n))
    cap = min(n, max(CELL_CAP, 4 * -(-n // (ncx * ncy))))
    return ncx, ncy, cap


def _params(job, ncx, ncy):
    from kernels.jamming import ENERGY_STEP
    from kernels.network import HALF_PLANE_TOL

    prm = np.zeros(N_PARAMS)
    prm[P_E_MIN] = job.e_min
    prm[P_WINDOW] = job.window
    prm[P_TOL] = job.tol
    prm[P_SEARCH_TOL] = job.search_tol
    prm[P_MAX_SEARCH] = job.max_search
    prm[P_MAX_STEPS] = job.max_steps
    prm[P_SKIN] = job.skin
    prm[P_DELTA] = job.delta
    prm[P_RULE] = job.rule
    prm[P_MAX_RADIUS] = job.max_radius
    prm[P_ENERGY_STEP] = ENERGY_STEP
    prm[P_ALPHA] = job.alpha
    prm[P_LX], prm[P_LY], prm[P_XY] = job.cell_box
    prm[P_MEAN_D] = 2.0 * float(np.mean(job.radii0))
    prm[P_RMAX] = float(job.radii0.max())
    prm[P_SIN_TOL] = math.sin(HALF_PLANE_TOL)
    prm[P_NCX] = ncx
    prm[P_NCY] = ncy
    return prm


def prepare(n, energies, seeds, starts=None, **settings):
    """The checked jobs of a batch (``kernels.jamming._prepare``), refusing what the block does
    not run: it runs FIRE 2.0 on the O'Hern route in a fixed cell, stopping on the force
    residual (any potential, size distribution and search rule)."""
    from kernels.jamming import _prepare

    energies = list(energies)
    seeds = list(seeds)
    starts = [None] * len(energies) if starts is None else list(starts)
    if not (len(energies) == len(seeds) == len(starts)) or not energies:
        raise ValueError(f"energies, seeds, starts: expected equal non-zero lengths, got "
                         f"{len(energies)}, {len(seeds)} and {len(starts)}")
    jobs = [_prepare(n, e, s, st, dict(settings)) for e, s, st in zip(energies, seeds, starts)]
    opt = jobs[0].opt
    if (opt["minimizer"], opt["stop"], opt["route"], opt["endgame"], opt["cell"]) != (
            "fire", "force", "ohern", "none", "fixed"):
        raise ValueError("device 'gpu' runs FIRE on the O'Hern route in a fixed cell; expected "
                         "minimizer 'fire', stop 'force', route 'ohern', endgame 'none' and cell "
                         f"'fixed', got {opt['minimizer']!r}, {opt['stop']!r}, {opt['route']!r}, "
                         f"{opt['endgame']!r} and {opt['cell']!r}")
    return jobs


def jam_batch(n, energies, seeds, starts=None, backend=None, threads=None, **settings):
    """Jammed packings of ``n`` disks, one per ``(energy, seed[, start])``, each in its own
    thread block; settings as ``kernels.jam`` (FIRE on the O'Hern route, fixed cell).

    Returns a list with, per packing, a ``Packing`` (``settings["device"]`` says what ran it;
    ``force_evaluations`` counts FIRE's force evaluations as on the CPU) or a
    ``BlockOverflow`` for a packing whose lists outgrew their slots. ``start_batch`` and
    ``finish_batch`` are its two halves: on a GPU the launch runs while the caller does other
    work (a GPU worker analyses the previous batch meanwhile)."""
    return finish_batch(start_batch(n, energies, seeds, starts, backend, threads, **settings))


def start_batch(n, energies, seeds, starts=None, backend=None, threads=None, **settings):
    """Prepare the batch and start it: on a GPU the kernel is launched and this returns at once;
    the emulation runs it here. Returns the handle ``finish_batch`` takes."""
    handle = _stage(n, energies, seeds, starts, backend, threads, **settings)
    if handle["backend"] == "emulate":
        _emulator()(handle["nt"], *handle["arrays"])
    else:
        handle["running"] = _device().launch(handle["nt"], handle["arrays"])
    return handle


def _stage(n, energies, seeds, starts=None, backend=None, threads=None, **settings):
    """The batch's host arrays (a handle for ``finish_batch``, nothing started yet)."""
    from kernels.protocol import _spatial_order

    jobs = prepare(n, energies, seeds, starts, **settings)
    which = resolve_backend(backend)
    nt = threads_for(n, threads)
    B = len(jobs)
    grids = [_grid(j, n) for j in jobs]
    ncell = max(g[0] * g[1] for g in grids)
    cap = max(g[2] for g in grids)
    fl = np.zeros((B, N_FL, n))
    prm = np.empty((B, N_PARAMS))
    orders = []
    for b, (job, (ncx, ncy, _)) in enumerate(zip(jobs, grids)):
        # the start sorted by cell once: neighbours in space become neighbours in memory
        order = _spatial_order(job.positions, job.cell_box, 2.0 * float(np.mean(job.radii0)))
        orders.append(order)
        fl[b, X] = job.positions[order, 0]
        fl[b, Y] = job.positions[order, 1]
        fl[b, R0] = job.radii0[order]
        prm[b] = _params(job, ncx, ncy)
    arrays = [fl, np.zeros((B, MAXNB, n), np.int32), np.zeros((B, MAXNB, n)),
              np.zeros((B, N_IV, n), np.int32), np.zeros((B, cap + 1, ncell), np.int32), prm,
              np.zeros((B, N_OUT))]
    return {"n": n, "jobs": jobs, "orders": orders, "cap": cap, "arrays": arrays, "backend": which,
            "nt": nt, "running": None}


def finish_batch(handle):
    """Wait for a batch ``start_batch`` started and make its packings (``jam_batch``'s list)."""
    from kernels.jamming import STATUS_NAMES, _packing

    n, jobs, orders, cap = handle["n"], handle["jobs"], handle["orders"], handle["cap"]
    if handle["running"] is None:
        fl, out = handle["arrays"][0], handle["arrays"][-1]
    else:
        fl, out = _device().collect(handle["running"])
    device = describe(handle["backend"])
    results = []
    for b, job in enumerate(jobs):
        status = int(out[b, O_STATUS])
        if status == ST_OVERFLOW:
            results.append(BlockOverflow(
                f"packing {b} (N={n}, E={job.e_min:g}): a neighbour row (at most {MAXNB} "
                f"disks within contact plus the skin) or a cell (at most {cap} disks) outgrew "
                "its slots; use a smaller skin"))
            continue
        final = np.empty((n, 2))
        final[orders[b], 0] = fl[b, X]
        final[orders[b], 1] = fl[b, Y]
        job.positions = final
        p = _packing(job, STATUS_NAMES[status], out[b, O_SCALE], out[b, O_ENERGY],
                     out[b, O_VIRIAL], out[b, O_RESIDUAL], int(out[b, O_ITERATIONS]),
                     int(out[b, O_FORCE_EVALS]), 0, device=device)
        results.append(p)
    return results


def _kernel_seconds(handle, bound):
    """Seconds of the batch's kernel alone (the arrays on the device before the clock, the
    results after it) with every minimisation bounded at ``bound`` steps, and the steps done."""
    import time

    arrays = [a.copy() for a in handle["arrays"]]
    arrays[5][:, P_MAX_STEPS] = bound
    if handle["backend"] == "emulate":
        t0 = time.perf_counter()
        _emulator()(handle["nt"], *arrays)
        wall = time.perf_counter() - t0
        out = arrays[-1]
    else:
        dev = _device()
        on = dev.upload(arrays)
        dev.wait()
        t0 = time.perf_counter()
        dev.start(handle["nt"], on)
        dev.wait()
        wall = time.perf_counter() - t0
        out = on[-1].copy_to_host()
    return wall, float(out[:, O_STEPS].sum())


def time_steps(n, batch, steps, backend=None, threads=None, energy=1e-12):
    """Seconds per FIRE step: ``(block, cpu)``. The block's per packing: a launch of ``batch``
    random starts, the first minimisation of each bounded at ``steps`` and then at ``2 steps``
    steps, the kernel's time alone (no host preparation or copies); the steps ``steps .. 2
    steps`` are timed (their difference), past the first steps' list rebuilds at every step,
    as in the long minimisations that make a packing's cost. The CPU kernel's
    (``kernels.fire._fire_core``) the same way on the first of those starts, one core. What
    ``benchmarks/bench_gpu.py`` and ``campaign calibrate --gpu`` measure."""
    import time

    from kernels.fire import _fire_core
    from kernels.minimiser import default_timestep

    jam_batch(n, [energy], [0], backend=backend, threads=threads, max_search=1, max_steps=10)
    handle = _stage(n, [energy] * batch, list(range(batch)), None, backend, threads, max_search=1,
                    max_steps=steps)
    (w1, d1), (w2, d2) = (_kernel_seconds(handle, b) for b in (steps, 2 * steps))
    gpu = (w2 - w1) / (d2 - d1) if d2 > d1 else math.nan
    job = handle["jobs"][0]
    box = job.cell_box
    dt = default_timestep(job.radii0, job.alpha, 1e-8)
    skin = job.skin * 2.0 * float(np.mean(job.radii0))
    _fire_core(job.positions.copy(), job.radii0, box, job.alpha, 1e-6, 10, skin, dt, 0.0)
    cpu = []
    for bound in (steps, 2 * steps):
        t0 = time.perf_counter()
        r = _fire_core(job.positions.copy(), job.radii0, box, job.alpha, 1e-6, bound, skin, dt, 0.0)
        cpu.append((time.perf_counter() - t0, r[1]))
    (c1, s1), (c2, s2) = cpu
    return gpu, ((c2 - c1) / (s2 - s1) if s2 > s1 else math.nan)


__all__ = ["jam_batch", "start_batch", "finish_batch", "time_steps", "prepare", "simulated", "BlockOverflow", "resolve_backend", "describe", "cuda_available",
           "threads_for", "MAXNB", "CELL_CAP", "DEFAULT_THREADS", "BACKENDS"]
