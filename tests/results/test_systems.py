"""Reduction across physical systems (variants overriding ``system``): campaign.results.systems."""

import csv
import os
import subprocess
import sys
from pathlib import Path

import h5py
import matplotlib  # noqa: F401 - the test extra installs it
import numpy as np
import pytest
from synthetic_store import SyntheticCampaign, Truth, write_store

from campaign.report import plots
from campaign.results import systems
from campaign.results import reduce as R
from campaign.results.finished import variant_systems
from campaign.results.tables import fmt_err
from campaign.report.writing import write_outputs

ROOT = Path(__file__).resolve().parents[2]
PNG = b"\x89PNG\r\n\x1a\n"

# three systems obeying beta_E = beta_Z / (2 alpha): alpha 2 and 2.5 share beta_Z = 1, alpha 3
# has beta_Z = 1.4; "broken" (alpha 3, another size distribution) has delta_Z ~ E_G^(1/4),
# as if alpha were 2, so its beta_E is not beta_Z / (2 alpha)
TRUTHS = {"default": Truth.jamming(2.0, 1.0), "hertz": Truth.jamming(2.5, 1.0),
          "alpha3": Truth.jamming(3.0, 1.4), "broken": Truth(alpha=3.0, z_exponent=0.25, beta_A=0.25)}
BROKEN_SIZES = {"sizes": {"distribution": "lognormal", "polydispersity": 0.1}}


@pytest.fixture(scope="module")
def multi(tmp_path_factory):
    path = tmp_path_factory.mktemp("systems") / "s.h5"
    camp = SyntheticCampaign(N=(64, 128, 256), seeds=12, variants=tuple(TRUTHS), truth=TRUTHS["default"],
                             variant_truth=TRUTHS, variant_system={"broken": BROKEN_SIZES},
                             histograms=("z_g",))
    write_store(path, camp)
    # the synthetic laws have no corrections to scaling: every energy (--fit-all) is their range
    return path, R.reduce_campaign(path, R.Settings(n_boot=200, fit_overlap=np.inf), distributions=False)


def test_synthetic_truths_obey_or_break_the_scaling_relation():
    # the premise of the other tests, from the synthetic laws alone
    for v in ("default", "hertz", "alpha3"):
        t = TRUTHS[v]
        assert t.beta_A == pytest.approx(t.beta_Z / (2 * t.alpha))
    b = TRUTHS["broken"]
    assert b.beta_Z == pytest.approx(1.0) and b.beta_A - b.beta_Z / (2 * b.alpha) > 0.08


def test_reducer_recovers_each_systems_exponents(multi):
    path, red = multi
    recs = {r["variant"]: r for r in red.systems}
    assert sorted(recs) == sorted(TRUTHS)
    for v, t in TRUTHS.items():
        r = recs[v]
        assert r["alpha"] == t.alpha
        for suffix in ("", "_largest"):
            for key, truth in (("beta_E", t.beta_A), ("beta_Z", t.beta_Z)):
                value, err = r[f"{key}{suffix}"], r[f"{key}{suffix}_err"]
                assert 0 < err < 0.1 * truth, (v, key, suffix, err)
                assert abs(value - truth) < 3.5 * err, (v, key, suffix, value, truth, err)
            pred = r[f"beta_Z{suffix}"] / (2 * t.alpha)
            assert r[f"beta_Z_over_2alpha{suffix}"] == pytest.approx(pred, rel=1e-12)
        assert r["N_G_largest"] == 256
        assert r["sizes"] == ("lognormal 10%" if v == "broken" else "bidisperse 1.4:1")


def test_scaling_tension_separates_the_broken_system(multi):
    path, red = multi
    recs = {r["variant"]: r for r in red.systems}
    for v in ("default", "hertz", "alpha3"):
        assert abs(recs[v]["scaling_tension"]) < 3, v
        assert abs(recs[v]["scaling_tension_largest"]) < 3, v
    assert recs["broken"]["scaling_tension"] > 5
    assert recs["broken"]["scaling_tension_largest"] > 5
    # the tension by hand from the record's own numbers
    r = recs["hertz"]
    t = (r["beta_E"] - r["beta_Z"] / 5.0) / np.hypot(r["beta_E_err"], r["beta_Z_err"] / 5.0)
    assert r["scaling_tension"] == pytest.approx(t, rel=1e-12)


