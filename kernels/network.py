"""Contact network of a disk configuration in a periodic rectangular box (numba).

Conventions (``docs/PHYSICS.md``, "The contact network"):

* a contact is a pair with minimum-image centre distance ``|d| < r_g + r_g'``;
* rattlers (fewer than 3 contacts, or all contacts in a closed half-plane through the
  centre) are removed repeatedly until none is left;
* every contact between grains ``g`` and ``g'`` gives two *half-edges*, ``g -> g'``
  carrying the displacement ``d = minimum image of (r_g' - r_g)`` and ``g' -> g``
  carrying ``-d``; the displacement is what lets the faces be walked on the torus;
* the *rotation system* lists each grain's half-edges in counter-clockwise order of
  ``atan2(d_y, d_x)`` (CSR arrays, ``offsets[g]:offsets[g+1]``);
* the contact point of ``g -> g'`` is ``r_g + r_g/(r_g + r_g') d``, the same point
  seen from either grain;
* faces (voids) are walked with ``next(u -> v) = `` the half-edge just clockwise of
  ``v -> u`` around ``v``; each face is then traversed counter-clockwise (the face
  is on the left), so its contact-point polygon has a positive signed area.

Jitted cores, usable from other numba code:

* ``_overlapping_core(positions, radii, box, pi, pj) -> (bi, bj, dx, dy)``: the
  overlapping pairs among candidates
* ``_contact_bonds_core(positions, radii, box) -> (bi, bj, dx, dy)``
* ``_rattlers_core(n, bi, bj, dx, dy, angle_tol) -> rattler`` (bool mask)
* ``_rotation_core(n, bi, bj, dx, dy, keep, radii)`` -> half-edge CSR arrays
* ``_grain_pass_core(...)`` -> per half-edge relative angle and edge-triangle area
* ``_faces_core(...)`` -> faces as CSR over half-edges, sides, displacement sums, areas
* ``_pair_energy_core(radii, bi, bj, dx, dy, exponent)`` -> (total energy, virial sum)
* ``_bond_order_core(offsets, angle, m)`` -> per grain ``|psi_m|`` over its contacts

Checked wrappers: ``contact_bonds``, ``rattlers``, ``network``.
"""

import numpy as np
from numba import njit

from kernels.cells import _candidate_pairs_core
from kernels.potential import pair_energy_force
from kernels.space import _as_box, _as_positions, separation


@njit(cache=True)
def _overlapping_core(positions, radii, box, pi, pj):
    """The candidate pairs ``(pi, pj)`` that overlap, ``|d| < r_i + r_j``, in their order,
    with ``dx, dy`` the minimum image of ``r_j - r_i``."""
    m = pi.shape[0]
    dx = np.empty(m)
    dy = np.empty(m)
    keep = np.zeros(m, dtype=np.bool_)
    count = 0
    for k in range(m):
        i = pi[k]
        j = pj[k]
        ddx, ddy = separation(positions[j, 0] - positions[i, 0], positions[j, 1] - positions[i, 1], box)
        s = radii[i] + radii[j]
        if ddx * ddx + ddy * ddy < s * s:
            keep[k] = True
            dx[k] = ddx
            dy[k] = ddy
            count += 1
    bi = np.empty(count, dtype=np.int64)
    bj = np.empty(count, dtype=np.int64)
    ox = np.empty(count)
    oy = np.empty(count)
    t = 0
    for k in range(m):
        if keep[k]:
            bi[t] = pi[k]
            bj[t] = pj[k]
            ox[t] = dx[k]
            oy[t] = dy[k]
            t += 1
    return bi, bj, ox, oy


@njit(cache=True)
def _contact_bonds_core(positions, radii, box):
    """Contacts ``|d| < r_i + r_j`` as sorted bonds ``i < j`` with displacements.

    ``dx, dy`` is the minimum image of ``r_j - r_i``.
    """
    ci, cj = _candidate_pairs_core(positions, radii, box, 0.0)
    return _overlapping_core(positions, radii, box, ci, cj)


