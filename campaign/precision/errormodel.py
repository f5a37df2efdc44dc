"""The model of a precision campaign's errors (docs/PRECISION.md, "The model of the errors").

Each target is an entry of the ``N_G -> inf`` row of one law ``y = a_N + c_N x^beta`` (y: ``A_G`` or
``psi_O``; x: ``E_G`` or ``delta_Z``), the exponent shared by the sizes and the intercepts extrapolated
as ``a_N = a_inf + b / N``. Linearised about the fitted values, the row is a weighted least-squares
fit of the cell means with parameters ``theta = (a_inf, b, beta, c_N1 .. c_NG)``, so its covariance
is the inverse of the Fisher information

    I(n) = sum over the cells c of the fit range  (n_c / s_c^2) J_c J_c^T,
    J_c = d(a_inf + b/N + c_N x_c^beta) / d theta = (1, 1/N, c_N x_c^beta ln x_c, x_c^beta e_N),

``n_c`` the cell's usable packings and ``s_c^2`` the variance between its packings of
``y - c_N beta x_c^(beta-1) x`` (the scatter of the abscissa carried through the law, as the
bootstrap carries it; pooled with the other sizes' at the cell's energy, ``_shrunk``). The same
with a free intercept per size gives the sizes' intercept errors, and with them the reducer's
``sqrt(chi^2/dof)`` of its 1/N_G line where a size lies off it (``LawModel.inflation``).
``campaign.precision.allocation`` turns this into decisions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from campaign.plan.targets import in_fit_range
from campaign.results import fits

#: a size whose intercept lies off the 1/N_G line by more than this many of its errors has a systematic
#: offset (a finite-size correction beyond 1/N_G) that the model keeps: more seeds at that size make the
#: reducer's sqrt(chi^2/dof) of the line larger, not its error smaller
SYSTEMATIC_SIGMA = 3.0
#: ... in a 1/N_G line whose chi^2 has a p-value below this (a few packings per cell make a size's
#: bootstrap error short, and one size in several lies 3 errors off now and then)
SYSTEMATIC_P = 0.001
#: ... and whose cells hold this many usable packings on average (fewer make a bootstrap error short)
SYSTEMATIC_PACKINGS = 10
#: a cell's variance between packings is pulled toward its energy's pooled one with this weight, in
#: degrees of freedom (its own: its packings less one)
PRIOR_DOF = 8
#: a law whose data show no dependence of y on x at this p-value or above has no exponent to measure
NO_DEPENDENCE_P = 0.01


@dataclass
class Cells:
    """The cells of a campaign (variant, N, E) in the task table's order, each holding the tasks
    ``first + seed`` for seeds 0 .. ``seeds - 1``."""

    variant: list
    N: np.ndarray
    E: np.ndarray
    exponent: np.ndarray   # the variant's potential exponent
    first: np.ndarray      # index of the cell's seed 0
    seeds: int             # tasks per cell (max_seeds)

    @property
    def C(self) -> int:
        return len(self.variant)

    def key(self, c) -> tuple:
        return (self.variant[c], int(self.N[c]), float(self.E[c]))

    def index(self) -> dict:
        return {self.key(c): c for c in range(self.C)}

    def tasks_of(self, counts) -> np.ndarray:
        """Task indices of the first ``counts[c]`` seeds of every cell (bool mask, one per task)."""
        mask = np.zeros(self.C * self.seeds, bool)
        for c in range(self.C):
            mask[self.first[c]:self.first[c] + int(counts[c])] = True
        return mask

    def relevant(self, targets) -> np.ndarray:
        """The cells in the default fit range of a variant that has targets: where seeds can move
        the ``N_G -> inf`` row (every variant has every target)."""
        return np.asarray(in_fit_range(self.E, self.exponent), bool) if targets else np.zeros(self.C, bool)


def campaign_cells(spec, tasks) -> Cells:
    """The cells of a precision campaign's task table (canonical order: variant, N, E, seed)."""
    S = spec.precision.max_seeds if spec.precision is not None else len(spec.seeds)
    first = np.arange(0, len(tasks), S)
    t = [tasks[i] for i in first]
    return Cells(variant=[x.variant for x in t], N=np.array([x.N for x in t], np.int64),
                 E=np.array([x.E for x in t], float), exponent=np.array([x.exponent for x in t], float),
                 first=first, seeds=S)


