"""GPU workers' kernels: a batch of packings, one thread block each (numba.cuda, the ``gpu``
extra), and the same block emulated on the CPU (numba.njit).

* ``jam_batch(n, energies, seeds, **settings) -> [Packing | BlockOverflow | Suspended]``
  (kernels.gpu.batch); ``start_batch``, ``batch_done`` and ``finish_batch`` its halves.
* ``kernels.gpu.block``: the block's phases and O'Hern search, written once for every target.

Importing this package needs numba only; numba-cuda is imported when a CUDA backend runs.
"""

from kernels.gpu.batch import (BACKENDS, BlockOverflow, Suspended, batch_done, cuda_available,
                               describe, finish_batch, jam_batch, resolve_backend, simulated,
                               start_batch, threads_for)

__all__ = ["jam_batch", "start_batch", "batch_done", "finish_batch", "BlockOverflow", "Suspended",
           "cuda_available", "describe", "resolve_backend", "threads_for", "simulated", "BACKENDS"]