@njit(cache=True)
def _pair_energy_core(radii, bi, bj, dx, dy, exponent):
    """Total pair energy and virial sum ``sum r f(r)`` over the bonds.

    The potential is ``kernels.potential.pair_energy_force`` (its one definition).
    """
    energy = 0.0
    virial = 0.0
    for k in range(bi.shape[0]):
        s = radii[bi[k]] + radii[bj[k]]
        r = np.sqrt(dx[k] * dx[k] + dy[k] * dy[k])
        v, f = pair_energy_force(r, s, exponent)
        energy += v
        virial += r * f
    return energy, virial


#: Default angular tolerance of the half-plane rattler rule (radians): all contacts of a
#: grain lie in a closed half-plane when some line through its centre has every contact
#: on one side or within this angle of the line. The analysis passes its own
#: ``angle_tolerance * pi`` (the same value by default), so no grain it keeps can fail its
#: semicircle identity.
HALF_PLANE_TOL = 1e-9 * np.pi


@njit(cache=True)
def _load_bearing(g, start, nbr, ux, uy, rattler, sin_tol):
    """True when grain ``g`` can carry load among the non-rattlers: at least 3 contacts
    and no closed half-plane through its centre holding all of them.

    ``ux, uy`` are the unit contact directions seen from the grain (CSR ``start``). All
    contacts lie in a closed half-plane exactly when one of them, ``u_k``, has every
    other one on its left or on its line: ``u_k x u_j >= 0``, here ``>= -sin_tol``.
    O(z^2) products, no trigonometry.
    """
    a = start[g]
    b = start[g + 1]
    z = 0
    for s in range(a, b):
        if not rattler[nbr[s]]:
            z += 1
    if z < 3:
        return False
    for k in range(a, b):
        if rattler[nbr[k]]:
            continue
        all_left = True
        for j in range(a, b):
            if j == k or rattler[nbr[j]]:
                continue
            if ux[k] * uy[j] - uy[k] * ux[j] < -sin_tol:
                all_left = False
                break
        if all_left:
            return False
    return True


@njit(cache=True)
def _rattlers_core(n, bi, bj, dx, dy, angle_tol):
    """Mask of disks removed as rattlers, repeatedly until none is left: a disk is a
    rattler when it has fewer than 3 contacts with non-rattlers, or when all those
    contacts lie in a closed half-plane (seen from its centre; ``angle_tol`` radians of
    slack, see ``HALF_PLANE_TOL``). Such a disk cannot balance repulsive forces.

    ``(dx, dy)`` is the displacement ``r_bj - r_bi`` of each bond. Both rules only get
    easier to meet as neighbours are removed, so the surviving set (the largest set in
    which every disk is load-bearing) does not depend on the removal order; the one
    exception is a pair of coincident centres (a zero displacement has no direction),
    of which the first one checked goes.
    """
    m = bi.shape[0]
    start = np.zeros(n + 1, dtype=np.int64)
    for k in range(m):
        start[bi[k] + 1] += 1
        start[bj[k] + 1] += 1
    for g in range(n):
        start[g + 1] += start[g]
    fill = start[:-1].copy()
    nbr = np.empty(2 * m, dtype=np.int64)
    ux = np.empty(2 * m)
    uy = np.empty(2 * m)
    for k in range(m):
        d = np.sqrt(dx[k] * dx[k] + dy[k] * dy[k])
        ex = dx[k] / d if d > 0.0 else 0.0
        ey = dy[k] / d if d > 0.0 else 0.0
        p = fill[bi[k]]
        fill[bi[k]] += 1
        nbr[p] = bj[k]
        ux[p] = ex
        uy[p] = ey
        q = fill[bj[k]]
        fill[bj[k]] += 1
        nbr[q] = bi[k]
        ux[q] = -ex
        uy[q] = -ey
    sin_tol = np.sin(angle_tol)
    rattler = np.zeros(n, dtype=np.bool_)
    queued = np.ones(n, dtype=np.bool_)
    queue = np.empty(n + 2 * m, dtype=np.int64)
    for g in range(n):
        queue[g] = g
    head = 0
    tail = n
    while head < tail:
        g = queue[head]
        head += 1
        queued[g] = False
        if rattler[g] or _load_bearing(g, start, nbr, ux, uy, rattler, sin_tol):
            continue
        rattler[g] = True
        for s in range(start[g], start[g + 1]):
            h = nbr[s]
            if not rattler[h] and not queued[h]:
                queued[h] = True
                queue[tail] = h
                tail += 1
    return rattler


