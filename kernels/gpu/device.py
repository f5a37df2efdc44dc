"""The CUDA side of the GPU block: the batch kernel, one thread block per packing (numba-cuda,
the ``gpu`` extra; imported only when a CUDA backend runs).

``numba.cuda`` is a module global here on purpose: numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1``) runs a kernel by swapping the ``cuda`` globals of its module for a
simulated one. Some numba-cuda builds call ``np.row_stack``, removed in numpy 2.4; the alias it
meant (``np.vstack``) is restored before the import.

The kernel is compiled without floating-point contraction (NVVM's ``-fma=0``; numba-cuda's
default contracts a multiply and an add into one fused multiply-add, which the CPU emulation
does not do), so that the kernel does the emulation's operations with the same rounding: a
search is a long chaotic sequence of steps, and one rounding apart is enough to end it in
another minimum of the same energy window. It is compiled to PTX and linked without link-time
optimisation (``lto=False``): numba-cuda's default where nvJitLink is installed hands NVVM's
intermediate code to nvJitLink, which generates the machine code itself and contracts again.
On an H200 with the LTO default, 0 of 16 whole searches (N_G 256 and 1024) ended with the
emulation's bits (same statuses, energies within the window; positions apart as far as a 1-ulp
change of the start moves them on the CPU); the PTX route is what ``tests/test_gpu.py`` checks.
"""

import contextlib
from functools import lru_cache

import numpy as np

if not hasattr(np, "row_stack"):
    np.row_stack = np.vstack

from numba import config, cuda, float64  # noqa: E402 (after the numpy alias)

from kernels.gpu.block import ROWS, make_block  # noqa: E402


def _sync():
    cuda.syncthreads()


def _slot_add(cells, c):
    return cuda.atomic.add(cells, (0, c), 1)


#: registers a thread may use: the whole search is one kernel and, unbounded, takes 255 per
#: thread (ptxas for sm_90); a block of ``nt`` threads must fit the SM's 65536 registers
REGISTER_FILE = 65536


@lru_cache(maxsize=None)
def kernel(nt, max_registers=None):
    """The batch kernel for blocks of ``nt`` threads: block ``b`` runs the O'Hern search of
    packing ``b`` (arguments: ``kernels.gpu.block``'s arrays with a leading batch axis).
    ``max_registers`` per thread (default: as many as let one block fit an SM, at most 255;
    fewer let more blocks share an SM, at the cost of spills). Registers never change the
    results."""
    device = cuda.jit(device=True)
    ohern = make_block(device, device(_sync), device(_slot_add)).ohern
    regs = max_registers or min(255, REGISTER_FILE // nt // 8 * 8)

    def run(fl, nbr, ninv, iv, cells, prm, out):
        b = cuda.blockIdx.x
        t = cuda.threadIdx.x
        red = cuda.shared.array((ROWS, nt), dtype=float64)
        ohern(t, t + 1, nt, fl[b], nbr[b], ninv[b], iv[b], cells[b], red, prm[b], out[b])

    if config.ENABLE_CUDASIM:  # (the simulator takes no register bound and links nothing)
        return cuda.jit(run)
    # (the function given to jit itself: numba-cuda 0.30's decorator form drops ``lto``)
    return cuda.jit(run, max_registers=regs, lto=False)


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


def upload(arrays):
    """The batch's arrays copied to the device."""
    return [cuda.to_device(a) for a in arrays]


def start(nt, dev, max_registers=None):
    """Launch one block of ``nt`` threads per packing on uploaded arrays; returns at once."""
    with _uncontracted():
        kernel(nt, max_registers)[dev[0].shape[0], nt](*dev)
    return dev


def launch(nt, arrays, max_registers=None):
    """Copy the batch's arrays to the device and launch one block per packing; returns at once
    (``collect`` waits). The handle holds the device arrays."""
    return start(nt, upload(arrays), max_registers)


def wait():
    """Wait for the launched kernels."""
    cuda.synchronize()


def collect(dev):
    """Wait for a launched batch and return ``fl`` and the results (the first and last arrays)
    copied back."""
    cuda.synchronize()
    return dev[0].copy_to_host(), dev[-1].copy_to_host()
