"""The sparse block Cholesky (kernels.sparse) against dense linear algebra."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from kernels import sparse


def _graph(rng, n, reach, box=(1.0, 1.0)):
    """Random positions and the pairs closer than ``reach`` (minimum image), i < j."""
    box = np.asarray(box, float)
    pos = rng.random((n, 2)) * box
    d = pos[:, None, :] - pos[None, :, :]
    d -= box * np.round(d / box)
    r = np.hypot(d[..., 0], d[..., 1])
    i, j = np.nonzero(np.triu(r < reach, 1))
    return pos, box, i, j


def _spd_blocks(rng, n, i, j, margin=1.0):
    """Random symmetric blocks shifted to be positive definite (smallest eigenvalue margin)."""
    off = rng.standard_normal((len(i), 3))
    diag = rng.standard_normal((n, 3)) * 0.1
    a = sparse.to_dense(n, i, j, diag, off)
    lo = np.linalg.eigvalsh(a).min()
    diag[:, 0] += margin - lo
    diag[:, 2] += margin - lo
    return diag, off


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 120), reach=st.floats(0.0, 0.5), seed=st.integers(0, 2**31 - 1),
       aspect=st.floats(0.3, 3.0))
def test_solve_matches_dense(n, reach, seed, aspect):
    rng = np.random.default_rng(seed)
    pos, box, i, j = _graph(rng, n, reach, box=(1.0, aspect))
    diag, off = _spd_blocks(rng, n, i, j)
    a = sparse.to_dense(n, i, j, diag, off)
    sym = sparse.analyse(pos, box, i, j)
    assert sorted(sym.perm) == list(range(n))
    lval = sparse.factor(sym, diag, off)
    b = rng.standard_normal(2 * n)
    x = sparse.solve(sym, lval, b)
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-9, atol=1e-9 * np.abs(x).max())


def test_factor_is_cholesky_of_the_permuted_matrix():
    """L L^T reassembled from the panels equals P A P^T entry by entry."""
    rng = np.random.default_rng(3)
    n = 80
    pos, box, i, j = _graph(rng, n, 0.25)
    diag, off = _spd_blocks(rng, n, i, j)
    a = sparse.to_dense(n, i, j, diag, off)
    sym = sparse.analyse(pos, box, i, j)
    lval = sparse.factor(sym, diag, off)
    lmat = np.zeros((2 * n, 2 * n))
    for s in range(len(sym.sup_first) - 1):
        f = sym.sup_first[s]
        w = 2 * (sym.sup_first[s + 1] - f)
        rows = list(range(2 * f, 2 * f + w))
        for u in sym.upd_rows[sym.upd_ptr[s]:sym.upd_ptr[s + 1]]:
            rows += [2 * u, 2 * u + 1]
        m = len(rows)
        panel = lval[sym.l_ptr[s]:sym.l_ptr[s + 1]].reshape(w, m)
        for c in range(w):
            lmat[rows, 2 * f + c] = panel[c]
    dof = np.ravel(np.column_stack([2 * sym.perm, 2 * sym.perm + 1]))
    np.testing.assert_allclose(lmat @ lmat.T, a[np.ix_(dof, dof)], atol=1e-10)
    assert np.all(np.triu(lmat, 1) == 0.0)


def test_not_positive_definite_is_refused():
    rng = np.random.default_rng(1)
    n = 30
    pos, box, i, j = _graph(rng, n, 0.3)
    diag, off = _spd_blocks(rng, n, i, j, margin=1.0)
    diag[7, 0] -= 50.0  # one strongly negative direction
    sym = sparse.analyse(pos, box, i, j)
    with pytest.raises(sparse.NotPositiveDefinite):
        sparse.factor(sym, diag, off)


def test_the_same_inputs_give_the_same_bits():
    rng = np.random.default_rng(5)
    n = 200
    pos, box, i, j = _graph(rng, n, 0.15)
    diag, off = _spd_blocks(rng, n, i, j)
    b = rng.standard_normal(2 * n)
    out = []
    for _ in range(2):
        sym = sparse.analyse(pos, box, i, j)
        out.append(sparse.solve(sym, sparse.factor(sym, diag, off), b).tobytes())
    assert out[0] == out[1]


def test_explicit_zero_blocks_and_pair_order_do_not_change_the_solution():
    """A pattern with extra zero blocks (a Verlet list) solves the same system."""
    rng = np.random.default_rng(8)
    n = 60
    pos, box, i, j = _graph(rng, n, 0.2)
    diag, off = _spd_blocks(rng, n, i, j)
    b = rng.standard_normal(2 * n)
    x0 = sparse.solve(sym := sparse.analyse(pos, box, i, j), sparse.factor(sym, diag, off), b)
    _, _, i2, j2 = _graph(np.random.default_rng(8), n, 0.3)  # same positions, more pairs
    key = {(a, c): k for k, (a, c) in enumerate(zip(i, j))}
    off2 = np.zeros((len(i2), 3))
    for k, (a, c) in enumerate(zip(i2, j2)):
        if (a, c) in key:
            off2[k] = off[key[(a, c)]]
    order = rng.permutation(len(i2))
    i3, j3, off3 = j2[order], i2[order], off2[order]  # shuffled, and (j, i) instead of (i, j)
    sym3 = sparse.analyse(pos, box, i3, j3)
    x3 = sparse.solve(sym3, sparse.factor(sym3, diag, off3), b)
    np.testing.assert_allclose(x3, x0, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("case", ["isolated", "coincident", "line"])
def test_degenerate_geometries(case):
    rng = np.random.default_rng(2)
    n = 50
    if case == "isolated":
        pos, box, i, j = _graph(rng, n, 0.0)  # no pairs at all
    elif case == "coincident":
        pos = np.full((n, 2), 0.5)
        box = np.array([1.0, 1.0])
        i, j = np.triu_indices(n, 1)
    else:
        pos = np.column_stack([np.linspace(0, 1, n, endpoint=False), np.full(n, 0.5)])
        box = np.array([1.0, 1.0])
        i = np.arange(n)
        j = (i + 1) % n
    diag, off = _spd_blocks(rng, n, i, j)
    sym = sparse.analyse(pos, box, i, j)
    b = rng.standard_normal(2 * n)
    x = sparse.solve(sym, sparse.factor(sym, diag, off), b)
    np.testing.assert_allclose(sparse.to_dense(n, i, j, diag, off) @ x, b, atol=1e-9)


def test_bad_input_is_refused():
    pos = np.random.default_rng(0).random((4, 2))
    with pytest.raises(ValueError, match="itself"):
        sparse.analyse(pos, (1, 1), [0], [0])
    with pytest.raises(ValueError, match="twice"):
        sparse.analyse(pos, (1, 1), [0, 1], [1, 0])
    with pytest.raises(ValueError, match="node indices"):
        sparse.analyse(pos, (1, 1), [0], [4])
    sym = sparse.analyse(pos, (1, 1), [0], [1])
    with pytest.raises(ValueError, match="shape"):
        sparse.factor(sym, np.ones((3, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="finite"):
        sparse.factor(sym, np.full((4, 3), np.nan), np.zeros((1, 3)))
