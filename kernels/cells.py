"""Cell list feeding a Verlet (pair) list with a skin, in a periodic box (numba).

A pair ``(i, j)`` is a *candidate* when its minimum-image centre distance is below
``radii[i] + radii[j] + skin``. The candidates are found with a cell list whose cells
are at least ``2 max(radii) + skin`` wide, so only the 3 x 3 block of cells around a
disk can hold its candidates. When fewer than 3 such cells fit along a side, that
direction gets a single cell (every disk is then checked along it), so the search is
exact for any box aspect and any disk size; it never misses a pair.

Only the nearest periodic image of each pair is considered (see ``kernels.space``):
a pair is listed once even if a second image would also be in range, which can only
happen when ``radii[i] + radii[j] + skin`` exceeds half a box side.

Jitted cores, usable from other numba code:

* ``_candidate_pairs_core(positions, radii, box, skin) -> (i, j)``: int64 arrays,
  ``i < j``, each pair once, sorted by ``i`` then ``j``. ``positions`` need not be
  wrapped into the box.
* ``_cell_grid(box, cutoff, n) -> (nx, ny)``: the cell counts used.

Checked wrapper: ``candidate_pairs(positions, radii, box, skin)``.
"""

import numpy as np
from numba import njit

from kernels.space import _as_box, _as_positions, remainder, widths


@njit(cache=True)
def _cell_grid(box, cutoff, n):
    """Number of cells along x and y for cells at least ``cutoff`` wide (between opposite
    sides: the cells of a tilted cell are parallelograms, see ``kernels.space.widths``).

    Fewer than 3 cells along a side collapse to 1 (so the 3 neighbouring cells along
    that side are never the same cell twice). The count is capped near ``2 sqrt(n)``
    per side, which keeps the grid small when ``cutoff`` is tiny; larger cells are
    always correct.
    """
    cap = 2 * int(np.sqrt(n)) + 3
    out = np.empty(2, dtype=np.int64)
    wx, wy = widths(box)
    for k in range(2):
        if cutoff > 0.0:
            m = (wx if k == 0 else wy) / cutoff
            nk = cap if m >= cap else int(m)
        else:
            nk = cap
        if nk < 3:
            nk = 1
        out[k] = nk
    return out[0], out[1]


@njit(cache=True)
def _candidate_pairs_core(positions, radii, box, skin):
    """All pairs with minimum-image distance < radii[i] + radii[j] + skin.

    Returns ``(pi, pj)``: int64 arrays, ``pi < pj``, sorted by ``pi`` then ``pj``.
    """
    n = positions.shape[0]
    Lx = box[0]
    Ly = box[1]
    xy = box[2]
    tilt = xy * Ly
    iLx = 1.0 / Lx
    iLy = 1.0 / Ly
    rmax = 0.0
    for i in range(n):
        if radii[i] > rmax:
            rmax = radii[i]
    cutoff = 2.0 * rmax + skin
    nx, ny = _cell_grid(box, cutoff, n)
    ncell = nx * ny

    # counting sort of disks into cells (stable: ascending index within a cell)
    cell_of = np.empty(n, dtype=np.int64)
    for i in range(n):
        # the cell's own (sheared) coordinates: x - xy y along a, y along b
        y = remainder(positions[i, 1], Ly)
        x = remainder(positions[i, 0] - xy * y, Lx)
        cx = int(x / Lx * nx)
        cy = int(y / Ly * ny)
        if cx >= nx:
            cx = nx - 1
        if cy >= ny:
            cy = ny - 1
        if cx < 0:
            cx = 0
        if cy < 0:
            cy = 0
        cell_of[i] = cx * ny + cy
    start = np.zeros(ncell + 1, dtype=np.int64)
    for i in range(n):
        start[cell_of[i] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    members = np.empty(n, dtype=np.int64)
    for i in range(n):
        c = cell_of[i]
        members[fill[c]] = i
        fill[c] += 1

    ox = np.array([-1, 0, 1]) if nx >= 3 else np.array([0])
    oy = np.array([-1, 0, 1]) if ny >= 3 else np.array([0])

    cap = 8 * n + 16
    out_i = np.empty(cap, dtype=np.int64)
    out_j = np.empty(cap, dtype=np.int64)
    count = 0
    row = np.empty(n, dtype=np.int64)
    for i in range(n):
        xi = positions[i, 0]
        yi = positions[i, 1]
        ri = radii[i]
        ci = cell_of[i]
        cx = ci // ny
        cy = ci - cx * ny
        m = 0
        for a in range(ox.shape[0]):
            gx = (cx + ox[a]) % nx
            for b in range(oy.shape[0]):
                gy = (cy + oy[b]) % ny
                g = gx * ny + gy
                for s in range(start[g], start[g + 1]):
                    j = members[s]
                    if j <= i:
                        continue
                    dx = positions[j, 0] - xi
                    dy = positions[j, 1] - yi
                    k = np.floor(dy * iLy + 0.5)
                    dy -= Ly * k
                    dx -= tilt * k
                    dx -= Lx * np.floor(dx * iLx + 0.5)
                    rc = ri + radii[j] + skin
                    if dx * dx + dy * dy < rc * rc:
                        row[m] = j
                        m += 1
        if m == 0:
            continue
        # insertion sort of the (short) row
        for t in range(1, m):
            v = row[t]
            u = t - 1
            while u >= 0 and row[u] > v:
                row[u + 1] = row[u]
                u -= 1
            row[u + 1] = v
        if count + m > cap:
            while count + m > cap:
                cap *= 2
            ni = np.empty(cap, dtype=np.int64)
            nj = np.empty(cap, dtype=np.int64)
            ni[:count] = out_i[:count]
            nj[:count] = out_j[:count]
            out_i = ni
            out_j = nj
        for t in range(m):
            out_i[count + t] = i
            out_j[count + t] = row[t]
        count += m
    return out_i[:count].copy(), out_j[:count].copy()


def _as_radii(radii, n):
    arr = np.asarray(radii, dtype=np.float64)
    if arr.shape != (n,):
        raise ValueError(f"radii: expected shape ({n},) to match positions, got {arr.shape}")
    if not (np.all(np.isfinite(arr)) and np.all(arr >= 0)):
        raise ValueError("radii: expected finite non-negative values, got negative, NaN or inf")
    return np.ascontiguousarray(arr)


def candidate_pairs(positions, radii, box, skin):
    """Pairs within ``radii[i] + radii[j] + skin`` of each other (minimum image).

    Parameters
    ----------
    positions : (n, 2) array of centres (need not be wrapped)
    radii : (n,) array of radii, >= 0
    box : (Lx, Ly), positive
    skin : float >= 0, the extra distance beyond contact

    Returns
    -------
    (i, j) : int64 arrays with ``i < j``, each pair once, sorted by ``i`` then ``j``.

    The jitted core is ``kernels.cells._candidate_pairs_core`` (same arguments, all
    float64 arrays), callable from other numba code.
    """
    pos = _as_positions(positions)
    rad = _as_radii(radii, pos.shape[0])
    b = _as_box(box)
    s = float(skin)
    if not (np.isfinite(s) and s >= 0.0):
        raise ValueError(f"skin: expected a finite number >= 0, got {skin!r}")
    return _candidate_pairs_core(pos, rad, b, s)
