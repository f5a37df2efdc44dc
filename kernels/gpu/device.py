"""The CUDA side of the GPU block: the batch kernel, one thread block per packing (numba-cuda,
the ``gpu`` extra; imported only when a CUDA backend runs).

``numba.cuda`` is a module global here on purpose: numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1``) runs a kernel by swapping the ``cuda`` globals of its module for a
simulated one. Some numba-cuda builds call ``np.row_stack``, removed in numpy 2.4; the alias it
meant (``np.vstack``) is restored before the import.

Block sums: each warp sums its threads' partials with shuffles (``shfl_down_sync``, offsets 16,
8, 4, 2, 1) and its lane 0 writes the warp's sum to shared memory; after one barrier the first
warp sums the warps' sums the same way (``put_sum``, ``put_max``, ``total``): two barriers a
reduction, one reduction a FIRE step, whatever the block's size. The order of the additions is
the shared-memory trees' of the emulation (``kernels.gpu.block.make_shared_reduction``).
numba's CUDA simulator has no shuffles: this module gives it one (``_simulated_shfl_down_sync``,
the lanes of a warp exchanging their values between two waits on the warp's own barrier), so
that the simulator runs the kernel's own reductions.

The kernel is compiled without floating-point contraction (NVVM's ``-fma=0``; numba-cuda's
default contracts a multiply and an add into one fused multiply-add, which the CPU emulation
does not do), so that the kernel does the emulation's operations with the same rounding: a
search is a long chaotic sequence of steps, and one rounding apart is enough to end it in
another minimum of the same energy window. It is compiled to PTX and linked without link-time
optimisation (``lto=False``): numba-cuda's default where nvJitLink is installed hands NVVM's
intermediate code to nvJitLink, which generates the machine code itself and contracts again.
On an H200 with the LTO default, 0 of 16 whole searches (N_G 256 and 1024) ended with the
emulation's bits; without it, 16 of 16 (``benchmarks/bench_gpu.py --check``).

The device's clock: ``%globaltimer`` (ns), read by thread 0 at a launch's start and end.
"""

import contextlib
from functools import lru_cache
import time

import numpy as np

if not hasattr(np, "row_stack"):
    np.row_stack = np.vstack

from numba import config, cuda, float64  # noqa: E402 (after the numpy alias)

from kernels.gpu.block import make_block  # noqa: E402
from kernels.gpu.state import N_ST, ROWS, WARP  # noqa: E402


def _sync():
    cuda.syncthreads()


def _slot_add(cells, c):
    return cuda.atomic.add(cells, (0, c), 1)


