"""The N_G -> inf row (docs/REDUCED.md, "The N_G -> inf row"): one fit per law with the exponent
shared by the sizes, undetermined per-size fits marked and never extrapolated, and synthetic
campaigns with the finite-size plateau (N_G Delta Z of order one) at 16 packings per cell."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from synthetic_store import SyntheticCampaign, Truth, task_table, write_store

from campaign.results import fits
from campaign.results import reduce as R
from campaign.results.scaling import TABLE_KEYS
from campaign.report.writing import table_csv, table_markdown

# The grid of a small campaign: four sizes, eight energies, 16 seeds (five energies inside the
# default window typical overlap <= 0.001, E_G <= 1e-6 at alpha = 2).
SMALL_E = (1e-14, 1e-12, 1e-10, 1e-8, 1e-6, 1e-5, 1e-4, 1e-3)
SIZES = (64, 128, 256, 512)


def plateau_truth(**kw):
    """Harmonic jamming scaling (beta_Z = 1.05, beta_E = beta_Z / 4) with the plateau below
    N_G Delta Z ~ 4.3, Delta Z = 5 E^(1/4) and A_G's per-packing spread 0.10 / sqrt(N_G):
    experiments/finite_size_fits.py's measured constants."""
    return Truth.jamming(2.0, 1.05, c_A=0.22 * 5.0**1.05, c_Z=5.0, sigma_A=0.10, sigma_Z=0.3,
                         a_N=-0.4, plateau=4.3, **kw)


# --------------------------------------------------------------------------- the shared fit
@settings(max_examples=40, deadline=None)
@given(beta=st.floats(0.1, 1.5), groups=st.integers(1, 4), seed=st.integers(0, 2**31))
def test_the_shared_fit_recovers_exact_laws(beta, groups, seed):
    """Noise-free y = a_g + c_g x^beta over groups of different ranges, intercepts and
    amplitudes: the exponent, intercepts and amplitudes come back; chi^2 is round-off. (The
    closed-form intercept and amplitude go through normal equations: where x^beta spans more
    than about twelve decades they lose digits; the fits of a campaign span at most about five.)"""
    rng = np.random.default_rng(seed)
    xs, ys, es, a, c = [], [], [], [], []
    for g in range(groups):
        x = np.geomspace(10.0 ** rng.uniform(-8, -3), 1.0, rng.integers(3, 7))
        a.append(rng.uniform(0.3, 0.5))
        c.append(rng.uniform(0.1, 2.0))
        xs.append(x)
        ys.append(a[-1] + c[-1] * x**beta)
        es.append(np.full(x.size, 1e-4))
    f = fits.fit_shared_exponent(xs, ys, es)
    assert f.exponent == pytest.approx(beta, abs=1e-5)
    np.testing.assert_allclose(f.intercepts, a, atol=1e-6)
    np.testing.assert_allclose(f.coeffs, c, rtol=1e-4)
    assert f.dof == sum(x.size for x in xs) - 2 * groups - 1
    assert f.chi2 < 1e-6


def test_the_shared_fit_is_invariant_under_units_and_order():
    """Rescaling one group's abscissa (another unit of E_G) only rescales its amplitude;
    reordering the groups changes nothing."""
    rng = np.random.default_rng(3)
    xs = [np.geomspace(1e-9, 1e-3, 5), np.geomspace(1e-7, 1e-3, 4), np.geomspace(1e-12, 1e-6, 6)]
    ys = [0.44 + 0.3 * x**0.28 + rng.normal(0, 1e-3, x.size) for x in xs]
    es = [np.full(x.size, 1e-3) for x in xs]
    f = fits.fit_shared_exponent(xs, ys, es)
    g = fits.fit_shared_exponent([xs[0] * 7.0, *xs[1:]], ys, es)
    assert g.exponent == pytest.approx(f.exponent, abs=1e-6)
    assert g.coeffs[0] == pytest.approx(f.coeffs[0] * 7.0 ** -f.exponent, rel=1e-5)
    h = fits.fit_shared_exponent(xs[::-1], ys[::-1], es[::-1])
    assert h.exponent == pytest.approx(f.exponent, abs=1e-6)
    np.testing.assert_allclose(h.intercepts[::-1], f.intercepts, atol=1e-9)


