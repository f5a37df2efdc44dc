"""Benchmark of the sparse Cholesky of the Newton endgame against the solvers PyPI offers.

The matrix is what ``kernels.newton`` factors: the Hessian of a jammed packing's contact
network (``kernels.hessian``, every disk kept) on the pattern of pairs within their contact
distance plus ``kernels.newton.PATTERN_SKIN`` mean diameters (explicit zeros where there is
no contact), plus ``1e-8 k0`` on the diagonal (``k0`` the mean contact stiffness; it lifts
the translations and the rattlers off zero). For each N (default 1024, 4096, 8192) and each
solver available, median CPU times over repeats of

* the symbolic analysis (ordering and structure, once per pattern in the endgame),
* the numeric factorisation (every Newton iteration),
* one solve,

and the relative residual ``|A x - b| / |b|``. Solvers: this project's (``kernels.sparse``,
always); ``scipy.sparse.linalg.splu`` (LU, scipy's SuperLU, always); and, when importable,
``qdldl`` (LDL^T, numeric refactorisation by ``update``), CHOLMOD through ``cvxopt``
(``cvxopt.cholmod.symbolic`` / ``numeric``; GPL) and ``cholespy``. None of the optional
ones is a dependency of the project; ``pip install qdldl cvxopt cholespy`` to compare.

Prints a table (ratios to this project's numeric factorisation) and, with ``--json FILE``,
writes every measurement as JSON. Run it on a quiet machine:

    python benchmarks/bench_sparse.py --json sparse.json        # docs/NEWTON.md
    python benchmarks/bench_sparse.py --sizes 1024 --repeats 5    # quick
"""

import argparse
import json
import platform
import statistics
import sys
import time

import numpy as np


def _timed(fn, repeats):
    times, out = [], None
    for _ in range(repeats):
        t = time.process_time()
        out = fn()
        times.append(time.process_time() - t)
    return 1e3 * statistics.median(times), out


def _matrix(n, seed):
    """A packing jammed at E_G = 1e-10 and its shifted Hessian on the endgame's pattern, built
    by the endgame's own kernels (``kernels.minimiser._verlet_rows``, ``kernels.hessian``)."""
    import kernels
    from kernels.minimiser import _verlet_rows
    from kernels.hessian import _hessian_rows
    from kernels.newton import PATTERN_SKIN
    from kernels.space import _as_box

    p = kernels.jam(n, 1e-10, seed, force_tolerance=1e-5)
    pos, rad, box = np.array(p.positions), np.asarray(p.radii), _as_box(p.box)
    pi, pj, start, nbr, inv_s = _verlet_rows(pos, rad, box, PATTERN_SKIN * 2 * rad.mean(), rad,
                                             np.empty_like(pos))
    diag = np.zeros((n, 3))
    off = np.empty((len(pi), 3))
    ncontact, ksum = _hessian_rows(pos, box, start, nbr, inv_s, 2.0, np.ones(n, dtype=np.bool_),
                                   diag, off, np.empty(n, dtype=np.int64))
    k0 = ksum / ncontact
    diag[:, 0] += 1e-8 * k0
    diag[:, 2] += 1e-8 * k0
    return pos, box, pi, pj, diag, off


def _scipy_upper(n, pi, pj, diag, off):
    import scipy.sparse as sp

    a = np.arange(n)
    rows = np.concatenate([2 * pi, 2 * pi, 2 * pi + 1, 2 * pi + 1, 2 * a, 2 * a, 2 * a + 1])
    cols = np.concatenate([2 * pj, 2 * pj + 1, 2 * pj, 2 * pj + 1, 2 * a, 2 * a + 1, 2 * a + 1])
    vals = np.concatenate([off[:, 0], off[:, 1], off[:, 1], off[:, 2], diag[:, 0], diag[:, 1], diag[:, 2]])
    upper = sp.coo_matrix((vals, (np.minimum(rows, cols), np.maximum(rows, cols))),
                          shape=(2 * n, 2 * n)).tocsc()
    return upper, (upper + sp.triu(upper, 1).T).tocsc()