def table_cells(table) -> Cells:
    """The cells of a reduction's grid (``reduce.Table``), as ``Cells`` (one seed slot each: a store of a
    fixed grid seen by the model, for the experiments that plan on a finished campaign's packings)."""
    g = table.grid
    order = sorted(range(g.C), key=lambda c: (str(g.cv[c]), int(g.cN[c]), float(g.cE[c])))
    systems = table.systems
    return Cells(variant=[str(g.cv[c]) for c in order], N=np.array([int(g.cN[c]) for c in order], np.int64),
                 E=np.array([float(g.cE[c]) for c in order]),
                 exponent=np.array([float(systems[str(g.cv[c])]["exponent"]) for c in order]),
                 first=np.arange(len(order)), seeds=1)


def cell_counts(table, cells: Cells) -> np.ndarray:
    """The packings each of ``cells`` holds in a reduction ``table`` (its grid's ``n_done``; 0 for a
    cell the reduction does not have)."""
    n = np.zeros(cells.C)
    index = cells.index()
    g = table.grid
    for gc in range(g.C):
        c = index.get((str(g.cv[gc]), int(g.cN[gc]), float(g.cE[gc])))
        if c is not None:
            n[c] = g.n_done[gc]
    return n


@dataclass
class LawModel:
    """One variant's law ``y = a_N + c_N x^beta``, linearised about a fit (the module docstring):
    the cells it fits (indices into ``Cells``, and the size of each), their means, the reducer's
    weights and their packings' moments, the point fit, and at any exponent the design vectors and the
    per-packing variances (``at``) from which the Fisher information follows."""

    variant: str
    quantity: str
    abscissa: str
    sizes: list
    cells: np.ndarray = field(default_factory=lambda: np.zeros(0, int))   # campaign cells in the fit
    size_of: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # index into sizes
    xbar: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ybar: np.ndarray = field(default_factory=lambda: np.zeros(0))
    yerr: np.ndarray = field(default_factory=lambda: np.zeros(0))          # the reducer's weights 1/yerr^2
    moments: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # per cell: its packings' sample
    #                                                                        var x, var y, cov(x, y)
    beta: float = np.nan
    sys2: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per size: its intercept's systematic
    #                         squared offset from the 1/N_G line (seeds do not remove it: the reducer's
    #                         sqrt(chi^2/dof) grows as the sizes' errors shrink)
    dof: int = 0            # degrees of freedom of the 1/N_G line (sizes - 2)
    ok: bool = True
    why: str = ""
    J: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))         # at the point fit
    s2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    left_out: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # per size: left out of the
    #                         reducer's 1/N_G extrapolation (its rule for sizes off the line): its intercept
    #                         is then a parameter of its own, which informs the exponent and not a_inf
    z2: float = np.nan      # the squared z-score of the 1/N_G^2 term the reducer's Akaike weight of its
    #                         parabola implies (NaN: the reducer extrapolates with the line alone)
    c2: float = np.nan      # that term's squared coefficient, in the model's units (``anchor``)

    @property
    def curved(self) -> bool:
        """Whether the reducer averages line and parabola here, so that an intercept's error holds the
        choice between them (``intercept_variance``)."""
        return bool(np.isfinite(self.z2))

    def free(self, J) -> np.ndarray:
        """The design vectors with a free intercept per size (``theta = (beta, a_N1 .. a_NG, c_N1 ..
        c_NG)``: the shared fit before the 1/N_G line), for the sizes' intercept errors."""
        G = len(self.sizes)
        F = np.zeros((len(J), 1 + 2 * G))
        F[:, 0] = J[:, 2]
        F[np.arange(len(J)), 1 + self.size_of] = 1.0
        F[:, 1 + G:] = J[:, 3:3 + G]
        return F

    def state(self, n, J=None, s2=None):
        """The inverses of the Fisher information at ``n``: joint (the line in 1/N_G), with free
        intercepts, and, where the law is ``curved``, joint with a 1/N_G^2 term (its parameter last)."""
        J = self.J if J is None else J
        s2 = self.s2 if s2 is None else s2
        w = np.asarray(n, float)[self.cells] / s2
        F = self.free(J)
        P = np.column_stack([J, J[:, 1] ** 2]) if self.curved else None
        return [inverse((J * w[:, None]).T @ J), inverse((F * w[:, None]).T @ F), J, F, s2,
                None if P is None else inverse((P * w[:, None]).T @ P), P]

    def add(self, st, i, dn):
        """``st`` with ``dn`` more usable packings in the law's cell ``i`` (rank-one updates)."""
        inv, invf, J, F, s2, inv2, P = st
        w = dn / s2[i]
        out = [inv, invf, inv2]
        for k, (A_, v) in enumerate(((inv, J[i]), (invf, F[i]), (inv2, None if P is None else P[i]))):
            if A_ is None:
                continue
            Av = A_ @ v
            q = float(v @ Av)
            if np.all(np.isfinite(Av)) and np.isfinite(q):
                out[k] = A_ - np.outer(Av, Av) * (w / (1.0 + w * q))
        return [out[0], out[1], J, F, s2, out[2], P]

    def anchor(self, st):
        """Fix the 1/N_G^2 coefficient's square from the reducer's z-score at the state ``st`` of the
        present packings: later states see that coefficient against their own error, so its z-score
        grows like the square root of the packings."""
        if self.curved and st[5] is not None and np.isfinite(st[5][-1, -1]):
            self.c2 = self.z2 * float(st[5][-1, -1])

    def intercept_variance(self, st) -> float:
        """The model's variance of the ``N_G -> inf`` intercept at the state ``st``. For the line alone,
        ``v1 = [I^-1]_00``. Where the reducer averages the line with the parabola (Akaike weight
        ``w(z) = 1 / (1 + exp((2 - z^2) / 2))`` of the parabola, z the z-score of its 1/N_G^2
        coefficient), the average is ``a1 - w(z) z sqrt(v2 - v1)`` (in a linear Gaussian model the
        line's intercept ``a1`` is independent of z, and ``a2 - a1 = z sqrt(v2 - v1)``), so its variance
        is ``v1 + (v2 - v1) choice_variance(zeta)``, v2 the parabola's, ``zeta`` the z-score at this
        state (``anchor``). On paper-small this gives the reducer's A_G_star_E error to 0.3%."""
        v1 = float(st[0][0, 0])
        inv2 = st[5] if len(st) > 5 else None
        if inv2 is None or not np.isfinite(self.c2):
            return v1
        v2, vc = float(inv2[0, 0]), float(inv2[-1, -1])
        if not (np.isfinite(v2) and np.isfinite(vc) and vc > 0 and np.isfinite(v1)):
            return v1
        return v1 + max(v2 - v1, 0.0) * choice_variance(self.c2 / vc)

    def inflation(self, invf) -> float:
        """The reducer's sqrt(chi^2/dof) of the 1/N_G line, squared, expected at the sizes' intercept
        errors of ``invf``: ``max(1, (dof + sum sys2 / sigma_N^2) / dof)``."""
        if self.dof <= 0 or not np.any(self.sys2 > 0):
            return 1.0
        G = len(self.sizes)
        var = np.diag(invf)[1:1 + G]
        chi2 = self.dof + float(np.sum(np.where(var > 0, self.sys2 / np.maximum(var, 1e-300), 0.0)))
        return max(1.0, chi2 / self.dof)

    def refit(self, beta):
        """The amplitudes c_N and chi^2 of the reducer's weighted fit with the exponent held at ``beta``."""
        G = len(self.sizes)
        coeffs, chi2 = np.zeros(G), 0.0
        for gi in range(G):
            m = self.size_of == gi
            x, y, w = self.xbar[m], self.ybar[m], 1.0 / self.yerr[m] ** 2
            f = np.where(x > 0, x, 0.0) ** beta
            a, c, ch = fits._solve_linear(f[None], y[None], w)
            coeffs[gi], chi2 = float(c[0]), chi2 + float(ch[0])
        return coeffs, chi2

    def at(self, beta, coeffs):
        """Design vectors (K, 3 + G + D) and per-packing residual variances (K,) at an exponent and its
        amplitudes; cells whose packings show no spread are left out (weight 0). The D sizes
        ``left_out`` have an intercept of their own (the last D columns) in place of ``a_inf + b / N``."""
        G = len(self.sizes)
        K = len(self.cells)
        out = np.zeros(G, bool) if len(self.left_out) != G else np.asarray(self.left_out, bool)
        own = np.cumsum(out) - 1  # a left-out size's column among the last D
        J, s2 = np.zeros((K, 3 + G + int(out.sum()))), np.full(K, np.inf)
        for i in range(K):
            gi, xc = int(self.size_of[i]), float(self.xbar[i])
            vx, vy, cxy = self.moments[i]
            cN = coeffs[gi]
            if xc > 0:
                xb = xc ** beta
                slope, dbeta = cN * beta * xc ** (beta - 1.0), cN * xb * math.log(xc)
                var = vy - 2.0 * slope * cxy + slope * slope * vx  # of y - slope x between packings
            else:  # an isostatic cell (every Delta Z = 0): a point at the intercept
                var, xb, dbeta = vy, 0.0, 0.0
            if not (np.isfinite(var) and var > 1e-12 * vy):
                var = vy
            if np.isfinite(var) and var > 0:
                s2[i] = var
            J[i, 2], J[i, 3 + gi] = dbeta, xb
            if out[gi]:
                J[i, 3 + G + own[gi]] = 1.0
            else:
                J[i, 0], J[i, 1] = 1.0, 1.0 / self.sizes[gi]
        return J, s2

    def info(self, n, J=None, s2=None) -> np.ndarray:
        """Fisher information at usable packings ``n`` per campaign cell."""
        J = self.J if J is None else J
        s2 = self.s2 if s2 is None else s2
        w = np.asarray(n, float)[self.cells] / s2
        return (J * w[:, None]).T @ J

    def inverse(self, n, J=None, s2=None) -> np.ndarray:
        return inverse(self.info(n, J, s2))

    def dependence_p(self) -> float:
        """The p-value of "y does not depend on x" against the best power law (the reducer's weighted
        chi^2 of a constant per size less the fit's, as a chi^2 of G + 1 degrees of freedom: the
        amplitudes and the exponent)."""
        const = 0.0
        for gi in range(len(self.sizes)):
            m = self.size_of == gi
            y, w = self.ybar[m], 1.0 / self.yerr[m] ** 2
            const += float(np.sum(w * (y - np.sum(w * y) / np.sum(w)) ** 2))
        best = min(ch for _, _, ch in self._profile())
        return fits.chi2_p_value(max(const - best, 0.0), len(self.sizes) + 1)

    def _profile(self, points=60):
        grid = np.linspace(fits.BETA_BOUNDS[0], fits.BETA_BOUNDS[1], points)
        return [(b, *self.refit(b)) for b in np.append(grid, self.beta)]

    def plausible(self, spread=9.0, points=60):
        """Exponents of the search range the data do not exclude (the reducer's weighted chi^2 within
        ``spread`` of its minimum: three standard deviations of a profile), with their amplitudes."""
        fitted = self._profile(points)
        best = min(ch for _, _, ch in fitted)
        return [(b, c) for b, c, ch in fitted if ch <= best + spread]


