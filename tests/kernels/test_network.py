"""Contact network kernels against a slow, obviously correct reference and analytic cases.

The reference (``references.ref_network``) is plain Python over all pairs, with
dictionaries for the rotation system and scipy's Delaunay for the voids; the packing
makers are in ``helpers.py``.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay

from kernels.network import contact_bonds, network, rattlers
from kernels.triangulate import triangulate_polygon
from helpers import RATIO, compressed_packing, jittered_crystal, random_configuration, three_touching_disks, triangular_crystal
from references import ref_network, ref_nonrattlers

# ----------------------------------------------------------------------------- packings


# ----------------------------------------------------------------------------- reference


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
    ref = ref_network(pos, rad, box)
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
    pos, rad, box = three_touching_disks(r)
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