def _solvers(n, pos, box, pi, pj, diag, off, repeats):
    """Yields (name, symbolic ms, numeric ms, solve ms, residual) per available solver."""
    from kernels import sparse

    upper, full = _scipy_upper(n, pi, pj, diag, off)
    b = np.random.default_rng(0).standard_normal(2 * n)
    res = lambda x: float(np.linalg.norm(full @ x - b) / np.linalg.norm(b))  # noqa: E731

    warm = sparse.analyse(pos, box, pi, pj)  # compile (or load) the kernels outside the timings
    sparse.solve(warm, sparse.factor(warm, diag, off), b)
    t_sym, sym = _timed(lambda: sparse.analyse(pos, box, pi, pj), max(1, repeats // 3))
    t_num, lval = _timed(lambda: sparse.factor(sym, diag, off), repeats)
    t_sol, x = _timed(lambda: sparse.solve(sym, lval, b), repeats)
    yield "kernels.sparse (this project, MIT)", t_sym, t_num, t_sol, res(x)

    from scipy.sparse.linalg import splu

    t_lu, lu = _timed(lambda: splu(full), max(1, repeats // 3))
    t_sol, x = _timed(lambda: lu.solve(b), repeats)
    yield "scipy splu (BSD)", None, t_lu, t_sol, res(x)
    try:
        import qdldl
    except ImportError:
        pass
    else:
        t_sym, solver = _timed(lambda: qdldl.Solver(upper), max(1, repeats // 3))
        t_num, _ = _timed(lambda: solver.update(upper), repeats)
        t_sol, x = _timed(lambda: solver.solve(b), repeats)
        yield "qdldl (Apache-2.0)", t_sym, t_num, t_sol, res(x)
    try:
        import cvxopt
        import cvxopt.cholmod as cholmod
    except ImportError:
        pass
    else:
        import scipy.sparse as sp

        low = sp.tril(full).tocoo()
        a = cvxopt.spmatrix(low.data.tolist(), low.row.tolist(), low.col.tolist(), (2 * n, 2 * n))
        t_sym, fac = _timed(lambda: cholmod.symbolic(a), max(1, repeats // 3))
        t_num, _ = _timed(lambda: cholmod.numeric(a, fac), repeats)

        def solve():
            xb = cvxopt.matrix(b)
            cholmod.solve(fac, xb)
            return np.array(xb).ravel()

        t_sol, x = _timed(solve, repeats)
        yield "CHOLMOD via cvxopt (GPL-3)", t_sym, t_num, t_sol, res(x)
    try:
        import cholespy
    except ImportError:
        pass
    else:
        coo = full.tocoo()
        rows, cols, vals = coo.row.astype(np.int32), coo.col.astype(np.int32), coo.data
        t_num, fac = _timed(lambda: cholespy.CholeskySolverD(2 * n, rows, cols, vals,
                                                             cholespy.MatrixType.COO), repeats)

        def solve():
            out = np.zeros(2 * n)
            fac.solve(b, out)
            return out

        t_sol, x = _timed(solve, repeats)
        yield "cholespy (BSD-3)", None, t_num, t_sol, res(x)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096, 8192])
    ap.add_argument("--repeats", type=int, default=9, help="repeats per timing (median)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", metavar="FILE", help="write all measurements as JSON")
    args = ap.parse_args(argv)

    import numba

    rows = []
    for n in args.sizes:
        pos, box, pi, pj, diag, off = _matrix(n, args.seed)
        ours = None
        for name, t_sym, t_num, t_sol, resid in _solvers(n, pos, box, pi, pj, diag, off, args.repeats):
            ours = t_num if ours is None else ours
            row = dict(n=n, solver=name, pattern_pairs=int(len(pi)), symbolic_ms=t_sym,
                       numeric_ms=t_num, solve_ms=t_sol, residual=resid, numeric_ratio=t_num / ours)
            rows.append(row)
            sym = f"{t_sym:.2f}" if t_sym is not None else "-"
            print(f"N={n} {name}: symbolic {sym} ms, numeric {t_num:.2f} ms, solve {t_sol:.2f} ms, "
                  f"residual {resid:.1e}", flush=True)
    print()
    print("| N | solver | symbolic (ms) | numeric factorisation (ms) | ratio to ours | solve (ms) | residual |")
    print("|---:|---|---:|---:|---:|---:|---:|")
    for r in rows:
        sym = f"{r['symbolic_ms']:.2f}" if r["symbolic_ms"] is not None else "(with numeric)"
        print(f"| {r['n']} | {r['solver']} | {sym} | {r['numeric_ms']:.2f} | {r['numeric_ratio']:.2f} | "
              f"{r['solve_ms']:.2f} | {r['residual']:.1e} |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(dict(machine=dict(python=platform.python_version(), numpy=np.__version__,
                                        numba=numba.__version__), rows=rows), fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
