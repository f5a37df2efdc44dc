"""The rounds' model of an intercept's error where the reducer averages the line and the parabola in
1/N_G (``errormodel.LawModel.intercept_variance``, ``errormodel.choice_variance``): against Monte
Carlo, against the reducer's own bootstrap on drawn intercepts, and on a campaign of known laws."""

from __future__ import annotations

import numpy as np
import pytest

from campaign.precision import errormodel as M
from campaign.results import fits

from helpers import FIVE_SIZES, PRECISION_SPEC, uniform_reduced

SIZES = np.array([64, 128, 256, 512, 1024], float)
SPEC = PRECISION_SPEC


def _akaike_weight(z):
    """The parabola's Akaike weight when its 1/N_G^2 coefficient sits z errors from zero (one parameter
    more, chi^2 lower by z^2)."""
    return 1.0 / (1.0 + np.exp((2.0 - z * z) / 2.0))


@pytest.mark.parametrize("zeta", [0.0, 1.0, 2.7, 4.0, 7.0])
def test_choice_variance_is_the_variance_of_the_weighted_z(zeta):
    rng = np.random.default_rng(11)
    z = zeta + rng.standard_normal(400_000)
    mc = np.var(_akaike_weight(z) * z)
    assert M.choice_variance(zeta ** 2) == pytest.approx(mc, rel=0.01)
    assert M.choice_variance(1e4) == 1.0  # far out the parabola alone


def _gls(X, cov, y):
    W = np.linalg.inv(cov)
    C = np.linalg.inv(X.T @ W @ X)
    return C @ X.T @ W @ y, C


@pytest.mark.parametrize("c", [0.0, 15.0, 30.0, 60.0, -25.0])
def test_the_formula_is_the_reducers_average_on_drawn_intercepts(c):
    """Sizes' intercepts ``a + b/N + c/N^2`` with independent errors, bootstrap replicas drawn about
    one realisation: the spread of ``fits.line_in_inverse_n``'s averaged replicas is
    ``sqrt(v1 + (v2 - v1) choice_variance(z^2))``, v1 and v2 the line's and the parabola's
    generalised-least-squares variances and z the 1/N_G^2 coefficient's z-score that the average's
    weight gives, in the linear Gaussian case exactly (here within the replicas' scatter)."""
    rng = np.random.default_rng(int(abs(c)) + 3)
    sd = 0.003 * np.sqrt(64.0 / SIZES)
    cov = np.diag(sd ** 2)
    y = 0.446 - 0.8 / SIZES + c / SIZES ** 2 + sd * rng.standard_normal(len(SIZES))
    reps = y + sd * rng.standard_normal((8000, len(SIZES)))
    line = fits.line_in_inverse_n(SIZES.astype(int), y, reps)
    kept = np.isin(SIZES, line.sizes)  # the reducer leaves the smallest out where both models fail
    assert kept.sum() >= 4 and not line.limited
    N, y, cov = SIZES[kept], y[kept], cov[np.ix_(kept, kept)]
    X = np.column_stack([np.ones(len(N)), 1 / N, 1 / N ** 2])
    _, c1 = _gls(X[:, :2], cov, y)
    p2, c2 = _gls(X, cov, y)
    z2 = p2[2] ** 2 / c2[2, 2]
    # the weight the reducer reports is that z's (its covariance is the replicas', close to cov)
    assert line.parabola_weight == pytest.approx(_akaike_weight(np.sqrt(z2)), abs=0.03)
    model = np.sqrt(c1[0, 0] + (c2[0, 0] - c1[0, 0]) * M.choice_variance(z2))
    assert np.std(line.replicas) == pytest.approx(model, rel=0.04)
    assert line.err == pytest.approx(model, rel=0.08)  # the reducer's 68% half-width of the same replicas


def test_the_model_holds_the_choice_on_a_campaign_of_known_laws():
    """A uniform campaign on five sizes whose A_G intercepts curve in 1/N_G (a 1/N_G^2 term): the
    model's error of A_G_star_E (the line's and the parabola's Fisher variances, mixed at the
    reducer's weight) is the reducer's bootstrap error within 20%; the line's alone falls short of it,
    as the rounds' model did before it held the choice."""
    spec = FIVE_SIZES.format(name="curved", seed=9, max_seeds=30)
    cells, table = uniform_reduced(spec, 30, {"a_N2": 20.0})
    n = M.cell_counts(table, cells)
    law = M.build_law(table, cells, "default", "A_G", "E_G")
    assert law.ok and law.curved, law.why
    st = law.state(n)
    law.anchor(st)
    err = table.extrapolated["default"]["A_G_star_E_err"]
    model = np.sqrt(law.intercept_variance(st))
    line_only = np.sqrt(st[0][0, 0])
    assert 0.85 < model / err < 1.18, (model, err)
    assert line_only / err < 0.82, (line_only, err)
    # more packings everywhere: the line's and the parabola's variances fall as 1/n, the z-score grows
    # as sqrt(n), and the mix follows choice_variance there
    st4 = law.state(4 * n)
    zeta2 = law.c2 / st4[5][-1, -1]
    assert zeta2 == pytest.approx(4 * law.z2, rel=1e-6)
    v1, v2 = st4[0][0, 0], st4[5][0, 0]
    assert law.intercept_variance(st4) == pytest.approx(v1 + (v2 - v1) * M.choice_variance(zeta2), rel=1e-9)
    assert v1 == pytest.approx(st[0][0, 0] / 4, rel=1e-9)