def _choice_table(zmax=12.0, points=241, nodes=80):
    zeta = np.linspace(0.0, zmax, points)
    x, wq = np.polynomial.hermite_e.hermegauss(nodes)
    wq = wq / wq.sum()
    z = zeta[:, None] + x[None, :]
    f = z / (1.0 + np.exp((2.0 - z * z) / 2.0))
    m = f @ wq
    return zeta, ((f - m[:, None]) ** 2) @ wq


_CHOICE = _choice_table()


def choice_variance(zeta2) -> float:
    """``Var[w(z) z]`` for ``z ~ N(zeta, 1)`` (``zeta2 = zeta^2``), ``w`` the parabola's Akaike weight:
    the share of ``v2 - v1`` the choice between line and parabola adds to an intercept's variance.
    0.38 at zeta = 0 (no curvature: the replicas' weights scatter about 0.27), a peak of 1.46 near
    zeta = 2.7 (the weight swings between the models from replica to replica), 1 for large zeta (the
    parabola alone)."""
    zeta = math.sqrt(max(float(zeta2), 0.0))
    if not np.isfinite(zeta) or zeta >= _CHOICE[0][-1]:
        return 1.0
    return float(np.interp(zeta, *_CHOICE))


def inverse(I) -> np.ndarray:
    """The inverse of a Fisher information; a parameter the data do not inform at all (an amplitude of
    zero leaves the exponent's column zero) gets an infinite variance and the others the inverse of
    the rest."""
    diag = np.diag(I).copy()
    live = diag > 1e-300 * max(1.0, float(np.max(np.abs(diag), initial=0.0)))
    out = np.zeros_like(I)
    out[~live, ~live] = np.inf
    if not live.any():
        return out
    sub = I[np.ix_(live, live)]
    d = np.sqrt(np.diag(sub))
    scaled = sub / np.outer(d, d)
    try:
        inv = np.linalg.inv(scaled)
        if not np.all(np.isfinite(inv)):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(scaled, rcond=1e-13)
    inv = inv / np.outer(d, d)
    bad = ~(np.diag(inv) > 0)  # a direction the data leave free (numerically singular)
    inv[bad, bad] = np.inf
    out[np.ix_(live, live)] = inv
    return out


