"""Fixed-bin histograms and radial distributions of a contact network (numba).

Histograms are raw counts on caller-given bin edges, so they add up across packings.
Binning follows ``numpy.histogram``: bin ``k`` is ``[e_k, e_{k+1})``, the last bin
also holds ``e_last``; values outside ``[e_0, e_last]`` and NaN are not counted.
Uniform edges take a fast path (direct index, corrected against the edges, so the
result is the same as the general binary search).

Radial distributions are raw counts of ordered pairs at normalised distance ``r``
(the ``2 pi r`` normalisation and the density are left to the reducer). Distances
are minimum-image, so bins beyond half the box side are incomplete.

Jitted cores: ``_histogram_core(values, edges, uniform, counts)`` and
``_radial_core(points, cls1, cls2, scales, box, edges, uniform, counts)`` (both add into
``counts``).
"""

import numpy as np
from numba import njit

from kernels.names import HISTOGRAMS, OBSERVABLES  # noqa: F401 - re-exported
from kernels.cells import _candidate_pairs_core
from kernels.space import minimum_image, separation


@njit(cache=True, inline="always")
def _uniform_code(x, e0, inv_w, nb):
    """The direct step of ``_bin_index`` on uniform edges, branch-free.

    Returns the bin when ``x`` is clear of every edge (the direct index is then
    exact), ``nb`` when ``x`` is not counted (far outside the edges, or NaN), and -1
    when ``x`` lies near an edge or just outside, where ``_bin_index`` corrects against
    the edges. Written with selects only, so that a vector loop can call it alone.
    """
    f = (x - e0) * inv_w
    inside = (f >= 0.0) & (f < nb)
    k = int(f if inside else 0.0)
    r = f - k
    clear = inside & (r > 1e-9) & (r < 1.0 - 1e-9)
    far = ~((f >= -1.0) & (f < nb + 1.0))
    return k if clear else (nb if far else -1)


@njit(cache=True, inline="always")
def _bin_index(x, edges, nb, uniform, inv_w, guide):
    """Bin of ``x`` (numpy.histogram convention) or -1 when outside or NaN.

    ``inv_w = nb / (edges[nb] - edges[0])``. With ``uniform`` the index is computed
    directly; a value within 1e-9 of a bin width of an edge is then corrected against
    the edges themselves, so both paths agree exactly. Otherwise ``guide`` (from
    ``_guide_table``) narrows a binary search to a few bins.
    """
    if uniform:
        c = _uniform_code(x, edges[0], inv_w, nb)
        if c >= 0:  # clear of both edges (the direct index is exact), or far outside or NaN
            return c if c < nb else -1
        k = min(max(int((x - edges[0]) * inv_w), 0), nb - 1)
        # one-step correction against the edges (uniform edges lie within a small
        # fraction of a bin of e0 + k w, see is_uniform), written without branches
        k -= x < edges[k]
        k += x >= edges[k + 1]
        if k < 0:
            return -1
        if k == nb:
            return nb - 1 if x == edges[nb] else -1
        return k
    if not (x >= edges[0] and x <= edges[nb]):
        return -1
    if x == edges[nb]:
        return nb - 1
    # guide table: the bins met by guide cell g lie in guide[g] .. guide[g + 1]
    m = guide.shape[0] - 1
    g = int((x - edges[0]) * (m * inv_w / nb))
    g = min(max(g, 0), m - 1)
    lo = max(guide[g] - 1, 0)
    hi = min(guide[g + 1] + 2, nb)  # edges[lo] <= x < edges[hi] once widened below
    while lo > 0 and x < edges[lo]:
        lo -= 1
    while hi < nb and x >= edges[hi]:
        hi += 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if x >= edges[mid]:
            lo = mid
        else:
            hi = mid
    return lo


@njit(cache=True)
def _guide_table(edges, uniform):
    """Guide table for non-uniform edges (4 guide cells per bin on average).

    ``guide[g]`` is the bin holding the left end of guide cell ``g`` of an even grid
    over ``[edges[0], edges[-1]]``; lookups then search only the few bins between
    ``guide[g]`` and ``guide[g + 1]``. Uniform edges need none (a 2-entry dummy).
    """
    nb = edges.shape[0] - 1
    if uniform:
        return np.zeros(2, dtype=np.int64)
    m = 4 * nb
    guide = np.empty(m + 1, dtype=np.int64)
    span = edges[nb] - edges[0]
    k = 0
    for g in range(m + 1):
        left = edges[0] + span * (g / m)
        while k < nb - 1 and edges[k + 1] <= left:
            k += 1
        guide[g] = k
    return guide


