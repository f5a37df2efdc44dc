"""Batches of packings, one thread block each: on a GPU (numba.cuda) or its CPU emulation.

``jam_batch(n, energies, seeds, **settings)`` prepares each packing as ``kernels.jam`` does
(same checks, same random start from the seed), sorts each start by cell once (memory
locality), runs the whole O'Hern search of every packing in its own block
(``kernels.gpu.block``) and returns one ``Packing`` per packing, in the caller's disk order.

Backends (``backend=`` or ``CAMPAIGN_GPU_BACKEND``; default ``auto``):

* ``cuda``: one kernel launch for the batch, one block of ``threads`` threads per packing
  (``numba-cuda``, the ``gpu`` extra), on a stream of its own: launches of several batches run
  side by side, and a block that ends frees its place for a waiting one. Under
  ``NUMBA_ENABLE_CUDASIM=1`` numba's CUDA simulator runs the same kernel on the CPU, one
  Python thread per GPU thread (tiny N only).
* ``emulate``: the block's phases compiled with ``numba.njit`` and looped over the threads
  (``kernels.gpu.block``): the GPU's arithmetic in the GPU's order, at about the speed of the
  CPU kernels; what the tests run whole packings with.
* ``auto``: ``cuda`` when a CUDA device (or the simulator) is available, else ``emulate``.

The blocks of a launch start most expensive first (the lowest energies; the hardware starts a
waiting block as soon as one ends). Every packing records its device clock: the start of its
first launch, its end and its block-seconds (``Packing.settings["device_clock"]``; the
emulation's clock is the host's).

Stop and go: ``budget`` bounds the FIRE steps of each packing in this launch. A packing that
reaches it comes back as a ``Suspended`` (its positions, velocities, the lists' reference
positions and the block's state row) instead of a ``Packing``; ``jam_batch(..., resume=[...])``
goes on from it, in this process or another, and ends with the bits of an uninterrupted search.

Capacities (refused with a ``BlockOverflow`` result for that packing, never a wrong list): at
most ``MAXNB`` neighbours within contact plus the skin per disk, and at most the cell
capacity per cell of the list's grid.
"""

from dataclasses import dataclass
from functools import lru_cache
import math
import os
import time

import numpy as np

from kernels.gpu.block import make_block, make_shared_reduction
from kernels.gpu.state import (N_FL, N_IV, N_PARAMS, N_ST, P_ALPHA, P_BUDGET, P_DELTA, P_E_MIN,
                               P_ENERGY_STEP, P_LX, P_LY, P_MAX_RADIUS, P_MAX_SEARCH,
                               P_MAX_STEPS, P_MEAN_D, P_NCX, P_NCY, P_RMAX, P_RULE, P_SEARCH_TOL,
                               P_SIN_TOL, P_SKIN, P_TOL, P_WINDOW, P_XY, R0, ROWS, RX, RY,
                               S_BUSY, S_CMD, S_E_LAST, S_IT, S_LAUNCHES, S_MNFORCE, S_NFORCE,
                               S_RES_LAST, S_SCALE, S_STATUS, S_STEP, S_STEPS, S_T_END,
                               S_T_FIRST, S_W_LAST, ST_OVERFLOW, VX, VY, C_DONE, C_SUSPEND,
                               start_state)

MAXNB = 32  # neighbour slots per disk (within r_i + r_j + skin: about 10-14 in a dense packing)
CELL_CAP = 48  # slots per cell of the list's grid (about 2-3 disks per cell on average)
DEFAULT_THREADS = 256
BACKENDS = ("auto", "cuda", "emulate")
NO_BUDGET = 2.0 ** 62  # FIRE steps: no bound
DEFAULTS_FORCE_TOLERANCE = 1e-6  # (kernels.jamming.DEFAULTS')


class BlockOverflow(RuntimeError):
    """A packing whose neighbour row or cell outgrew its slots (returned, not raised, in its
    place in ``jam_batch``'s list)."""


