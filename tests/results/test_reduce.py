"""The reducer on synthetic campaign files (layout of docs/CONTRACTS.md)."""

import json
import math

import h5py
import numpy as np
import pytest

from campaign import cli
from campaign.errors import UserError
from campaign.results import reduce as R
from campaign.results.tables import fmt_err
from campaign.report.writing import table_markdown, write_reduced
from synthetic_store import SyntheticCampaign, Truth, split_store, write_store

FAST = R.Settings(n_boot=150)
EVERY = R.Settings(n_boot=150, fit_overlap=np.inf)  # fits over every energy (--fit-all)


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    path = tmp_path_factory.mktemp("full") / "c.h5"
    camp = SyntheticCampaign(N=(64, 128, 256, 512), seeds=16)
    data = write_store(path, camp)
    return path, camp, data, R.reduce_campaign(path, FAST)


def test_cell_statistics_match_a_direct_computation(full):
    path, camp, data, red = full
    c = red.cells
    assert len(c["N"]) == len(camp.N) * len(camp.E)
    for i in range(len(c["N"])):
        m = (data["N_label"] == c["N"][i]) & (data["E_target"] == c["E"][i])
        assert c["n_packings"][i] == m.sum() == camp.seeds
        for name in ("A_G", "psi_O", "E_G", "delta_Z", "phi"):
            v = data[name][m]
            assert c[f"mean_{name}"][i] == pytest.approx(v.mean(), rel=1e-12)
            assert c[f"sem_{name}"][i] == pytest.approx(v.std(ddof=1) / np.sqrt(v.size), rel=1e-9)


def test_histograms_are_the_sums_over_each_cell(full):
    path, camp, data, red = full
    with h5py.File(path, "r") as f:
        for name in ("contact_angle", "z_v", "radial_contacts"):
            counts = f[f"histograms/{name}/counts"][...]
            edges = f[f"histograms/{name}/edges"][...]
            d = red.distributions[name]
            np.testing.assert_array_equal(d["edges"], edges)
            for i in range(len(red.cells["N"])):
                m = (data["N_label"] == red.cells["N"][i]) & (data["E_target"] == red.cells["E"][i])
                np.testing.assert_array_equal(d["counts"][i], counts[m].sum(axis=0))
                assert np.sum(d["density"][i] * np.diff(edges)) == pytest.approx(1.0)


def test_fits_and_extrapolation_recover_the_synthetic_truth(full):
    path, camp, data, red = full
    t = camp.truth
    assert [r["N_G"] for r in red.rows] == list(camp.N)
    for r in red.rows:
        assert abs(r["A_G_star_E"] - t.A_star(r["N_G"])) < 4 * r["A_G_star_E_err"]
        assert abs(r["beta_E"] - t.beta_A) < 4 * r["beta_E_err"]
        assert abs(r["psi_O_star"] - t.P_star(r["N_G"])) < 4 * r["psi_O_star_err"]
        # delta_Z ~ E^(1/4) in the synthetic data, so A_G - A* ~ delta_Z^(0.28/0.25)
        assert abs(r["beta_Z"] - t.beta_A / 0.25) < 4 * r["beta_Z_err"] + 0.02
    x = red.extrapolated["default"]
    assert abs(x["A_G_star_E"] - t.A_inf) < 4 * x["A_G_star_E_err"]
    assert abs(x["psi_O_star"] - t.P_inf) < 4 * x["psi_O_star_err"]
    assert x["A_G_star_E_err"] < 2e-3


def test_width_of_P_AG_scales_as_inverse_square_root(full):
    path, camp, data, red = full
    gam = np.array([w["gamma"] for w in red.width_scaling])
    err = np.array([w["gamma_err"] for w in red.width_scaling])
    assert len(gam) == len(camp.E)
    pull = (gam - 0.5) / err
    assert np.all(np.abs(pull) < 4)
    assert abs(np.mean(gam) - 0.5) < 4 * np.sqrt(np.mean(err**2) / len(gam))


