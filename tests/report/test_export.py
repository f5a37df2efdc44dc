"""Results where physicists work: ``campaign.read_packings``/``read_cells`` (pandas), ``campaign
export`` to CSV, Parquet, GSD and extended XYZ, and those frames read back by ``campaign analyze``
and ``campaign draw``.

Every expectation is computed independently of the code under test: the store's columns read
with plain h5py (the README's rule for the rows the reducer uses), the exported files read with
their own libraries (pandas, pyarrow, gsd, ASE) or the csv module.
"""

import csv
import json
import sys
import tracemalloc

import h5py
import numpy as np
import pandas as pd  # the test extra installs pandas, pyarrow, gsd and ase: nothing here skips
import pytest

import campaign
from campaign import cli
from campaign.errors import MissingExtra, UserError
from helpers import reseal

REAL_SPEC = """\
name: exporttest
seed: 11
grid: {N_G: [64], E_G: [1.0e-12, 1.0e-4], seeds: 2}
variants:
  - {name: capped, max_steps: 20}   # stopped early: finished, but left out by the reducer
observables: [scalars, connectivity]
store: {configurations: true}
"""

SYNTH_SPEC = """\
name: synthexport
seed: 3
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 4}
variants:
  - {name: loose, force_tolerance: 1.0e-3}
observables: [scalars, connectivity]
run: {retries: 0}
"""


def _run(spec_text, d, name, *extra):
    spec, out = d / f"{name}.yaml", d / f"{name}.h5"
    spec.write_text(spec_text)
    assert cli.main(["run", str(spec), "--out", str(out), "--launcher", "inline", "--quiet", *extra]) == 0
    return out


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    """A real campaign (kernels): N_G = 64 at E_G = 1e-12 and 1e-4, configurations kept; the
    'capped' variant's packings are finished with jam_status != 0."""
    return _run(REAL_SPEC, tmp_path_factory.mktemp("real"), "real")


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """A synthetic campaign without configurations, with failed rows (seed 1), and rows marked
    by hand: one pending again, two with jam_status != 0, one with identities_ok = 0."""
    d = tmp_path_factory.mktemp("synth")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("CAMPAIGN_SYNTHETIC_FAIL", "seed:1")
        out = _run(SYNTH_SPEC, d, "synth", "--task-function", "synthetic")
    with h5py.File(out, "r+") as f:
        st = f["tasks/status"][:]
        done = np.flatnonzero(st == 1)
        st[done[0]] = 0
        f["tasks/status"][:] = st
        js, ok = f["scalars/jam_status"][:], f["scalars/identities_ok"][:]
        js[done[[3, 9]]] = 2.0
        ok[done[5]] = 0.0
        f["scalars/jam_status"][:], f["scalars/identities_ok"][:] = js, ok
        reseal(f, "tasks/status", "scalars/jam_status", "scalars/identities_ok")
    return out


def _h5(path):
    """The store read with plain h5py: the task columns, every scalar, the README's good rows."""
    with h5py.File(path, "r", locking=False) as f:
        t = {k: f[f"tasks/{k}"][:] for k in ("id", "variant", "N", "E", "seed", "status")}
        t["id"] = t["id"].astype(str)
        t["variant"] = t["variant"].astype(str)
        s = {k: f[f"scalars/{k}"][:] for k in f["scalars"]}
    done = t["status"] == 1
    good = done & (s["jam_status"] == 0) & (s["identities_ok"] == 1)
    return t, s, done, good


def _bits_equal(a, b):
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype.kind == "f":
        return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint64), b.view(np.uint64))
    return a.dtype.kind == b.dtype.kind and np.array_equal(a, b)


def _assert_frame_matches(df, path, rows):
    t, s, _, _ = _h5(path)
    assert df.index.name == "row" and np.array_equal(df.index.to_numpy(), rows)
    assert list(df.columns[:6]) == ["id", "variant", "N", "E", "seed", "status"]
    assert set(df.columns[6:]) == set(s) - {"N"}  # the scalar N is the task's N
    assert np.array_equal(s["N"][rows], t["N"][rows])
    for k in ("N", "E", "seed", "status"):
        assert df[k].dtype == t[k].dtype and _bits_equal(df[k].to_numpy(), t[k][rows]), k
    for k in ("id", "variant"):
        assert df[k].tolist() == t[k][rows].tolist(), k
    for k in df.columns[6:]:
        assert _bits_equal(df[k].to_numpy(), s[k][rows]), k