@njit(cache=True)
def _rotation_core(n, bi, bj, dx, dy, rattler, radii):
    """Half-edges of the non-rattler network in counter-clockwise order per grain.

    Returns ``(offsets, src, dst, hdx, hdy, angle, twin, frac)``: grain ``g`` owns
    half-edges ``offsets[g]:offsets[g+1]`` sorted by ``angle`` in ``(-pi, pi]``;
    ``src``/``dst`` the grains, ``hdx, hdy`` the displacement ``dst - src``,
    ``twin`` the position of the reverse half-edge, ``frac = r_src/(r_src + r_dst)``.
    """
    m = bi.shape[0]
    count = np.zeros(n + 1, dtype=np.int64)
    nb = 0
    for k in range(m):
        if not rattler[bi[k]] and not rattler[bj[k]]:
            count[bi[k] + 1] += 1
            count[bj[k] + 1] += 1
            nb += 1
    for g in range(n):
        count[g + 1] += count[g]
    offsets = count
    nh = 2 * nb
    src = np.empty(nh, dtype=np.int64)
    dst = np.empty(nh, dtype=np.int64)
    hdx = np.empty(nh)
    hdy = np.empty(nh)
    ang = np.empty(nh)
    twin = np.empty(nh, dtype=np.int64)
    fill = offsets[:-1].copy()
    for k in range(m):
        i = bi[k]
        j = bj[k]
        if rattler[i] or rattler[j]:
            continue
        p = fill[i]
        fill[i] += 1
        q = fill[j]
        fill[j] += 1
        src[p] = i
        dst[p] = j
        hdx[p] = dx[k]
        hdy[p] = dy[k]
        ang[p] = np.arctan2(dy[k], dx[k])
        src[q] = j
        dst[q] = i
        hdx[q] = -dx[k]
        hdy[q] = -dy[k]
        ang[q] = np.arctan2(-dy[k], -dx[k])
        twin[p] = q
        twin[q] = p
    # insertion sort of each grain's block by angle, carrying the twin links along
    for g in range(n):
        a = offsets[g]
        b = offsets[g + 1]
        for s in range(a + 1, b):
            t = s
            while t > a and ang[t - 1] > ang[t]:
                u = t - 1
                # swap u and t, fixing the twins' back pointers
                tu = twin[u]
                tt = twin[t]
                ang[u], ang[t] = ang[t], ang[u]
                dst[u], dst[t] = dst[t], dst[u]
                hdx[u], hdx[t] = hdx[t], hdx[u]
                hdy[u], hdy[t] = hdy[t], hdy[u]
                twin[u] = tt
                twin[t] = tu
                twin[tt] = u
                twin[tu] = t
                t -= 1
    frac = np.empty(nh)
    for p in range(nh):
        ru = radii[src[p]]
        frac[p] = ru / (ru + radii[dst[p]])
    return offsets, src, dst, hdx, hdy, ang, twin, frac


@njit(cache=True)
def _grain_pass_core(offsets, hdx, hdy, ang, frac):
    """Relative angle and edge-triangle area for each half-edge.

    For the half-edge at position ``p`` of grain ``g`` and its counter-clockwise
    successor ``p'`` (cyclically), ``theta[p] = angle[p'] - angle[p]`` in ``[0, 2 pi)``
    (the last one wraps by ``2 pi``; a grain with one contact gets ``2 pi``) and
    ``area[p] = 1/2 (r_gc x r_gc')`` with ``r_gc = frac d``.
    """
    n = offsets.shape[0] - 1
    nh = hdx.shape[0]
    theta = np.empty(nh)
    area = np.empty(nh)
    twopi = 2.0 * np.pi
    for g in range(n):
        a = offsets[g]
        b = offsets[g + 1]
        for p in range(a, b):
            q = p + 1 if p + 1 < b else a
            t = ang[q] - ang[p]
            if q == a:
                t += twopi
            theta[p] = t
            ux = frac[p] * hdx[p]
            uy = frac[p] * hdy[p]
            vx = frac[q] * hdx[q]
            vy = frac[q] * hdy[q]
            area[p] = 0.5 * (ux * vy - uy * vx)
    return theta, area