def test_self_averaging_ratios_are_one_for_identically_drawn_packings(full):
    path, camp, data, red = full
    for name in ("alpha_e", "z_g", "contact_angle"):
        sa = red.self_averaging[name]
        n = red.cells["n_packings"][:, None]
        # mean of per-packing ratios is 1 up to its standard error (and a small Jensen bias)
        assert np.all(np.abs(sa["ratio_mean"] - 1) < 4 * sa["ratio_std"] / np.sqrt(n) + 0.01)
        assert np.all(sa["ratio_std"] > 0)
    assert "radial_grains" not in red.self_averaging


def test_many_small_files_give_the_same_reduction_as_one(full, tmp_path):
    path, camp, data, red = full
    parts = [tmp_path / f"part{k}.h5" for k in range(3)]
    split_store(path, parts)
    red3 = R.reduce_campaign(parts, FAST)
    assert set(red3.distributions) == set(red.distributions)
    for name, d in red.distributions.items():
        key = "counts" if "counts" in d else "density"  # sin_theta is derived: no counts
        np.testing.assert_array_equal(red3.distributions[name][key], d[key])
    for k in ("n_packings", "mean_A_G", "sem_A_G", "mean_E_G"):
        np.testing.assert_allclose(red3.cells[k], red.cells[k], rtol=1e-12)
    # the same file twice: every packing counts once
    red2 = R.reduce_campaign([path, parts[0]], FAST)
    np.testing.assert_array_equal(red2.cells["n_packings"], red.cells["n_packings"])
    np.testing.assert_array_equal(red2.distributions["z_g"]["counts"],
                                  red.distributions["z_g"]["counts"])