def _put_sum(red, k, t, v):
    """Thread ``t``'s partial of row ``k``: the warp's tree by shuffles, lane 0 writes it."""
    nt = cuda.blockDim.x
    mask = 0xFFFFFFFF if nt >= 32 else (1 << nt) - 1
    s = (32 if nt >= 32 else nt) // 2
    while s > 0:
        v += cuda.shfl_down_sync(mask, v, s)
        s //= 2
    if t % 32 == 0:
        red[k, t // 32] = v


def _put_max(red, k, t, v):
    nt = cuda.blockDim.x
    mask = 0xFFFFFFFF if nt >= 32 else (1 << nt) - 1
    s = (32 if nt >= 32 else nt) // 2
    while s > 0:
        o = cuda.shfl_down_sync(mask, v, s)
        if o > v:
            v = o
        s //= 2
    if t % 32 == 0:
        red[k, t // 32] = v


def _total(t0, t1, nt, red, sh, out, nsum, nmax):
    """After a barrier, the first warp sums (rows ``< nsum``) or maxes the warps' results by
    shuffles; lane 0 writes them to ``sh[out ...]``."""
    cuda.syncthreads()
    if t0 < 32:
        nw = nt // 32 if nt >= 32 else 1
        mask = 0xFFFFFFFF if nt >= 32 else (1 << nt) - 1
        for k in range(nsum + nmax):
            v = red[k, t0] if t0 < nw else 0.0
            s = nw // 2
            while s > 0:
                o = cuda.shfl_down_sync(mask, v, s)
                if k < nsum:
                    v += o
                elif o > v:
                    v = o
                s //= 2
            if t0 == 0:
                sh[out + k] = v


def _now_simulated():
    return float(time.time_ns())


def _simulated_shfl_down_sync(self, mask, value, delta):
    """``shfl_down_sync`` for numba's simulator (a method of its fake ``cuda`` module): lane
    ``l`` gets lane ``l + delta``'s value, its own where that lane is not in the warp. Every
    lane of the warp must call it (as on a GPU, where ``mask`` names them all)."""
    import threading

    th = threading.current_thread()
    nt = self.blockDim.x
    width = 32 if nt >= 32 else nt
    lane = th.thread_id % 32
    key = (tuple(th.blockIdx), th.thread_id // 32)
    with _SIM_LOCK:
        slot = self.__dict__.setdefault("_warps", {}).get(key)
        if slot is None:
            slot = self._warps[key] = ([None] * width, threading.Barrier(width))
    values, barrier = slot
    values[lane] = value
    barrier.wait()
    src = lane + delta
    out = values[src] if src < width else value
    barrier.wait()
    return out


if config.ENABLE_CUDASIM:
    import threading as _threading

    from numba.cuda.simulator.kernelapi import FakeCUDAModule

    _SIM_LOCK = _threading.Lock()
    if not hasattr(FakeCUDAModule, "shfl_down_sync"):
        FakeCUDAModule.shfl_down_sync = _simulated_shfl_down_sync


if not config.ENABLE_CUDASIM:
    from llvmlite import ir
    from numba.cuda import types
    from numba.cuda.extending import intrinsic

    @intrinsic
    def _globaltimer_u64(typingctx):
        sig = types.uint64()

        def codegen(context, builder, sig, args):
            asm = ir.InlineAsm(ir.FunctionType(ir.IntType(64), []), "mov.u64 $0, %globaltimer;",
                               "=l", side_effect=True)
            return builder.call(asm, [])

        return sig, codegen

    def _now():
        """The device's ``%globaltimer`` in ns, as float64."""
        return float64(_globaltimer_u64())


#: registers a thread may use by default: 64 lets 1024 threads share an SM (its 65536 registers
#: / 64: 32 warps, half of the 64 it can hold; 4 blocks of 256 threads, 2 of 512, 1 of 1024).
#: ptxas then keeps the forces' pair loop free of spills (the per-disk sums and the cold phases
#: spill a few words to local memory, which the L1 cache holds: benchmarks/gpu_ptx.py and
#: docs/GPU.md).
DEFAULT_REGISTERS = 64
REGISTER_FILE = 65536  # registers an SM holds (sm_90)


def register_bound(nt, max_registers=None) -> int:
    """The bound on registers per thread a kernel of ``nt`` threads per block is compiled with:
    ``max_registers`` (default ``DEFAULT_REGISTERS``), at most 255 and at most what lets one
    block fit an SM (``REGISTER_FILE / nt``, a multiple of 8: 128 at 512 threads, 64 at 1024).
    Two requests with the same bound are one kernel, compiled once."""
    return min(max_registers or DEFAULT_REGISTERS, 255, REGISTER_FILE // nt // 8 * 8)


def kernel(nt, exponent=2.0, max_registers=None):
    """The batch kernel for blocks of ``nt`` threads and the potential's ``exponent`` (2.0,
    2.5 or None: ``kernels.gpu.batch.exponent_kind``): block ``k`` runs the O'Hern search of
    packing ``which[k]`` from its state (arguments: ``which`` and ``kernels.gpu.block``'s
    arrays with a leading batch axis). ``max_registers`` per thread: ``register_bound``'s
    (default ``DEFAULT_REGISTERS``). Registers never change the results. One kernel per
    (``nt``, ``exponent``, bound), made once per process."""
    return _kernel(nt, exponent, register_bound(nt, max_registers))


@lru_cache(maxsize=None)
def _kernel(nt, exponent, regs):
    device = cuda.jit(device=True)
    put_sum, put_max, total = device(_put_sum), device(_put_max), device(_total)
    now = device(_now_simulated if config.ENABLE_CUDASIM else _now)
    search = make_block(device, device(_sync), device(_slot_add), put_sum, put_max, total, now,
                        exponent).search

    def run(which, xy, fl, nbr, ninv, iv, cells, prm, st):
        b = which[cuda.blockIdx.x]
        t = cuda.threadIdx.x
        red = cuda.shared.array((ROWS, WARP), dtype=float64)
        sh = cuda.shared.array(N_ST, dtype=float64)
        search(t, t + 1, nt, xy[b], fl[b], nbr[b], ninv[b], iv[b], cells[b], red, sh, prm[b],
               st[b])

    if config.ENABLE_CUDASIM:  # (the simulator takes no register bound and links nothing)
        return cuda.jit(run)
    # (the function given to jit itself: numba-cuda 0.30's decorator form drops ``lto``)
    return cuda.jit(run, max_registers=regs, lto=False)


def occupancy(nt, exponent=2.0, max_registers=None) -> dict:
    """What a compiled kernel takes and how many of its blocks the device holds at once:
    ``registers`` and ``local_bytes`` (spills) per thread, ``shared_bytes`` per block,
    ``blocks_per_sm``, ``sms`` and ``slots`` (blocks resident at once, the CUDA occupancy
    calculator's). The kernel must have been launched (compiled) with these arguments. Under
    the simulator: one slot."""
    if config.ENABLE_CUDASIM:
        return {"registers": 0, "local_bytes": 0, "shared_bytes": 0, "blocks_per_sm": 1, "sms": 1,
                "slots": 1}
    k = kernel(nt, exponent, max_registers)
    if not k.overloads:
        raise RuntimeError("occupancy: the kernel has not been compiled yet (launch it first)")
    kern = next(iter(k.overloads.values()))
    slots = int(kern.max_cooperative_grid_blocks(nt))
    sms = int(cuda.get_current_device().MULTIPROCESSOR_COUNT)
    return {"registers": int(kern.regs_per_thread), "local_bytes": int(kern.local_mem_per_thread),
            "shared_bytes": int(kern.shared_mem_per_block), "blocks_per_sm": slots // sms,
            "sms": sms, "slots": slots}


def available() -> bool:
    """Whether a CUDA device (or the simulator) is there."""
    return bool(cuda.is_available())


def name() -> str:
    """``cuda:<device name>`` or ``cuda-simulator``."""
    if config.ENABLE_CUDASIM:
        return "cuda-simulator"
    n = cuda.get_current_device().name
    return "cuda:" + (n.decode() if isinstance(n, bytes) else str(n))


@contextlib.contextmanager
def _uncontracted():
    """NVVM compiles without fused multiply-adds while this is open (the kernel compiles at its
    first launch)."""
    if config.ENABLE_CUDASIM:
        yield
        return
    from numba.cuda.cudadrv import nvvm

    compile_ir = nvvm.compile_ir

    def no_fma(llvmir, **options):
        options["fma"] = False
        return compile_ir(llvmir, **options)

    nvvm.compile_ir = no_fma
    try:
        yield
    finally:
        nvvm.compile_ir = compile_ir


def upload(arrays, stream=0):
    """The batch's arrays copied to the device."""
    return [cuda.to_device(a, stream=stream) for a in arrays]


def start(nt, exponent, which, dev, max_registers=None, stream=0):
    """Launch one block of ``nt`` threads per entry of ``which`` on uploaded arrays; returns at
    once."""
    with _uncontracted():
        k = kernel(nt, exponent, max_registers)
        if stream:
            k[which.shape[0], nt, stream](which, *dev)
        else:
            k[which.shape[0], nt](which, *dev)
    return dev


def launch(nt, exponent, which, arrays, max_registers=None):
    """Copy the batch's arrays to the device on a stream of their own and launch one block per
    packing there; returns at once (``collect`` waits, ``ended`` asks). The handle holds the
    stream, the device arrays and an event recorded after the kernel."""
    stream = cuda.stream()
    dev = upload(arrays, stream)
    on = cuda.to_device(which, stream=stream)
    start(nt, exponent, on, dev, max_registers, stream)
    event = None  # (the simulator runs a launch before it returns, and has no event queries)
    if not config.ENABLE_CUDASIM:
        event = cuda.event(timing=False)
        event.record(stream)
    return {"stream": stream, "arrays": dev, "which": on, "event": event}


def ended(handle) -> bool:
    """Whether a launch has ended (never waits)."""
    return handle["event"] is None or bool(handle["event"].query())


def wait():
    """Wait for the launched kernels."""
    cuda.synchronize()


def collect(handle):
    """Wait for a launch and return ``xy``, ``fl`` and the state rows (the first, second and
    last arrays) copied back."""
    stream = handle["stream"]
    stream.synchronize()
    dev = handle["arrays"]
    out = dev[0].copy_to_host(stream=stream), dev[1].copy_to_host(stream=stream), \
        dev[-1].copy_to_host(stream=stream)
    stream.synchronize()
    return out