@njit(cache=True)
def _faces_core(offsets, src, dst, hdx, hdy, twin, frac):
    """Walk the faces of the map.

    Returns ``(face_of, face_ptr, face_he, sides, sum_dx, sum_dy, area)``:
    ``face_he[face_ptr[f]:face_ptr[f+1]]`` are the half-edges of face ``f`` in walk
    (counter-clockwise) order, starting from its lowest half-edge position;
    ``sum_dx, sum_dy`` the sum of their displacements (zero for a contractible face);
    ``area`` the signed area of the polygon of their contact points.
    """
    nh = src.shape[0]
    face_of = np.full(nh, -1, dtype=np.int64)
    face_he = np.empty(nh, dtype=np.int64)
    ptr = np.empty(nh + 1, dtype=np.int64)
    sides_buf = np.empty(nh, dtype=np.int64)
    sx_buf = np.empty(nh)
    sy_buf = np.empty(nh)
    area_buf = np.empty(nh)
    nf = 0
    pos = 0
    ptr[0] = 0
    for p0 in range(nh):
        if face_of[p0] >= 0:
            continue
        p = p0
        # unwrapped centre of the current source grain, relative to the first one
        cx = 0.0
        cy = 0.0
        # previous contact point, for the shoelace sum
        first_x = 0.0
        first_y = 0.0
        prev_x = 0.0
        prev_y = 0.0
        acc = 0.0
        k = 0
        while face_of[p] < 0:
            face_of[p] = nf
            face_he[pos] = p
            pos += 1
            px = cx + frac[p] * hdx[p]
            py = cy + frac[p] * hdy[p]
            if k == 0:
                first_x = px
                first_y = py
            else:
                acc += prev_x * py - prev_y * px
            prev_x = px
            prev_y = py
            cx += hdx[p]
            cy += hdy[p]
            k += 1
            # next half-edge: clockwise neighbour of the twin around dst[p]
            t = twin[p]
            v = dst[p]
            if t == offsets[v]:
                p = offsets[v + 1] - 1
            else:
                p = t - 1
        acc += prev_x * first_y - prev_y * first_x
        sides_buf[nf] = k
        sx_buf[nf] = cx
        sy_buf[nf] = cy
        area_buf[nf] = 0.5 * acc
        nf += 1
        ptr[nf] = pos
    return (
        face_of,
        ptr[: nf + 1].copy(),
        face_he,
        sides_buf[:nf].copy(),
        sx_buf[:nf].copy(),
        sy_buf[:nf].copy(),
        area_buf[:nf].copy(),
    )


@njit(cache=True)
def _bond_order_core(offsets, angle, m):
    """Local bond-orientational order ``|psi_m| = |(1/z) sum exp(i m theta)|`` per grain.

    The sum runs over the grain's half-edges ``offsets[g]:offsets[g+1]`` (its contacts
    in the network), ``theta`` their direction ``angle``. 1 when every contact lies
    along the axes of one m-fold star (a triangular crystal for ``m = 6``); 0 for a
    grain without contacts.
    """
    n = offsets.shape[0] - 1
    out = np.zeros(n)
    for g in range(n):
        a = offsets[g]
        b = offsets[g + 1]
        if b == a:
            continue
        re = 0.0
        im = 0.0
        for p in range(a, b):
            re += np.cos(m * angle[p])
            im += np.sin(m * angle[p])
        out[g] = np.sqrt(re * re + im * im) / (b - a)
    return out


# ----------------------------------------------------------------------------- wrappers


def _checked_config(positions, radii, box):
    pos = _as_positions(positions)
    n = pos.shape[0]
    rad = np.asarray(radii, dtype=np.float64)
    if rad.shape != (n,):
        raise ValueError(f"radii: expected shape ({n},) to match positions, got {rad.shape}")
    if not (np.all(np.isfinite(rad)) and np.all(rad > 0)):
        raise ValueError("radii: expected finite positive values, got zero, negative, NaN or inf")
    b = _as_box(box)
    return _writable(pos), _writable(np.ascontiguousarray(rad)), _writable(b)