@dataclass(eq=False)
class Suspended:
    """A packing stopped at its launch's step budget: what its search goes on from
    (``jam_batch(..., resume=[...])``). Arrays in the block's disk order (the start sorted by
    cell): ``positions`` (n, 2), ``velocities`` (2, n), ``reference`` (2, n) the positions the
    neighbour lists were built from, ``state`` the block's state row (``kernels.gpu.block``'s
    ``S_*``). ``steps`` and ``force_evaluations`` so far, ``device_clock`` as a packing's."""

    positions: np.ndarray
    velocities: np.ndarray
    reference: np.ndarray
    state: np.ndarray
    n: int
    energy: float  # the target E_G (what it resumes for: checked on resumption)

    ARRAYS = ("positions", "velocities", "reference", "state")

    @property
    def steps(self) -> int:
        """FIRE steps so far (the minimisation under way's included)."""
        return int(self.state[S_STEPS] + self.state[S_STEP])

    @property
    def force_evaluations(self) -> int:
        return int(self.state[S_NFORCE] + self.state[S_MNFORCE])

    @property
    def device_clock(self) -> dict:
        return _clock(self.state)

    def arrays(self) -> dict:
        """The four arrays by name (what a store keeps)."""
        return {k: getattr(self, k) for k in self.ARRAYS}

    @classmethod
    def from_arrays(cls, arrays, energy):
        """Back from ``arrays()`` (checked: shapes and the state row's length)."""
        pos = np.ascontiguousarray(arrays["positions"], np.float64)
        n = pos.shape[0]
        shapes = {"positions": (n, 2), "velocities": (2, n), "reference": (2, n), "state": (N_ST,)}
        got = {k: np.ascontiguousarray(arrays[k], np.float64) for k in cls.ARRAYS}
        for k, shape in shapes.items():
            if got[k].shape != shape:
                raise ValueError(f"suspended packing: {k} has shape {got[k].shape}, expected {shape}")
        if int(got["state"][S_CMD]) != C_SUSPEND:
            raise ValueError("suspended packing: its state row is not that of a suspended search")
        return cls(got["positions"], got["velocities"], got["reference"], got["state"], n,
                   float(energy))


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


def exponent_kind(alpha):
    """The exponent the block is compiled for: 2.0 and 2.5 (no ``pow``), else None (any)."""
    return float(alpha) if float(alpha) in (2.0, 2.5) else None


def _noop():
    pass


def _no_clock():
    return 0.0


def _slot_add(cells, c):
    old = cells[0, c]
    cells[0, c] = old + 1
    return old


@lru_cache(maxsize=None)
def emulated_block(exponent=2.0):
    """The block's phases compiled for the CPU (``make_block``'s namespace), for the
    ``exponent`` of ``exponent_kind``."""
    from numba import njit

    sync = njit(_noop)
    put_sum, put_max, total = make_shared_reduction(njit, sync)
    return make_block(njit, sync, njit(_slot_add), put_sum, put_max, total, njit(_no_clock),
                      exponent)


_SEARCH = None  # the block's search that the runner being compiled calls (see _emulator)


def _source_tag(exponent):
    """What the emulation's compiled code depends on: the sources of the block and of the rules
    it compiles, and the exponent. It keys the numba cache entry of the runner, which numba
    would otherwise reuse after a change of the block (numba keys a cached function by its own
    file only)."""
    import hashlib

    h = hashlib.sha256(repr(exponent).encode())
    base = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for rel in ("gpu/block.py", "gpu/control.py", "gpu/state.py", "gpu/batch.py", "rules.py",
                "space.py"):
        with open(os.path.join(base, rel), "rb") as fh:
            h.update(fh.read())
    return h.hexdigest()


def _runner(tag):
    from numba import njit

    @njit(cache=True)
    def run(nt, xy, fl, nbr, ninv, iv, cells, prm, st):
        if len(tag) == 0:  # (the tag keys the cache entry; it is never empty)
            return
        red = np.zeros((ROWS, nt))
        sh = np.zeros(N_ST)
        _SEARCH(0, nt, nt, xy, fl, nbr, ninv, iv, cells, red, sh, prm, st)

    return run


@lru_cache(maxsize=None)
def _emulator(exponent):
    """One packing's search with the block compiled for the CPU (``NUMBA_CACHE_DIR``'s cache
    under the tag of its sources: a process loads it in seconds instead of compiling it for
    a minute)."""
    global _SEARCH
    import numba

    run = _runner(_source_tag(exponent))
    f2, i2 = numba.float64[:, ::1], numba.int32[:, ::1]
    sig = (numba.int64, f2, f2, i2, f2, i2, i2, numba.float64[::1], numba.float64[::1])
    _SEARCH = emulated_block(exponent).search  # (a global: frozen into the code it compiles)
    try:
        run.compile(sig)
    finally:
        _SEARCH = None
    return run


