"""Contact network kernels against a slow, obviously correct reference and analytic cases.

The reference here (``reference_network``) is plain Python over all pairs, with
dictionaries for the rotation system and scipy's Delaunay for the voids; the other
analysis tests import it and the packing helpers from this file.
"""

import math
from functools import lru_cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay

from kernels.network import contact_bonds, network, rattlers
from kernels.triangulate import triangulate_polygon
from reference import in_closed_half_plane, ref_nonrattlers

RATIO = 1.4  # sigma_A / sigma_B (docs/PHYSICS.md)


# ----------------------------------------------------------------------------- packings


def _forces_energy(pos, rad, box):
    d = pos[None, :, :] - pos[:, None, :]
    d -= box * np.round(d / box)
    r = np.sqrt((d**2).sum(-1))
    np.fill_diagonal(r, np.inf)
    s = rad[:, None] + rad[None, :]
    x = np.clip(1.0 - r / s, 0.0, None)
    f = x / s / r
    return -(f[:, :, None] * d).sum(1), 0.25 * (x**2).sum()


@lru_cache(maxsize=None)
def compressed_packing(n, seed, phi=0.9, box=(1.0, 1.0)):
    """A force-balanced bidisperse packing above jamming (FIRE on harmonic springs).

    Independent of ``kernels.jam``: a small numpy FIRE over all pairs, stopped when
    the largest net force is 1e-12 of the typical contact force. Returns read-only
    ``(positions, radii, box)``.
    """
    rng = np.random.default_rng([n, seed])
    box = np.asarray(box, dtype=float)
    rel = np.r_[np.full(n // 2, RATIO), np.ones(n - n // 2)]
    rad = rel * np.sqrt(phi * box.prod() / (np.pi * np.sum(rel**2)))
    pos = rng.random((n, 2)) * box
    v = np.zeros_like(pos)
    dt = 0.05 * rad.min()
    dtmax = 10 * dt
    alpha = 0.1
    npos = 0
    F, _ = _forces_energy(pos, rad, box)
    fscale = None
    for _ in range(50000):
        P = (F * v).sum()
        if P > 0:
            v = (1 - alpha) * v + alpha * F / np.linalg.norm(F) * np.linalg.norm(v)
            npos += 1
            if npos > 5:
                dt = min(dt * 1.1, dtmax)
                alpha *= 0.99
        else:
            npos = 0
            dt *= 0.5
            v[:] = 0
            alpha = 0.1
        v += dt * F
        pos += dt * v
        F, E = _forces_energy(pos, rad, box)
        if fscale is None:
            fscale = np.sqrt(2 * E / n) / rad.mean()
        if np.abs(F).max() < 1e-12 * max(fscale, 1e-300) + 1e-300:
            break
    pos = pos % box
    for a in (pos, rad, box):
        a.setflags(write=False)
    return pos, rad, box


def random_configuration(n, seed, phi=0.85, box=(1.0, 1.0)):
    """Uniformly random bidisperse disks (overlapping, not force balanced)."""
    rng = np.random.default_rng([7, n, seed])
    box = np.asarray(box, dtype=float)
    rel = np.r_[np.full(n // 2, RATIO), np.ones(n - n // 2)]
    rad = rel * np.sqrt(phi * box.prod() / (np.pi * np.sum(rel**2)))
    return rng.random((n, 2)) * box, rad, box


def jittered_crystal(nx, ny, seed, box=None, poly=0.05, jitter=0.03, overlap=0.15):
    """A generic network with every grain load-bearing: a triangular crystal with its
    centres moved by ``jitter`` lattice spacings (normal), radii ``0.5 a (1 + overlap)``
    times ``1 + poly U(-1, 1)`` (all distinct), stretched into ``box`` if given. No two
    contact angles coincide, and every grain keeps contacts all around (unlike random
    overlapping disks, which erode completely under the half-plane rattler rule)."""
    rng = np.random.default_rng([11, nx, ny, seed])
    pos, rad, b = triangular_crystal(nx, ny, overlap=overlap)
    pos = pos + jitter * (1.0 / nx) * rng.standard_normal(pos.shape)
    rad = rad * (1.0 + poly * rng.uniform(-1.0, 1.0, rad.size))
    if box is not None:
        box = np.asarray(box, dtype=float)
        pos = pos * (box / b)
        rad = rad * np.sqrt(box.prod() / b.prod())
        b = box
    return pos % b, rad, b


def triangular_crystal(nx, ny, overlap=1e-6, a=None):
    """Triangular crystal of equal disks, nx per row, ny rows (even), fitting its box."""
    assert ny % 2 == 0
    a = 1.0 / nx if a is None else a
    j, i = np.divmod(np.arange(nx * ny), nx)
    pos = np.stack([(i + 0.5 * (j % 2)) * a, j * a * np.sqrt(3) / 2], axis=1)
    box = np.array([nx * a, ny * a * np.sqrt(3) / 2])
    rad = np.full(nx * ny, 0.5 * a * (1 + overlap))
    return pos, rad, box


# ----------------------------------------------------------------------------- reference


def _shoelace(points):
    x = np.array([p[0] for p in points])
    y = np.array([p[1] for p in points])
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def reference_network(pos, rad, box, remove_rattlers=True, exponent=2.0):
    """Everything about the contact network, the slow and obvious way."""
    n = len(rad)
    nbrs = {g: {} for g in range(n)}
    energy = 0.0
    virial = 0.0
    for i in range(n):
        for j in range(i + 1, n):
            d = pos[j] - pos[i]
            d = d - box * np.round(d / box)
            r = math.hypot(d[0], d[1])
            s = rad[i] + rad[j]
            if r < s:
                nbrs[i][j] = d
                nbrs[j][i] = -d
                energy += (1 - r / s) ** exponent / exponent
                virial += r * (1 - r / s) ** (exponent - 1) / s
    bonds = sorted((i, j) for i in range(n) for j in nbrs[i] if i < j)
    alive = set(range(n))
    if remove_rattlers:
        changed = True
        while changed:
            changed = False
            for g in sorted(alive):
                ang = [math.atan2(d[1], d[0]) for h, d in nbrs[g].items() if h in alive]
                if len(ang) < 3 or in_closed_half_plane(ang):
                    alive.remove(g)
                    changed = True
    rot = {}
    for g in alive:
        rot[g] = sorted((math.atan2(d[1], d[0]), h) for h, d in nbrs[g].items() if h in alive)
    # grains: polygon of contact points, relative angles, edge triangles
    theta, alpha_e, a_g = [], [], {}
    contact_len = []
    for g in alive:
        ring = [nbrs[g][h] * rad[g] / (rad[g] + rad[h]) for _, h in rot[g]]
        a_g[g] = _shoelace(ring) if len(ring) >= 3 else 0.0
        angles = [a for a, _ in rot[g]]
        k = len(angles)
        for t in range(k):
            nxt = angles[(t + 1) % k] + (2 * math.pi if t + 1 == k else 0.0)
            theta.append(nxt - angles[t])
            u, v = ring[t], ring[(t + 1) % k]
            alpha_e.append(0.5 * (u[0] * v[1] - u[1] * v[0]) / rad[g] ** 2)
            contact_len.append(math.hypot(*ring[t]) / rad[g])
    # faces: next(u -> v) = the half-edge clockwise of v -> u around v
    seen = set()
    faces = []
    for g in sorted(alive):
        for _, h in rot[g]:
            if (g, h) in seen:
                continue
            face = []
            u, v = g, h
            while (u, v) not in seen:
                seen.add((u, v))
                face.append((u, v))
                ring = [w for _, w in rot[v]]
                k = ring.index(u)
                u, v = v, ring[(k - 1) % len(ring)]
            faces.append(face)
    voids = []
    for face in faces:
        p = np.zeros(2)
        centres, contacts = [], []
        for u, v in face:
            d = nbrs[u][v]
            centres.append(p.copy())
            contacts.append(p + d * rad[u] / (rad[u] + rad[v]))
            p = p + d
        voids.append(dict(grains=[u for u, _ in face], centres=np.array(centres),
                          area=_shoelace(contacts), winding=p, z=len(face)))
    return dict(n=n, bonds=bonds, alive=alive, N_G=len(alive),
                N_C=sum(len(rot[g]) for g in alive), z_g={g: len(rot[g]) for g in alive},
                theta=np.array(theta), alpha_e=np.array(alpha_e), contact_len=np.array(contact_len),
                A_G=sum(a_g.values()), voids=voids, energy=energy, virial=virial)


def reference_fictitious(ref, rad):
    """Fictitious contacts of every void from scipy's Delaunay of its centre cycle."""
    lengths = []
    for v in ref["voids"]:
        k = v["z"]
        if k < 4:
            continue
        P = v["centres"]
        sides = {frozenset((t, (t + 1) % k)) for t in range(k)}
        edges = set()
        for simplex in Delaunay(P).simplices:
            for a in range(3):
                edges.add(frozenset((int(simplex[a]), int(simplex[(a + 1) % 3]))))
        for e in edges - sides:
            i, j = sorted(e)
            gi, gj = v["grains"][i], v["grains"][j]
            lengths.append(np.linalg.norm(P[j] - P[i]) / (rad[gi] + rad[gj]))
    return np.sort(lengths)


# ----------------------------------------------------------------------------- tests


def _cases():
    return [
        ("packing", *compressed_packing(48, 0)),
        ("packing-rect", *compressed_packing(40, 1, box=(1.0, 0.7))),
        ("random", *random_configuration(60, 0)),  # erodes completely
        ("jittered", *jittered_crystal(8, 6, 0)),
        ("jittered-rect", *jittered_crystal(7, 8, 1, box=(1.0, 1.3))),
    ]


@pytest.mark.parametrize("case", range(5))
def test_kernels_match_reference(case):
    name, pos, rad, box = _cases()[case]
    net = network(pos, rad, box)
    ref = reference_network(pos, rad, box)
    # contacts and rattlers
    assert list(zip(net["bi"].tolist(), net["bj"].tolist())) == ref["bonds"], name
    assert set(np.flatnonzero(~net["rattler"]).tolist()) == ref["alive"]
    # rotation system: counter-clockwise, each grain's contacts
    z = np.diff(net["offsets"])
    assert {g: int(z[g]) for g in ref["alive"]} == ref["z_g"]
    assert np.all(z[net["rattler"]] == 0)
    for g in ref["alive"]:
        a = net["angle"][net["offsets"][g]:net["offsets"][g + 1]]
        assert np.all(np.diff(a) >= 0)
    assert np.all(net["twin"][net["twin"]] == np.arange(net["twin"].size))
    assert np.all(net["src"][net["twin"]] == net["dst"])
    # grain quantities
    np.testing.assert_allclose(np.sort(net["theta"]), np.sort(ref["theta"]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.sort(net["edge_area"] / rad[net["src"]] ** 2), np.sort(ref["alpha_e"]),
                               rtol=0, atol=1e-12)
    assert math.isclose(net["edge_area"].sum(), ref["A_G"], rel_tol=1e-12, abs_tol=1e-15)
    # faces
    rz = sorted(v["z"] for v in ref["voids"])
    assert sorted(net["sides"].tolist()) == rz
    np.testing.assert_allclose(np.sort(net["void_area"]), np.sort([v["area"] for v in ref["voids"]]),
                               rtol=0, atol=1e-12 * box.prod())
    wind = np.sort(np.hypot(net["sum_dx"], net["sum_dy"]))
    np.testing.assert_allclose(wind, np.sort([np.hypot(*v["winding"]) for v in ref["voids"]]),
                               rtol=0, atol=1e-12)
    # every half-edge in exactly one face, faces listed in walk order
    assert np.array_equal(np.sort(net["face_he"]), np.arange(net["src"].size))
    for f in range(net["sides"].size):
        he = net["face_he"][net["face_ptr"][f]:net["face_ptr"][f + 1]]
        assert np.array_equal(net["src"][np.roll(he, -1)], net["dst"][he])


def test_contact_is_strict_and_minimum_image():
    box = np.array([1.0, 1.0])
    rad = np.full(3, 0.125)
    # 0-1 touch exactly (distance 0.25 = 2 r, not a contact); 0-2 overlap across the
    # periodic boundary (all numbers exact in binary)
    pos = np.array([[0.875, 0.5], [0.875, 0.75], [0.0625, 0.5]])
    bi, bj, dx, dy = contact_bonds(pos, rad, box)
    assert list(zip(bi.tolist(), bj.tolist())) == [(0, 2)]
    assert (dx[0], dy[0]) == (0.1875, 0.0)


def _bonds(pairs, angles_deg):
    """Bond arrays from (i, j) pairs and the direction of each bond seen from i."""
    t = np.radians(np.asarray(angles_deg, dtype=float))
    i, j = np.array(pairs).T
    return i, j, np.cos(t), np.sin(t)


def _crystal_core(nx=6, ny=6):
    """A periodic triangular crystal: every grain has 6 contacts 60 degrees apart, no
    rattler. Returns (n, bi, bj, dx, dy, positions, box)."""
    pos, rad, box = triangular_crystal(nx, ny)
    bi, bj, dx, dy = contact_bonds(pos, rad, box)
    return len(rad), bi, bj, dx, dy, pos, box


def _attach(core, new_bonds):
    """Append bonds (i, j, angle in degrees seen from i) to a crystal core."""
    n, bi, bj, dx, dy = core[:5]
    i, j, ex, ey = _bonds([(a, b) for a, b, _ in new_bonds], [t for _, _, t in new_bonds])
    return (np.concatenate([bi, i]), np.concatenate([bj, j]),
            np.concatenate([dx, ex]), np.concatenate([dy, ey]))


def test_rattler_removal_is_iterative():
    # a chain hanging off a K4 whose bonds point in all directions (as on a torus)
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3), (3, 4), (4, 5)]
    angles = [0, 60, 210, 120, 330, 90, 10, 20]
    mask = rattlers(6, *_bonds(pairs, angles))
    # 5 (1 contact) goes, then 4 (1 left) goes; each of 0..3 keeps 3 contacts spread over
    # more than 180 degrees
    assert mask.tolist() == [False, False, False, False, True, True]
    # removing one K4 bond leaves two disks with 2 contacts, which takes the rest down
    mask = rattlers(4, *_bonds(pairs[:5], angles[:5]))
    assert mask.tolist() == [True, True, True, True]


@pytest.mark.parametrize("angles, rattler", [
    ((0, 85, 170), True),          # three contacts within 170 degrees: an open half-plane
    ((0, 90, 180), True),          # two collinear contacts: exactly 180, a closed half-plane
    ((0, 179.9999, 90), True),     # just inside 180, listed in another order
    ((0, 100, 200), False),        # spread over 200 degrees: no half-plane holds them
    ((0, 120, 240), False),
    ((0, 90, 180, 270), False),    # a square: every line through the centre has one on each side
    ((0, 45, 90, 135, 180), True), # five contacts, still a closed half-plane
])
def test_half_plane_rattlers(angles, rattler):
    core = _crystal_core()
    n = core[0]
    grain = n  # the new grain, bonded to three or more distinct crystal grains
    new = [(grain, k, t) for k, t in enumerate(angles)]
    mask = rattlers(n + 1, *_attach(core, new))
    assert bool(mask[grain]) is rattler
    assert not mask[:n].any()  # the crystal itself keeps all its grains
    # the slow reference agrees
    bi, bj, dx, dy = _attach(core, new)
    ref = ref_nonrattlers(n + 1, bi, bj, np.stack([dx, dy], 1))
    assert np.array_equal(~ref, mask)


def test_removal_exposes_a_half_plane_rattler():
    """Grain Y has its contacts in a half-plane and goes; grain X then has three contacts
    left within 135 degrees (no longer 3 spread over more than 180) and goes too, although
    it still has three of them."""
    core = _crystal_core()
    n = core[0]
    X, Y = n, n + 1
    new = [(X, 0, 0), (X, 1, 90), (X, 2, 135), (X, Y, 225),   # X: 4 contacts, spread OK
           (Y, 3, 0), (Y, 4, 20)]                              # Y: X at 45 and these two
    bi, bj, dx, dy = _attach(core, new)
    mask = rattlers(n + 2, bi, bj, dx, dy)
    assert mask[X] and mask[Y] and not mask[:n].any()
    # without Y's half-plane problem (a contact at 200 degrees as well) both stay
    bi2, bj2, dx2, dy2 = _attach(core, new + [(Y, 5, 200)])
    mask2 = rattlers(n + 2, bi2, bj2, dx2, dy2)
    assert not mask2.any()


@settings(max_examples=60, deadline=None)
@given(st.integers(4, 24), st.data())
def test_rattlers_match_reference_and_ignore_order(n, data):
    """Random bond graphs with random directions: the kernel equals the slow angle-sorting
    reference, and relabelling disks or reordering bonds gives the same rattlers."""
    m = data.draw(st.integers(0, 4 * n))
    pairs = set()
    for _ in range(m):
        i = data.draw(st.integers(0, n - 1))
        j = data.draw(st.integers(0, n - 1))
        if i != j:
            pairs.add((min(i, j), max(i, j)))
    pairs = sorted(pairs)
    # directions on a 10-degree lattice: many exact collinear and half-plane ties
    ang = [10 * data.draw(st.integers(0, 35)) for _ in pairs]
    if pairs:
        bi, bj, dx, dy = _bonds(pairs, ang)
    else:
        bi = bj = np.empty(0, np.int64)
        dx = dy = np.empty(0)
    got = rattlers(n, bi, bj, dx, dy)
    ref = ref_nonrattlers(n, bi, bj, np.stack([dx, dy], 1) if pairs else np.empty((0, 2)))
    assert np.array_equal(got, ~ref)
    perm = np.array(data.draw(st.permutations(range(n))))
    order = np.array(data.draw(st.permutations(range(len(pairs)))), dtype=np.int64)
    pi, pj = perm[bi[order]], perm[bj[order]]
    flip = pi > pj  # keep i < j: swap the ends and reverse the direction
    qi = np.where(flip, pj, pi)
    qj = np.where(flip, pi, pj)
    sgn = np.where(flip, -1.0, 1.0)
    got2 = rattlers(n, qi, qj, sgn * dx[order], sgn * dy[order])
    assert np.array_equal(got2[perm], got)


def test_finite_cluster_has_no_load_bearing_grain():
    """Repulsive disks alone cannot balance forces: the outermost grain of any finite
    cluster has all its contacts in a half-plane, so the whole cluster erodes."""
    pos, rad, _ = triangular_crystal(4, 4)
    big = np.array([50.0, 50.0])
    bi, bj, dx, dy = contact_bonds(pos + 10.0, rad, big)
    assert len(bi) > 0
    assert rattlers(len(rad), bi, bj, dx, dy).all()


def _three_disks(radii):
    """Three mutually touching disks (relative overlap 1e-10) in a large box."""
    r = np.asarray(radii, dtype=float)
    s = 1 - 1e-10
    a, b, c = (r[1] + r[2]) * s, (r[0] + r[2]) * s, (r[0] + r[1]) * s  # sides opposite 0, 1, 2
    p0 = np.array([0.0, 0.0])
    p1 = np.array([c, 0.0])
    x = (b * b - a * a + c * c) / (2 * c)
    p2 = np.array([x, math.sqrt(b * b - x * x)])
    box = np.array([40.0, 40.0]) * r.max()
    return np.array([p0, p1, p2]) + box / 2, r, box


def _angle_at(r, g):
    """Interior angle of the centre triangle at grain g (law of cosines) = relative angle."""
    o = [k for k in range(3) if k != g]
    p, q = r[g] + r[o[0]], r[g] + r[o[1]]
    opp = r[o[0]] + r[o[1]]
    return math.acos((p * p + q * q - opp * opp) / (2 * p * q))


# (cluster of three, grain looked at) -> docs/PHYSICS.md table value (theta, alpha_e)
TABLE = {
    "B(AA)": (1.245653, 0.473803),
    "B(AB)": (1.141021, 0.454530),
    "A(AA)": (1.047198, 0.433013),
    "B(BB)": (1.047198, 0.433013),
    "A(AB)": (0.947970, 0.406116),
    "A(BB)": (0.859551, 0.378775),
}
VOID_TABLE = {"AAA": 0.433013, "AAB": 0.338430, "ABB": 0.270553, "BBB": 0.220925}


@pytest.mark.parametrize("cluster", ["AAA", "AAB", "ABB", "BBB"])
def test_three_disks_first_principles(cluster):
    size = {"A": RATIO, "B": 1.0}
    r = np.array([size[c] for c in cluster]) * 0.01
    pos, rad, box = _three_disks(r)
    net = network(pos, rad, box, remove_rattlers=False)
    assert net["sides"].tolist() in ([3, 3],)
    sigma_A = size["A"] * 0.01  # the A radius, whichever disks the cluster has
    for g in range(3):
        sl = slice(net["offsets"][g], net["offsets"][g + 1])
        th = net["theta"][sl]
        inner = np.argmin(th)
        theta = _angle_at(rad, g)
        alpha_e = 0.5 * math.sin(theta)  # |r_gc| = sigma_g at contact
        assert th[inner] == pytest.approx(theta, rel=1e-8)
        assert th[1 - inner] == pytest.approx(2 * math.pi - theta, rel=1e-8)
        assert net["edge_area"][sl][inner] / rad[g] ** 2 == pytest.approx(alpha_e, rel=1e-8)
        others = "".join(sorted(cluster[k] for k in range(3) if k != g))
        label = f"{cluster[g]}({others})"
        t_tab, a_tab = TABLE[label]
        assert theta == pytest.approx(t_tab, abs=2e-6)
        assert alpha_e == pytest.approx(a_tab, abs=2e-6)
    # the void: the triangle of centres minus the three sector triangles (Heron)
    sa, sb, sc = rad[1] + rad[2], rad[0] + rad[2], rad[0] + rad[1]
    s = (sa + sb + sc) / 2
    heron = math.sqrt(s * (s - sa) * (s - sb) * (s - sc))
    void = heron - sum(0.5 * rad[g] ** 2 * math.sin(_angle_at(rad, g)) for g in range(3))
    inner_face = int(np.argmax(net["void_area"]))
    assert net["void_area"][inner_face] / sigma_A**2 == pytest.approx(void / sigma_A**2, rel=1e-7)
    assert void / sigma_A**2 == pytest.approx(VOID_TABLE[cluster], abs=2e-6)
    # the outer face runs the other way round the same three contact points
    assert net["void_area"].sum() == pytest.approx(0.0, abs=1e-12 * heron)


def test_crystal_network():
    pos, rad, box = triangular_crystal(6, 6)
    net = network(pos, rad, box)
    assert not net["rattler"].any()
    assert np.all(np.diff(net["offsets"]) == 6)
    assert np.all(net["sides"] == 3)
    np.testing.assert_allclose(net["theta"], np.pi / 3, atol=1e-12)
    assert np.allclose(net["sum_dx"], 0) and np.allclose(net["sum_dy"], 0)


def test_polygon_triangulation_matches_scipy():
    rng = np.random.default_rng(3)
    for k in range(4, 16):
        # points on an ellipse-like convex curve, counter-clockwise, radii jittered
        t = np.sort(rng.random(k)) * 2 * np.pi
        pts = np.stack([np.cos(t) * (1 + 0.3 * rng.random()), np.sin(t)], axis=1)
        ci, cj = triangulate_polygon(pts)
        assert ci.size == k - 3
        mine = {frozenset(e) for e in zip(ci.tolist(), cj.tolist())}
        sides = {frozenset((t, (t + 1) % k)) for t in range(k)}
        theirs = set()
        for simplex in Delaunay(pts).simplices:
            for a in range(3):
                theirs.add(frozenset((int(simplex[a]), int(simplex[(a + 1) % 3]))))
        assert mine == theirs - sides


def test_square_void_tie_is_deterministic():
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    a = triangulate_polygon(square)
    b = triangulate_polygon(square)
    assert a[0].tolist() == b[0].tolist() and a[1].tolist() == b[1].tolist()
    assert a[0].size == 1


def test_wrappers_reject_bad_input():
    with pytest.raises(ValueError, match="radii"):
        network(np.zeros((3, 2)), np.array([0.1, -0.1, 0.1]), (1.0, 1.0))
    with pytest.raises(ValueError, match="box"):
        contact_bonds(np.zeros((3, 2)), np.full(3, 0.1), (1.0, 0.0))
    with pytest.raises(ValueError, match="positions"):
        contact_bonds(np.zeros((3, 3)), np.full(3, 0.1), (1.0, 1.0))
    with pytest.raises(ValueError, match="indices"):
        rattlers(3, np.array([0]), np.array([3]), np.array([1.0]), np.array([0.0]))
    with pytest.raises(ValueError, match="one displacement per bond"):
        rattlers(3, np.array([0]), np.array([1]), np.array([1.0, 2.0]), np.array([0.0]))
    with pytest.raises(ValueError, match="angle_tolerance"):
        rattlers(3, np.array([0]), np.array([1]), np.array([1.0]), np.array([0.0]), angle_tolerance=-1)
    with pytest.raises(ValueError, match="points"):
        triangulate_polygon(np.zeros((2, 2)))
