"""A_G and A_V are fractions of the box area: the same packing in a larger, smaller or
stretched box, and campaigns on boxes of other shapes, give the same numbers."""

import json
import math

import numpy as np
import pytest

import kernels
from campaign import cli
from kernels.analysis import analyze
from helpers import triangular_crystal


@pytest.mark.parametrize("box", [(1.0, 1.0), (1.5, 1.0)])
def test_same_packing_scaled_into_boxes_of_area_half_one_and_two(box):
    p = kernels.jam(128, 1e-8, 3, box=box)
    base = analyze(p.positions, p.radii, p.box)
    assert base.ok
    a0 = base.scalars["A_G"]
    assert 0.4 < a0 < 0.5  # a fraction, like phi
    for area in (0.5, 1.0, 2.0):
        f = math.sqrt(area / (box[0] * box[1]))
        s = analyze(p.positions * f, p.radii * f, p.box * f).scalars
        assert s["A_G"] == pytest.approx(a0, rel=1e-12)
        assert s["A_V"] == pytest.approx(1.0 - a0, rel=1e-9)
        assert s["area_G"] == pytest.approx(area * a0, rel=1e-12)
        assert s["phi"] == pytest.approx(p.phi, rel=1e-12)


def test_crystal_in_a_small_box_through_the_command_line(tmp_path, capsys):
    """The triangular crystal covers 3/4 of any box it fills (here of area 0.55)."""
    pos, rad, box = triangular_crystal(8, 8, overlap=1e-7, a=0.1)
    assert box[0] * box[1] == pytest.approx(0.554, abs=1e-3)
    path = tmp_path / "crystal.txt"
    lines = [f"{float(box[0])!r} {float(box[1])!r}"] + [f"{float(x)!r} {float(y)!r} {float(r)!r}"
                                                         for (x, y), r in zip(pos, rad)]
    path.write_text("\n".join(lines) + "\n")
    assert cli.main(["analyze", str(path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["A_G"] == pytest.approx(0.75, abs=1e-6)
    assert s["A_V"] == pytest.approx(0.25, abs=1e-6)


SPEC = """\
name: box-{tag}
seed: 77
system: {{box: [{lx}, 1.0]}}
grid: {{N_G: [96], E_G: {{log_range: [1.0e-10, 1.0e-4], per_decade: 1}}, seeds: 8}}
observables: [scalars]
"""


def test_campaign_on_a_wide_box_gives_the_unit_box_A_G_star(tmp_path, capsys):
    """Packings in a 1.5 x 1 box and a unit box give the same A_G* within errors (it was 1.5
    times larger when A_G was an absolute area)."""
    out = {}
    for tag, lx in (("unit", 1.0), ("wide", 1.5)):
        spec = tmp_path / f"{tag}.yaml"
        spec.write_text(SPEC.format(tag=tag, lx=lx))
        h5 = tmp_path / f"{tag}.h5"
        assert cli.main(["run", str(spec), "--out", str(h5), "--workers", "2"]) == 0
        assert cli.main(["reduce", str(h5), "--out", str(tmp_path / tag), "--json", "--boot", "200"]) == 0
        (row,) = json.loads(capsys.readouterr().out)["rows"]
        out[tag] = row
    u, w = out["unit"], out["wide"]
    assert 0.40 < u["A_G_star_E"] < 0.47 and 0.40 < w["A_G_star_E"] < 0.47
    err = math.hypot(u["A_G_star_E_err"], w["A_G_star_E_err"])
    assert abs(u["A_G_star_E"] - w["A_G_star_E"]) < 3 * err, (u["A_G_star_E"], w["A_G_star_E"], err)