def param_index(kind) -> int:
    """The parameter of ``theta`` a table key is: the intercept ``a_inf`` or the exponent ``beta``."""
    return 0 if kind == "intercept" else 2


def _shrunk(moments, n, N, E):
    """Each cell's moments (var x, var y, cov) pulled toward what the law's other sizes at its energy
    say (their moments times N_G over this N_G: the spread between packings falls like 1/sqrt(N_G)),
    weighted by degrees of freedom, the cell's ``n - 1`` against ``PRIOR_DOF``. A variance from a few
    packings is off by tens of per cent; the cells whose estimate came out low would look the most
    informative and get the seeds, and the gain projected from them would not come (the winner's
    curse), which the pooled estimate damps."""
    out = moments.copy()
    for i in range(len(moments)):
        same = np.flatnonzero(np.isclose(E, E[i], rtol=1e-9, atol=0.0))
        if len(same) < 2:
            continue
        pooled = np.median(moments[same] * (N[same] / N[i])[:, None], axis=0)
        nu = max(n[i] - 1, 0)
        out[i] = (nu * moments[i] + PRIOR_DOF * pooled) / (nu + PRIOR_DOF)
    return out


def build_law(table, cells: Cells, variant, quantity, absc) -> LawModel:
    """The model of one variant's law from its reduction ``table`` (``reduce.Table``): the sizes
    that entered the shared fit, their cells, the point fit and each cell's packings' moments."""
    per_n = table.shared_in.get((variant, quantity, absc), {})
    sizes = sorted(n for n, d in per_n.items() if not isinstance(d, str))
    index = cells.index()
    g = table.grid
    if len(sizes) < 2:
        return LawModel(variant, quantity, absc, sizes, ok=False,
                        why=f"{len(sizes)} size(s) in the shared fit of {quantity} against {absc}; the N_G -> inf "
                            "row needs two")
    xs, ys, yerrs = [per_n[n][0] for n in sizes], [per_n[n][1] for n in sizes], [per_n[n][2] for n in sizes]
    f = fits.fit_shared_exponent(xs, ys, yerrs)
    beta = float(f.exponent)
    if not (f.ok and np.isfinite(beta)):
        return LawModel(variant, quantity, absc, sizes, ok=False, why=f"no fit of {quantity} against {absc}")
    cell_ids, size_of, xbar, ybar, yerr, packs, held = [], [], [], [], [], [], []
    for gi, n in enumerate(sizes):
        x, y, ye, _, _, gcells = per_n[n]
        for xc, yc, ec, gc in zip(x, y, ye, gcells):
            c = index.get((str(g.cv[gc]), int(g.cN[gc]), float(g.cE[gc])))
            if c is None:
                continue
            p = g.packings(gc)
            yv, xv = table.fin.scalars[quantity][p], table.fin.scalars[absc][p]
            good = np.isfinite(yv) & np.isfinite(xv)
            yv, xv = yv[good], xv[good]
            if len(yv) < 2:
                continue
            cov = np.cov(np.vstack([xv, yv]), ddof=1)
            cell_ids.append(c)
            size_of.append(gi)
            xbar.append(xc)
            ybar.append(yc)
            yerr.append(ec)
            packs.append((cov[0, 0], cov[1, 1], cov[0, 1]))
            held.append(len(yv))
    moments = _shrunk(np.array(packs).reshape(-1, 3), np.array(held), cells.N[cell_ids], cells.E[cell_ids])
    law = LawModel(variant, quantity, absc, sizes, np.array(cell_ids, int), np.array(size_of, int), np.array(xbar),
                   np.array(ybar), np.array(yerr), moments, beta, dof=max(0, len(sizes) - 2))
    got = table.shared_fits.get((variant, quantity, absc))
    if got is not None and list(got[0]) == list(sizes):
        line = got[2]
        law.left_out = np.isin(np.asarray(sizes), np.asarray(line.left_out, dtype=np.int64))
        law.dof = max(0, int(np.count_nonzero(~law.left_out)) - 2)  # of the line through the sizes kept
        if len(line.sizes) >= 4:  # the reducer averages line and parabola through the sizes it keeps
            w2 = min(max(float(line.parabola_weight), 1e-300), 1.0 - 1e-15)
            law.z2 = max(0.0, 2.0 + 2.0 * math.log(w2 / (1.0 - w2)))
    law.J, law.s2 = law.at(beta, np.asarray(f.coeffs, float))
    law.sys2 = np.zeros(len(sizes))
    if got is not None and law.dof > 0:
        fsizes, sf, line = got
        if list(fsizes) == list(sizes) and np.isfinite(line.value) and np.isfinite(line.slope):
            resid = np.asarray(sf.intercepts) - (line.value + line.slope / np.asarray(sizes, float))
            err = np.asarray(sf.intercept_errs, float)
            # a size off the line by more than SYSTEMATIC_SIGMA of its error, in a line that fails its
            # chi^2 test (p < SYSTEMATIC_P): its offset is taken as real
            chi2 = float(line.chi2_dof) * law.dof if np.isfinite(line.chi2_dof) else 0.0
            held = np.array([np.mean([g.n_done[gc] for gc in per_n[n][5]]) for n in sizes])
            if fits.chi2_p_value(chi2, law.dof) < SYSTEMATIC_P:
                law.sys2 = np.where((np.abs(resid) > SYSTEMATIC_SIGMA * err) & (held >= SYSTEMATIC_PACKINGS)
                                    & ~law.left_out, resid ** 2 - err ** 2, 0.0)
    return law
