"""Periodic rectangular box: minimum image and wrapping (numba).

The box is ``[0, Lx) x [0, Ly)`` with periodic boundaries in both directions.
Only the nearest periodic image of a pair is ever considered, so callers must keep
every interaction range below half the box side (``kernels.jamming`` checks it).

Jitted functions usable from other numba code:

* ``minimum_image(dx, L)``: the component ``dx`` reduced to ``[-L/2, L/2]``.
* ``_wrap_core(positions, box)``: positions folded into ``[0, L)`` (new array).

Checked wrapper: ``wrap(positions, box)``.
"""

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def minimum_image(dx, L):
    """Nearest-image separation component: ``dx - L * round(dx / L)``.

    ``dx`` and ``L`` are float64 scalars, ``L > 0``. The result lies in
    ``[-L/2, L/2]`` (ties at exactly ``L/2`` go to ``-L/2``).
    """
    return dx - L * np.floor(dx / L + 0.5)


@njit(cache=True)
def _wrap_core(positions, box):
    """Return a copy of ``positions`` (n, 2) folded into ``[0, box[k])``."""
    n = positions.shape[0]
    out = np.empty((n, 2))
    for i in range(n):
        for k in range(2):
            L = box[k]
            x = positions[i, k] - L * np.floor(positions[i, k] / L)
            # floor can return x == L for tiny negative inputs: fold it back
            if x >= L:
                x -= L
            if x < 0.0:
                x = 0.0
            out[i, k] = x
    return out


def _as_positions(positions, name="positions"):
    arr = np.asarray(positions, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name}: expected an (n, 2) array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    return np.ascontiguousarray(arr)


def _as_box(box):
    arr = np.asarray(box, dtype=np.float64)
    if arr.shape != (2,):
        raise ValueError(f"box: expected two side lengths (Lx, Ly), got shape {arr.shape}")
    if not (np.all(np.isfinite(arr)) and np.all(arr > 0)):
        raise ValueError(f"box: expected two finite positive lengths, got {arr.tolist()}")
    return np.ascontiguousarray(arr)


def wrap(positions, box):
    """Fold ``positions`` (n, 2) into the periodic box ``[0, Lx) x [0, Ly)``."""
    return _wrap_core(_as_positions(positions), _as_box(box))
