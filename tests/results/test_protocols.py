"""The jamming point (phi_J, the rattler fraction) per variant and the protocols compared
(campaign.results.protocols, docs/PROTOCOLS.md): against synthetic truths, a slow reference of
Holm's procedure, the bootstrap's errors against the spread of repeated experiments, and the
family-wise error rate of the tests under the null."""

from __future__ import annotations

import math

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from synthetic_store import SyntheticCampaign, Truth, write_store

from campaign import cli
from campaign.plan.targets import typical_overlap
from campaign.results import protocols as P
from campaign.results import reduce as R

FAST = R.Settings(n_boot=200)
N_SIZES = (64, 128, 256, 512)
# three protocols of one system: the reference, one whose jamming point moves (phi_J, the rattlers;
# A_G* too: the synthetic store shifts A_G by 0.01 per variant), one that differs only in A_G
TRUTHS = {"default": Truth(sigma_phi=0.02, phi_N=-0.3),
          "dilute": Truth(sigma_phi=0.02, phi_N=-0.3, phi_inf=0.836, f_R=0.03),
          "same-jamming": Truth(sigma_phi=0.02, phi_N=-0.3)}


@pytest.fixture(scope="module")
def three(tmp_path_factory):
    path = tmp_path_factory.mktemp("prot") / "p.h5"
    camp = SyntheticCampaign(N=N_SIZES, seeds=16, variants=tuple(TRUTHS), truth=TRUTHS["default"],
                             variant_truth=TRUTHS, histograms=("z_g",))
    write_store(path, camp)
    return path, camp, R.reduce_campaign(path, FAST, distributions=False)


def test_the_jamming_point_is_the_truth_at_every_size_and_at_infinity(three):
    _, camp, red = three
    pulls = []
    for r in red.protocols.jamming_sizes:
        t = TRUTHS[r["variant"]]
        assert r["n_cells"] == 5 and r["n_packings"] == 5 * camp.seeds  # the fit range: E_G <= 5e-7
        pulls.append((r["phi_J"] - (t.phi_inf + t.phi_N / r["N_G"])) / r["phi_J_err"])
        pulls.append((r["rattler_fraction"] - t.f_R) / r["rattler_fraction_err"])
    assert np.all(np.abs(pulls) < 4.5) and 0.5 < np.std(pulls) < 1.6
    for v, x in red.protocols.jamming_limits.items():
        t = TRUTHS[v]
        assert abs(x["phi_J"] - t.phi_inf) < 4 * x["phi_J_err"] and x["phi_J_err"] < 2e-3
        assert abs(x["rattler_fraction"] - t.f_R) < 4 * x["rattler_fraction_err"]
        assert x["phi_J_sizes"] == " ".join(map(str, N_SIZES))


def test_a_moved_jamming_point_is_found_and_an_unmoved_one_is_not(three):
    _, _, red = three
    prot = red.protocols.comparison
    assert prot["reference"] == "default" and [r["variant"] for r in prot["values"]][0] == "default"
    sig = {(p["variant"], p["quantity"]): p["significant"] for p in prot["pairs"]}
    # dilute: phi_J 0.004 and the rattlers 0.01 lower, A_G* 0.01 off (the store's variant shift)
    assert sig[("dilute", "phi_J")] and sig[("dilute", "rattler_fraction")] and sig[("dilute", "A_G_star_E")]
    assert not sig[("same-jamming", "phi_J")] and not sig[("same-jamming", "rattler_fraction")]
    assert sig[("same-jamming", "A_G_star_E")]  # shifted by 0.02
    assert not any(sig[(v, q)] for v in ("dilute", "same-jamming") for q in ("beta_E", "psi_O_star"))
    hom = {h["quantity"]: h for h in prot["homogeneity"]}
    assert hom["phi_J"]["significant"] and hom["A_G_star_E"]["significant"] and hom["phi_J"]["dof"] == 2
    assert not hom["beta_E"]["significant"] and not hom["psi_O_star"]["significant"]
    d = next(p for p in prot["pairs"] if p["variant"] == "dilute" and p["quantity"] == "phi_J")
    assert abs(d["difference"] + 0.004) < 4 * d["error"]
    # the synthetic packings of two variants are drawn independently: their pairs do not correlate
    assert abs(d["pair_correlation_A_G"]) < 0.15