@njit(cache=True)
def _histogram_core(values, edges, uniform, counts):
    """Add the counts of ``values`` on ``edges`` into ``counts`` (int64, len(edges) - 1)."""
    nb = edges.shape[0] - 1
    inv_w = nb / (edges[nb] - edges[0])
    guide = _guide_table(edges, uniform)
    for t in range(values.shape[0]):
        k = _bin_index(values[t], edges, nb, uniform, inv_w, guide)
        if k >= 0:
            counts[k] += 1


@njit(cache=True)
def _radial_pairs(points, cls1, cls2, scales, box, edges, uniform, counts, guide, inv_w):
    """``_radial_core`` in any cell, tilted ones included: the pairs within reach from the
    cell list of ``kernels.cells`` (nearest images, ``kernels.space``), each binned once per
    centre. Same counts as ``_radial_core``'s grid, at a few times its cost."""
    nb = edges.shape[0] - 1
    npt = points.shape[0]
    smax = 0.0
    for p in range(npt):
        smax = max(smax, scales[cls1[p]])
        if cls2[p] >= 0:
            smax = max(smax, scales[cls2[p]])
    half = np.full(npt, 0.5 * edges[nb] * smax)
    pi, pj = _candidate_pairs_core(points, half, box, 0.0)
    for k in range(pi.shape[0]):
        p = pi[k]
        q = pj[k]
        dx, dy = separation(points[q, 0] - points[p, 0], points[q, 1] - points[p, 1], box)
        d = np.sqrt(dx * dx + dy * dy)
        for c in (cls1[p], cls2[p], cls1[q], cls2[q]):
            if c >= 0:
                b = _bin_index(d / scales[c], edges, nb, uniform, inv_w, guide)
                if b >= 0:
                    counts[b] += 1