def test_a_group_needs_three_cells():
    with pytest.raises(ValueError, match="3 cells"):
        fits.fit_shared_exponent([np.array([1e-6, 1e-4])], [np.array([0.45, 0.46])], [np.full(2, 1e-3)])
    assert fits.fit_shared_exponent([], [], []).undetermined


@pytest.mark.parametrize("kw, word", [
    (dict(ok=False, exponent=np.nan, err=np.nan, at_bound=False, boot_at_bound=np.nan), "no fit"),
    (dict(ok=True, exponent=4.0, err=0.1, at_bound=True, boot_at_bound=0.0), "search bound"),
    (dict(ok=True, exponent=0.3, err=np.nan, at_bound=False, boot_at_bound=np.nan), "no bootstrap error"),
    (dict(ok=True, exponent=0.3, err=0.0, at_bound=False, boot_at_bound=0.0), "no bootstrap error"),
    (dict(ok=True, exponent=0.3, err=0.5, at_bound=False, boot_at_bound=0.2), "20%"),
    (dict(ok=True, exponent=0.3, err=0.05, at_bound=False, boot_at_bound=0.02), ""),
])
def test_what_makes_an_exponent_undetermined(kw, word):
    why = fits.undetermined_reason(**kw)
    assert (word in why) if word else why == ""


# --------------------------------------------------------------------------- the reducer
def _reduce(tmp_path, name, truth, E=SMALL_E, N=SIZES, seeds=16, seed=0, n_boot=200):
    path = tmp_path / f"{name}.h5"
    write_store(path, SyntheticCampaign(N=N, E=E, seeds=seeds, truth=truth, histograms=(), seed=seed))
    return R.reduce_campaign([path], R.Settings(n_boot=n_boot), distributions=False)


@pytest.mark.slow
def test_the_default_covers_the_truth_at_its_nominal_rate_with_a_plateau(tmp_path):
    """40 synthetic campaigns of the small grid (N_G 64..512, 16 packings per cell) with the
    finite-size plateau: the N_G -> inf exponents and A_G* of the default reduction cover the
    truth with their errors at about 68% and 95% (binomial bounds at 40 trials), and the
    per-size fits whose exponent is undetermined are marked. The former default (per-size fits,
    every size extrapolated in 1/N_G) covers the truth too, but with median errors 0.044 on
    beta_E and 0.19 on beta_Z where this default has 0.022 and 0.10: the precision asserted here
    (0.035, 0.15) fails it."""
    t = plateau_truth()
    truth = {"beta_E": t.beta_A, "beta_Z": t.beta_Z, "A_G_star_E": t.A_inf, "A_G_star_Z": t.A_inf}
    hits = {k: [0, 0] for k in truth}
    errs = {k: [] for k in truth}
    marked = 0
    for rep in range(40):
        red = _reduce(tmp_path, f"r{rep}", t, seed=rep)
        ex = red.extrapolated["default"]
        for k, v in truth.items():
            assert np.isfinite(ex[k]) and ex[f"{k}_err"] > 0, (rep, k)
            d = abs(ex[k] - v) / ex[f"{k}_err"]
            hits[k][0] += d <= 1
            hits[k][1] += d <= 2
            errs[k].append(ex[f"{k}_err"])
        marked += sum(bool(r["beta_E_undetermined"]) for r in red.rows)
    for k, (one, two) in hits.items():
        assert 19 <= one <= 36, (k, one)      # nominal 27 of 40
        assert two >= 33, (k, two)            # nominal 38 of 40
    assert np.median(errs["beta_E"]) <= 0.035 and np.median(errs["beta_Z"]) <= 0.15, errs
    assert marked > 0  # the plateau leaves some N_G = 64 fits undetermined


def test_an_undetermined_size_is_marked_and_named(tmp_path):
    """A per-size fit at a search bound or with its bootstrap cut by one shows ``*`` in the
    table, says why in the notes and the CSV, and the N_G -> inf row names its sizes."""
    red = None
    for seed in range(10):
        red = _reduce(tmp_path, f"m{seed}", plateau_truth(), seed=seed)
        if any(r["beta_E_undetermined"] for r in red.rows):
            break
    row = next(r for r in red.rows if r["beta_E_undetermined"])
    text = table_markdown(red)
    line = next(x for x in text.splitlines() if x.startswith(f"| {row['N_G']} |"))
    assert line.split(" | ")[2].endswith("*")
    assert "not determined" in text.split("\n\n")[-2] or "not determined" in text
    assert any(f"N={row['N_G']}: exponents not determined, marked * in the table: A_G against E_G (" in n
               for n in red.notes)
    csv = table_csv(red)
    assert row["beta_E_undetermined"] in csv
    ex = red.extrapolated["default"]
    assert ex["beta_E_sizes"] == " ".join(str(n) for n in SIZES)
    assert "sizes 64..512" in text