def test_differences_are_the_rows_and_the_homogeneity_test_is_its_definition(three):
    _, _, red = three
    prot = red.protocols.comparison
    vals = {r["variant"]: r for r in prot["values"]}
    for v in ("default", "dilute"):
        for q in ("A_G_star_E", "beta_E", "psi_O_star"):
            assert vals[v][q] == red.extrapolated[v][q] and vals[v][f"{q}_err"] == red.extrapolated[v][f"{q}_err"]
    ratios = []
    for p in prot["pairs"]:
        a, r = vals[p["variant"]], vals["default"]
        q = p["quantity"]
        assert p["difference"] == a[q] - r[q]
        assert p["error_quadrature"] == pytest.approx(math.hypot(a[f"{q}_err"], r[f"{q}_err"]), rel=1e-12)
        assert p["z"] == pytest.approx(p["difference"] / p["error"], rel=1e-12)
        assert p["p"] == pytest.approx(math.erfc(abs(p["z"]) / math.sqrt(2)), rel=1e-12)
        ratios.append(p["error"] / p["error_quadrature"])
    # the synthetic variants are drawn independently: pairing them changes their errors only by the
    # bootstrap's own noise
    assert 0.75 < np.median(ratios) < 1.25 and np.all(np.array(ratios) > 0.5)
    from scipy import stats

    for h in prot["homogeneity"]:
        assert h["dof"] == h["n_variants"] - 1 == 2 and h["chi2"] >= 0
        assert h["p"] == pytest.approx(stats.chi2.sf(h["chi2"], h["dof"]), rel=1e-9, abs=1e-300)


def test_paired_errors_and_the_homogeneity_test_use_the_replicas_drawn_together():
    """Replicas drawn with the same seeds for every variant: the pair's error is the spread of the
    replicas' differences (small where two protocols move together, as the pressure route and FIRE
    do packing by packing), the quadrature error stays beside it, and the homogeneity test is the
    chi^2 of the values with the replicas' correlations."""
    from campaign.results import fits

    rng = np.random.default_rng(8)
    B = 4000
    common = rng.normal(0, 1, B)
    reps = {"ref": 0.446 + 1e-3 * common,
            "twin": 0.447 + 1e-3 * (0.95 * common + math.sqrt(1 - 0.95**2) * rng.normal(0, 1, B)),
            "other": 0.446 + 1e-3 * rng.normal(0, 1, B)}
    q = "A_G_star_E"
    ex = {v: {q: float(r.mean()), f"{q}_err": fits.spread(r)} for v, r in reps.items()}
    replicas = {(v, q): (r, 1.0) for v, r in reps.items()}
    out = P.compare(ex, {}, "ref", list(reps), replicas=replicas)
    pair = {p["variant"]: p for p in out["pairs"] if p["quantity"] == q}
    assert pair["twin"]["error"] == fits.spread(reps["twin"] - reps["ref"])
    assert pair["twin"]["error"] < 0.4 * pair["twin"]["error_quadrature"]   # sqrt(2 (1 - 0.95)) = 0.32
    assert pair["twin"]["significant"] and not pair["twin"]["z_quadrature"] > 1.96
    assert pair["other"]["error"] == pytest.approx(pair["other"]["error_quadrature"], rel=0.06)
    h = next(h for h in out["homogeneity"] if h["quantity"] == q)
    x = np.array([ex[v][q] for v in reps])
    e = np.array([ex[v][f"{q}_err"] for v in reps])
    C = np.corrcoef(np.column_stack(list(reps.values())).T) * np.outer(e, e)
    Ci = np.linalg.inv(C)
    one = np.ones(3)
    m = one @ Ci @ x / (one @ Ci @ one)
    assert h["mean"] == pytest.approx(m, rel=1e-9)
    assert h["chi2"] == pytest.approx((x - m) @ Ci @ (x - m), rel=1e-6)
    # without replicas, the errors in quadrature decide
    plain = P.compare(ex, {}, "ref", list(reps))
    assert all(p["error"] == p["error_quadrature"] for p in plain["pairs"] if p["quantity"] == q)


def _holm_reference(p, alpha):
    """Holm's step-down procedure as written: sort, reject while p_(k) <= alpha / (m - k)."""
    order = sorted(range(len(p)), key=lambda i: p[i])
    rejected = set()
    for k, i in enumerate(order):
        if p[i] <= alpha / (len(p) - k):
            rejected.add(i)
        else:
            break
    return rejected


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=40), st.sampled_from([0.01, 0.05, 0.1]))
def test_holm_rejects_what_the_step_down_procedure_rejects(p, alpha):
    adj = P.holm(p)
    assert np.all(adj >= np.asarray(p) - 1e-15) and np.all(adj <= 1.0)
    # the adjusted values rejected at alpha are the procedure's rejections (ties at alpha aside)
    if not any(abs(x * k - alpha) < 1e-12 for x in p for k in range(1, len(p) + 1)):
        assert {i for i, a in enumerate(adj) if a <= alpha} == _holm_reference(p, alpha)


