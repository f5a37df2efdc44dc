"""Per-void Delaunay triangulation and fictitious contacts (numba).

Each void of a valid packing is bounded by a convex cycle of grain centres (its
*minimum cycle*, ``docs/PHYSICS.md``). The cycle is unwrapped with the half-edge
displacements, so voids that straddle the periodic boundary need no special care.
Its Delaunay triangulation is built by the classical recursion for points in convex
position: the Delaunay triangle on a chord ``(i, j)`` has its apex at the vertex
between ``i`` and ``j`` that sees the chord under the largest angle (its
circumcircle then holds no other vertex of that side). That is O(k^2) for a k-gon.
Exact ties (cocircular vertices, e.g. a square void) go to the lowest vertex index
along the walk, so the choice is deterministic.

The ``z_v - 3`` chords that are not sides are the fictitious contacts; their length
is ``r = |r_gg'| / (r_g + r_g')``.

Jitted core: ``_triangulate_faces_core(face_ptr, face_he, src, dst, hdx, hdy, radii,
face_ok, max_sides)``. Checked wrapper: ``triangulate_polygon(points)`` for one
convex polygon (used in tests and by anyone with a polygon at hand).
"""

import numpy as np
from numba import njit


@njit(cache=True)
def _polygon_chords(px, py, k, chord_i, chord_j):
    """Delaunay chords of the convex polygon ``(px[:k], py[:k])`` (counter-clockwise).

    Writes the ``k - 3`` diagonals into ``chord_i, chord_j`` (vertex indices,
    ``i < j``) and returns their count.
    """
    if k < 4:
        return 0
    stack_i = np.empty(k, dtype=np.int64)
    stack_j = np.empty(k, dtype=np.int64)
    top = 0
    stack_i[0] = 0
    stack_j[0] = k - 1
    top = 1
    nc = 0
    while top > 0:
        top -= 1
        i = stack_i[top]
        j = stack_j[top]
        if j - i < 2:
            continue
        best = -1.0
        mbest = i + 1
        for m in range(i + 1, j):
            ax = px[i] - px[m]
            ay = py[i] - py[m]
            bx = px[j] - px[m]
            by = py[j] - py[m]
            ang = np.arctan2(abs(ax * by - ay * bx), ax * bx + ay * by)
            if ang > best:
                best = ang
                mbest = m
        m = mbest
        if m - i >= 2:
            chord_i[nc] = i
            chord_j[nc] = m
            nc += 1
            stack_i[top] = i
            stack_j[top] = m
            top += 1
        if j - m >= 2:
            chord_i[nc] = m
            chord_j[nc] = j
            nc += 1
            stack_i[top] = m
            stack_j[top] = j
            top += 1
    return nc


@njit(cache=True)
def _triangulate_faces_core(face_ptr, face_he, src, dst, hdx, hdy, radii, face_ok, max_sides):
    """Fictitious contacts of every face with ``face_ok`` and at most ``max_sides`` sides.

    Returns ``(fa, fb, flen, fface, triangles, done)``: the fictitious contacts as
    grain pairs ``(fa, fb)`` with their length ``r`` and face; ``triangles[f]`` the
    number of triangles of face ``f`` (``z_v - 2``; 0 when not triangulated) and
    ``done[f]`` whether face ``f`` was triangulated.
    """
    nf = face_ptr.shape[0] - 1
    total = 0
    kmax = 0
    for f in range(nf):
        k = face_ptr[f + 1] - face_ptr[f]
        if face_ok[f] and 3 <= k <= max_sides:
            total += k - 3
            if k > kmax:
                kmax = k
    fa = np.empty(total, dtype=np.int64)
    fb = np.empty(total, dtype=np.int64)
    flen = np.empty(total)
    fface = np.empty(total, dtype=np.int64)
    triangles = np.zeros(nf, dtype=np.int64)
    done = np.zeros(nf, dtype=np.bool_)
    px = np.empty(kmax + 1)
    py = np.empty(kmax + 1)
    vg = np.empty(kmax + 1, dtype=np.int64)
    ci = np.empty(kmax + 1, dtype=np.int64)
    cj = np.empty(kmax + 1, dtype=np.int64)
    t = 0
    for f in range(nf):
        a = face_ptr[f]
        k = face_ptr[f + 1] - a
        if not (face_ok[f] and 3 <= k <= max_sides):
            continue
        x = 0.0
        y = 0.0
        for s in range(k):
            p = face_he[a + s]
            px[s] = x
            py[s] = y
            vg[s] = src[p]
            x += hdx[p]
            y += hdy[p]
        nc = _polygon_chords(px, py, k, ci, cj)
        for c in range(nc):
            i = ci[c]
            j = cj[c]
            ddx = px[j] - px[i]
            ddy = py[j] - py[i]
            fa[t] = vg[i]
            fb[t] = vg[j]
            flen[t] = np.sqrt(ddx * ddx + ddy * ddy) / (radii[vg[i]] + radii[vg[j]])
            fface[t] = f
            t += 1
        triangles[f] = nc + 1
        done[f] = True
    return fa[:t].copy(), fb[:t].copy(), flen[:t].copy(), fface[:t].copy(), triangles, done


def triangulate_polygon(points):
    """Delaunay diagonals of a convex polygon given counter-clockwise, as ``(i, j)`` arrays."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 3:
        raise ValueError(f"points: expected a (k, 2) array with k >= 3, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points: expected finite coordinates, got NaN or inf")
    k = pts.shape[0]
    ci = np.empty(k, dtype=np.int64)
    cj = np.empty(k, dtype=np.int64)
    px = np.ascontiguousarray(pts[:, 0])
    py = np.ascontiguousarray(pts[:, 1])
    nc = _polygon_chords(px, py, k, ci, cj)
    return ci[:nc].copy(), cj[:nc].copy()