@njit(cache=True)
def _radial_core(points, cls1, cls2, scales, box, edges, uniform, counts):
    """Ordered-pair counts of normalised distances between distinct points.

    Every point ``p`` stands for one or two centres whose length scales are
    ``scales[cls1[p]]`` and ``scales[cls2[p]]`` (``cls2[p] = -1``: no second centre).
    For each unordered pair ``{p, q}`` at minimum-image distance ``d``, every centre
    of ``p`` counts ``d / scale`` and so does every centre of ``q``. Grains: one
    centre per grain (its radius). Contacts: one centre per side of the contact (the
    radii of its two grains). Values outside the edges are not counted.

    Method: the points are sorted into a grid of cells about half the reach wide,
    stored column by column (``y`` fastest), so consecutive neighbour cells of one
    column that share a periodic shift form one contiguous run of points. For each
    cell, the runs within reach (each unordered pair of cells once; the run that
    begins with the cell itself first) are gathered into contiguous arrays with
    their shifts. Each point of the cell then works on the gathered points after it
    in a few tight loops that the compiler vectorises: the squared distances (one
    loop per kind of boundary: the minimum image is taken per pair only along a side
    where the neighbour cells would wrap onto themselves, i.e. a reach longer than
    about 0.4 of the box side), the pairs within reach kept without branches, and,
    with uniform edges and at most two distinct scales (the common case: bidisperse
    packings), their square roots and bins (``_uniform_code``; the rare values near
    a bin edge go through ``_bin_index``). A scalar loop then adds the counts with
    their multiplicities. Otherwise each pair within reach is binned with
    ``_bin_index``: with few distinct scales (``len(scales) <= 4``) the centres of a
    pair that share a scale are binned once with their multiplicity; with more every
    centre is binned on its own. Each distance is computed with the same operations
    as in a plain pair-by-pair loop over the same cells, so the counts are exact and
    do not depend on the method.

    A tilted cell (``box[2] != 0``) takes the plain pair loop of ``_radial_pairs``.
    """
    nb = edges.shape[0] - 1
    inv_w = nb / (edges[nb] - edges[0])
    guide = _guide_table(edges, uniform)
    rmax = edges[nb]
    npt = points.shape[0]
    if npt < 2 or rmax <= 0.0:
        return
    if box[2] != 0.0:
        _radial_pairs(points, cls1, cls2, scales, box, edges, uniform, counts, guide, inv_w)
        return
    Lx = box[0]
    Ly = box[1]
    nk = scales.shape[0]
    smax = 0.0
    for p in range(npt):
        if scales[cls1[p]] > smax:
            smax = scales[cls1[p]]
        if cls2[p] >= 0 and scales[cls2[p]] > smax:
            smax = scales[cls2[p]]
    inv = np.empty(nk)
    for k in range(nk):
        inv[k] = 1.0 / scales[k]
    grouped = nk <= 4
    vector = uniform and nk <= 2
    inv0 = inv[0]
    inv1 = inv[1] if nk > 1 else inv[0]
    e0 = edges[0]
    weight = np.zeros(max(nk, 1), dtype=np.int64)
    reach = rmax * smax
    reach2 = reach * reach
    # cells about half the reach wide, at most ~2 per point per side
    cap = 2 * int(np.sqrt(npt)) + 1
    nx = min(max(int(Lx / (reach / 2.0)), 1), cap)
    ny = min(max(int(Ly / (reach / 2.0)), 1), cap)
    hx = Lx / nx
    hy = Ly / ny
    cell_of = np.empty(npt, dtype=np.int64)
    wx = np.empty(npt)
    wy = np.empty(npt)
    for p in range(npt):
        x = points[p, 0] - Lx * np.floor(points[p, 0] / Lx)
        y = points[p, 1] - Ly * np.floor(points[p, 1] / Ly)
        wx[p] = x
        wy[p] = y
        cx = min(max(int(x / hx), 0), nx - 1)
        cy = min(max(int(y / hy), 0), ny - 1)
        cell_of[p] = cx * ny + cy
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    for p in range(npt):
        start[cell_of[p] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    mx = np.empty(npt)
    my = np.empty(npt)
    m1 = np.empty(npt, dtype=np.int64)
    m2 = np.empty(npt, dtype=np.int64)
    for p in range(npt):
        c = cell_of[p]
        s = fill[c]
        mx[s] = wx[p]
        my[s] = wy[p]
        m1[s] = cls1[p]
        m2[s] = cls2[p]
        fill[c] += 1
    # centres of scale 1 and of scale 0 per point (used with at most two scales)
    n1 = np.empty(npt, dtype=np.int64)
    n0 = np.empty(npt, dtype=np.int64)
    for s in range(npt):
        n1[s] = (m1[s] == 1) + (m2[s] == 1)
        n0[s] = 1 + (m2[s] >= 0) - n1[s]
    # Neighbour cells within the reach. When they would wrap onto themselves along
    # a side, every cell of that side is visited once and the minimum image is
    # taken per pair; otherwise the periodic shift is applied per cell.
    sx = int(np.ceil(reach / hx))
    sy = int(np.ceil(reach / hy))
    full_x = 2 * sx + 1 >= nx
    full_y = 2 * sy + 1 >= ny
    ax0 = 0 if full_x else -sx
    ax1 = nx if full_x else sx + 1
    ay0 = 0 if full_y else -sy
    ay1 = ny if full_y else sy + 1
    # The neighbour points of one cell, gathered: coordinates, periodic shift, and
    # centres per scale (vector path) or index (general path); first the run of
    # cells that begins with the cell itself, then the other runs of consecutive
    # cells of one column with one shift. + 8: the vector loops run over whole
    # vectors of 8.
    nbx = np.zeros(npt + 8)
    nby = np.zeros(npt + 8)
    nsx = np.zeros(npt + 8)
    nsy = np.zeros(npt + 8)
    nn0 = np.empty(npt, dtype=np.int64)
    nn1 = np.empty(npt, dtype=np.int64)
    nt = np.empty(npt, dtype=np.int64)
    mruns = 2 * (ax1 - ax0) + 2
    run_lo = np.empty(mruns, dtype=np.int64)
    run_hi = np.empty(mruns, dtype=np.int64)
    run_sx = np.empty(mruns)
    run_sy = np.empty(mruns)
    buf = np.empty(npt + 8)  # squared distances of one point to the gathered ones
    dacc = np.zeros(npt + 8)  # those within reach, then their distances
    iacc = np.empty(npt, dtype=np.int64)  # and their places in buf
    code0 = np.empty(npt + 8, dtype=np.int64)
    code1 = np.empty(npt + 8, dtype=np.int64)
    padded = np.zeros(nb + 1, dtype=np.int64)  # bin nb: not counted
    for ic in range(nx * ny):
        if start[ic] == start[ic + 1]:
            continue
        ix = ic // ny
        iy = ic - ix * ny
        nrun = 1  # run 0: the one beginning with cell ic
        for a in range(ax0, ax1):
            shx = 0.0
            if full_x:
                gx = a
                gapx = 0.0
            else:
                gx = ix + a
                if gx < 0:
                    gx += nx
                    shx = -Lx
                elif gx >= nx:
                    gx -= nx
                    shx = Lx
                gapx = (abs(a) - 1) * hx if abs(a) > 1 else 0.0
            last = -2  # last cell appended to the open run (-2: none)
            cur = -1  # the open run
            for b in range(ay0, ay1):
                shy = 0.0
                if full_y:
                    gy = b
                    gapy = 0.0
                else:
                    gy = iy + b
                    if gy < 0:
                        gy += ny
                        shy = -Ly
                    elif gy >= ny:
                        gy -= ny
                        shy = Ly
                    gapy = (abs(b) - 1) * hy if abs(b) > 1 else 0.0
                if gapx * gapx + gapy * gapy >= reach2:
                    continue
                g = gx * ny + gy
                if g < ic:
                    continue
                if g == last + 1 and shy == run_sy[cur]:
                    run_hi[cur] = start[g + 1]
                else:
                    cur = 0 if g == ic else nrun
                    if cur:
                        nrun += 1
                    run_lo[cur] = start[g]
                    run_hi[cur] = start[g + 1]
                    run_sx[cur] = shx
                    run_sy[cur] = shy
                last = g
        m = 0
        for j in range(nrun):
            lo = run_lo[j]
            ln = run_hi[j] - lo
            nbx[m:m + ln] = mx[lo:lo + ln]
            nby[m:m + ln] = my[lo:lo + ln]
            nsx[m:m + ln] = run_sx[j]
            nsy[m:m + ln] = run_sy[j]
            if vector:
                nn0[m:m + ln] = n0[lo:lo + ln]
                nn1[m:m + ln] = n1[lo:lo + ln]
            else:
                for i in range(ln):
                    nt[m + i] = lo + i
            m += ln
        for s in range(start[ic], start[ic + 1]):
            i0 = s - start[ic] + 1  # pairs with the later points of the cell and beyond
            n = m - i0
            xs = mx[s]
            ys = my[s]
            # views from i0, so that the loops index from 0 (no negative-index checks)
            n8 = (n + 7) & -8  # whole vectors (the tail is ignored)
            bx = nbx[i0:i0 + n8]
            by = nby[i0:i0 + n8]
            bsx = nsx[i0:i0 + n8]
            bsy = nsy[i0:i0 + n8]
            if full_x and full_y:
                for i in range(n8):
                    dx = minimum_image(bx[i] - (xs - bsx[i]), Lx)
                    dy = minimum_image(by[i] - (ys - bsy[i]), Ly)
                    buf[i] = dx * dx + dy * dy
            elif full_x:
                for i in range(n8):
                    dx = minimum_image(bx[i] - (xs - bsx[i]), Lx)
                    dy = by[i] - (ys - bsy[i])
                    buf[i] = dx * dx + dy * dy
            elif full_y:
                for i in range(n8):
                    dx = bx[i] - (xs - bsx[i])
                    dy = minimum_image(by[i] - (ys - bsy[i]), Ly)
                    buf[i] = dx * dx + dy * dy
            else:
                for i in range(n8):
                    dx = bx[i] - (xs - bsx[i])
                    dy = by[i] - (ys - bsy[i])
                    buf[i] = dx * dx + dy * dy
            # the pairs within reach (kept without branches), then their distances
            na = 0
            for i in range(n):
                d2 = buf[i]
                dacc[na] = d2
                iacc[na] = i
                na += not (d2 > reach2)
            if vector:
                for j in range((na + 7) & -8):  # whole vectors (the tail is ignored)
                    d = np.sqrt(dacc[j])
                    dacc[j] = d
                    code0[j] = _uniform_code(d * inv0, e0, inv_w, nb)
                    code1[j] = _uniform_code(d * inv1, e0, inv_w, nb)
                w0 = n0[s]
                w1 = n1[s]
                b0 = nn0[i0:m]
                b1 = nn1[i0:m]
                # the two scales written out: the same lines behind one inlined helper
                # measured three times slower for the whole kernel
                for j in range(na):
                    i = iacc[j]
                    k = code0[j]
                    if k < 0:
                        k = _bin_index(dacc[j] * inv0, edges, nb, uniform, inv_w, guide)
                        if k < 0:
                            k = nb
                    padded[k] += w0 + b0[i]
                    k = code1[j]
                    if k < 0:
                        k = _bin_index(dacc[j] * inv1, edges, nb, uniform, inv_w, guide)
                        if k < 0:
                            k = nb
                    padded[k] += w1 + b1[i]
                continue
            for j in range(na):
                d = np.sqrt(dacc[j])
                t = nt[i0 + iacc[j]]
                if nk <= 2:
                    w0 = n0[s] + n0[t]
                    w1 = n1[s] + n1[t]
                    if w0:
                        k = _bin_index(d * inv0, edges, nb, uniform, inv_w, guide)
                        if k >= 0:
                            counts[k] += w0
                    if w1:
                        k = _bin_index(d * inv1, edges, nb, uniform, inv_w, guide)
                        if k >= 0:
                            counts[k] += w1
                elif grouped:
                    weight[m1[s]] += 1
                    weight[m1[t]] += 1
                    if m2[s] >= 0:
                        weight[m2[s]] += 1
                    if m2[t] >= 0:
                        weight[m2[t]] += 1
                    for c in range(nk):
                        w = weight[c]
                        if w:
                            weight[c] = 0
                            k = _bin_index(d * inv[c], edges, nb, uniform, inv_w, guide)
                            if k >= 0:
                                counts[k] += w
                else:
                    k = _bin_index(d * inv[m1[s]], edges, nb, uniform, inv_w, guide)
                    if k >= 0:
                        counts[k] += 1
                    k = _bin_index(d * inv[m1[t]], edges, nb, uniform, inv_w, guide)
                    if k >= 0:
                        counts[k] += 1
                    if m2[s] >= 0:
                        k = _bin_index(d * inv[m2[s]], edges, nb, uniform, inv_w, guide)
                        if k >= 0:
                            counts[k] += 1
                    if m2[t] >= 0:
                        k = _bin_index(d * inv[m2[t]], edges, nb, uniform, inv_w, guide)
                        if k >= 0:
                            counts[k] += 1
    for k in range(nb):
        counts[k] += padded[k]


@njit(cache=True)
def _contact_points_core(src, dst, twin, hdx, hdy, frac, positions):
    """Unique contact points (one per contact) with their two grains.

    The contact of half-edge ``p`` is stored once, for the lower of ``p`` and its twin.
    Returns ``(points (m, 2), grain_a, grain_b)``.
    """
    nh = src.shape[0]
    pts = np.empty((nh // 2, 2))
    ra = np.empty(nh // 2, dtype=np.int64)
    rb = np.empty(nh // 2, dtype=np.int64)
    t = 0
    for p in range(nh):
        if p < twin[p]:
            g = src[p]
            pts[t, 0] = positions[g, 0] + frac[p] * hdx[p]
            pts[t, 1] = positions[g, 1] + frac[p] * hdy[p]
            ra[t] = g
            rb[t] = dst[p]
            t += 1
    return pts, ra, rb


def is_uniform(edges):
    """True when every edge lies within 1e-6 of a bin width of an evenly spaced grid.

    The uniform fast path of the binning corrects its direct index by at most one
    bin, which this guarantees.
    """
    nb = edges.shape[0] - 1
    ideal = np.linspace(edges[0], edges[-1], nb + 1)
    w = (edges[-1] - edges[0]) / nb
    return bool(np.all(np.abs(edges - ideal) <= 1e-6 * w))


def check_edges(name, edges):
    """Bin edges as a float64 array; ValueError naming the histogram when unusable."""
    arr = np.asarray(edges, dtype=np.float64)
    if arr.ndim != 1 or arr.shape[0] < 2:
        raise ValueError(f"bins[{name!r}]: expected a 1-D array of at least 2 edges, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"bins[{name!r}]: expected finite edges, got NaN or inf")
    if not np.all(np.diff(arr) > 0):
        raise ValueError(f"bins[{name!r}]: expected strictly increasing edges")
    return np.ascontiguousarray(arr)


def histogram(values, edges):
    """Counts of ``values`` on ``edges`` (int64), numpy.histogram convention."""
    e = check_edges("values", edges)
    v = np.ascontiguousarray(np.asarray(values, dtype=np.float64).ravel())
    counts = np.zeros(e.shape[0] - 1, dtype=np.int64)
    _histogram_core(v, e, is_uniform(e), counts)
    return counts
