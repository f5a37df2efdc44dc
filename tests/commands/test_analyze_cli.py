"""``campaign analyze CONFIG``: reading other programs' files, JSON output, malformed input.

Each malformed input has its own test: exit status 2, a message naming the file, the
line (or array) where it applies and what was expected, and no traceback.
"""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from campaign.cli import main as cli_main
from kernels.analysis import analyze

DATA = Path(__file__).resolve().parents[1] / "data"
EXAMPLE = DATA / "config_packing32.txt"
REQUIRED = ["N", "N_G", "N_R", "E_G", "phi", "pressure", "A_G", "A_V", "N_C", "N_V", "N_F",
            "z_g_mean", "z_iso", "delta_Z", "psi_O", "psi_DO", "identities_ok"]


def _example_arrays():
    rows = [line.split() for line in EXAMPLE.read_text().splitlines() if line and not line.startswith("#")]
    box = np.array([float(x) for x in rows[0]])
    arr = np.array([[float(x) for x in r] for r in rows[1:]])
    return arr[:, :2], arr[:, 2], box


def run(args, capsys):
    code = cli_main(["analyze", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def _user_error(capsys, path, *args, expect=()):
    code, out, err = run([path, *args], capsys)
    assert code == 2, (out, err)
    assert "Traceback" not in err and "Traceback" not in out
    assert str(path) in err
    for piece in expect:
        assert piece in err, (piece, err)
    return err


def _write(tmp_path, text, name="c.txt"):
    p = tmp_path / name
    p.write_text(text)
    return p


GOOD_HEAD = "1 1\n0.1 0.1 0.05\n0.5 0.5 0.05\n"


# ----------------------------------------------------------------------------- good input


def test_json_keys_and_values_match_analyze(capsys):
    code, out, err = run([EXAMPLE, "--json"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert set(REQUIRED) <= set(data)
    pos, rad, box = _example_arrays()
    res = analyze(pos, rad, box, ["scalars"])
    for k in REQUIRED:
        v = res.scalars[k]
        if isinstance(v, float) and math.isnan(v):
            assert data[k] is None
        else:
            assert data[k] == v, k
    assert data["identities_ok"] is True
    assert data["identities"] == res.identities
    assert "histograms" not in data


def test_json_with_histograms(capsys):
    code, out, _ = run([EXAMPLE, "--json", "--observables", "connectivity,contact_angles"], capsys)
    assert code == 0
    data = json.loads(out)
    assert set(data["histograms"]) == {"z_g", "z_v", "contact_angle"}
    assert sum(data["histograms"]["z_g"]["counts"]) == data["N_G"]
    assert sum(data["histograms"]["z_v"]["counts"]) == data["N_V"]
    assert len(data["histograms"]["z_v"]["edges"]) == len(data["histograms"]["z_v"]["counts"]) + 1


def test_npz_and_hdf5_give_the_same_result(tmp_path, capsys):
    pos, rad, box = _example_arrays()
    np.savez(tmp_path / "c.npz", positions=pos, radii=rad, box=box)
    with h5py.File(tmp_path / "c.h5", "w") as fh:
        g = fh.create_group("configurations/abc")
        g["positions"], g["radii"], g["box"] = pos, rad, box
    outs = []
    for args in ([EXAMPLE], [tmp_path / "c.npz"], [tmp_path / "c.h5", "--group", "/configurations/abc"]):
        code, out, err = run([*args, "--json"], capsys)
        assert code == 0, err
        outs.append(json.loads(out))
    assert outs[0] == outs[1] == outs[2]


def test_human_output(capsys):
    code, out, _ = run([EXAMPLE], capsys)
    assert code == 0
    assert "N_G" in out and "identities:" in out and "euler" in out


def test_comments_commas_and_square_box_line(tmp_path, capsys):
    p = _write(tmp_path, "# made by hand\n\n1.0   # one side: square box\n0.1, 0.1, 0.05\n0.5 0.5 0.05  # second\n")
    code, out, err = run([p, "--json"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert data["N"] == 2 and data["N_C"] == 0 and data["identities_ok"] is False
    assert data["phi"] == pytest.approx(2 * math.pi * 0.05**2)


def test_console_script_subprocess():
    proc = subprocess.run([sys.executable, "-m", "campaign", "analyze", str(EXAMPLE), "--json"],
                          capture_output=True, text=True, timeout=300, env={**os.environ})
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["N"] == 32
    proc = subprocess.run([sys.executable, "-m", "campaign", "analyze", "/nonexistent/config.txt"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and "/nonexistent/config.txt" in proc.stderr


# ----------------------------------------------------------------------------- malformed input


def test_missing_file(tmp_path, capsys):
    _user_error(capsys, tmp_path / "absent.txt", expect=["no such file"])


def test_wrong_column_count(tmp_path, capsys):
    p = _write(tmp_path, GOOD_HEAD + "0.3 0.3\n")
    _user_error(capsys, p, expect=["line 4", "expected 3 columns", "got 2"])


def test_too_many_columns(tmp_path, capsys):
    p = _write(tmp_path, GOOD_HEAD + "0.3 0.3 0.05 7\n")
    _user_error(capsys, p, expect=["line 4", "expected 3 columns", "got 4"])


def test_bad_box_line(tmp_path, capsys):
    p = _write(tmp_path, "1 1 0.1 1\n0.1 0.1 0.05\n0.5 0.5 0.05\n")  # 'Lx Ly xy' is a tilted cell
    _user_error(capsys, p, expect=["line 1", "box line"])


def test_not_a_number(tmp_path, capsys):
    p = _write(tmp_path, GOOD_HEAD + "0.3 abc 0.05\n")
    _user_error(capsys, p, expect=["line 4", "expected a number", "'abc'"])


def test_nan_value(tmp_path, capsys):
    p = _write(tmp_path, GOOD_HEAD + "0.3 nan 0.05\n")
    _user_error(capsys, p, expect=["line 4", "finite"])


def test_infinite_value(tmp_path, capsys):
    p = _write(tmp_path, GOOD_HEAD + "inf 0.3 0.05\n")
    _user_error(capsys, p, expect=["line 4", "finite"])


def test_negative_radius(tmp_path, capsys):
    p = _write(tmp_path, GOOD_HEAD + "0.3 0.3 -0.05\n")
    _user_error(capsys, p, expect=["line 4", "positive radius", "-0.05"])


def test_zero_radius(tmp_path, capsys):
    p = _write(tmp_path, "1 1\n0.1 0.1 0\n0.5 0.5 0.05\n")
    _user_error(capsys, p, expect=["line 2", "positive radius"])


def test_zero_box(tmp_path, capsys):
    p = _write(tmp_path, "1 0\n0.1 0.1 0.05\n0.5 0.5 0.05\n")
    _user_error(capsys, p, expect=["line 1", "positive box sides"])


def test_negative_box(tmp_path, capsys):
    p = _write(tmp_path, "# box\n-1 1\n0.1 0.1 0.05\n0.5 0.5 0.05\n")
    _user_error(capsys, p, expect=["line 2", "positive box sides"])


def test_fewer_than_two_disks(tmp_path, capsys):
    p = _write(tmp_path, "1 1\n0.1 0.1 0.05\n")
    _user_error(capsys, p, expect=["at least 2 disks", "got 1"])


def test_empty_file(tmp_path, capsys):
    p = _write(tmp_path, "# nothing here\n")
    _user_error(capsys, p, expect=["empty", "box line"])


def test_position_far_outside_box(tmp_path, capsys):
    p = _write(tmp_path, GOOD_HEAD + "0.3 0.3 0.05\n5.0 0.3 0.05\n")
    _user_error(capsys, p, expect=["line 5", "far outside the box"])


def test_radius_too_large_for_box(tmp_path, capsys):
    p = _write(tmp_path, "1 1\n0.1 0.1 0.05\n0.5 0.5 0.3\n")
    _user_error(capsys, p, expect=["line 3", "half the smaller box side"])


def test_binary_file_as_text(tmp_path, capsys):
    p = tmp_path / "c.dat"
    p.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00")
    _user_error(capsys, p, expect=["not a text file"])


def test_npz_missing_array(tmp_path, capsys):
    p = tmp_path / "c.npz"
    np.savez(p, positions=np.zeros((3, 2)), radii=np.full(3, 0.1))
    _user_error(capsys, p, expect=["missing box"])


def test_npz_wrong_shape(tmp_path, capsys):
    p = tmp_path / "c.npz"
    np.savez(p, positions=np.zeros((3, 3)), radii=np.full(3, 0.1), box=np.ones(2))
    _user_error(capsys, p, expect=["'positions'", "expected shape (n, 2)"])


def test_npz_nan(tmp_path, capsys):
    p = tmp_path / "c.npz"
    pos = np.array([[0.1, 0.1], [0.5, np.nan], [0.7, 0.7]])
    np.savez(p, positions=pos, radii=np.full(3, 0.1), box=np.ones(2))
    _user_error(capsys, p, expect=["'positions', row 1", "finite"])


def test_npz_not_an_archive(tmp_path, capsys):
    p = _write(tmp_path, "hello", name="c.npz")
    _user_error(capsys, p, expect=["not a readable .npz"])


def test_hdf5_missing_dataset(tmp_path, capsys):
    p = tmp_path / "c.h5"
    with h5py.File(p, "w") as fh:
        fh["positions"] = np.zeros((3, 2))
        fh["box"] = np.ones(2)
    _user_error(capsys, p, expect=["missing radii"])


def test_hdf5_missing_group(tmp_path, capsys):
    p = tmp_path / "c.h5"
    with h5py.File(p, "w") as fh:
        fh["positions"] = np.zeros((3, 2))
    _user_error(capsys, p, "--group", "/configurations/nope", expect=["no group"])


def test_unknown_observable(capsys):
    code, out, err = run([EXAMPLE, "--observables", "scalars,bogus"], capsys)
    assert code == 2 and "bogus" in err and "Traceback" not in err


def test_npz_scalar_box_and_species(tmp_path, capsys):
    pos, rad, box = _example_arrays()
    species = (rad < rad.max()).astype(np.int32)
    np.savez(tmp_path / "c.npz", positions=pos, radii=rad, box=np.float64(box[0]), species=species)
    code, out, err = run([tmp_path / "c.npz", "--json"], capsys)
    assert code == 0, err
    assert json.loads(out)["N"] == 32


def test_npz_bad_species(tmp_path, capsys):
    pos, rad, box = _example_arrays()
    np.savez(tmp_path / "c.npz", positions=pos, radii=rad, box=box, species=np.zeros(5, dtype=int))
    _user_error(capsys, tmp_path / "c.npz", expect=["'species'", "(32,)"])


def test_directory_instead_of_file(tmp_path, capsys):
    _user_error(capsys, tmp_path, expect=["is a directory"])


def test_hdf5_not_readable(tmp_path, capsys):
    p = _write(tmp_path, "not hdf5", name="c.h5")
    _user_error(capsys, p, expect=["not a readable HDF5 file"])


def test_header_words_instead_of_box(tmp_path, capsys):
    p = _write(tmp_path, "Lx Ly\n1 1\n0.1 0.1 0.05\n0.5 0.5 0.05\n")
    _user_error(capsys, p, expect=["line 1", "expected a number for a box side", "'Lx'"])


def test_crlf_line_endings(tmp_path, capsys):
    p = tmp_path / "c.txt"
    p.write_bytes(EXAMPLE.read_bytes().replace(b"\n", b"\r\n"))
    code, out, err = run([p, "--json"], capsys)
    assert code == 0, err
    code0, out0, _ = run([EXAMPLE, "--json"], capsys)
    assert json.loads(out) == json.loads(out0)
