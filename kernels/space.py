"""Periodic cell: minimum image and wrapping (numba).

The cell is spanned by the lattice vectors ``a = (Lx, 0)`` and ``b = (xy Ly, Ly)``
(HOOMD's tilt factor ``xy``); ``xy = 0`` is the rectangular box ``[0, Lx) x [0, Ly)``.
Inside numba every kernel takes the cell as ``box = [Lx, Ly, xy]`` (float64, length 3);
the checked wrappers also accept ``(Lx, Ly)`` and read it as ``xy = 0``
(``_as_box``), which gives bit for bit the results of the rectangular code: every
tilt term is a product with ``xy = 0`` added to or subtracted from a coordinate.

Positions are kept in the fundamental domain ``[0, Lx) x [0, Ly)`` (a rectangle is a
fundamental domain of the tilted lattice too: fold ``y`` with ``b`` first, then ``x``
with ``a``). A separation is reduced the same way: ``dy`` to ``[-Ly/2, Ly/2]`` with
``b`` (which moves ``dx`` by ``xy Ly`` per period), then ``dx`` to ``[-Lx/2, Lx/2]``.
Any nonzero lattice vector is at least ``min(Lx, Ly)`` long, so for interaction
ranges below ``min(Lx, Ly) / 2`` this finds the only image in range, whatever the
tilt (``kernels.jamming`` checks the range). Cell lists need the widths between
opposite sides: ``Ly`` and ``Lx / sqrt(1 + xy^2)`` (``widths``).

Jitted functions usable from other numba code:

* ``minimum_image(dx, L)``: one component reduced to ``[-L/2, L/2]``.
* ``separation(dx, dy, box) -> (dx, dy)``: the nearest-image separation in the cell.
* ``near_image(dx, dy, Lx, Ly, tilt, hx, hy)``: the same by single shifts, for the force loops.
* ``remainder(x, L)``: one coordinate folded into ``[0, L)`` (cell lists, spatial orders).
* ``_fold(x, y, Lx, Ly, tilt)``: one point folded into the fundamental domain.
* ``widths(box) -> (wx, wy)``: distances between opposite sides of the cell.
* ``_wrap_core(positions, box)``: positions folded into ``[0, Lx) x [0, Ly)`` (new array);
  ``_wrap_inplace(positions, box)`` the same in place; ``_wrap_with(positions, ref, box)`` in
  place, moving a reference configuration ``ref`` by the same lattice vectors.

Checked wrappers: ``wrap(positions, box)``, ``_as_box(box)``.
"""

import math

import numpy as np
from numba import njit

from kernels.names import MAX_TILT


@njit(cache=True, inline="always")
def minimum_image(dx, L):
    """Nearest-image separation component: ``dx - L * round(dx / L)``.

    ``dx`` and ``L`` are float64 scalars, ``L > 0``. The result lies in
    ``[-L/2, L/2]`` (ties at exactly ``L/2`` go to ``-L/2``).
    """
    return dx - L * np.floor(dx / L + 0.5)


@njit(cache=True, inline="always")
def remainder(x, L):
    """``x`` folded into ``[0, L)`` by whole periods ``L``: ``x - L floor(x / L)`` (a tiny
    negative ``x`` may round to ``L``: ``_fold`` fixes that edge where it matters)."""
    return x - L * np.floor(x / L)


@njit(cache=True, inline="always")
def separation(dx, dy, box):
    """Nearest-image separation ``(dx, dy)`` in the cell ``box = [Lx, Ly, xy]``: ``dy`` reduced
    by whole periods ``b`` (each moves ``dx`` by ``xy Ly``), then ``dx`` by periods ``a``."""
    Ly = box[1]
    k = np.floor(dy / Ly + 0.5)
    dy = dy - Ly * k
    dx = dx - box[2] * Ly * k
    return dx - box[0] * np.floor(dx / box[0] + 0.5), dy


def near_image_py(dx, dy, Lx, Ly, tilt, hx, hy):
    """``separation`` by single shifts, for the force loops: ``dy`` (within one period of the
    image in range: positions wrapped, then moved less than a quarter box) shifted once by
    ``b`` (moving ``dx`` by ``tilt = xy Ly``), then ``dx`` by as many ``a`` as it takes (one in
    a rectangular box). ``hx, hy`` are ``Lx / 2, Ly / 2``. Branches instead of ``floor``: the
    shifts are rare, and the result is ``separation``'s. Plain Python on scalars, compiled here
    for the CPU (``near_image``) and by ``kernels.gpu.block`` for the GPU."""
    if dy > hy:
        dy -= Ly
        dx -= tilt
    elif dy < -hy:
        dy += Ly
        dx += tilt
    while dx > hx:
        dx -= Lx
    while dx < -hx:
        dx += Lx
    return dx, dy