# ----------------------------------------------------------------------------- DataFrames


def test_read_packings_is_the_store_bit_for_bit(real):
    t, s, done, good = _h5(real)
    assert good.sum() == 4 and done.sum() == 8  # the capped packings are finished, not good
    _assert_frame_matches(campaign.read_packings(real), real, np.flatnonzero(good))
    _assert_frame_matches(campaign.read_packings(real, good=False), real, np.flatnonzero(done))
    cap = campaign.read_packings(str(real), variant="capped", good=False)
    _assert_frame_matches(cap, real, np.flatnonzero(done & (t["variant"] == "capped")))
    assert campaign.read_packings(real, variant=["capped"]).empty


def test_read_packings_keeps_the_rows_the_reducer_uses(synth):
    from campaign.results.finished import load_finished

    t, s, done, good = _h5(synth)
    assert (t["status"] == 2).any() and (t["status"] == 0).any() and (done & ~good).sum() == 3
    df = campaign.read_packings(synth)
    _assert_frame_matches(df, synth, np.flatnonzero(good))
    everything = load_finished(synth)  # the reducer's own reading
    mask, _ = everything.usable()
    assert sorted(df["id"]) == sorted(everything.ids[mask].tolist())
    small = campaign.read_packings(synth, good=False, block=256)  # many blocks: the same rows
    _assert_frame_matches(small, synth, np.flatnonzero(done))
    loose = campaign.read_packings(synth, variant="loose")
    _assert_frame_matches(loose, synth, np.flatnonzero(good & (t["variant"] == "loose")))


def test_read_cells_is_the_reducers_table(synth, tmp_path, capsys):
    cells = campaign.read_cells(synth)
    assert cli.main(["reduce", str(synth), "--out", str(tmp_path / "r"), "--boot", "0"]) == 0
    capsys.readouterr()
    with h5py.File(tmp_path / "r" / "reduced.h5", "r") as f:
        g = f["reduced/cells"]
        assert set(cells.columns) == set(g)
        for k in g:
            ref = g[k][:]
            if ref.dtype.kind in "OS":
                assert cells[k].tolist() == ref.astype(str).tolist()
            else:
                assert np.array_equal(cells[k].to_numpy(), ref, equal_nan=True), k
    # and the counts agree with the packings read_packings gives
    df = campaign.read_packings(synth)
    n = df.groupby(["variant", "N", "E"]).size()
    for _, c in cells.iterrows():
        assert c["n_packings"] == n.get((c["variant"], c["N"], c["E"]), 0)
        sel = df[(df.variant == c["variant"]) & (df.N == c["N"]) & (df.E == c["E"])]
        if len(sel):
            assert c["mean_A_G"] == pytest.approx(sel["A_G"].mean(), rel=1e-12)


