"""The fit range of the scaling laws (docs/REDUCED.md, "The fit range"): the default rule, the
fixed ranges, the refusals, every output naming the range or rule it used, and the one test of
which cells a range holds."""

import csv
import io
import json
import math

import h5py
import numpy as np
import pytest
from helpers import fit_cells
from synthetic_store import SyntheticCampaign, Truth, write_store

from campaign import cli

from campaign.results import fits
from campaign.results import reduce as R
from campaign.plan.targets import in_fit_range
from campaign.results.scaling import DEFAULT_FIT_OVERLAP, typical_overlap
from campaign.errors import UserError

E13 = tuple(10.0 ** -np.arange(3, 16))       # paper-small's grid: 1e-3 .. 1e-15, one per decade


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    path = tmp_path_factory.mktemp("range") / "s.h5"
    write_store(path, SyntheticCampaign(N=(64, 128), seeds=6, histograms=("z_g",)))
    return path


# --------------------------------------------------------------------------- the default range
# The synthetic law of experiments/fit_rules.py's scenario "like paper-small", written in E_G:
# Delta A_G = c E^beta (1 + k E^omega) with omega = 1/4 (a correction proportional to Delta Z);
# per-packing spread 0.10 / sqrt(N_G), 20 packings per cell, as on paper-small.
BETA, C, K, OMEGA = 0.2625, 0.22 * 5.0**1.05, -0.2 * 5.0, 0.25


def _cells(rng, N, k, n=20):
    """Per-packing (E_G, A_G) of paper-small's grid at size N: groups (n, 2), lowest E first."""
    groups = []
    for e in E13[::-1]:
        x = e * (1 + 0.1 * rng.random(n))
        y = 0.446 + C * x**BETA * (1 + k * x**OMEGA) + rng.normal(0, 0.10 / np.sqrt(N), n)
        groups.append(np.column_stack([x, y]))
    return groups


def _fit(groups, keep, seed):
    return fit_cells([x for x, k in zip(groups, keep) if k], 100, seed)


@pytest.mark.parametrize("k", [0.0, K], ids=["no correction", "correction like paper-small"])
def test_the_default_range_recovers_a_known_exponent_within_its_errors(k):
    """Over 100 synthetic realisations at N_G = 256 the default range (typical overlap <= 0.001,
    E_G <= 1e-6 at alpha = 2) covers the true beta_E with its bootstrap error about as often as
    stated, with or without a correction to scaling; the fit over every energy does not once the
    correction is there (the test can fail)."""
    rng = np.random.default_rng(23)
    E = np.asarray(E13[::-1])
    window = typical_overlap(E, 2.0) <= DEFAULT_FIT_OVERLAP * (1 + 1e-9)
    assert window.sum() == 10 and E[window].max() == pytest.approx(1e-6)
    M = 100
    z_win, z_all, err_win = [], [], []
    for m in range(M):
        groups = _cells(rng, 256, k)
        f = _fit(groups, window, m)
        z_win.append((f.exponent - BETA) / f.exponent_err)
        err_win.append(f.exponent_err)
        f = _fit(groups, np.ones(E.size, bool), m)
        z_all.append((f.exponent - BETA) / f.exponent_err)
    z_win, z_all = np.array(z_win), np.array(z_all)
    assert 0.5 <= np.mean(np.abs(z_win) < 1) <= 0.85      # nominal 0.68
    assert np.mean(np.abs(z_win) < 2) >= 0.85              # nominal 0.95
    assert abs(np.mean(z_win)) < 0.5                       # bias below half an error
    assert 0.02 < np.median(err_win) < 0.05                # the price: errors of a few hundredths
    if k:
        assert np.mean(np.abs(z_all) < 2) < 0.1 and np.mean(z_all) < -5
    else:
        assert np.mean(np.abs(z_all) < 2) >= 0.85


