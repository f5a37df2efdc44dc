"""GPU workers' kernels: a batch of packings, one thread block each (numba.cuda, the ``gpu``
extra), and the same block emulated on the CPU (numba.njit).

* ``jam_batch(n, energies, seeds, **settings) -> [Packing | BlockOverflow]`` (kernels.gpu.batch)
* ``kernels.gpu.block``: the block's phases and O'Hern search, written once for both targets.

Importing this package needs numba only; numba-cuda is imported when a CUDA backend runs.
"""

from kernels.gpu.batch import (BACKENDS, BlockOverflow, cuda_available, describe, jam_batch,
                               resolve_backend, simulated, threads_for)

__all__ = ["jam_batch", "BlockOverflow", "cuda_available", "describe", "resolve_backend",
           "threads_for", "simulated", "BACKENDS"]