near_image = njit(cache=True, inline="always")(near_image_py)


@njit(cache=True, inline="always")
def widths(box):
    """Distances between opposite sides of the cell: across ``b`` (``Lx / sqrt(1 + xy^2)``)
    and across ``a`` (``Ly``)."""
    return box[0] / np.sqrt(1.0 + box[2] * box[2]), box[1]


def fold_py(x, y, Lx, Ly, tilt):
    """One point ``(x, y)`` folded into ``[0, Lx) x [0, Ly)`` by lattice vectors of the cell
    (``tilt = xy Ly``). Plain Python on scalars, compiled here for the CPU (``_wrap_core``) and
    by ``kernels.gpu.block`` for the GPU."""
    k = math.floor(y / Ly)
    y = y - Ly * k
    x = x - tilt * k
    # floor can return y == L for tiny negative inputs: fold it back
    if y >= Ly:
        y -= Ly
        x -= tilt
    if y < 0.0:
        y = 0.0
    x = x - Lx * math.floor(x / Lx)
    if x >= Lx:
        x -= Lx
    if x < 0.0:
        x = 0.0
    return x, y


_fold = njit(cache=True, inline="always")(fold_py)


@njit(cache=True)
def _wrap_core(positions, box):
    """Return a copy of ``positions`` (n, 2) folded into ``[0, Lx) x [0, Ly)`` by lattice
    vectors of the cell ``box = [Lx, Ly, xy]``."""
    n = positions.shape[0]
    out = np.empty((n, 2))
    Lx = box[0]
    Ly = box[1]
    tilt = box[2] * Ly
    for i in range(n):
        out[i, 0], out[i, 1] = _fold(positions[i, 0], positions[i, 1], Lx, Ly, tilt)
    return out


@njit(cache=True)
def _wrap_inplace(positions, box):
    """``positions`` folded into the cell in place (``_wrap_core``'s values)."""
    w = _wrap_core(positions, box)
    for i in range(positions.shape[0]):
        positions[i, 0] = w[i, 0]
        positions[i, 1] = w[i, 1]


@njit(cache=True)
def _wrap_with(positions, ref, box):
    """Fold ``positions`` into the cell in place and shift ``ref`` by the same lattice vectors
    (so that a Verlet list built at ``ref`` stays valid; ``kernels.cg``). The steps are
    ``remainder``'s, counted so that ``ref`` can take them too; without ``_fold``'s edge fixes."""
    Lx = box[0]
    Ly = box[1]
    tilt = box[2] * Ly
    for i in range(positions.shape[0]):
        # y first: its period b moves x by the tilt (kernels.space)
        k = np.floor(positions[i, 1] / Ly)
        if k != 0.0:
            positions[i, 1] -= Ly * k
            ref[i, 1] -= Ly * k
            positions[i, 0] -= tilt * k
            ref[i, 0] -= tilt * k
        s = Lx * np.floor(positions[i, 0] / Lx)
        if s != 0.0:
            positions[i, 0] -= s
            ref[i, 0] -= s


def _as_positions(positions, name="positions"):
    arr = np.asarray(positions, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name}: expected an (n, 2) array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    return np.ascontiguousarray(arr)


def _as_box(box):
    """The cell as the kernels take it, ``[Lx, Ly, xy]`` (float64, contiguous), from
    ``(Lx, Ly)`` (xy = 0) or ``(Lx, Ly, xy)``; ValueError on anything else."""
    arr = np.asarray(box, dtype=np.float64)
    if arr.shape not in ((2,), (3,)):
        raise ValueError(f"box: expected the sides (Lx, Ly) or a tilted cell (Lx, Ly, xy), "
                         f"got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"box: expected finite values, got {arr.tolist()}")
    if not np.all(arr[:2] > 0):
        raise ValueError(f"box: expected two positive lengths, got {arr.tolist()}")
    if arr.shape == (3,) and abs(arr[2]) > MAX_TILT:
        raise ValueError(f"box: expected a tilt factor |xy| <= {MAX_TILT:g} (xy and xy - Lx/Ly "
                         f"describe the same lattice: reduce it), got xy = {arr[2]!r}")
    out = np.zeros(3)
    out[:arr.shape[0]] = arr
    return out


def wrap(positions, box):
    """Fold ``positions`` (n, 2) into ``[0, Lx) x [0, Ly)`` by lattice vectors of the cell
    ``box`` (``(Lx, Ly)`` or ``(Lx, Ly, xy)``)."""
    return _wrap_core(_as_positions(positions), _as_box(box))