def _emulate(nt, exponent, which, arrays):
    """The emulation of a launch: its packings one after the other, each timed by the host's
    clock (the block's own reads 0)."""
    run = _emulator(exponent)
    xy, fl, nbr, ninv, iv, cells, prm, st = arrays
    for b in which:
        first = st[b, S_LAUNCHES] == 0.0
        t0 = time.time_ns()
        run(nt, xy[b], fl[b], nbr[b], ninv[b], iv[b], cells[b], prm[b], st[b])
        t1 = time.time_ns()
        if first:
            st[b, S_T_FIRST] = float(t0)
        st[b, S_BUSY] += float(t1 - t0)
        if int(st[b, S_CMD]) == C_DONE:
            st[b, S_T_END] = float(t1)


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


def _params(job, ncx, ncy, budget):
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
    prm[P_BUDGET] = budget
    return prm


def _budget(budget):
    if budget is None:
        return NO_BUDGET
    if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < 1:
        raise ValueError(f"budget: expected an integer >= 1 (FIRE steps per launch), got {budget!r}")
    return float(min(int(budget), NO_BUDGET))


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
    if len({j.alpha for j in jobs}) != 1:
        raise ValueError("a batch's packings share one potential exponent")
    return jobs


def jam_batch(n, energies, seeds, starts=None, backend=None, threads=None, budget=None,
              resume=None, registers=None, **settings):
    """Jammed packings of ``n`` disks, one per ``(energy, seed[, start])``, each in its own
    thread block; settings as ``kernels.jam`` (FIRE on the O'Hern route, fixed cell).

    Returns a list with, per packing, a ``Packing`` (``settings["device"]`` says what ran it,
    ``settings["device_clock"]`` when and how long; ``force_evaluations`` counts FIRE's force
    evaluations as on the CPU), a ``BlockOverflow`` for a packing whose lists outgrew their
    slots, or a ``Suspended`` for one that reached ``budget`` FIRE steps in this launch
    (``resume``: per packing None or the ``Suspended`` it goes on from). ``registers``: a
    bound on the kernel's registers per thread (``kernels.gpu.device.DEFAULT_REGISTERS``; it
    never changes the results). ``start_batch`` and ``finish_batch`` are its two halves: on a
    GPU the launch runs while the caller does other work."""
    return finish_batch(start_batch(n, energies, seeds, starts, backend, threads, budget, resume,
                                    registers, **settings))


def start_batch(n, energies, seeds, starts=None, backend=None, threads=None, budget=None,
                resume=None, registers=None, **settings):
    """Prepare the batch and start it: on a GPU the kernel is launched on a stream of its own and
    this returns at once; the emulation runs it here. Returns the handle ``finish_batch`` takes
    (``batch_done(handle)`` says whether it has ended)."""
    handle = _stage(n, energies, seeds, starts, backend, threads, budget, resume, registers,
                    **settings)
    if handle["backend"] == "emulate":
        _emulate(handle["nt"], handle["exponent"], handle["which"], handle["arrays"])
    else:
        handle["running"] = _device().launch(handle["nt"], handle["exponent"], handle["which"],
                                             handle["arrays"], registers)
    return handle


def batch_done(handle) -> bool:
    """Whether a started batch has ended (never waits)."""
    return handle["running"] is None or _device().ended(handle["running"])


def occupancy(handle) -> dict:
    """Registers, spills and resident blocks of a started batch's kernel
    (``kernels.gpu.device.occupancy``); the emulation runs one packing at a time: one slot."""
    if handle["backend"] == "emulate":
        return {"registers": 0, "local_bytes": 0, "shared_bytes": 0, "blocks_per_sm": 1, "sms": 1,
                "slots": 1}
    return _device().occupancy(handle["nt"], handle["exponent"], handle["registers"])


