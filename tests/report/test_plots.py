"""Every figure is written, for complete and for partly finished campaigns, and draws the
reduction's numbers: the finite-size rows and the extrapolated value where the extrapolation
figure puts its markers, the cells' means behind the scaling figure's axes."""

import matplotlib  # noqa: F401 - the test extra installs it; a missing one must fail, not skip
import numpy as np
import pytest
from synthetic_store import SyntheticCampaign, Truth, write_store

from campaign import cli

from campaign.report import plots
from campaign.results import reduce as R

PNG = b"\x89PNG\r\n\x1a\n"


def _check(paths, expected):
    assert sorted(p.name for p in paths) == sorted(expected)
    for p in paths:
        data = p.read_bytes()
        assert data[:8] == PNG and len(data) > 5000, p


def _recording(monkeypatch):
    """Record every per-variant figure ``make_figures`` draws, with the reduction it drew."""
    drawn = []

    def wrap(name, fn):
        def draw(red, cs, plt):
            fig = fn(red, cs, plt)
            drawn.append((name, cs.v, red, fig))
            return fig
        return draw

    monkeypatch.setattr(plots, "FIGURES", {n: wrap(n, f) for n, f in plots.FIGURES.items()})
    return drawn


def _points(ax, marker, filled=True):
    """(x, y) of the markers of one style on an axis (errorbar's data lines)."""
    out = []
    for line in ax.lines:
        if line.get_marker() != marker or line.get_linestyle() not in ("None", "none", ""):
            continue
        if (line.get_markerfacecolor() != "none") != filled:
            continue
        out += list(zip(np.asarray(line.get_xdata(), float), np.asarray(line.get_ydata(), float)))
    return sorted(out)


def _check_extrapolation(red, v, fig, every_size=True):
    """The finite-size rows at x = 1/N_G (``every_size``: a finite value expected for every
    size) and, where the reduction has one, the extrapolated value at x = 0 (nothing there
    where it has none), for A_G* (left axis) and Psi_O* (right axis); every drawn value finite."""
    rows = [r for r in red.rows if r["variant"] == v]
    ex = red.extrapolated[v]
    for ax, key in zip(fig.axes[:2], ("A_G_star_E", "psi_O_star")):
        want = sorted((1.0 / r["N_G"], r[key]) for r in rows if np.isfinite(r[key]))
        if every_size:
            assert want and len(want) == len(rows), (v, key, rows)
        got = _points(ax, "o")
        assert np.isfinite(np.asarray(got, float)).all(), got
        sizes = [p for p in got if p[0] > 0]
        assert [x for x, _ in sizes] == pytest.approx([x for x, _ in want], rel=1e-12)
        assert [y for _, y in sizes] == pytest.approx([y for _, y in want], rel=1e-12)
        assert not [p for p in got if p[0] == 0]
        at_zero = _points(ax, "o", filled=False)  # the extrapolated value: an open marker
        if np.isfinite(ex[key]):
            assert at_zero == [(0.0, pytest.approx(ex[key], rel=1e-12))]
        else:
            assert at_zero == []


def _check_scaling(red, v, fig):
    """Filled markers of Delta A_G against E_G: cells' mean E_G and mean A_G minus the fit's
    intercept, one marker per fitted cell."""
    c = red.cells
    mine = np.asarray(c["variant"]).astype(str) == v
    got = _points(fig.axes[0], "o")
    assert got and np.isfinite(np.asarray(got)).all()
    cells = []
    for f in red.fits:
        if f["variant"] == v and f["quantity"] == "A_G" and f["abscissa"] == "E_G" and f["ok"]:
            i = np.flatnonzero(mine & (np.asarray(c["N"]) == f["N_G"]))
            cells += [(c["mean_E_G"][k], c["mean_A_G"][k] - f["intercept"]) for k in i]
    for x, y in got:
        assert any(x == pytest.approx(a, rel=1e-12) and y == pytest.approx(b, rel=1e-9) for a, b in cells), (x, y)


def test_plot_writes_every_figure(tmp_path, capsys, monkeypatch):
    drawn = _recording(monkeypatch)
    # isostatic low-energy cells (Delta Z = 0 exactly) must not break the log axes
    camp = SyntheticCampaign(N=(64, 128, 256), seeds=6, truth=Truth(iso_E=1e-10))
    write_store(tmp_path / "c.h5", camp)
    assert cli.main(["plot", str(tmp_path / "c.h5"), "--out", str(tmp_path / "fig"),
                     "--boot", "20"]) == 0
    _check(list((tmp_path / "fig").glob("*.png")), [f"{n}.png" for n in plots.FIGURES])
    assert f"wrote {len(plots.FIGURES)} figures" in capsys.readouterr().err
    figs = {name: (red, fig) for name, v, red, fig in drawn}
    assert set(figs) == set(plots.FIGURES)
    red, fig = figs["extrapolation"]
    _check_extrapolation(red, "default", fig)
    red, fig = figs["scaling_A_G"]
    _check_scaling(red, "default", fig)


@pytest.mark.slow
def test_plot_survives_missing_cells_histograms_and_variants(tmp_path, monkeypatch):
    camp = SyntheticCampaign(N=(64,), E=(1e-3, 1e-9), seeds=3, variants=("default", "hertz"),
                             histograms=("z_g",))
    st = np.ones(camp.n_tasks, np.int8)
    st[:4] = 0
    write_store(tmp_path / "p.h5", camp, status=st)
    red = R.reduce_campaign(tmp_path / "p.h5", R.Settings(n_boot=0))
    drawn = _recording(monkeypatch)
    written = plots.make_figures(red, tmp_path / "f")
    extrapolations = {v: fig for name, v, _, fig in drawn if name == "extrapolation"}
    assert set(extrapolations) == {"default", "hertz"}
    for v, fig in extrapolations.items():  # one size, two energies: rows without a fit draw nothing
        _check_extrapolation(red, v, fig, every_size=False)
    # one set per variant, and the campaign-wide figures: cost against deviation, and the protocols
    # compared (A_G against Delta Z per variant; no N_G -> inf value to compare with one size)
    _check(written, [f"{n}_{v}.png" for n in plots.FIGURES for v in ("default", "hertz")]
           + ["pareto.png", "protocols.png"])