def test_holm_leaves_missing_tests_out():
    adj = P.holm([0.01, np.nan, 0.04])
    assert np.isnan(adj[1]) and adj[0] == pytest.approx(0.02) and adj[2] == pytest.approx(0.04)


def test_under_the_null_the_family_wise_error_rate_is_held():
    """Five protocols equal to the reference in all seven quantities, errors known: the chance
    that any of the 35 differences is called significant is at most alpha (Holm)."""
    rng = np.random.default_rng(4)
    variants = ["default", "a", "b", "c", "d", "e"]
    reps, false = 2000, 0
    for _ in range(reps):
        ex = {v: {} for v in variants}
        jam = {v: {} for v in variants}
        for v in variants:
            for q in P.QUANTITIES:
                d = jam[v] if q in ("phi_J", "rattler_fraction") else ex[v]
                e = 10.0 ** rng.uniform(-4, -2)
                d[q], d[f"{q}_err"] = rng.normal(0.5, e), e
        out = P.compare(ex, jam, "default", variants)
        false += any(p["significant"] for p in out["pairs"])
    rate = false / reps
    assert rate <= P.ALPHA + 3 * math.sqrt(P.ALPHA * (1 - P.ALPHA) / reps)
    assert rate > 0.01  # the tests are not empty: Holm is conservative, not blind


def _experiment(rng, seeds, energies, a, b, sd_packing, sd_seed):
    """One (variant, N_G): value = a + b x(E) + a per-seed offset shared by the seed's energies
    (as along an energy ladder) + per-packing noise."""
    E = np.repeat(energies, seeds)
    seed = np.tile(np.arange(seeds), len(energies))
    offset = rng.normal(0, sd_seed, seeds)[seed]
    return E, seed, a + b * typical_overlap(E, 2.0) + offset + rng.normal(0, sd_packing, len(E))


def _size_fit(E, seed, y, n_boot, rng, ladder):
    """``protocols.size_fit`` with replica weights drawn as ``bootstrap.replica_weights`` draws them:
    a ladder's seeds whole (every energy together), independent packings per cell."""
    from campaign.results import bootstrap

    energies = np.unique(E)
    W = bootstrap.seed_weights(rng, int(seed.max()) + 1, n_boot)
    values, weights = [], []
    for e in energies:
        m = E == e
        values.append(y[m])
        w = W if ladder else bootstrap.seed_weights(rng, int(seed.max()) + 1, n_boot)
        weights.append(w[:, seed[m]] if n_boot else None)
    return P.size_fit(typical_overlap(energies, 2.0), values, weights)


@pytest.mark.parametrize("sd_seed", [0.0, 0.01])
def test_the_seed_bootstrap_error_is_the_spread_of_repeated_experiments(sd_seed):
    """Independent packings (sd_seed 0) and packings sharing a seed's history (a ladder, its seeds
    drawn whole): the bootstrap gives the spread of the intercept over repeated experiments, the
    resampled means scaled by sqrt(n / (n - 1)) (a plain bootstrap of 12 seeds runs short by
    sqrt(11 / 12))."""
    rng = np.random.default_rng(11)
    energies = 10.0 ** -np.arange(7, 16, 2.0)
    est, errs = [], []
    for k in range(300):
        E, seed, y = _experiment(rng, 12, energies, 0.84, 0.6, 0.01, sd_seed)
        f = _size_fit(E, seed, y, 200, np.random.default_rng(k), ladder=sd_seed > 0)
        est.append(f["value"])
        errs.append(f["err"])
    spread = np.std(est, ddof=1)
    assert abs(np.mean(est) - 0.84) < 4 * spread / math.sqrt(len(est))
    assert 0.88 < np.median(errs) / spread < 1.12
    if sd_seed:  # what a per-cell error would give is far too small: the seeds carry the error
        assert spread > 2.5 * 0.01 / math.sqrt(12 * len(energies))


