"""The reducer's linear-response section (campaign.results.response) and its figures: exponent fits on
draws from known laws, and a real campaign of moduli, modes and gaps through run, reduce and
plot, checked against the store's own per-packing scalars."""

import csv
import json

import h5py
import numpy as np
import pytest

from campaign import cli
from campaign.results import response as resp

EDGES = np.r_[0.0, np.logspace(-16, 0, 129)]


@pytest.mark.parametrize("gamma", [0.41, 0.2])
def test_the_gap_exponent_of_draws_from_a_known_law(gamma):
    """P(h) ~ h^-gamma on (0, 1): F(h) = h^(1 - gamma); 60 'packings' of 400 gaps each."""
    rng = np.random.default_rng(5)
    per = np.array([np.histogram(rng.random(400) ** (1 / (1 - gamma)), EDGES)[0] for _ in range(60)])
    slope, err, lo, hi, n, msg = resp.cumulative_exponent(EDGES, per.sum(axis=0), 1e-5, 1e-2, per, n_boot=300)
    assert msg == "" and n >= 12 and lo >= 1e-5 and hi == 1e-2
    assert 0 < err < 0.1
    assert abs((1 - slope) - gamma) < 3 * err


def test_the_bootstrap_errors_cover_the_exponent():
    """Over 40 independent ensembles the 2-sigma intervals hold the true gamma most of the time."""
    rng = np.random.default_rng(8)
    gamma, inside = 0.41, 0
    for _ in range(40):
        per = np.array([np.histogram(rng.random(200) ** (1 / (1 - gamma)), EDGES)[0] for _ in range(40)])
        slope, err, *_ = resp.cumulative_exponent(EDGES, per.sum(axis=0), 1e-5, 1e-2, per, n_boot=200)
        inside += abs((1 - slope) - gamma) < 2 * err
    assert inside >= 32


def test_too_few_small_values_give_no_exponent():
    counts = np.zeros(len(EDGES) - 1, int)
    counts[-1] = 1000  # every gap near 1
    slope, err, *_, msg = resp.cumulative_exponent(EDGES, counts, 1e-6, 1e-2)
    assert np.isnan(slope) and "fewer than" in msg


def test_power_fit_recovers_a_power_law():
    x = np.geomspace(1e-4, 1e-1, 7)
    y = 0.7 * x**0.5
    beta, berr, c, cerr, chi, n = resp.power_fit(x, y, 0.01 * y)
    assert beta == pytest.approx(0.5, abs=1e-12) and c == pytest.approx(0.7, rel=1e-12) and n == 7
    # negative or missing means are left out, not fitted
    y2 = y.copy()
    y2[0] = -1.0
    assert resp.power_fit(x, y2, 0.01 * np.abs(y2))[5] == 6


SPEC = """\
name: resp
seed: 11
grid: {N_G: [24, 32], E_G: [1.0e-2, 1.0e-3, 1.0e-4, 1.0e-5, 1.0e-6, 1.0e-7, 1.0e-8, 1.0e-9], seeds: 6}
protocol: {skin: 0.1}
observables: [scalars, connectivity, moduli, modes, gaps]
"""


@pytest.fixture(scope="module")
def reduced(tmp_path_factory):
    d = tmp_path_factory.mktemp("resp")
    (d / "s.yaml").write_text(SPEC)
    assert cli.main(["run", str(d / "s.yaml"), "--out", str(d / "r.h5"), "--launcher", "inline"]) == 0
    assert cli.main(["reduce", str(d / "r.h5"), "--out", str(d / "red"), "--boot", "50"]) == 0
    return d


def test_reduce_writes_the_response_tables(reduced):
    d = reduced
    cells = list(csv.DictReader(open(d / "red" / "response_cells.csv")))
    fits = list(csv.DictReader(open(d / "red" / "response_fits.csv")))
    pooled = list(csv.DictReader(open(d / "red" / "response_exponents.csv")))
    assert len(cells) == 16 and {r["fit"] for r in fits} == {"G_vs_p", "G_vs_dZ", "omega_min_vs_dZ"}
    assert {int(r["N_G"]) for r in pooled} == {24, 32}
    with h5py.File(d / "r.h5", "r") as f:
        N, E = f["tasks/N"][:], f["tasks/E"][:]
        G, cmin, s = f["scalars/G"][:], f["scalars/c_min"][:], f["scalars/contact_distance"][:]
        om, osc = f["scalars/omega_min"][:], f["scalars/omega_scale"][:]
        p = f["scalars/pressure"][:]
        ok = f["scalars/moduli_ok"][:]
    for r in cells:
        m = (N == int(r["N"])) & (E == float(r["E"]))
        g = G[m][ok[m] == 1]
        assert float(r["frac_G_negative"]) == pytest.approx(np.mean(g < 0))
        assert float(r["frac_c_min_negative"]) == pytest.approx(np.mean(cmin[m][ok[m] == 1] < 0))
        assert float(r["mean_G_s2"]) == pytest.approx(np.mean(g * s[m][ok[m] == 1] ** 2), rel=1e-9)
        assert float(r["mean_p_s2"]) == pytest.approx(np.mean(p[m] * s[m] ** 2), rel=1e-9)
        assert float(r["mean_omega_min_scaled"]) == pytest.approx(np.mean(om[m] / osc[m]), rel=1e-9)
    summary = json.loads((d / "red" / "summary.json").read_text())
    assert {"cells", "fits", "exponents", "alpha"} <= set(summary["response"])
    with h5py.File(d / "red" / "reduced.h5", "r") as f:
        assert "reduced/response/cells" in f and "reduced/response/fits" in f
        assert "reduced/distributions/gap" in f and "reduced/distributions/omega" in f


@pytest.mark.slow
def test_plot_draws_the_response_figures(reduced):
    d = reduced
    assert cli.main(["plot", str(d / "r.h5"), "--out", str(d / "fig"), "--boot", "20"]) == 0
    for name in ("response_moduli.png", "response_distributions.png"):
        data = (d / "fig" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