def test_read_packings_reads_no_histogram(tmp_path):
    """A store of 40 000 rows whose histogram counts would take 640 MB: read in blocks, the
    histograms untouched, the peak stays that of the scalars."""
    T, nb = 40_000, 2000
    path = tmp_path / "big.h5"
    rng = np.random.default_rng(1)
    with h5py.File(path, "w") as f:
        f.attrs.update(schema="jamming-campaign/1", format_version=2, name="big")
        t = f.create_group("tasks")
        t["id"] = np.array([f"{i:032x}" for i in range(T)], dtype="S32")
        t["variant"] = np.array(["default"] * T, dtype="S64")
        t["N"] = np.full(T, 1024, np.int64)
        t["E"] = np.full(T, 1e-6)
        t["seed"] = np.arange(T, dtype=np.int64)
        t["status"] = np.ones(T, np.int8)
        s = f.create_group("scalars")
        s["A_G"] = rng.random(T)
        s["jam_status"] = np.where(np.arange(T) % 7 == 0, 1.0, 0.0)
        s["identities_ok"] = np.ones(T)
        f.create_dataset("histograms/z_v/counts", shape=(T, nb), dtype=np.int64, chunks=(256, nb),
                         compression="gzip")
        f["histograms/z_v/edges"] = np.arange(nb + 1) - 0.5
    tracemalloc.start()
    try:
        df = campaign.read_packings(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(df) == T - len(range(0, T, 7))
    assert peak < 60e6, f"peak {peak / 1e6:.0f} MB: more than the scalars' few MB"


def test_missing_pandas_is_a_clear_error(real, monkeypatch):
    monkeypatch.setitem(sys.modules, "pandas", None)
    for fn in (campaign.read_packings, campaign.read_cells):
        with pytest.raises(MissingExtra, match=r"pip install 'jamming-campaign\[frames\]'") as e:
            fn(real)
        assert isinstance(e.value, ImportError) and isinstance(e.value, UserError)


def test_read_packings_refuses_foreign_files(tmp_path):
    with pytest.raises(UserError, match="no such file"):
        campaign.read_packings(tmp_path / "nope.h5")
    with h5py.File(tmp_path / "x.h5", "w") as f:
        f["data"] = [1, 2]
    with pytest.raises(UserError, match="not a campaign store"):
        campaign.read_packings(tmp_path / "x.h5")
    (tmp_path / "t.h5").write_text("text")
    with pytest.raises(UserError, match="not a readable HDF5 file"):
        campaign.read_packings(tmp_path / "t.h5")


# ----------------------------------------------------------------------------- export: tables


def _serial_ase(monkeypatch):
    """ASE talks to MPI when mpi4py is imported, as it is once a campaign has run in this process
    (without initialising MPI): MPICH would abort. The tests read serially."""
    import ase.parallel

    monkeypatch.setattr(ase.parallel.world, "comm", ase.parallel.DummyMPI())


def _export(capsys, *args):
    code = cli.main(["export", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def test_parquet_round_trip(real, tmp_path, capsys):
    import pyarrow.parquet as pq

    out = tmp_path / "p.parquet"
    code, _, err = _export(capsys, real, "--out", out)
    assert code == 0 and "4 row(s)" in err
    back = pd.read_parquet(out).set_index("row")
    _assert_frame_matches(back, real, np.flatnonzero(_h5(real)[3]))
    meta = json.loads(pq.read_schema(out).metadata[b"campaign"])
    assert meta["name"] == "exporttest" and meta["good"] is True
    code, _, _ = _export(capsys, real, "--format", "parquet", "--out", out, "--all-finished")
    assert code == 0 and len(pq.read_table(out)) == 8


def test_csv_round_trip_at_full_precision(real, tmp_path, capsys):
    out = tmp_path / "p.csv"
    code, _, err = _export(capsys, real, "--format", "csv", "--out", out, "--all-finished")
    assert code == 0, err
    t, s, done, _ = _h5(real)
    rows = np.flatnonzero(done)
    with open(out, newline="") as fh:
        table = list(csv.reader(fh))
    head, body = table[0], table[1:]
    assert head[:7] == ["row", "id", "variant", "N", "E", "seed", "status"] and len(body) == len(rows)
    col = {h: [r[i] for r in body] for i, h in enumerate(head)}
    assert [int(x) for x in col["row"]] == rows.tolist()
    assert col["id"] == t["id"][rows].tolist()
    for k in ("N", "seed", "status"):
        assert [int(x) for x in col[k]] == t[k][rows].tolist()
    assert _bits_equal(np.array([float(x) for x in col["E"]]), t["E"][rows])
    for k in set(s) - {"N"}:
        assert _bits_equal(np.array([float(x) for x in col[k]]), s[k][rows]), k
    # pandas reads it back too (before pandas 3 its default float parser may miss the last bit)
    exact = {} if int(pd.__version__.split(".")[0]) >= 3 else {"float_precision": "round_trip"}
    back = pd.read_csv(out, **exact).set_index("row")
    assert _bits_equal(back["A_G"].to_numpy(), s["A_G"][rows])


# ----------------------------------------------------------------------------- export: frames


def _store_configuration(path, tid):
    with h5py.File(path, "r") as f:
        g = f[f"configurations/{tid}"]
        return {k: g[k][()] for k in ("positions", "radii", "box", "species")}


def test_gsd_frames_read_with_the_gsd_package(real, tmp_path, capsys):
    import gsd.hoomd

    out = tmp_path / "p.gsd"
    code, _, err = _export(capsys, real, "--format", "gsd", "--out", out)
    assert code == 0 and "4 frame(s)" in err
    t, s, _, good = _h5(real)
    rows = np.flatnonzero(good)
    with gsd.hoomd.open(str(out), "r") as traj:
        assert len(traj) == len(rows)
        for k, r in enumerate(rows):
            fr = traj[k]
            c = _store_configuration(real, t["id"][r])
            L = c["box"]
            assert fr.configuration.dimensions == 2 and fr.particles.N == len(c["radii"])
            assert np.array_equal(fr.configuration.box, np.array([L[0], L[1], 1, 0, 0, 0], np.float32))
            assert fr.particles.types == ["A", "B"]
            assert np.array_equal(fr.particles.typeid, c["species"])
            pos32 = fr.particles.position
            assert pos32.dtype == np.float32 and np.all(pos32[:, 2] == 0)
            assert np.all(pos32[:, :2] >= -L.astype(np.float32) / 2) and np.all(pos32[:, :2] < L.astype(np.float32) / 2)
            # float32 positions: HOOMD's centred box, within float32 rounding of the packing
            d = pos32[:, :2].astype(np.float64) - (c["positions"] - L / 2)
            d -= L * np.round(d / L)
            assert np.max(np.abs(d)) <= 2 * np.finfo(np.float32).eps * L.max()
            assert np.array_equal(fr.particles.diameter, (2 * c["radii"]).astype(np.float32))
            # float64 in the log: exactly the stored packing
            assert _bits_equal(fr.log["particles/campaign/position64"], c["positions"])
            assert _bits_equal(fr.log["particles/campaign/radius64"], c["radii"])
            assert _bits_equal(fr.log["campaign/box64"], L)
            assert bytes(fr.log["campaign/id"].astype(np.uint8)).decode() == t["id"][r]
            assert fr.log["campaign/row"][0] == r and fr.log["campaign/N"][0] == t["N"][r]
            for name in ("A_G", "N_G", "psi_O", "E_G"):
                assert _bits_equal(fr.log[f"campaign/{name}"], s[name][r:r + 1]), name
    logged = gsd.hoomd.read_log(str(out), scalar_only=True)  # the scalars as a time series
    assert _bits_equal(logged["log/campaign/A_G"], s["A_G"][rows])


def test_float32_positions_alone_are_not_the_packing(real, tmp_path, capsys):
    """Why the frames keep float64: at E_G = 1e-12 the schema's float32 data give another
    contact network (here for one of the two packings at N = 64)."""
    import gsd.hoomd

    from kernels.analysis import analyze

    out = tmp_path / "p.gsd"
    assert _export(capsys, real, "--out", out)[0] == 0
    t, s, _, good = _h5(real)
    rows = np.flatnonzero(good)
    differ = 0
    with gsd.hoomd.open(str(out), "r") as traj:
        for k, r in enumerate(rows):
            fr = traj[k]
            L = fr.log["campaign/box64"]
            a = analyze(fr.particles.position[:, :2].astype(np.float64) + L / 2,
                        fr.particles.diameter.astype(np.float64) / 2, L, ["scalars"])
            differ += t["E"][r] == 1e-12 and a.scalars["N_C"] != s["N_C"][r]
    assert differ >= 1


def test_extended_xyz_read_by_ase(real, tmp_path, capsys, monkeypatch):
    import ase.io as ase_io

    _serial_ase(monkeypatch)
    out = tmp_path / "p.xyz"
    code, _, err = _export(capsys, real, "--out", out, "--all-finished")
    assert code == 0 and "8 frame(s)" in err
    t, s, done, _ = _h5(real)
    rows = np.flatnonzero(done)
    frames = ase_io.read(str(out), index=":", format="extxyz")
    assert len(frames) == len(rows)
    for atoms, r in zip(frames, rows):
        c = _store_configuration(real, t["id"][r])
        L = c["box"]
        assert np.array_equal(atoms.cell.array, np.diag([L[0], L[1], 1.0]))
        assert atoms.pbc.tolist() == [True, True, False]
        assert _bits_equal(atoms.positions[:, :2].copy(), c["positions"]) and np.all(atoms.positions[:, 2] == 0)
        assert _bits_equal(atoms.arrays["radius"], c["radii"])
        assert atoms.arrays["type"].tolist() == np.array(["A", "B"])[c["species"]].tolist()
        assert atoms.info["id"] == t["id"][r] and atoms.info["variant"] == t["variant"][r]
        assert atoms.info["row"] == r and atoms.info["seed"] == t["seed"][r]
        for name in ("A_G", "psi_O", "E_G", "pressure"):  # psi_O is NaN for some capped packings
            assert _bits_equal(np.float64(atoms.info[name]), s[name][r]), name
        assert atoms.info["N_G"] == s["N_G"][r] and atoms.info["exponent"] == 2.0


@pytest.mark.parametrize("fmt", ["gsd", "xyz"])
def test_analyze_an_exported_frame_gives_the_stores_scalars(real, tmp_path, capsys, fmt):
    out = tmp_path / f"p.{fmt}"
    assert _export(capsys, real, "--out", out)[0] == 0
    t, s, _, good = _h5(real)
    rows = np.flatnonzero(good)
    checked = 0
    for k, r in enumerate(rows):
        if t["E"][r] != 1e-12:
            continue
        code = cli.main(["analyze", str(out), "--frame", str(k), "--json"])
        got = json.loads(capsys.readouterr().out)
        assert code == 0
        assert got["N_G"] == s["N_G"][r] and got["A_G"] == s["A_G"][r]
        for name in ("E_G", "psi_O", "pressure", "N_C", "N_V", "delta_Z"):
            assert got[name] == s[name][r], name
        checked += 1
    assert checked == 2
    code = cli.main(["analyze", str(out), "--frame", "-1"])  # the last frame, human output
    assert code == 0 and f"frame {len(rows) - 1}: 64 disks" in capsys.readouterr().out


def test_draw_an_exported_frame(real, tmp_path, capsys):
    from campaign.report import draw

    out = tmp_path / "p.gsd"
    assert _export(capsys, real, "--out", out)[0] == 0
    png = tmp_path / "f.png"
    assert cli.main(["draw", str(out), "--frame", "1", "--out", str(png)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    src = draw.read_source(out, frame=1)
    t = _h5(real)[0]
    r = np.flatnonzero(_h5(real)[3])[1]
    assert _bits_equal(src.positions, _store_configuration(real, t["id"][r])["positions"])
    assert "frame 1, default, N = 64" in src.label


def test_reader_takes_other_programs_extended_xyz(tmp_path, monkeypatch):
    """ASE's own writer (a diameter column, element symbols) and an OVITO-style header."""
    import ase
    from ase.io import write

    _serial_ase(monkeypatch)
    from campaign.storage.configio import read_configuration

    rng = np.random.default_rng(2)
    pos = np.column_stack([rng.random(20) * 3.0, rng.random(20) * 2.0, np.zeros(20)])
    atoms = ase.Atoms("Cu10Ni10", positions=pos, cell=[3.0, 2.0, 1.0], pbc=[True, True, True])
    atoms.new_array("diameter", np.full(20, 0.2))
    write(tmp_path / "a.extxyz", [atoms, atoms], format="extxyz")
    c = read_configuration(tmp_path / "a.extxyz", frame=-1)  # the last: the frames are counted
    assert np.allclose(c.positions, pos[:, :2], atol=1e-8) and np.all(c.radii == 0.1)
    assert c.box.tolist() == [3.0, 2.0] and c.species.tolist() == [0] * 10 + [1] * 10
    assert (c.frame, c.n_frames) == (1, 2)
    (tmp_path / "o.xyz").write_text(
        '3\nLattice="2.0 0.0 0.0 0.0 2.0 0.0 0.0 0.0 2.0" Properties=species:S:1:pos:R:3:Radius:R:1 '
        'Time=5 pbc="T T T"\nA 0.5 0.5 0.0 0.25\nB 1.5 0.5 0.0 0.2\nA 1.0 1.5 0.0 0.25\n')
    c = read_configuration(tmp_path / "o.xyz")
    assert c.radii.tolist() == [0.25, 0.2, 0.25] and c.species.tolist() == [0, 1, 0]
    assert c.info == {"Time": 5} and c.exponent is None


def test_reader_takes_float32_gsd_from_other_programs(tmp_path, capsys):
    """A HOOMD-style frame without the float64 log: the float32 data, shifted to [0, L), and a note."""
    import gsd.hoomd

    fr = gsd.hoomd.Frame()
    fr.configuration.box = [2.0, 2.0, 1.0, 0, 0, 0]
    fr.configuration.dimensions = 2
    fr.particles.N = 3
    fr.particles.types = ["A"]
    fr.particles.position = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.0, 0.5, 0]], np.float32)
    fr.particles.diameter = np.array([0.5, 0.4, 0.5], np.float32)
    with gsd.hoomd.open(str(tmp_path / "h.gsd"), "w") as t:
        t.append(fr)
    from campaign.storage.configio import read_configuration

    c = read_configuration(tmp_path / "h.gsd")
    assert c.positions.tolist() == [[0.5, 0.5], [1.5, 0.5], [1.0, 1.5]]
    assert np.array_equal(c.radii, np.array([0.5, 0.4, 0.5], np.float32) / 2.0) and c.notes
    assert cli.main(["analyze", str(tmp_path / "h.gsd"), "--json"]) == 0
    assert "float32" in capsys.readouterr().err


# ----------------------------------------------------------------------------- errors: exit 2


def _user_error(capsys, argv, expect):
    code = cli.main(list(map(str, argv)))
    out, err = capsys.readouterr()
    assert code == 2, (out, err)
    assert "Traceback" not in err + out
    for piece in expect:
        assert piece in err, (piece, err)
    return err


def test_export_refusals(real, synth, tmp_path, capsys):
    out = tmp_path / "o.gsd"
    cases = [
        (["export", synth, "--format", "gsd", "--out", out],
         ["holds no configurations", "store: {configurations: true}", "campaign run SPEC --out NEW.h5"]),
        (["export", synth, "--format", "xyz", "--out", tmp_path / "o.xyz"], ["holds no configurations"]),
        (["export", real, "--variant", "nope", "--out", tmp_path / "o.csv"], ["no variant 'nope'", "capped, default"]),
        (["export", real, "--format", "gsd", "--out", tmp_path / "o.csv"], ["its suffix says csv"]),
        (["export", real, "--out", tmp_path / "o.dat"], ["give --format"]),
        (["export", real], ["give --format"]),
        (["export", real, "--format", "csv", "--out", tmp_path / "nodir" / "o.csv"], ["no directory"]),
        (["export", real, "--format", "csv", "--out", tmp_path], ["is a directory"]),
        (["export", tmp_path / "missing.h5", "--format", "csv", "--out", tmp_path / "m.csv"], ["no such file"]),
        (["export", real, "--format", "csv", "--out", real], ["is the campaign store itself"]),
    ]
    for argv, expect in cases:
        _user_error(capsys, argv, expect)
    assert not list(tmp_path.glob("o.*")) and not list(tmp_path.glob(".o.*"))  # nothing half-written
    with pytest.raises(SystemExit) as e:  # argparse: an unknown format
        cli.main(["export", str(real), "--format", "hdf5"])
    assert e.value.code == 2


@pytest.mark.parametrize("fmt, module", [("parquet", "pyarrow"), ("gsd", "gsd")])
def test_export_without_its_extra(real, tmp_path, capsys, monkeypatch, fmt, module):
    monkeypatch.setitem(sys.modules, module, None)
    monkeypatch.setitem(sys.modules, f"{module}.hoomd", None)
    _user_error(capsys, ["export", real, "--format", fmt, "--out", tmp_path / f"o.{fmt}"],
                [f"--format {fmt} needs", "pip install 'jamming-campaign[export]'"])
    assert not (tmp_path / f"o.{fmt}").exists()


def test_analyze_without_gsd(real, tmp_path, capsys, monkeypatch):
    out = tmp_path / "p.gsd"
    assert _export(capsys, real, "--out", out)[0] == 0
    monkeypatch.setitem(sys.modules, "gsd", None)
    monkeypatch.setitem(sys.modules, "gsd.hoomd", None)
    _user_error(capsys, ["analyze", out, "--frame", "0"], ["pip install 'jamming-campaign[export]'"])


def test_frame_choice_errors(real, tmp_path, capsys):
    for fmt in ("gsd", "xyz"):
        out = tmp_path / f"p.{fmt}"
        assert _export(capsys, real, "--out", out)[0] == 0
        _user_error(capsys, ["analyze", out], ["holds 4 frames", "--frame K (0 to 3"])
        _user_error(capsys, ["analyze", out, "--frame", "4"], ["--frame 4", "holds 4 frame(s)"])
        _user_error(capsys, ["analyze", out, "--frame", "-5"], ["--frame -5"])
        _user_error(capsys, ["draw", out, "--frame", "9", "--out", tmp_path / "d.png"], ["--frame 9"])
    text = tmp_path / "c.txt"
    text.write_text("1 1\n0.1 0.1 0.05\n0.5 0.5 0.05\n")
    _user_error(capsys, ["analyze", text, "--frame", "0"], ["picks a frame of a .gsd or extended XYZ file"])
    _user_error(capsys, ["draw", real, "--frame", "0", "--out", tmp_path / "d.png"], ["--task ID or --index ROW"])


XYZ_HEAD = 'Lattice="1.0 0.0 0.0 0.0 1.0 0.0 0.0 0.0 1.0" Properties=type:S:1:pos:R:3:radius:R:1 pbc="T T F"'


@pytest.mark.parametrize("text, expect", [
    ("two\n" + XYZ_HEAD + "\n", ["line 1", "expected the number of particles", "--format text"]),
    ("2\n" + XYZ_HEAD + "\nA 0.1 0.1 0.0 0.05\n", ["line 4", "ends inside the frame"]),
    ("2\nProperties=type:S:1:pos:R:3:radius:R:1\nA 0.1 0.1 0.0 0.05\nA 0.5 0.5 0.0 0.05\n", ["no Lattice"]),
    ('2\nLattice="1 0 0 0 1 0 0 0 1" Properties=type:S:1:pos:R:3\nA 0.1 0.1 0\nA 0.5 0.5 0\n',
     ["no radius:R:1 (or diameter:R:1) column"]),
    ('2\nLattice="1 0.5 0 0 1 0 0 0 1" Properties=pos:R:2:radius:R:1\n0.1 0.1 0.05\n0.5 0.5 0.05\n', ["tilted"]),
    ('2\nLattice="1 0 0 0 1 0 0 0 1" Properties=pos:R:2:radius:R:1 pbc="T F T"\n0.1 0.1 0.05\n0.5 0.5 0.05\n',
     ["not periodic in x and y"]),
    ("2\n" + XYZ_HEAD + "\nA 0.1 0.1 0.0 0.05\nA 0.5 nan 0.0 0.05\n", ["line 4", "finite number for y"]),
    ("2\n" + XYZ_HEAD + "\nA 0.1 0.1 0.0 0.05\nA 0.5 0.5 0.05\n", ["line 4", "expected 5 columns"]),
    ("2\n" + XYZ_HEAD + "\nA 0.1 0.1 0.0 0.05\nA 0.5 0.5 0.3 0.05\n", ["different z"]),
    ("2\n" + XYZ_HEAD + ' id="abc\nA 0.1 0.1 0.0 0.05\nA 0.5 0.5 0.0 0.05\n', ["never closed"]),
    ("2\n" + XYZ_HEAD + "\nA 0.1 0.1 0.0 0.05\nA 0.5 0.5 0.0 -0.05\n", ["positive radius"]),
])
def test_malformed_extended_xyz_exits_2(tmp_path, capsys, text, expect):
    p = tmp_path / "bad.xyz"
    p.write_text(text)
    err = _user_error(capsys, ["analyze", p], expect)
    assert str(p) in err


def test_malformed_gsd_exits_2(tmp_path, capsys):
    import gsd.hoomd

    bad = tmp_path / "bad.gsd"
    bad.write_bytes(b"not a gsd file at all" * 10)
    _user_error(capsys, ["analyze", bad], ["not a readable GSD file"])
    fr = gsd.hoomd.Frame()
    fr.configuration.box = [2.0, 2.0, 2.0, 0, 0, 0]
    fr.particles.N = 2
    fr.particles.position = np.array([[0, 0, 0], [0.5, 0.5, 0.5]], np.float32)
    with gsd.hoomd.open(str(tmp_path / "d3.gsd"), "w") as t:
        t.append(fr)
    _user_error(capsys, ["analyze", tmp_path / "d3.gsd"], ["3-dimensional frame"])
    fr.configuration.dimensions = 2
    fr.configuration.box = [2.0, 2.0, 1.0, 0.0, 0.3, 0]  # xz: tilted out of the plane (xy is read)
    fr.particles.position = np.array([[0, 0, 0], [0.5, 0.5, 0]], np.float32)
    with gsd.hoomd.open(str(tmp_path / "tilt.gsd"), "w") as t:
        t.append(fr)
    _user_error(capsys, ["analyze", tmp_path / "tilt.gsd"], ["tilted out of the plane"])
    with gsd.hoomd.open(str(tmp_path / "empty.gsd"), "w"):
        pass
    _user_error(capsys, ["analyze", tmp_path / "empty.gsd"], ["holds no frames"])


def test_extended_xyz_header_parser():
    from campaign.storage.configio import parse_xyz_header

    quoted = set()
    h = parse_xyz_header('Lattice="1 0 0 0 2 0 0 0 1" a = 3  name="say \\"hi\\"" v="1e5" flag '
                         'arr={1 2 3} b=[4, 5] Properties=pos:R:2', quoted=quoted)
    assert h == {"Lattice": "1 0 0 0 2 0 0 0 1", "a": "3", "name": 'say "hi"', "v": "1e5", "flag": True,
                 "arr": "1 2 3", "b": "4, 5", "Properties": "pos:R:2"}
    assert quoted == {"Lattice", "name", "v"}
    with pytest.raises(UserError, match="never closed"):
        parse_xyz_header('x="open')


def test_frame_columns_keep_their_types(tmp_path):
    """Strings stay strings (a variant named like a number, a one-letter one), numbers numbers."""
    from campaign.storage.configio import read_configuration
    from campaign.report.export import xyz_frame

    conf = {"positions": np.array([[0.1, 0.2], [0.6, 0.7]]), "radii": np.array([0.1, 0.12]),
            "box": np.array([1.0, 1.0]), "species": np.array([0, 1])}
    cols = {"row": np.int64(3), "id": "0123456789e12345678901234567890a", "variant": "1e5", "N": np.int64(2),
            "E": np.float64(1e-12), "status": np.int8(1), "A_G": np.float64(0.1 + 0.2), "psi_O": np.float64("nan")}
    (tmp_path / "f.xyz").write_text(xyz_frame(cols, conf, ["big one", "B"], 2.5))
    c = read_configuration(tmp_path / "f.xyz")
    assert c.info["variant"] == "1e5" and c.info["id"] == cols["id"] and c.info["row"] == 3
    assert c.info["A_G"] == 0.1 + 0.2 and np.isnan(c.info["psi_O"]) and c.exponent == 2.5
    assert c.species.tolist() == [0, 1] and _bits_equal(c.positions, conf["positions"])