def test_beta_Z_against_the_default_system(multi):
    path, red = multi
    recs = {r["variant"]: r for r in red.systems}
    assert all(r["reference"] == "default" for r in red.systems)
    assert recs["default"]["beta_Z_diff"] == 0
    for v in ("hertz", "broken"):  # beta_Z = 1 as in the default system
        assert abs(recs[v]["beta_Z_diff_tension"]) < 3, v
    a3 = recs["alpha3"]
    assert abs(a3["beta_Z_diff"] - 0.4) < 3.5 * a3["beta_Z_diff_err"]
    assert a3["beta_Z_diff_tension"] > 3
    assert a3["beta_Z_diff_err"] == pytest.approx(np.hypot(a3["beta_Z_err"], recs["default"]["beta_Z_err"]))


def test_markdown_table(multi):
    path, red = multi
    text = systems.table_markdown(red.systems)
    head, lines = text.strip().split("\n\n")[0], text.strip().split("\n\n")[1].splitlines()
    assert head == "Fits: every energy."  # the fit rule the exponents come from
    assert lines[0].startswith("| system | N_G | alpha | sizes | A_G* | beta_E | beta_Z | beta_Z/(2 alpha)")
    assert len(lines) == 2 + 2 * len(TRUTHS)
    hertz = [ln for ln in lines if ln.startswith("| hertz | inf |")]
    assert len(hertz) == 1 and "| 2.5 | bidisperse 1.4:1 |" in hertz[0]
    r = next(r for r in red.systems if r["variant"] == "hertz")
    assert fmt_err(r["beta_E"], r["beta_E_err"]) in hertz[0]
    assert systems.table_markdown([]) == ""


SPEC = """
name: s
seed: 1
grid: {N_G: [16], E_G: [1.0e-3], seeds: 1}
system:
  box: [1.0, 1.0]
  species: [{name: A, fraction: 0.5, radius: 1.4}, {name: B, fraction: 0.5, radius: 1.0}]
  potential: {exponent: 2.0}
variants:
  - name: hertz
    system: {potential: {exponent: 2.5}}
  - name: alpha3
    system: {potential: {exponent: 3.0}}
  - name: poly20
    system: {sizes: {distribution: lognormal, polydispersity: 0.2}}
  - name: loose
    force_tolerance: 1.0e-4
  - name: wide
    system: {box: [2.0, 1.0], potential: {exponent: 2.5}}
"""


def test_variant_systems_merges_overrides():
    s = variant_systems({"spec_yaml": SPEC})
    assert set(s) == {"default", "hertz", "alpha3", "poly20", "loose", "wide"}
    assert s["default"]["exponent"] == 2.0 and s["default"]["sizes"] == "bidisperse 1.4:1"
    assert s["hertz"]["exponent"] == 2.5 and s["hertz"]["sizes"] == "bidisperse 1.4:1"
    assert s["alpha3"]["exponent"] == 3.0
    assert s["poly20"] == {"exponent": 2.0, "sizes": "lognormal 20%", "box": (1.0, 1.0), "radii": ()}
    assert s["hertz"]["radii"] == (1.4, 1.0)
    assert s["loose"] == s["default"]  # protocol-only: the base system
    assert s["wide"]["box"] == (2.0, 1.0) and s["wide"]["exponent"] == 2.5
    # data variants the spec does not list have the base system
    assert variant_systems({"spec_yaml": SPEC}, variants=["extra"])["extra"] == s["default"]


def test_variant_systems_species_and_sizes_replace_each_other():
    spec = """
name: s
seed: 1
grid: {N_G: [16], E_G: [1.0e-3], seeds: 1}
system:
  sizes: {distribution: uniform, polydispersity: 0.1}
  potential: {exponent: 2.5}
variants:
  - name: mix
    system: {species: [{name: A, fraction: 0.3, radius: 2.0}, {name: B, fraction: 0.7, radius: 1.0}]}
  - name: mono
    system: {species: [{name: A, fraction: 1.0, radius: 1.0}]}
  - name: wider
    system: {sizes: {polydispersity: 0.25}}
"""
    s = variant_systems({"spec_yaml": spec})
    assert s["default"]["sizes"] == "uniform 10%" and s["default"]["exponent"] == 2.5
    assert s["mix"]["sizes"] == "bidisperse 2:1, 30:70" and s["mix"]["exponent"] == 2.5
    assert s["mono"]["sizes"] == "monodisperse"
    assert s["wider"]["sizes"] == "uniform 25%"


