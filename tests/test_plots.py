"""Smoke tests: every figure is written, for complete and for partly finished campaigns."""

import matplotlib  # noqa: F401 - the test extra installs it; a missing one must fail, not skip
import numpy as np
import pytest
from synthetic_store import SyntheticCampaign, Truth, write_store

from campaign import cli

from campaign.results import plots
from campaign.results import reduce as R

PNG = b"\x89PNG\r\n\x1a\n"


def _check(paths, expected):
    assert sorted(p.name for p in paths) == sorted(expected)
    for p in paths:
        data = p.read_bytes()
        assert data[:8] == PNG and len(data) > 5000, p


def test_plot_writes_every_figure(tmp_path, capsys):
    # isostatic low-energy cells (Delta Z = 0 exactly) must not break the log axes
    camp = SyntheticCampaign(N=(64, 128, 256), seeds=6, truth=Truth(iso_E=1e-10))
    write_store(tmp_path / "c.h5", camp)
    assert cli.main(["plot", str(tmp_path / "c.h5"), "--out", str(tmp_path / "fig"),
                     "--boot", "20"]) == 0
    _check(list((tmp_path / "fig").glob("*.png")), [f"{n}.png" for n in plots.FIGURES])
    assert f"wrote {len(plots.FIGURES)} figures" in capsys.readouterr().err


def test_plot_survives_missing_cells_histograms_and_variants(tmp_path):
    camp = SyntheticCampaign(N=(64,), E=(1e-3, 1e-9), seeds=3, variants=("default", "hertz"),
                             histograms=("z_g",))
    st = np.ones(camp.n_tasks, np.int8)
    st[:4] = 0
    write_store(tmp_path / "p.h5", camp, status=st)
    red = R.reduce_campaign(tmp_path / "p.h5", R.Settings(n_boot=0))
    written = plots.make_figures(red, tmp_path / "f")
    # one set per variant, and the campaign-wide cost-against-deviation figure
    _check(written, [f"{n}_{v}.png" for n in plots.FIGURES for v in ("default", "hertz")] + ["pareto.png"])