def test_partly_finished_file_reduces_what_is_done_and_says_what_is_missing(tmp_path):
    camp = SyntheticCampaign(N=(64, 128), seeds=6)
    T = camp.n_tasks
    status = np.ones(T, np.int8)
    status[:4] = 0            # N=64, highest... first cell: 4 of 6 pending -> 2 done
    status[10] = 2            # one failure
    status[T // 2:T // 2 + 9] = 0
    data = write_store(tmp_path / "p.h5", camp, status=status)
    red = R.reduce_campaign(tmp_path / "p.h5", EVERY)  # the short cell, E = 1e-3, in the fits' range
    assert red.meta["done"] == int((status == 1).sum())
    assert red.meta["pending"] == int((status == 0).sum())
    assert red.meta["failed"] == 1
    c = red.cells
    for i in range(len(c["N"])):
        m = (data["N_label"] == c["N"][i]) & (data["E_target"] == c["E"][i])
        assert c["n_packings"][i] == int((status[m] == 1).sum())
        assert c["n_pending"][i] == int((status[m] == 0).sum())
        done = m & (status == 1)
        if done.sum() >= 2:
            assert c["mean_A_G"][i] == pytest.approx(data["A_G"][done].mean(), rel=1e-12)
    text = "\n".join(red.notes)
    assert "pending" in text and "failed" in text and "synthetic failure" in text
    assert "fewer than 3" in text  # the cell with 2 packings is left out of the fits, and said so
    assert all(r["n_cells"] <= len(camp.E) for r in red.rows)
    small = np.flatnonzero(c["n_packings"] < 3)
    assert len(small) >= 1
    assert np.all(np.isnan(red.residuals[:, small]))


def test_unconverged_and_broken_packings_are_counted_but_left_out(tmp_path, capsys):
    camp = SyntheticCampaign(N=(64, 128), seeds=6, variants=("default", "loose"))
    path = tmp_path / "x.h5"
    data = write_store(path, camp)
    T = camp.n_tasks
    jam_status = np.zeros(T)
    identities = np.ones(T)
    jam_status[[0, 7, 40]] = (1, 3, 2)       # max_search, stalled, max_steps
    identities[[1, 7, T - 1]] = 0            # row 7 fails both
    with h5py.File(path, "r+") as f:
        f["scalars/jam_status"][...] = jam_status
        f["scalars/identities_ok"][...] = identities
    good = (jam_status == 0) & (identities == 1)
    red = R.reduce_campaign(path, FAST)
    c = red.cells
    with h5py.File(path, "r") as f:
        counts = f["histograms/z_v/counts"][...]
    for i in range(len(c["N"])):
        m = ((data["variant"] == c["variant"][i]) & (data["N_label"] == c["N"][i])
             & (data["E_target"] == c["E"][i]))
        assert c["n_packings"][i] == (m & good).sum()
        assert c["n_excluded"][i] == (m & ~good).sum()
        assert c["n_tasks"][i] == m.sum()
        assert c["mean_A_G"][i] == pytest.approx(data["A_G"][m & good].mean(), rel=1e-12)
        np.testing.assert_array_equal(red.distributions["z_v"]["counts"][i],
                                      counts[m & good].sum(axis=0))
    assert red.meta["excluded"] == 5 and red.meta["done"] == T - 5
    text = "\n".join(red.notes)
    assert "5 finished packing(s) left out" in text
    assert "3 with jam_status != 0" in text and "3 with identities_ok != 1" in text
    by_variant = {r["variant"]: r for r in red.tradeoff}
    assert by_variant["default"]["n_excluded"] == (~good[data["variant"] == "default"]).sum()
    assert by_variant["loose"]["n_excluded"] == (~good[data["variant"] == "loose"]).sum()
    assert by_variant["loose"]["n_packings"] == T // 2  # finished ones, used or not
    # written out with the reduction
    write_reduced(red, tmp_path / "r.h5")
    with h5py.File(tmp_path / "r.h5", "r") as f:
        assert f["reduced"].attrs["n_excluded"] == 5
        np.testing.assert_array_equal(f["reduced/cells/n_excluded"][...], c["n_excluded"])
    assert cli.main(["reduce", str(path), "--out", str(tmp_path / "red"), "--boot", "20"]) == 0
    assert f"{T - 5} of {T} packings used, 5 finished but left out" in capsys.readouterr().out
    # a file without the two columns uses every finished packing
    with h5py.File(path, "r+") as f:
        del f["scalars/jam_status"], f["scalars/identities_ok"]
    red = R.reduce_campaign(path, FAST)
    assert red.meta["excluded"] == 0 and red.cells["n_packings"].sum() == T


def test_a_file_with_nothing_finished(tmp_path):
    camp = SyntheticCampaign(N=(64,), E=(1e-3, 1e-6), seeds=3)
    write_store(tmp_path / "z.h5", camp, status=np.zeros(camp.n_tasks, np.int8))
    red = R.reduce_campaign(tmp_path / "z.h5", FAST)
    assert red.meta["done"] == 0 and red.meta["pending"] == camp.n_tasks
    assert any("no finished packings" in n for n in red.notes)
    assert np.isnan(red.rows[0]["A_G_star_E"])


def test_cli_reduce_json_and_output_files(full, tmp_path, capsys):
    path, camp, data, red = full
    out = tmp_path / "out"
    rc = cli.main(["reduce", str(path), "--out", str(out), "--json", "--boot", "50"])
    assert rc == 0
    cap = capsys.readouterr()
    obj = json.loads(cap.out)
    assert "N_G" in cap.err and "A_G*(E_G=0)" in cap.err  # the table goes to the terminal
    keys = ("A_G_star_E", "beta_E", "A_G_star_Z", "beta_Z", "psi_O_star")
    assert len(obj["rows"]) == len(camp.N)
    for r in obj["rows"]:
        assert r["variant"] == "default"
        for k in keys:  # numbers, finite (JSON's NaN would pass as a float)
            assert isinstance(r[k], float) and math.isfinite(r[k]), (k, r[k])
            assert isinstance(r[f"{k}_err"], float) and math.isfinite(r[f"{k}_err"]), (k, r[f"{k}_err"])
    for k in keys:
        got = obj["extrapolated"]["default"]
        assert isinstance(got[k], float) and math.isfinite(got[k]), (k, got[k])
        assert isinstance(got[f"{k}_err"], float) and math.isfinite(got[f"{k}_err"]), (k, got[f"{k}_err"])
    for name in ("table.md", "table.csv", "table.tex", "cells.csv", "fits.csv", "reduced.h5"):
        assert (out / name).stat().st_size > 0
    md = (out / "table.md").read_text()
    assert md.count("\n| ") == len(camp.N) + 2  # header + one per N + the extrapolation
    assert md.startswith("Fits over the cells of typical overlap")  # the range, first
    assert "N_G -> inf" in md
    assert r"\begin{tabular}" in (out / "table.tex").read_text()
    with h5py.File(out / "reduced.h5", "r") as f:
        g = f["reduced"]
        for name in ("cells", "fits", "table", "extrapolated", "distributions", "peaks",
                     "self_averaging", "width_scaling"):
            assert name in g
        assert g["cells/N"].shape == (len(camp.N) * len(camp.E),)
        assert g["fits/residuals"].shape == (4 * len(camp.N), len(camp.N) * len(camp.E))
        np.testing.assert_array_equal(g["distributions/z_g/counts"][...],
                                      red.distributions["z_g"]["counts"])


def test_cli_reduce_prints_the_table_without_json(full, tmp_path, capsys):
    path, *_ = full
    assert cli.main(["reduce", str(path), "--out", str(tmp_path), "--boot", "0"]) == 0
    out = capsys.readouterr().out
    assert out.count("| 64 |") == 1 and "Psi_O*" in out


def test_in_place_writes_the_group_and_refuses_while_pending(tmp_path, capsys):
    camp = SyntheticCampaign(N=(64,), E=(1e-3, 1e-6, 1e-9, 1e-12), seeds=4)
    write_store(tmp_path / "a.h5", camp)
    assert cli.main(["reduce", str(tmp_path / "a.h5"), "--in-place", "--boot", "20"]) == 0
    with h5py.File(tmp_path / "a.h5", "r") as f:
        assert "reduced/table/A_G_star_E" in f and "tasks/status" in f
    st = np.ones(camp.n_tasks, np.int8)
    st[0] = 0
    write_store(tmp_path / "b.h5", camp, status=st)
    assert cli.main(["reduce", str(tmp_path / "b.h5"), "--in-place", "--boot", "20"]) == 2
    assert "pending" in capsys.readouterr().err


@pytest.mark.parametrize("content", [None, b"not an hdf5 file", "empty-h5"])
def test_cli_reduce_bad_files_are_user_errors(tmp_path, capsys, content):
    p = tmp_path / "bad.h5"
    if content == "empty-h5":
        h5py.File(p, "w").close()
    elif content is not None:
        p.write_bytes(content)
    assert cli.main(["reduce", str(p)]) == 2
    err = capsys.readouterr().err
    assert "bad.h5" in err and "Traceback" not in err


def test_cli_reduce_bad_options(full, capsys):
    path, *_ = full
    assert cli.main(["reduce", str(path), "--boot", "1"]) == 2
    assert cli.main(["reduce", str(path), "--min-packings", "1"]) == 2


@pytest.mark.parametrize("value, err, text", [
    (0.44163, 0.00021, "0.4416(2)"), (1.0012, 0.0023, "1.001(2)"), (0.284, 0.03, "0.28(3)"),
    (0.2849, 0.0031, "0.285(3)"), (0.446, 0.00096, "0.446(1)"), (12.3, 2.0, "12(2)"),
    (0.5, float("nan"), "0.5"), (float("nan"), 0.1, "--"),
])
def test_value_error_format(value, err, text):
    assert fmt_err(value, err) == text


def test_variants_are_separate_rows(tmp_path):
    camp = SyntheticCampaign(N=(64, 128), seeds=5, variants=("default", "loose"))
    write_store(tmp_path / "v.h5", camp)
    red = R.reduce_campaign(tmp_path / "v.h5", FAST)
    assert sorted({r["variant"] for r in red.rows}) == ["default", "loose"]
    assert set(red.extrapolated) == {"default", "loose"}
    # the synthetic "loose" variant is shifted by +0.01 in A_G
    d = {(r["variant"], r["N_G"]): (r["A_G_star_E"], r["A_G_star_E_err"]) for r in red.rows}
    for n in camp.N:
        (a, ea), (b, eb) = d[("loose", n)], d[("default", n)]
        assert abs(a - b - 0.01) < 4 * np.hypot(ea, eb)
    assert "Variant `loose`" in table_markdown(red)


ENGINE_SPEC = """\
name: reduce-integration
seed: 7
system:
  box: [1.0, 1.0]
  species: [{name: A, fraction: 0.5, radius: 1.4}, {name: B, fraction: 0.5, radius: 1.0}]
  potential: {exponent: 2.0}
grid:
  N_G: [16, 32]
  E_G: [1.0e-3, 1.0e-6, 1.0e-9, 1.0e-12]
  seeds: 3
protocol: {window: 0.1, force_tolerance: 1.0e-6}
observables: [scalars, connectivity, edge_triangles]
store: {configurations: false}
output: out.h5
"""


def test_reduce_reads_a_file_written_by_the_engine(tmp_path, capsys):
    """The engine's own store (with its cheap stand-in task function), read back."""
    spec = tmp_path / "s.yaml"
    spec.write_text(ENGINE_SPEC)
    out = tmp_path / "e.h5"
    rc = cli.main(["run", str(spec), "--out", str(out), "--launcher", "inline",
                   "--task-function", "synthetic", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    red = R.reduce_campaign(out, FAST)
    with h5py.File(out, "r") as f:
        status = f["tasks/status"][...]
        N = f["tasks/N"][...]
        E = f["tasks/E"][...]
        A = f["scalars/A_G"][...]
        zg = f["histograms/z_g/counts"][...]
    assert red.meta["done"] == int((status == 1).sum()) == 24
    for i in range(len(red.cells["N"])):
        m = (N == red.cells["N"][i]) & (E == red.cells["E"][i]) & (status == 1)
        assert red.cells["n_packings"][i] == m.sum() == 3
        assert red.cells["mean_A_G"][i] == pytest.approx(A[m].mean(), rel=1e-12)
        np.testing.assert_array_equal(red.distributions["z_g"]["counts"][i], zg[m].sum(axis=0))
    assert set(red.distributions) >= {"z_g", "z_v", "alpha_e"}


@pytest.mark.slow
def test_reduce_while_a_run_is_writing(tmp_path, capsys):
    """A real run writes the file meanwhile: reduce uses what is done and says what is missing."""
    import os
    import subprocess
    import sys
    import time

    spec = tmp_path / "s.yaml"
    spec.write_text(ENGINE_SPEC)
    out = tmp_path / "live.h5"
    env = dict(os.environ, CAMPAIGN_SYNTHETIC_DELAY="0.15")
    proc = subprocess.Popen([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out),
                             "--launcher", "inline", "--task-function", "synthetic", "--quiet"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        red = None
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            time.sleep(0.2)
            if not out.exists():
                continue
            try:
                red = R.reduce_campaign(out, FAST)
            except UserError:  # caught mid-flush: the message says to try again
                continue
            if red.meta["done"] >= 4:
                break
        assert red is not None and proc.poll() is None, "the run ended before it could be observed"
        assert 4 <= red.meta["done"] < 24 and red.meta["pending"] == 24 - red.meta["done"]
        assert any("pending" in n for n in red.notes)
        assert red.cells["n_packings"].sum() == red.meta["done"]
        # the one-writer rule: no in-place write while the run holds the file
        assert cli.main(["reduce", str(out), "--in-place", "--boot", "0",
                         "--out", str(tmp_path / "r1")]) == 2
        assert "pending" in capsys.readouterr().err
    finally:
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err.decode()
    red = R.reduce_campaign(out, FAST)
    assert red.meta["done"] == 24 and red.meta["pending"] == 0
    assert not any("pending" in n for n in red.notes)
    assert cli.main(["reduce", str(out), "--in-place", "--boot", "0",
                     "--out", str(tmp_path / "r2")]) == 0


def test_in_place_refuses_while_the_journal_is_locked(tmp_path, capsys):
    import fcntl
    import os

    camp = SyntheticCampaign(N=(64,), E=(1e-3, 1e-6, 1e-9, 1e-12), seeds=3)
    path = tmp_path / "j.h5"
    write_store(path, camp)
    journal = tmp_path / "j.h5.journal"
    journal.write_bytes(b"")
    fd = os.open(journal, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # what a running master holds
        assert cli.main(["reduce", str(path), "--in-place", "--boot", "0"]) == 2
        assert "locked" in capsys.readouterr().err
    finally:
        os.close(fd)
    assert cli.main(["reduce", str(path), "--in-place", "--boot", "0"]) == 0
    with h5py.File(path, "r") as f:
        assert "reduced" in f


def test_isostatic_cells_enter_the_delta_Z_fit_at_the_intercept(tmp_path):
    camp = SyntheticCampaign(N=(256,), seeds=12, truth=Truth(iso_E=1e-10))
    write_store(tmp_path / "i.h5", camp)
    red = R.reduce_campaign(tmp_path / "i.h5", EVERY)
    zero = red.cells["mean_delta_Z"] == 0
    assert zero.sum() == 3  # E = 1e-11, 1e-13, 1e-15
    k = next(j for j, f in enumerate(red.fits) if f["abscissa"] == "delta_Z" and f["quantity"] == "A_G")
    f = red.fits[k]
    assert f["ok"] and f["n_points"] == len(camp.E)
    assert np.all(np.isfinite(red.residuals[k][zero]))
    # the isostatic cells sit at A* + c E^0.28 with E <= 1e-11: A* within their spread
    assert abs(f["intercept"] - camp.truth.A_star(256)) < 4 * f["intercept_err"] + 2e-4
    assert f["x_min"] > 0


def test_a_fresh_file_without_scalar_columns(tmp_path):
    """The engine creates /scalars/<name> with the first finished packing."""
    camp = SyntheticCampaign(N=(64, 128), E=(1e-3, 1e-6, 1e-9, 1e-12), seeds=3)
    path = tmp_path / "fresh.h5"
    write_store(path, camp, status=np.zeros(camp.n_tasks, np.int8))
    with h5py.File(path, "r+") as f:
        for k in list(f["scalars"]):
            del f[f"scalars/{k}"]
    red = R.reduce_campaign(path, FAST)
    assert red.meta["pending"] == camp.n_tasks and red.meta["done"] == 0
    assert any("no finished packings" in n for n in red.notes)
    assert all(np.isnan(r["A_G_star_E"]) for r in red.rows)


def test_files_with_different_bins_are_refused(tmp_path, capsys):
    camp = SyntheticCampaign(N=(64,), E=(1e-3, 1e-6), seeds=2)
    write_store(tmp_path / "a.h5", camp)
    write_store(tmp_path / "b.h5", camp)
    with h5py.File(tmp_path / "b.h5", "r+") as f:
        e = f["histograms/z_g/edges"]
        e[...] = e[...] + 0.25
    assert cli.main(["reduce", str(tmp_path / "a.h5"), str(tmp_path / "b.h5")]) == 2
    assert "z_g" in capsys.readouterr().err


def test_fit_energy_range_selects_the_cells_of_the_fits(tmp_path, capsys):
    """--fit-energies LO HI: the scaling fits use exactly the cells in the range, and equal a
    fit to those cells' means (the paper's fit range, docs/PAPER.md)."""
    from campaign.results.fits import fit_power_law

    camp = SyntheticCampaign(N=(64, 128), seeds=8)
    path = tmp_path / "c.h5"
    write_store(path, camp)
    lo, hi = 1e-14, 1e-6
    red = R.reduce_campaign(path, R.Settings(n_boot=0, fit_energies=(lo, hi), fit_overlap=np.inf))
    inside = [e for e in camp.E if lo <= e <= hi]
    assert 4 <= len(inside) < len(camp.E)
    assert any("E_G in [1e-14, 1e-06]" in n for n in red.notes)
    c = red.cells
    for row in red.rows:
        assert row["n_cells"] == len(inside)
        m = (c["N"] == row["N_G"]) & (c["E"] >= lo) & (c["E"] <= hi)
        x, y, ye, *_ = red.fit_inputs[("default", "A_G", "E_G")][row["N_G"]]
        np.testing.assert_array_equal(x, c["mean_E_G"][m])  # exactly the range's cells
        np.testing.assert_array_equal(y, c["mean_A_G"][m])
        f = fit_power_law(x, y, ye)
        assert row["beta_E"] == pytest.approx(f.exponent, rel=1e-9)
        assert row["A_G_star_E"] == pytest.approx(f.intercept, rel=1e-9)
    full = R.reduce_campaign(path, R.Settings(n_boot=0, fit_overlap=np.inf))
    assert all(r["n_cells"] == len(camp.E) for r in full.rows)
    assert cli.main(["reduce", str(path), "--out", str(tmp_path / "o"), "--fit-energies", "1e-3", "1e-5"]) == 2
    assert "--fit-energies expects 0 <= LO < HI" in capsys.readouterr().err