@pytest.mark.parametrize("attrs", [{}, {"spec_yaml": ""}, {"spec_yaml": "[1, 2"},
                                   {"spec_yaml": "just a string"}, {"spec_yaml": "system: 3"}])
def test_variant_systems_falls_back_on_foreign_specs(attrs):
    s = variant_systems(attrs, variants=["default", "hertz"])
    assert set(s) == {"default", "hertz"}
    for d in s.values():
        assert d["exponent"] == 2.0 and d["sizes"] == "bidisperse 1.4:1"


def _row(v, N, bE, bZ):
    return {"variant": v, "N_G": N, "A_G_star_E": 0.44, "A_G_star_E_err": 1e-3, "beta_E": bE,
            "beta_E_err": 0.01, "beta_Z": bZ, "beta_Z_err": 0.02, "psi_O_star": 0.37,
            "psi_O_star_err": 1e-3}


def test_compare_is_empty_with_one_system():
    rows = [_row("default", 64, 0.25, 1.0), _row("loose", 64, 0.26, 1.05)]
    ex = {v: {k: r[k] for k in r if k not in ("variant", "N_G")} for v, r in
          (("default", rows[0]), ("loose", rows[1]))}
    one = {"default": {"exponent": 2.0, "sizes": "bidisperse 1.4:1", "box": (1.0, 1.0)}}
    assert systems.compare(rows, ex, one) == []
    assert systems.compare(rows, ex, {**one, "loose": dict(one["default"])}) == []
    assert systems.compare(rows[:1], {"default": ex["default"]}, one) == []
    # another exponent makes two systems; hand-computed numbers
    two = {**one, "loose": {"exponent": 2.5, "sizes": "bidisperse 1.4:1", "box": (1.0, 1.0)}}
    recs = {r["variant"]: r for r in systems.compare(rows, ex, two)}
    assert recs["loose"]["beta_Z_over_2alpha"] == pytest.approx(1.05 / 5)
    assert recs["loose"]["scaling_tension"] == pytest.approx((0.26 - 0.21) / np.hypot(0.01, 0.004))
    assert recs["loose"]["beta_Z_diff"] == pytest.approx(0.05)
    assert recs["loose"]["beta_Z_diff_tension"] == pytest.approx(0.05 / np.hypot(0.02, 0.02))
    # a missing error gives no tension
    ex["loose"]["beta_E_err"] = float("nan")
    assert np.isnan({r["variant"]: r for r in systems.compare(rows, ex, two)}["loose"]["scaling_tension"])


def _pngs(paths):
    for p in paths:
        data = p.read_bytes()
        assert data[:8] == PNG and len(data) > 5000, p


def test_figures_for_several_systems_only(multi, tmp_path, monkeypatch):
    path, red = multi
    # one cheap per-variant figure keeps the test short; the system figures are the point
    monkeypatch.setattr(plots, "FIGURES", {"extrapolation": plots.fig_extrapolation})
    written = plots.make_figures(red, tmp_path / "multi")
    names = {p.name for p in written}
    assert {"universality.png", "exponents_vs_alpha.png"} <= names
    _pngs([p for p in written if p.name in ("universality.png", "exponents_vs_alpha.png")])
    # the same variants, one system (the spec lists no variants): no system figures
    camp = SyntheticCampaign(N=(64, 128), E=(1e-3, 1e-6, 1e-9, 1e-12), seeds=4,
                             variants=("default", "loose"), histograms=("z_g",))
    write_store(tmp_path / "one.h5", camp)
    red1 = R.reduce_campaign(tmp_path / "one.h5", R.Settings(n_boot=0), distributions=False)
    assert red1.systems == []
    names1 = {p.name for p in plots.make_figures(red1, tmp_path / "one")}
    assert not names1 & {"universality.png", "exponents_vs_alpha.png"}
    assert "extrapolation_loose.png" in names1


