"""The Hessian of the contact network (kernels.hessian): finite differences of the forces, a
dense reference, invariances and the zero modes of a jammed packing."""

import numpy as np
import pytest

import kernels
from kernels import potential
from kernels.hessian import hessian
from references import ref_hessian_dense


def _overlapping(seed, n=24, phi=1.0, box=(1.0, 1.0)):
    """A random, strongly overlapping configuration with no pair near its contact distance."""
    rng = np.random.default_rng(seed)
    box = np.asarray(box, float)
    for _ in range(100):
        pos = rng.random((n, 2)) * box
        rad = np.where(np.arange(n) < n // 2, 1.4, 1.0)
        rad *= np.sqrt(phi * box.prod() / (np.pi * np.sum(rad**2)))
        d = pos[:, None] - pos[None]
        d -= box * np.round(d / box)
        x = 1 - np.hypot(d[..., 0], d[..., 1]) / (rad[:, None] + rad[None])
        np.fill_diagonal(x, -1)
        if np.all(np.abs(x) > 1e-3):
            return pos, rad, box
    raise AssertionError("no configuration away from contact found")


@pytest.mark.parametrize("alpha", [2.0, 2.5, 3.0])
@pytest.mark.parametrize("seed", [0, 1])
def test_hessian_is_minus_the_force_derivative(alpha, seed):
    pos, rad, box = _overlapping(seed)
    hb = hessian(pos, rad, box, alpha)
    h = hb.dense()
    n = len(rad)
    step = 1e-6 * rad.mean()
    fd = np.empty((2 * n, 2 * n))
    for k in range(2 * n):
        e = np.zeros((n, 2))
        e.flat[k] = step
        fp = potential.forces(pos + e, rad, box, alpha).ravel()
        fm = potential.forces(pos - e, rad, box, alpha).ravel()
        fd[:, k] = -(fp - fm) / (2 * step)
    np.testing.assert_allclose(h, fd, atol=1e-6 * np.abs(h).max())
    np.testing.assert_allclose(h, ref_hessian_dense(pos, rad, box, alpha), rtol=1e-12,
                               atol=1e-12 * np.abs(h).max())


def test_symmetry_translations_and_rectangular_boxes():
    pos, rad, box = _overlapping(4, n=30, box=(1.3, 0.8))
    h = hessian(pos, rad, box, 2.5).dense()
    np.testing.assert_allclose(h, h.T, atol=0)
    n = len(rad)
    for c in range(2):
        t = np.zeros(2 * n)
        t[c::2] = 1.0
        np.testing.assert_allclose(h @ t, 0.0, atol=1e-10 * np.abs(h).max())
    # the same packing shifted and relabelled has the same Hessian, permuted
    perm = np.random.default_rng(0).permutation(n)
    shifted = (pos[perm] + [0.37, 0.21]) % box
    h2 = hessian(shifted, rad[perm], box, 2.5).dense()
    dof = np.ravel(np.column_stack([2 * perm, 2 * perm + 1]))
    np.testing.assert_allclose(h2, h[np.ix_(dof, dof)], atol=1e-9 * np.abs(h).max())


def test_a_jammed_packing_has_exactly_two_zero_modes_without_rattlers():
    p = kernels.jam(64, 1e-8, seed=3)
    hb = hessian(p.positions, p.radii, p.box, rattlers=False)
    assert len(hb.nodes) == p.n_nonrattlers
    ev = np.linalg.eigvalsh(hb.dense())
    scale = ev.max()
    assert np.sum(np.abs(ev) < 1e-9 * scale) == 2
    assert ev[2] > 1e-7 * scale


def test_no_contact_no_blocks():
    pos = np.array([[0.1, 0.1], [0.6, 0.6]])
    hb = hessian(pos, [0.01, 0.01], (1, 1))
    assert hb.pairs_i.size == 0 and np.all(hb.diag == 0.0)