def test_an_exact_line_is_recovered_and_few_cells_say_why():
    energies = np.array([1e-7, 1e-9, 1e-11, 1e-13])
    E = np.repeat(energies, 3)
    seed = np.tile(np.arange(3), 4)
    f = _size_fit(E, seed, 0.8412 + 0.3 * typical_overlap(E, 2.0), 50, np.random.default_rng(0), ladder=False)
    assert f["value"] == pytest.approx(0.8412, abs=1e-12) and f["slope"] == pytest.approx(0.3, rel=1e-9)
    assert f["err"] == pytest.approx(0.0, abs=1e-12) and f["n_cells"] == 4 and f["dof"] == 2
    short = _size_fit(E[:6], seed[:6], np.ones(6), 50, np.random.default_rng(0), ladder=False)
    assert math.isnan(short["value"]) and "2 cell(s)" in short["note"]


def test_reduce_writes_the_jamming_point_and_the_comparison(three, tmp_path, capsys):
    path, _, _ = three
    assert cli.main(["reduce", str(path), "--out", str(tmp_path / "red"), "--boot", "30"]) == 0
    md = (tmp_path / "red" / "protocols.md").read_text()
    assert "| dilute | inf |" in md and "Holm" in md and "| phi_J |" in md
    assert (tmp_path / "red" / "protocols.csv").read_text().startswith("variant,reference,quantity,difference")
    assert "phi_J" in (tmp_path / "red" / "jamming.csv").read_text().splitlines()[0]
    with h5py.File(tmp_path / "red" / "reduced.h5") as f:
        assert f["reduced/protocols"].attrs["reference"] == "default"
        assert len(f["reduced/protocols/pairs/quantity"]) == 2 * len(P.QUANTITIES)
        assert len(f["reduced/jamming/phi_J"]) == 3 * len(N_SIZES)


def test_one_variant_has_its_jamming_point_and_no_comparison(tmp_path):
    camp = SyntheticCampaign(N=(64, 128), seeds=6, histograms=("z_g",))
    write_store(tmp_path / "one.h5", camp)
    red = R.reduce_campaign(tmp_path / "one.h5", R.Settings(n_boot=50), distributions=False)
    assert red.protocols.comparison["pairs"] == [] and red.protocols.comparison["homogeneity"] == []
    x = red.protocols.jamming_limits["default"]
    assert abs(x["phi_J"] - 0.84) < 1e-3 and math.isfinite(x["rattler_fraction_err"])
    from campaign.report.writing import write_outputs

    written = [p.name for p in write_outputs(red, tmp_path / "o", write_h5=False)]
    assert "protocols.md" in written and "protocols.csv" not in written