def test_default_range_in_the_reducer_recovers_a_corrected_law(tmp_path):
    """A synthetic store with the correction above (paper-small's grid and noise): the reducer's
    default recovers beta_E and A_G* within their errors at every size and extrapolated; the fit
    over every energy misses beta_E by many errors."""
    truth = Truth(beta_A=BETA, c_A=C, k_A=K, omega_A=OMEGA, sigma_A=0.10)
    camp = SyntheticCampaign(N=(128, 256, 512), E=E13, seeds=20, truth=truth, histograms=("z_g",))
    path = tmp_path / "c.h5"
    write_store(path, camp)
    red = R.reduce_campaign(path, R.Settings(n_boot=300), distributions=False)
    for r in red.rows:
        assert r["fit_E_min"] == pytest.approx(1e-15) and r["fit_E_max"] == pytest.approx(1e-6)
        assert r["n_cells"] == 10
        assert abs(r["beta_E"] - BETA) < 3 * r["beta_E_err"], r
        assert abs(r["A_G_star_E"] - truth.A_star(r["N_G"])) < 3 * r["A_G_star_E_err"], r
    x = red.extrapolated["default"]
    assert abs(x["beta_E"] - BETA) < 3 * x["beta_E_err"]
    every = R.reduce_campaign(path, R.Settings(n_boot=300, fit_overlap=np.inf), distributions=False)
    for r in every.rows:
        assert r["fit_E_max"] == pytest.approx(1e-3)
        assert BETA - r["beta_E"] > 4 * r["beta_E_err"], r


def test_one_distance_from_jamming_for_every_potential():
    """The default keeps E_G <= (2 / alpha) 0.001^alpha: 1e-6, 2.5e-8, 6.7e-10 for alpha = 2, 2.5, 3."""
    assert DEFAULT_FIT_OVERLAP == 0.001
    for alpha, e_max in ((2.0, 1e-6), (2.5, 0.8 * 10**-7.5), (3.0, 2.0 / 3.0 * 1e-9)):
        assert typical_overlap(e_max, alpha) == pytest.approx(0.001, rel=1e-12)
        assert typical_overlap(e_max * 1.01, alpha) > DEFAULT_FIT_OVERLAP


def test_the_default_on_several_systems_is_one_distance_from_jamming(tmp_path):
    """A campaign of three potentials on one grid (1e-3 .. 1e-21): the default keeps, per system,
    E_G <= 1e-6, 2.5e-8, 6.7e-10 (grid energies 1e-6, 1e-8, 1e-10), the same typical overlap."""
    truths = {"default": Truth.jamming(2.0, 1.0), "hertz": Truth.jamming(2.5, 1.0),
              "alpha3": Truth.jamming(3.0, 1.0)}
    camp = SyntheticCampaign(N=(64, 128), E=tuple(10.0 ** -np.arange(3, 22)), seeds=4,
                             variants=tuple(truths), truth=truths["default"], variant_truth=truths,
                             histograms=("z_g",))
    write_store(tmp_path / "m.h5", camp)
    red = R.reduce_campaign(tmp_path / "m.h5", R.Settings(n_boot=0), distributions=False)
    expect = {"default": (1e-6, 16), "hertz": (1e-8, 14), "alpha3": (1e-10, 12)}  # cells from 1e-21
    for r in red.rows:
        e_max, n = expect[r["variant"]]
        assert r["fit_E_max"] == pytest.approx(e_max) and r["n_cells"] == n, r
        alpha = truths[r["variant"]].alpha
        assert typical_overlap(r["fit_E_max"], alpha) <= 0.001 * (1 + 1e-9)
        assert typical_overlap(10 * r["fit_E_max"], alpha) > 0.001
    assert len(red.systems) == 3 and all(x["fit_rule"] == "typical overlap <= 0.001 (default)" for x in red.systems)