def _writable(arr):
    """``arr``, or a copy when it is read-only: numba compiles a kernel once per argument
    type, and read-only arrays (a ``Packing``'s) are a type of their own."""
    return arr if arr.flags.writeable else arr.copy()


def contact_bonds(positions, radii, box):
    """Contacts of a configuration: ``(bi, bj, dx, dy)``, ``bi < bj`` sorted.

    ``(dx, dy)`` is the minimum image of ``r_bj - r_bi``; a pair is in contact when
    ``|d| < r_bi + r_bj``.
    """
    pos, rad, b = _checked_config(positions, radii, box)
    return _contact_bonds_core(pos, rad, b)


def rattlers(n, bi, bj, dx, dy, angle_tolerance=HALF_PLANE_TOL):
    """Boolean mask of the rattlers of a network of ``n`` disks with bonds ``(bi, bj)``
    and bond displacements ``(dx, dy) = r_bj - r_bi`` (see ``_rattlers_core``)."""
    n = int(n)
    bi = np.ascontiguousarray(bi, dtype=np.int64)
    bj = np.ascontiguousarray(bj, dtype=np.int64)
    if bi.shape != bj.shape or bi.ndim != 1:
        raise ValueError(f"bi, bj: expected two 1-D arrays of equal length, got {bi.shape} and {bj.shape}")
    if bi.size and (min(bi.min(), bj.min()) < 0 or max(bi.max(), bj.max()) >= n):
        raise ValueError(f"bi, bj: expected disk indices in [0, {n}), got values outside")
    dx = np.ascontiguousarray(dx, dtype=np.float64)
    dy = np.ascontiguousarray(dy, dtype=np.float64)
    if dx.shape != bi.shape or dy.shape != bi.shape:
        raise ValueError(f"dx, dy: expected one displacement per bond, shape {bi.shape}, got {dx.shape} and {dy.shape}")
    tol = float(angle_tolerance)
    if not (np.isfinite(tol) and 0.0 <= tol < 0.5 * np.pi):
        raise ValueError(f"angle_tolerance: expected radians in [0, pi/2), got {angle_tolerance!r}")
    return _rattlers_core(n, bi, bj, dx, dy, tol)


def network(positions, radii, box, remove_rattlers=True):
    """The non-rattler contact network as a dict of arrays (rotation system and faces).

    With ``remove_rattlers=False`` every contact is kept (useful for small clusters).

    Keys: ``bi, bj, dx, dy`` (all contacts), ``rattler``, ``offsets, src, dst, hdx,
    hdy, angle, twin, frac`` (half-edges, counter-clockwise per grain), ``theta,
    edge_area`` (per half-edge), ``face_of, face_ptr, face_he, sides, sum_dx,
    sum_dy, void_area`` (faces).
    """
    pos, rad, b = _checked_config(positions, radii, box)
    n = pos.shape[0]
    bi, bj, dx, dy = _contact_bonds_core(pos, rad, b)
    rat = _rattlers_core(n, bi, bj, dx, dy, HALF_PLANE_TOL) if remove_rattlers else np.zeros(n, dtype=np.bool_)
    offsets, src, dst, hdx, hdy, ang, twin, frac = _rotation_core(n, bi, bj, dx, dy, rat, rad)
    theta, earea = _grain_pass_core(offsets, hdx, hdy, ang, frac)
    face_of, fptr, fhe, sides, sx, sy, varea = _faces_core(offsets, src, dst, hdx, hdy, twin, frac)
    return dict(
        bi=bi, bj=bj, dx=dx, dy=dy, rattler=rat, offsets=offsets, src=src, dst=dst,
        hdx=hdx, hdy=hdy, angle=ang, twin=twin, frac=frac, theta=theta, edge_area=earea,
        face_of=face_of, face_ptr=fptr, face_he=fhe, sides=sides, sum_dx=sx, sum_dy=sy,
        void_area=varea,
    )