def test_round_zero_from_the_prior(tmp_path, monkeypatch):
    """Round 0 where the prior holds the campaign: at least the pilot everywhere, the pilot alone outside
    the targets' fit range, never above max_seeds, more than the pilot where the prior's plan puts
    seeds; the same whatever calibration is in force (priced by the packaged one); the uniform pilot for
    a system the prior does not hold."""
    import json

    from campaign.plan import calibration
    from campaign.plan.parse import parse_spec
    from campaign.plan.tasks import expand
    from campaign.precision import planner as P

    spec = parse_spec(SPEC)
    tasks = expand(spec)
    cells = M.campaign_cells(spec, tasks)
    first, how = P.first_round(spec, tasks)
    p, m = spec.precision.pilot, spec.precision.max_seeds
    relevant = cells.relevant(spec.precision.settings()["target"])
    assert how.startswith("designed from the prior")
    assert first.min() >= p and first.max() <= m and np.all(first[~relevant] == p)
    assert first.sum() > p * cells.C
    plan = P.plan_from_prior(spec, tasks, cal=calibration.packaged())
    np.testing.assert_array_equal(first, np.maximum(p, np.floor(p + P.PRIOR_SHARE * (np.array(plan["allocation"]) - p)
                                                                + 1e-9)))
    # another calibration (the cost growing faster with N_G): the plan in force moves, round 0 does not
    d = json.loads(calibration.packaged_text())
    d["fire"]["values"][1] *= 1.3
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(d))
    with calibration.using(path):
        assert P.plan_from_prior(spec, tasks)["allocation"] != plan["allocation"]  # the plan in force moves
        np.testing.assert_array_equal(P.first_round(spec, tasks)[0], first)
    hertz = parse_spec(SPEC.replace("seed: 5\n", "seed: 5\nsystem: {potential: {exponent: 2.5}}\n"))
    counts, how = P.first_round(hertz, expand(hertz))
    assert np.all(counts == p) and how.startswith("a uniform pilot")


@pytest.mark.parametrize("dropped", [(), (0,), (0, 1)])
def test_a_size_the_reducer_leaves_out_has_an_intercept_of_its_own(dropped):
    """Where the reducer's rule for sizes off the line leaves the smallest out of the 1/N_G
    extrapolation, the model gives that size an intercept of its own (it still informs the exponent):
    the joint Fisher variance of a_inf is then exactly that of the two-stage estimate, the generalised
    least-squares line (and parabola) through the kept sizes' intercepts with their covariance from
    the fit with a free intercept per size (a slow reference)."""
    spec = FIVE_SIZES.format(name="five", seed=3, max_seeds=12)
    cells, table = uniform_reduced(spec, 12)
    law = M.build_law(table, cells, "default", "A_G", "E_G")
    G = len(law.sizes)
    law.left_out = np.isin(np.arange(G), dropped)
    law.J, law.s2 = law.at(law.beta, law.refit(law.beta)[0])  # the design with those sizes' own intercepts
    kept = ~law.left_out
    law.z2 = 1.0  # curved: the parabola's state too
    n = np.array([12.0 + (c % 5) for c in range(cells.C)])  # unequal counts
    st = law.state(n)
    C = st[1][1:1 + G, 1:1 + G][np.ix_(kept, kept)]  # the kept sizes' intercepts, from the free fit
    Ninv = 1.0 / np.asarray(law.sizes, float)[kept]
    W = np.linalg.inv(C)
    for X, inv in ((np.column_stack([np.ones(kept.sum()), Ninv]), st[0]),
                   (np.column_stack([np.ones(kept.sum()), Ninv, Ninv ** 2]), st[5])):
        ref = np.linalg.inv(X.T @ W @ X)[0, 0]
        assert inv[0, 0] == pytest.approx(ref, rel=1e-8)