def _stage(n, energies, seeds, starts=None, backend=None, threads=None, budget=None, resume=None,
           registers=None, **settings):
    """The batch's host arrays (a handle for ``finish_batch``, nothing started yet)."""
    from kernels.protocol import _spatial_order

    jobs = prepare(n, energies, seeds, starts, **settings)
    which = resolve_backend(backend)
    nt = threads_for(n, threads)
    B = len(jobs)
    resume = [None] * B if resume is None else list(resume)
    if len(resume) != B:
        raise ValueError(f"resume: expected {B} entries (None or a Suspended), got {len(resume)}")
    grids = [_grid(j, n) for j in jobs]
    ncell = max(g[0] * g[1] for g in grids)
    cap = max(g[2] for g in grids)
    bud = _budget(budget)
    xy = np.zeros((B, n, 2))
    fl = np.zeros((B, N_FL, n))
    prm = np.empty((B, N_PARAMS))
    st = np.zeros((B, N_ST))
    orders = []
    for b, (job, (ncx, ncy, _), back) in enumerate(zip(jobs, grids, resume)):
        # the start sorted by cell once: neighbours in space become neighbours in memory
        order = _spatial_order(job.positions, job.cell_box, 2.0 * float(np.mean(job.radii0)))
        orders.append(order)
        fl[b, R0] = job.radii0[order]
        prm[b] = _params(job, ncx, ncy, bud)
        if back is None:
            xy[b] = job.positions[order]
            start_state(st[b])
            continue
        if not isinstance(back, Suspended) or back.n != n or back.energy != job.e_min:
            raise ValueError(f"resume[{b}]: expected a Suspended packing of N={n} at E={job.e_min:g}")
        xy[b] = back.positions
        fl[b, VX], fl[b, VY] = back.velocities
        fl[b, RX], fl[b, RY] = back.reference
        st[b] = back.state
    arrays = [xy, fl, np.zeros((B, MAXNB, n), np.int32), np.zeros((B, MAXNB, n)),
              np.zeros((B, N_IV, n), np.int32), np.zeros((B, cap + 1, ncell), np.int32), prm, st]
    # most expensive first: the lowest energies (then the caller's order)
    launch = np.array(sorted(range(B), key=lambda b: (jobs[b].e_min, b)), np.int32)
    return {"n": n, "jobs": jobs, "orders": orders, "cap": cap, "arrays": arrays, "backend": which,
            "nt": nt, "exponent": exponent_kind(jobs[0].alpha), "which": launch, "running": None,
            "registers": registers}


def _clock(state):
    """A packing's device clock from its state row: ``start`` and ``end`` (seconds of the
    device's clock; the end NaN while it runs), ``seconds`` its block-time, ``launches``."""
    end = state[S_T_END]
    return {"start": state[S_T_FIRST] * 1e-9, "end": end * 1e-9 if end > 0.0 else math.nan,
            "seconds": state[S_BUSY] * 1e-9, "launches": int(state[S_LAUNCHES])}


def finish_batch(handle):
    """Wait for a batch ``start_batch`` started and make its packings (``jam_batch``'s list)."""
    from kernels.jamming import STATUS_NAMES, _packing

    n, jobs, orders, cap = handle["n"], handle["jobs"], handle["orders"], handle["cap"]
    if handle["running"] is None:
        xy, fl, st = handle["arrays"][0], handle["arrays"][1], handle["arrays"][-1]
    else:
        xy, fl, st = _device().collect(handle["running"])
    device = describe(handle["backend"])
    results = []
    for b, job in enumerate(jobs):
        if int(st[b, S_CMD]) == C_SUSPEND:
            results.append(Suspended(xy[b].copy(), fl[b, [VX, VY]].copy(), fl[b, [RX, RY]].copy(),
                                     st[b].copy(), n, job.e_min))
            continue
        status = int(st[b, S_STATUS])
        if status == ST_OVERFLOW:
            results.append(BlockOverflow(
                f"packing {b} (N={n}, E={job.e_min:g}): a neighbour row (at most {MAXNB} "
                f"disks within contact plus the skin) or a cell (at most {cap} disks) outgrew "
                "its slots; use a smaller skin"))
            continue
        final = np.empty((n, 2))
        final[orders[b]] = xy[b]
        job.positions = final
        p = _packing(job, STATUS_NAMES[status], st[b, S_SCALE], st[b, S_E_LAST],
                     st[b, S_W_LAST], st[b, S_RES_LAST], int(st[b, S_IT]),
                     int(st[b, S_NFORCE]), 0, device=device)
        p.settings["device_clock"] = _clock(st[b])
        results.append(p)
    return results