def test_a_size_with_too_few_cells_does_not_enter(tmp_path):
    """N_G = 64 with only two energies inside the window finished (the others pending): the
    N_G -> inf row comes from 128 and 256 and says why 64 did not enter; 64's row has no fit."""
    c = SyntheticCampaign(N=(64, 128, 256), E=SMALL_E, seeds=16, truth=plateau_truth(), histograms=())
    _, N, E, _ = task_table(c)
    status = np.where((N == 64) & (E < 1e-9), 0, 1)
    write_store(tmp_path / "p.h5", c, status=status)
    red = R.reduce_campaign([tmp_path / "p.h5"], R.Settings(n_boot=100), distributions=False)
    ex = red.extrapolated["default"]
    assert np.isfinite(ex["beta_E"]) and ex["beta_E_sizes"] == "128 256"
    assert "N_G=64: 2 cell(s) with a positive mean E_G in the fit range (3 needed)" in ex["beta_E_left_out"]
    assert not np.isfinite(next(r for r in red.rows if r["N_G"] == 64)["beta_E"])
    assert any("N_G -> inf from the sizes 128, 256" in n and "left out: N_G=64" in n for n in red.notes)


def test_four_energies_give_a_note_not_a_number(tmp_path):
    """1e-3 ... 1e-9 every second decade: two energies inside the default window, so neither
    the per-size fits nor the N_G -> inf row give a number, and the notes say why."""
    red = _reduce(tmp_path, "four", plateau_truth(), E=(1e-9, 1e-7, 1e-5, 1e-3))
    ex = red.extrapolated["default"]
    for k in TABLE_KEYS:
        assert not np.isfinite(ex[k])
    assert any("no N_G -> inf value of A_G against E_G" in n and "3 needed" in n for n in red.notes)
    assert "| N_G -> inf | -- | -- | -- | -- | -- | -- |" in table_markdown(red)


def test_a_flat_law_gives_no_exponent(tmp_path):
    """A_G independent of E_G (c_A = 0): the shared exponent is not determined, so the
    N_G -> inf row has no exponent rather than a number at the search bound."""
    red = _reduce(tmp_path, "flat", Truth(c_A=0.0, sigma_A=0.01), E=tuple(10.0 ** -np.arange(6, 16)),
                  N=(64, 128), seeds=8)
    ex = red.extrapolated["default"]
    assert not np.isfinite(ex["beta_E"]) and ex["beta_E_note"]


def test_the_row_is_the_shared_fit_of_the_cells_not_the_per_size_fits(tmp_path):
    """A reference computation: the N_G -> inf exponent recomputed from the reduction's own cell
    means (typical overlap <= 0.001, every size) with the shared fit equals the reducer's,
    whatever the per-size fits gave (one size's is undetermined here)."""
    red = None
    for seed in range(10):
        red = _reduce(tmp_path, f"s{seed}", plateau_truth(), seed=seed, n_boot=50)
        if any(r["beta_E_undetermined"] for r in red.rows):
            break
    c = red.cells
    xs, ys, es, Ns = [], [], [], []
    for N in SIZES:
        m = (np.asarray(c["N"]) == N) & (np.sqrt(np.asarray(c["E"], float)) <= 0.001 * (1 + 1e-9))
        x, y, e, *_ = red.fit_inputs[("default", "A_G", "E_G")][N]
        np.testing.assert_array_equal(x, c["mean_E_G"][m])  # the range's cells, their own means
        np.testing.assert_array_equal(y, c["mean_A_G"][m])
        xs.append(x)
        ys.append(y)
        es.append(e)  # the variance model's errors (docs/REDUCED.md, "Error bars that hold")
        Ns.append(N)
    f = fits.fit_shared_exponent(xs, ys, es)
    ex = red.extrapolated["default"]
    assert ex["beta_E"] == pytest.approx(f.exponent, abs=1e-9)
    # the per-size fit of an undetermined size differs: the row did not come from it
    row = next(r for r in red.rows if r["beta_E_undetermined"])
    assert abs(row["beta_E"] - f.exponent) > 1e-3
