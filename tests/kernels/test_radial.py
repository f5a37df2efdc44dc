"""Radial pair counts (kernels.observables._radial_core) against brute force, exactly.

Points on a lattice of spacing 1/16 in boxes whose sides are multiples of it, with
length scales 1 and 1/2: every distance and every ratio ``d / scale`` is then exact in
float64, and many of them fall exactly on bin edges, where the kernel's vectorised
binning must hand over to the edge correction and still agree with ``numpy.histogram``.
The reach runs from a few lattice spacings (cell grid with periodic shifts) to more
than half the box (minimum image per pair along one side or both).
"""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from kernels.observables import _radial_core, is_uniform
from kernels.space import _as_box
from references import ref_radial_counts_by_class

H = 1.0 / 16.0


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), sides=st.sampled_from([(16, 16), (48, 16), (16, 40), (8, 64)]),
       npt=st.integers(2, 160), width=st.integers(1, 12), nbins=st.integers(1, 60),
       uniform=st.booleans(), two_scales=st.booleans())
def test_lattice_points_match_brute_force(seed, sides, npt, width, nbins, uniform, two_scales):
    rng = np.random.default_rng(seed)
    box = np.array(sides, dtype=float) * H
    cells = rng.choice(sides[0] * sides[1], size=min(npt, sides[0] * sides[1]), replace=False)
    points = np.c_[cells % sides[0], cells // sides[0]] * H
    points += rng.integers(-1, 2, points.shape) * box  # unwrapped images too
    scales = np.array([1.0, 0.5]) if two_scales else np.array([1.0])
    cls1 = rng.integers(0, len(scales), len(points))
    cls2 = np.where(rng.random(len(points)) < 0.5, -1, rng.integers(0, len(scales), len(points)))
    # bins width/4 lattice spacings wide: edges exact, their inverse width mostly not
    w = width * H / 4
    if uniform:
        edges = np.arange(nbins + 1) * w
    else:
        edges = np.unique(np.r_[0.0, rng.integers(1, nbins + 1, nbins) * w, nbins * w])
    counts = np.zeros(len(edges) - 1, dtype=np.int64)
    _radial_core(points, cls1, cls2, scales, _as_box(box), edges, is_uniform(edges), counts)
    assert np.array_equal(counts, ref_radial_counts_by_class(points, cls1, cls2, scales, box, edges))


@given(top=st.floats(0.05, 3.0), nbins=st.integers(1, 200), seed=st.integers(0, 2**32 - 1))
@settings(max_examples=40, deadline=None)
def test_distances_one_ulp_from_every_edge(top, nbins, seed):
    """Pairs at distances e_k and one ulp either side of every edge e_k (uniform edges
    whose width has no exact inverse): the vectorised binning must defer to the edge
    correction wherever the direct index could be off by one."""
    edges = np.linspace(0.0, top, nbins + 1)
    assert is_uniform(edges)
    x = np.concatenate([np.nextafter(edges, -np.inf), edges, np.nextafter(edges, np.inf)])
    x = x[x > 0]
    rng = np.random.default_rng(seed)
    scales = np.array([1.0, 0.5])
    # the distance to scale ratio is x / 1 or 2 x / 1: make both land on the probes
    cls1 = rng.integers(0, 2, len(x))
    d = np.where(cls1 == 1, x / 2, x)  # exact: halving
    gap = 3.0 * top  # farther than the reach between pairs
    a = np.c_[np.zeros(len(x)), gap * np.arange(len(x))]
    b = a + np.c_[d, np.zeros(len(x))]
    points = np.concatenate([a, b])
    c1 = np.r_[cls1, cls1]
    c2 = np.full(len(points), -1)
    box = _as_box([gap, gap * len(x)])
    counts = np.zeros(nbins, dtype=np.int64)
    _radial_core(points, c1, c2, scales, box, edges, True, counts)
    expected = 2 * np.histogram(x, edges)[0]
    assert np.array_equal(counts, expected)