def test_outputs_and_reduced_group(multi, tmp_path):
    path, red = multi
    write_outputs(red, tmp_path / "out")
    with open(tmp_path / "out" / "systems.csv") as f:
        rows = list(csv.DictReader(f))
    assert sorted(r["variant"] for r in rows) == sorted(TRUTHS)
    assert "| alpha3 | inf |" in (tmp_path / "out" / "systems.md").read_text()
    with h5py.File(tmp_path / "out" / "reduced.h5", "r") as f:
        g = f["reduced/systems"]
        assert sorted(x.decode() for x in g["variant"][...]) == sorted(TRUTHS)
        assert g["scaling_tension"].shape == (len(TRUTHS),)
    assert {r["variant"] for r in red.to_json()["systems"]} == set(TRUTHS)


def test_cli_reduce_prints_the_systems_table(multi, tmp_path):
    path, red = multi
    out = tmp_path / "cli"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-m", "campaign", "reduce", str(path), "--boot", "20",
                        "-o", str(out)], capture_output=True, text=True, env=env, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "Systems (beta_E against the prediction" in p.stdout
    assert "| broken | inf | 3 | lognormal 10% |" in p.stdout
    # after the finite-size table
    assert p.stdout.index("A_G*(E_G=0)") < p.stdout.index("| system | N_G | alpha |")
    with open(out / "systems.csv") as f:
        assert sorted(r["variant"] for r in csv.DictReader(f)) == sorted(TRUTHS)


def test_speed_accuracy_compares_only_packings_of_the_reference_system(multi):
    """Pairing (N, E, seed) across physical systems means nothing: those variants are left out
    of campaign.results.tradeoff and named in the notes."""
    _, red = multi
    assert red.tradeoff == []  # every other variant is another system
    assert any("other systems than 'default'" in n for n in red.notes)


@pytest.mark.parametrize("dmax", [1e-2, 3e-3])
def test_fit_overlap_picks_the_same_distance_from_jamming_per_system(multi, dmax):
    """--fit-overlap keeps, per variant, the cells whose (alpha E / 2)^(1/alpha) <= dmax."""
    path, _ = multi
    red = R.reduce_campaign(path, R.Settings(n_boot=0, fit_overlap=dmax),
                            distributions=False)
    grid = np.asarray(SyntheticCampaign().E)
    for row in red.rows:
        alpha = TRUTHS[row["variant"]].alpha
        # E_G <= (2 / alpha) dmax^alpha, counted here from the grid, not by the reducer's helper
        assert row["n_cells"] == int(np.sum(grid <= 2.0 / alpha * dmax ** alpha * (1 + 1e-9))), row
    kept = {r["variant"]: r["n_cells"] for r in red.rows if r["N_G"] == 64}
    assert kept["alpha3"] <= kept["hertz"] <= kept["default"] and kept["alpha3"] < kept["default"]
    assert any("typical overlap <= " in n for n in red.notes)


def test_fit_overlap_with_too_few_energies_is_refused(multi, capsys):
    """At overlaps <= 1e-3 the alpha = 3 systems keep 3 energies of the grid (E_G <= 6.7e-10:
    1e-11, 1e-13, 1e-15), too few for a power law with an intercept: refused, naming the system."""
    from campaign import cli
    from campaign.errors import UserError

    path, _ = multi
    grid = np.asarray(SyntheticCampaign().E)
    assert int(np.sum(grid <= 2.0 / 3.0 * 1e-9)) == 3
    with pytest.raises(UserError, match=r"alpha3 N=64: .* holds 3 energies"):
        R.reduce_campaign(path, R.Settings(n_boot=0, fit_overlap=1e-3, strict_range=True), distributions=False)
    assert cli.main(["reduce", str(path), "--fit-overlap", "1e-3", "--boot", "0"]) == 2
    err = capsys.readouterr().err
    assert "holds 3 energies of the grid, fewer than the 4" in err and "Traceback" not in err


def test_fit_overlap_is_checked(multi, capsys):
    from campaign import cli

    path, _ = multi
    assert cli.main(["reduce", str(path), "--fit-overlap", "0"]) == 2
    assert "--fit-overlap expects a relative overlap > 0" in capsys.readouterr().err
    # campaign plot takes the same fit-range options
    assert cli.main(["plot", str(path), "--fit-overlap", "-1"]) == 2
    assert "--fit-overlap expects a relative overlap > 0" in capsys.readouterr().err
