"""The CUDA side of the GPU block: the batch kernel, one thread block per packing (numba-cuda,
the ``gpu`` extra; imported only when a CUDA backend runs).

``numba.cuda`` is a module global here on purpose: numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1``) runs a kernel by swapping the ``cuda`` globals of its module for a
simulated one. Some numba-cuda builds call ``np.row_stack``, removed in numpy 2.4; the alias it
meant (``np.vstack``) is restored before the import.
"""

from functools import lru_cache

import numpy as np

if not hasattr(np, "row_stack"):
    np.row_stack = np.vstack

from numba import cuda, float64  # noqa: E402 (after the numpy alias)

from kernels.gpu.block import ROWS, make_block  # noqa: E402


def _sync():
    cuda.syncthreads()


def _slot_add(arr, i, v):
    return cuda.atomic.add(arr, i, v)


@lru_cache(maxsize=None)
def kernel(nt):
    """The batch kernel for blocks of ``nt`` threads: block ``b`` runs the O'Hern search of
    packing ``b`` (arguments: ``kernels.gpu.block``'s arrays with a leading batch axis)."""
    device = cuda.jit(device=True)
    block = make_block(device, device(_sync), device(_slot_add))

    @cuda.jit
    def run(pos, vel, frc, ref, rad0, rad, nbr, ninv, nnb, cell_of, cell_cnt, cell_mem, alive,
            alive2, prm, out):
        b = cuda.blockIdx.x
        t = cuda.threadIdx.x
        red = cuda.shared.array((ROWS, nt), dtype=float64)
        block(t, t + 1, nt, pos[b], vel[b], frc[b], ref[b], rad0[b], rad[b], nbr[b], ninv[b],
              nnb[b], cell_of[b], cell_cnt[b], cell_mem[b], alive[b], alive2[b], red, prm[b],
              out[b])

    return run


def available() -> bool:
    """Whether a CUDA device (or the simulator) is there."""
    return bool(cuda.is_available())


def name() -> str:
    """``cuda:<device name>`` or ``cuda-simulator``."""
    import os

    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        return "cuda-simulator"
    n = cuda.get_current_device().name
    return "cuda:" + (n.decode() if isinstance(n, bytes) else str(n))


def run_batch(nt, arrays):
    """Copy the batch's arrays to the device, run one block per packing, and return the
    positions and results (the first and last arrays) copied back."""
    dev = [cuda.to_device(a) for a in arrays]
    kernel(nt)[arrays[0].shape[0], nt](*dev)
    cuda.synchronize()
    return dev[0].copy_to_host(), dev[-1].copy_to_host()