def test_the_protocols_figure(three, tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    from campaign.report import plots

    _, _, red = three
    monkeypatch.setattr(plots, "FIGURES", {})
    written = [p.name for p in plots.make_figures(red, tmp_path / "fig")]
    assert "protocols.png" in written and (tmp_path / "fig" / "protocols.png").stat().st_size > 10_000


LADDER_SPEC = """\
name: ladder-errors
seed: 3
system:
  box: [1.0, 1.0]
  species: [{name: A, fraction: 0.5, radius: 1.4}, {name: B, fraction: 0.5, radius: 1.0}]
  potential: {exponent: 2.0}
grid:
  N_G: [64, 128, 256]
  E_G: [1.0e-15, 1.0e-13, 1.0e-11, 1.0e-9, 1.0e-7]
  seeds: 12
protocol: {window: 0.1, force_tolerance: 1.0e-6}
variants:
  - {name: ladder, start: ladder}
"""


def _chained(rng, sd_seed=0.003, sd_packing=0.001):
    """The same packings under two names, 'default' and 'ladder', on the synthetic laws, with a
    per-seed offset of A_G at every energy (as along a ladder: one seed's packings share a history)."""
    from campaign.results.finished import finished_from_arrays

    Ns, Es, S = np.array([64, 128, 256]), np.array([1e-15, 1e-13, 1e-11, 1e-9, 1e-7]), 12
    N, E, seed = (a.ravel() for a in np.meshgrid(Ns, Es, np.arange(S), indexing="ij"))
    N = N.astype(float)
    off = np.broadcast_to(rng.normal(0, 1, (3, 1, S)), (3, 5, S)).ravel() * sd_seed / np.sqrt(N / 64)
    A = 0.45 - 0.5 / N + 2.0 * E ** 0.28 + off + rng.normal(0, sd_packing, len(N))
    scal = {"E_G": E, "A_G": A, "delta_Z": 3.0 * E ** 0.25 * (1 + 0.05 * rng.normal(0, 1, len(N))),
            "psi_O": 0.37 + 0.6 * E ** 0.27 + rng.normal(0, 0.005, len(N)), "phi": 0.84 + np.sqrt(E),
            "N": N, "N_G": N, "N_R": np.zeros(len(N))}
    two = {k: np.concatenate([x, x]) for k, x in scal.items()}
    n = 2 * len(N)
    return finished_from_arrays(attrs={"spec_yaml": LADDER_SPEC, "schema": "jamming-campaign/1"},
                                variant=np.array(["default"] * len(N) + ["ladder"] * len(N), object),
                                N=np.concatenate([N, N]).astype(int), E=np.concatenate([E, E]), ids=np.arange(n),
                                seed=np.concatenate([seed, seed]), status=np.ones(n, int), scalars=two)


@pytest.mark.slow
def test_a_ladders_table_errors_come_from_whole_seeds():
    """A_G* of packings sharing a seed's history: the ladder variant's bootstrap over whole seeds
    gives the spread of repeated campaigns; resampling packings within cells (what the reducer
    does for independent packings: the 'default' variant, given the same packings) gives errors
    too small, about sqrt(sum of the squared weights of the cells in the intercept) ~ 0.7 here."""
    rng = np.random.default_rng(5)
    s = R.Settings(n_boot=100)
    est, err = [], {"default": [], "ladder": []}
    for _ in range(60):
        t = R.reduce_table(_chained(rng), s, per_size=False)
        est.append(t.extrapolated["ladder"]["A_G_star_E"])
        for v in err:
            err[v].append(t.extrapolated[v]["A_G_star_E_err"])
    spread = np.std(est, ddof=1)
    assert 0.8 < np.median(err["ladder"]) / spread < 1.25
    assert np.median(np.array(err["ladder"]) / np.array(err["default"])) > 1.15


def test_the_seed_bootstrap_moves_a_seeds_packings_together():
    """Cells whose packings are one per-seed value (a ladder's extreme), their seeds drawn whole:
    the replicas of every cell are the same. Cells drawn apart: their replicas do not correlate,
    each with the variance of a mean."""
    from campaign.results import bootstrap

    rng = np.random.default_rng(2)
    seeds = [np.arange(10), np.arange(10), np.arange(10)[::-1]]
    per_seed = rng.normal(0, 1, 10)
    W = bootstrap.seed_weights(bootstrap.generator(1), 10, 400)
    b = np.stack([bootstrap.cell_moments(np.column_stack([per_seed[sd], 2 * per_seed[sd]]), W[:, sd])[0]
                  for sd in seeds], 1)
    assert b.shape == (401, 3, 2)
    assert np.allclose(b[:, 0], b[:, 1]) and np.allclose(b[:, 0], b[:, 2]) and np.allclose(b[:, 0, 1], 2 * b[:, 0, 0])
    gen = bootstrap.generator(2)
    indep = [rng.normal(0, 1, (10, 1)) for _ in seeds]
    b = np.stack([bootstrap.cell_moments(g, bootstrap.seed_weights(gen, 10, 4000))[0][1:, 0] for g in indep], 1)
    assert abs(np.corrcoef(b[:, 0], b[:, 1])[0, 1]) < 0.06
    for k, g in enumerate(indep):
        assert np.var(b[:, k]) == pytest.approx(np.var(g, ddof=1) / 10, rel=0.1)


@pytest.mark.slow
def test_the_shipped_stores_reduce_to_the_documented_table():
    """docs/PROTOCOLS.md's N_G -> inf table is what `campaign reduce data/protocols.h5
    data/protocols-more.h5` gives (the default settings), entry for entry as printed."""
    from pathlib import Path

    from campaign.results.tables import fmt_err

    root = Path(__file__).resolve().parents[2]
    red = R.reduce_campaign([root / "data" / "protocols.h5", root / "data" / "protocols-more.h5"],
                            R.Settings(), distributions=False)
    text = (root / "docs" / "PROTOCOLS.md").read_text()
    table = text[text.index("## The table"):text.index("Does each quantity depend")]
    lines = {ln.split("|")[1].strip().split(" ")[0]: [c.strip() for c in ln.split("|")[2:-1]]
             for ln in table.splitlines() if ln.startswith("| ") and "variant" not in ln}
    assert set(lines) == {r["variant"] for r in red.protocols.comparison["values"]}
    for r in red.protocols.comparison["values"]:
        assert lines[r["variant"]] == [fmt_err(r[q], r[f"{q}_err"]) for q in P.QUANTITIES], r["variant"]
    assert red.meta["done"] == 9360 and red.meta["excluded"] == 0