def _kernel_seconds(handle, bound):
    """Seconds of the batch's kernel alone (the arrays on the device before the clock, the
    results after it) with every minimisation bounded at ``bound`` steps, and the steps done."""
    arrays = [a.copy() for a in handle["arrays"]]
    arrays[-2][:, P_MAX_STEPS] = bound
    if handle["backend"] == "emulate":
        t0 = time.perf_counter()
        _emulate(handle["nt"], handle["exponent"], handle["which"], arrays)
        wall = time.perf_counter() - t0
        st = arrays[-1]
    else:
        dev = _device()
        on = dev.upload(arrays)
        which = dev.upload([handle["which"]])[0]
        dev.wait()
        t0 = time.perf_counter()
        dev.start(handle["nt"], handle["exponent"], which, on, handle["registers"])
        dev.wait()
        wall = time.perf_counter() - t0
        st = on[-1].copy_to_host()
    return wall, float(st[:, S_STEPS].sum())


def time_steps(n, batch, steps, backend=None, threads=None, energy=1e-12, starts=None, cpu=True,
               registers=None):
    """Seconds per FIRE step of a launch of ``batch`` packings: the first minimisation of each
    bounded at ``steps`` and then at ``2 steps`` steps, the kernel's time alone (no host
    preparation or copies); the steps ``steps .. 2 steps`` are timed (their difference), past
    the first steps' list rebuilds at every step, as in the long minimisations that make a
    packing's cost. Random starts, or ``starts`` (``batch`` tuples ``(positions, radii,
    species)``: near a minimum, where the minimisation then stops on the final tolerance).

    Returns ``{"gpu": per step per packing, "block_step": per step of one resident block (per
    packing times the packings resident at once), "cpu": the CPU kernel's
    (``kernels.fire._fire_core``) per step on the first start, one core (NaN without
    ``cpu``), "occupancy": the kernel's (``occupancy``)}``. What ``benchmarks/bench_gpu.py``
    and ``campaign calibrate --gpu`` measure."""
    from kernels.fire import _fire_core
    from kernels.minimiser import default_timestep

    kw = {"max_search": 1}
    if starts is not None:
        kw["search_tolerance"] = DEFAULTS_FORCE_TOLERANCE
    jam_batch(n, [energy], [0], starts=None if starts is None else starts[:1], backend=backend,
              threads=threads, registers=registers, max_steps=10, **kw)
    handle = _stage(n, [energy] * batch, list(range(batch)), starts, backend, threads,
                    registers=registers, max_steps=steps, **kw)
    (w1, d1), (w2, d2) = (_kernel_seconds(handle, b) for b in (steps, 2 * steps))
    gpu = (w2 - w1) / (d2 - d1) if d2 > d1 else math.nan
    occ = occupancy(handle)
    out = {"gpu": gpu, "block_step": gpu * min(batch, occ["slots"]), "cpu": math.nan, "occupancy": occ}
    if not cpu:
        return out
    job = handle["jobs"][0]
    box = job.cell_box
    dt = default_timestep(job.radii0, job.alpha, 1e-8)
    skin = job.skin * 2.0 * float(np.mean(job.radii0))
    _fire_core(job.positions.copy(), job.radii0, box, job.alpha, 1e-6, 10, skin, dt, 0.0)
    times = []
    for bound in (steps, 2 * steps):
        t0 = time.perf_counter()
        r = _fire_core(job.positions.copy(), job.radii0, box, job.alpha, job.search_tol, bound, skin,
                       dt, 0.0)
        times.append((time.perf_counter() - t0, r[1]))
    (c1, s1), (c2, s2) = times
    out["cpu"] = (c2 - c1) / (s2 - s1) if s2 > s1 else math.nan
    return out


__all__ = ["jam_batch", "start_batch", "finish_batch", "batch_done", "occupancy", "time_steps", "prepare",
           "simulated", "BlockOverflow", "Suspended", "resolve_backend", "describe",
           "cuda_available", "threads_for", "exponent_kind", "MAXNB", "CELL_CAP",
           "DEFAULT_THREADS", "BACKENDS"]