def test_a_grid_too_short_for_the_default_range_gives_no_fit_and_says_why(tmp_path):
    camp = SyntheticCampaign(N=(64,), E=(1e-3, 1e-5, 1e-7, 1e-9), seeds=4, histograms=("z_g",))
    write_store(tmp_path / "c.h5", camp)
    red = R.reduce_campaign(tmp_path / "c.h5", R.Settings(n_boot=0), distributions=False)
    assert np.isnan(red.rows[0]["beta_E"])
    assert any("holds 2 energies of the grid, fewer than the 4" in n and "--fit-all" in n for n in red.notes)
    # asked for explicitly, the same range is refused
    with pytest.raises(UserError, match="holds 2 energies"):
        R.reduce_campaign(tmp_path / "c.h5", R.Settings(n_boot=0, strict_range=True), distributions=False)
    # every energy is enough
    every = R.reduce_campaign(tmp_path / "c.h5", R.Settings(n_boot=0, fit_overlap=np.inf), distributions=False)
    assert np.isfinite(every.rows[0]["beta_E"]) and every.rows[0]["n_cells"] == 4


# --------------------------------------------------------------------------- the command line
def test_fit_all_is_the_fit_over_every_energy(small, tmp_path, capsys):
    assert cli.main(["reduce", str(small), "--fit-all", "--boot", "0", "--out", str(tmp_path / "o"), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    red = R.reduce_campaign(small, R.Settings(n_boot=0), distributions=False)
    c = red.cells
    every = R.reduce_campaign(small, R.Settings(n_boot=0, fit_overlap=np.inf), distributions=False)
    for row in obj["rows"]:
        m = c["N"] == row["N_G"]
        x, y, ye, *_ = every.fit_inputs[("default", "A_G", "E_G")][row["N_G"]]
        np.testing.assert_array_equal(x, c["mean_E_G"][m])  # every cell of the size, in order
        np.testing.assert_array_equal(y, c["mean_A_G"][m])
        f = fits.fit_power_law(x, y, ye)
        assert row["beta_E"] == pytest.approx(f.exponent, rel=1e-9)
        assert row["n_cells"] == m.sum() and row["fit_E_max"] == pytest.approx(1e-3)
    assert obj["fit_rule"]["name"] == "every energy" and obj["fit_rule"]["default"] is False


@pytest.mark.parametrize("args, message", [
    (["--fit-all", "--fit-energies", "0", "1e-5"], "--fit-all fits every energy"),
    (["--fit-all", "--fit-overlap", "0.01"], "--fit-all fits every energy"),
    (["--fit-energies", "0", "1e-10"], "holds 3 energies of the grid, fewer than the 4"),
    (["--fit-overlap", "1e-5"], "holds 3 energies of the grid, fewer than the 4"),
])
def test_ranges_with_too_few_energies_are_refused(small, tmp_path, capsys, args, message):
    # the synthetic grid: 1e-3, 1e-5, ..., 1e-15; overlap 1e-5 at alpha = 2 is E_G <= 1e-10
    assert cli.main(["reduce", str(small), "--boot", "0", "--out", str(tmp_path / "o"), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert cli.main(["plot", str(small), "--boot", "0", "--out", str(tmp_path / "f"), *args]) == 2


@pytest.mark.parametrize("args, name, first, hi", [
    ([], "typical overlap <= 0.001 (default)", "Fits over the cells of typical overlap (alpha E_G / 2)^(1/alpha) "
     "<= 0.001 (the default range", "1e-7"),
    (["--fit-all"], "every energy", "Fits over every energy.", "1e-3"),
    (["--fit-energies", "0", "1e-5"], "E_G in [0, 1e-05]", "Fits over the cells with E_G in [0, 1e-05].", "1e-5"),
    (["--fit-overlap", "0.01"], "typical overlap <= 0.01", "Fits over the cells with typical overlap <= 0.01.",
     "1e-5"),
])
def test_every_table_names_its_range_or_rule(small, tmp_path, capsys, args, name, first, hi):
    """The synthetic grid is 1e-3, 1e-5, ..., 1e-15; at alpha = 2 an overlap of 0.001 is
    E_G <= 1e-6 and 0.01 is E_G <= 1e-4."""
    out = tmp_path / "o"
    assert cli.main(["reduce", str(small), "--boot", "0", "--out", str(out), *args]) == 0
    terminal = capsys.readouterr().out
    assert first in terminal and terminal.index(first) < terminal.index("| N_G |")
    md = (out / "table.md").read_text()
    assert md.startswith(first) and "| E_G fitted |" in md
    assert md.count(f"| 1e-15..{hi} |") == 2  # one per N_G
    rows = list(csv.DictReader(io.StringIO((out / "table.csv").read_text())))
    assert len(rows) == 3 and all(r["fit_rule"] == name for r in rows)
    assert [float(r["fit_E_max"]) for r in rows[:2]] == pytest.approx([float(hi)] * 2)
    tex = (out / "table.tex").read_text()
    assert "fits: " in tex and r"$E_G$ fitted" in tex and f"1e-15..{hi}" in tex
    obj = json.loads((out / "summary.json").read_text())
    assert obj["fit_rule"]["name"] == name and obj["fit_rule"]["text"].startswith(first.rstrip("."))
    assert all(r["fit_E_max"] == pytest.approx(float(hi)) for r in obj["rows"])
    with h5py.File(out / "reduced.h5", "r") as f:
        g = f["reduced"]
        assert g.attrs["fit_rule_name"] == name
        assert g.attrs["fit_default"] == (0 if args else 1)
        np.testing.assert_allclose(g["table/fit_E_max"][...], float(hi))
        assert "fit_p" in g["table"] and "E_max" in g["fits"] and "p_value" in g["fits"]
    with open(out / "fits.csv") as fh:
        assert all(float(r["E_max"]) == pytest.approx(float(hi)) for r in csv.DictReader(fh))


def test_every_system_and_variant_table_names_its_rule(tmp_path, capsys):
    # two physical systems (hertz overrides the exponent): the systems table
    camp = SyntheticCampaign(N=(64, 128), seeds=6, variants=("default", "hertz"),
                             variant_truth={"hertz": Truth.jamming(2.5, 1.1)}, histograms=("z_g",))
    write_store(tmp_path / "m.h5", camp)
    out = tmp_path / "o"
    assert cli.main(["reduce", str(tmp_path / "m.h5"), "--boot", "0", "--out", str(out)]) == 0
    assert capsys.readouterr().out.count("Fits: typical overlap <= 0.001 (default).") == 1
    assert (out / "systems.md").read_text().startswith("Fits: typical overlap <= 0.001 (default).")
    # two protocol variants of one system: the variants table
    camp = SyntheticCampaign(N=(64, 128), seeds=6, variants=("default", "loose"), histograms=("z_g",))
    write_store(tmp_path / "v.h5", camp)
    assert cli.main(["reduce", str(tmp_path / "v.h5"), "--boot", "0", "--out", str(out), "--fit-all"]) == 0
    assert capsys.readouterr().out.count("dA_G*(E=0), dbeta_E: the scaling fits' (every energy).") == 1
    for name, rule in (("systems.csv", "typical overlap <= 0.001 (default)"), ("variants.csv", "every energy")):
        with open(out / name) as fh:
            recs = list(csv.DictReader(fh))
        assert recs and all(r["fit_rule"] == rule for r in recs), name


def test_the_fit_range_is_one_test():
    E = np.array([1e-15, 1e-9, 1e-6, 1e-6 * (1 + 1e-12), 1e-5, 1e-3])
    assert list(in_fit_range(E, 2.0)) == [True, True, True, True, False, False]  # to a relative 1e-9
    assert list(in_fit_range(E, 2.0, math.inf)) == [True] * 6
    assert list(in_fit_range(E, 2.0, math.inf, (1e-9, 1e-5))) == [False, True, True, True, True, False]
    assert list(in_fit_range(E, 3.0, 0.01, (0.0, 1e-6))) == list((typical_overlap(E, 3.0) <= 0.01) & (E <= 1e-6))
