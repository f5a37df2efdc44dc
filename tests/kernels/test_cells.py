"""Cell/Verlet candidate pairs against a brute-force O(n^2) reference."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from kernels.cells import _cell_grid, candidate_pairs
from references import ref_candidate_pairs


def as_list(ij):
    i, j = ij
    assert i.dtype == np.int64 and j.dtype == np.int64
    return list(zip(i.tolist(), j.tolist()))


def random_system(rng, n, box, size):
    box = np.asarray(box, float)
    pos = rng.random((n, 2)) * box
    rad = size * (0.5 + rng.random(n)) * box.min() / np.sqrt(n)
    return pos, rad, box


@pytest.mark.parametrize("n", [2, 3, 7, 64, 300])
@pytest.mark.parametrize("box", [(1.0, 1.0), (3.0, 0.4), (0.3, 2.0)])
def test_matches_brute_force(n, box):
    rng = np.random.default_rng(n)
    pos, rad, box = random_system(rng, n, box, 0.4)
    skin = 0.3 * rad.mean()
    got = as_list(candidate_pairs(pos, rad, box, skin))
    assert got == ref_candidate_pairs(pos, rad, box, skin)
    assert got == sorted(set(got))  # each pair once, sorted by i then j


def test_across_boundary_and_unwrapped_input():
    box = np.array([1.0, 2.0])
    pos = np.array([[0.01, 0.01], [0.99, 1.99], [0.5, 1.0], [0.01, 1.0]])
    rad = np.array([0.02, 0.02, 0.02, 0.02])
    assert as_list(candidate_pairs(pos, rad, box, 0.0)) == [(0, 1)]
    shifted = pos + np.array([[3.0, -4.0], [-1.0, 2.0], [0.0, 0.0], [7.0, 0.0]])
    assert as_list(candidate_pairs(shifted, rad, box, 0.0)) == [(0, 1)]


def test_few_cells_per_side():
    # disks large compared with the box: fewer than 3 cells fit along y
    rng = np.random.default_rng(5)
    box = np.array([4.0, 0.5])
    pos = rng.random((40, 2)) * box
    rad = np.full(40, 0.1)
    nx, ny = _cell_grid(box, 2 * 0.1 + 0.05, 40)
    assert ny == 1 and nx >= 3
    assert as_list(candidate_pairs(pos, rad, box, 0.05)) == ref_candidate_pairs(pos, rad, box, 0.05)


def test_after_moves_and_radius_change():
    rng = np.random.default_rng(11)
    pos, rad, box = random_system(rng, 200, (1.0, 1.0), 0.5)
    for _ in range(3):
        pos = pos + 0.01 * rng.standard_normal(pos.shape)
        rad = rad * 1.05
        skin = 0.2 * rad.mean()
        assert as_list(candidate_pairs(pos, rad, box, skin)) == ref_candidate_pairs(pos, rad, box, skin)


def test_large_n_against_vectorised_reference():
    # 4096 disks: vectorised all-pairs reference (same definition, numpy)
    rng = np.random.default_rng(4096)
    n = 4096
    pos, rad, box = random_system(rng, n, (1.0, 1.0), 0.6)
    skin = 0.25 * rad.mean()
    got = set(as_list(candidate_pairs(pos, rad, box, skin)))
    want = set()
    for i in range(n - 1):
        d = pos[i + 1:] - pos[i]
        d -= box * np.round(d / box)
        js = np.nonzero(np.hypot(d[:, 0], d[:, 1]) < rad[i] + rad[i + 1:] + skin)[0] + i + 1
        want.update((i, int(j)) for j in js)
    assert got == want and len(want) > n


@settings(max_examples=40, deadline=None)
@given(n=st.integers(2, 40), seed=st.integers(0, 2**32 - 1),
       aspect=st.floats(0.2, 5.0), size=st.floats(0.05, 3.0), skin=st.floats(0.0, 0.2))
def test_property_brute_force(n, seed, aspect, size, skin):
    rng = np.random.default_rng(seed)
    pos, rad, box = random_system(rng, n, (1.0, aspect), size)
    # keep the interaction range below half a side so the nearest image is unique
    rad = np.minimum(rad, 0.2 * box.min())
    skin = skin * box.min() * 0.1
    assert as_list(candidate_pairs(pos, rad, box, skin)) == ref_candidate_pairs(pos, rad, box, skin)


@pytest.mark.parametrize("bad, match", [
    (dict(positions=np.zeros((3, 3))), "positions"),
    (dict(radii=np.ones(2)), "radii"),
    (dict(radii=-np.ones(3)), "radii"),
    (dict(box=(1.0, 0.0)), "box"),
    (dict(box=(1.0,)), "box"),
    (dict(skin=-1.0), "skin"),
    (dict(positions=np.full((3, 2), np.nan)), "positions"),
])
def test_bad_input(bad, match):
    args = dict(positions=np.zeros((3, 2)), radii=np.ones(3) * 0.1, box=(1.0, 1.0), skin=0.1)
    args.update(bad)
    with pytest.raises(ValueError, match=match):
        candidate_pairs(**args)


def test_core_callable_from_numba():
    from numba import njit

    from kernels.cells import _candidate_pairs_core

    @njit
    def count(pos, rad, box, skin):
        i, j = _candidate_pairs_core(pos, rad, box, skin)
        return i.shape[0]

    rng = np.random.default_rng(2)
    pos, rad, box = random_system(rng, 50, (1.0, 1.0), 0.5)
    assert count(pos, rad, np.append(box, 0.0), 0.01) == len(ref_candidate_pairs(pos, rad, box, 0.01))
