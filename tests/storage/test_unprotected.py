"""Stores written before the block checksums (0.2.7 and older; docs/STORE.md, "Stores written before the
block checksums"): every reader (status, reduce, export, plot, analyze and draw) names them as
unprotected, a run resuming one says it adds no checksums (and adds none), `campaign verify --repair`
checks what can be checked and writes them anew with block checksums, keeping every value. The stores are 0.2.7's own
(tests/data/v027_stores.py, blocks of 4 rows); the chunk-index damage sweep over them is in
tests/storage/test_reader_damage.py.
"""

import contextlib
import io
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from campaign import cli
from campaign.plan.parse import parse_spec
from campaign.plan.tasks import expand
from campaign.storage.journal import encode_record

DATA = Path(__file__).resolve().parents[1] / "data"
NOTE = "has no block checksums (written before 0.3.0)"


def _cli(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def _note(command, path):
    """The one line a reader prints about a store without block checksums."""
    return (f"campaign {command}: note: {path} {NOTE}: damage to HDF5's chunk index would change what is read "
            f"without an error. `campaign verify {path} --repair` checks what can be checked and adds them")


def _notes(err):
    return [line for line in err.splitlines() if NOTE in line]


@pytest.fixture(params=["configs", pytest.param("plain", marks=pytest.mark.slow)])
def old(request, tmp_path):
    for suffix in ("", ".journal"):
        shutil.copy(DATA / f"v027-{request.param}.h5{suffix}", tmp_path / f"s.h5{suffix}")
    return tmp_path / "s.h5"


def _values(path):
    """Every dataset's values and every group's attributes but the block checksums' (and their attribute)."""
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if name.startswith("checksums"):
                return
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
            else:
                out[name + "@"] = {k: v for k, v in obj.attrs.items() if k != "crc32"}
        f.visititems(visit)
        out["@"] = {k: v for k, v in f.attrs.items() if k != "block_checksums"}
    return out


def _same(a, b):
    assert set(a) == set(b)
    for k in a:
        if k.endswith("@"):
            assert a[k].keys() == b[k].keys(), k
            for key in a[k]:
                assert np.array_equal(np.asarray(a[k][key]), np.asarray(b[k][key])), (k, key)
        else:
            x, y = np.asarray(a[k]), np.asarray(b[k])
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), k


def test_readers_name_it_and_the_command_that_protects_it(old, tmp_path):
    """One line from each reader, naming the store and `campaign verify FILE --repair`; none once done."""
    argvs = [("status", old), ("reduce", old, "--boot", 0, "--out", tmp_path / "r"),
             ("export", old, "--out", tmp_path / "x.csv")]
    for argv in argvs:
        code, out, err = _cli(*argv)
        assert code == 0, err
        assert _notes(err) == [_note(argv[0], old)], err
    code, out, err = _cli("verify", old)
    assert code == 0 and "UNPROTECTED: no block checksums" in out and f"campaign verify {old} --repair" in out, out
    code, out, err = _cli("verify", old, "--repair")
    assert code == 0, out + err
    for argv in argvs:
        code, out, err = _cli(*argv)
        assert code == 0 and "block checksums" not in err, err
    code, out, err = _cli("verify", old)
    assert code == 0 and "UNPROTECTED" not in out and "block checksums added" in out and "OK: no damage" in out, out


@pytest.fixture
def configs(tmp_path):
    """0.2.7's store that keeps configurations (and failed tasks: every task of seed 1), its spec, and
    one of its configuration groups."""
    for suffix in ("", ".journal"):
        shutil.copy(DATA / f"v027-configs.h5{suffix}", tmp_path / f"s.h5{suffix}")
    with h5py.File(tmp_path / "s.h5", "r") as f:
        (tmp_path / "s.yaml").write_text(f.attrs["spec_yaml"])
        group = "/configurations/" + sorted(f["configurations"])[0]
    return tmp_path / "s.h5", tmp_path / "s.yaml", group


def test_analyze_and_draw_name_it(configs, tmp_path):
    """`analyze` and `draw` of one of its configurations say it in one line, as the other readers do;
    nothing once `verify --repair` added the checksums."""
    old, _, group = configs
    argvs = [("analyze", old, "--group", group), ("draw", old, "--group", group, "--out", tmp_path / "d.png")]
    for argv in argvs:
        code, out, err = _cli(*argv)
        assert code == 0, err
        assert _notes(err) == [_note(argv[0], old)], err
    assert _cli("verify", old, "--repair")[0] == 0
    for argv in argvs:
        code, out, err = _cli(*argv)
        assert code == 0 and "block checksums" not in err, err


@pytest.mark.slow  # every figure (25, about half a minute): tests/report/test_plots.py draws them in the quick suite
def test_plot_names_it(configs, tmp_path):
    old, _, _ = configs
    code, out, err = _cli("plot", old, "--boot", 0, "--out", tmp_path / "fig", "--dpi", 20)
    assert code == 0, err
    assert _notes(err) == [_note("plot", old)], err


def test_a_run_resuming_it_says_it_adds_no_checksums_and_adds_none(configs, monkeypatch):
    """A run resuming it (its failed tasks run again) says so in one line and writes its rows as 0.2.7 did:
    the store stays without block checksums, and `verify` finds it sound and unprotected."""
    old, spec, _ = configs
    monkeypatch.delenv("CAMPAIGN_NO_CHECKSUMS", raising=False)
    code, out, err = _cli("run", spec, "--out", old, "--launcher", "inline", "--task-function", "synthetic",
                          "--retry-failed", "--quiet")
    assert code == 0, err
    assert _notes(err) == [f"campaign: note: {old} {NOTE}: damage to HDF5's chunk index would change what is read "
                           f"without an error. `campaign verify {old} --repair` checks what can be checked and adds "
                           "them (this run adds none to it)"], err
    with h5py.File(old, "r") as f:
        assert (f["tasks/status"][:] == 1).all()
        assert "checksums" not in f and "block_checksums" not in f.attrs, (list(f), dict(f.attrs))
    code, out, err = _cli("verify", old)
    assert code == 0 and "UNPROTECTED: no block checksums" in out and "OK: no damage" in out, out


def test_repair_adds_the_checksums_and_keeps_every_value(old):
    """Every dataset and attribute as 0.2.7 wrote it (its checksums aside), with block checksums that
    match; the store says how it got them."""
    before = _values(old)
    code, out, err = _cli("verify", old, "--repair", "--json")
    assert code == 0, err
    _same(before, _values(old))
    with h5py.File(old, "r") as f:
        assert f.attrs["block_checksums"].startswith("added ") and "cannot be found" in f.attrs["block_checksums"]
        names = [n for n in f["scalars"]] + [f"histograms/{h}/counts" for h in f["histograms"]]
        assert all(f"checksums/{n.replace('/', '.')}" in f or f"checksums/scalars.{n}" in f for n in names)
    code, out, err = _cli("verify", old, "--json")
    assert code == 0 and '"block_checksums": true' in out, out


def test_a_task_table_block_read_from_another_place_is_found(old):
    """Without block checksums, a block of task ids that is not the spec's ids of its rows, in their order
    (what a chunk listed off its place gives) is found, and the repair writes the spec's ids."""
    with h5py.File(old, "r+") as f:
        ids = f["tasks/id"][:]
        f["tasks/id"][4:8] = ids[8:12]  # the next block's ids in this block's rows
        spec = parse_spec(f.attrs["spec_yaml"])
    code, out, err = _cli("verify", old)
    assert code == 1 and "tasks/id rows 4-7 are not the spec's id of those rows" in out, out
    code, out, err = _cli("verify", old, "--repair")
    assert code == 0 and "PROTECTED: wrote" in out, out
    with h5py.File(old, "r") as f:
        assert f["tasks/id"][:].tolist() == [t.id.encode() for t in expand(spec)]


def test_a_chunk_failing_its_checksum_is_dropped_before_the_checksums_are_added(old):
    """The repair drops a damaged chunk's rows (pending again), then writes every block's checksum."""
    with h5py.File(old, "r") as f:
        info = f["scalars/A_G"].id.get_chunk_info_by_coord((8,))
        finished = int((f["tasks/status"][8:12] != 0).sum())  # done or failed: the whole row goes
    with open(old, "r+b") as fh:
        fh.seek(info.byte_offset + 3)
        b = fh.read(1)
        fh.seek(info.byte_offset + 3)
        fh.write(bytes([b[0] ^ 0x10]))
    code, out, err = _cli("verify", old)
    assert code == 1 and "scalars/A_G rows 8-11" in out, out
    code, out, err = _cli("verify", old, "--repair")
    assert code == 0 and f"{finished} task(s) are pending" in out and "PROTECTED: wrote" in out, out
    with h5py.File(old, "r") as f:
        assert (f["tasks/status"][8:12] == 0).all() and np.isnan(f["scalars/A_G"][8:12]).all()
        assert "checksums/scalars.A_G" in f
    assert _cli("verify", old)[0] == 0


def test_a_row_unlike_the_journal_record_of_its_task_is_dropped(old):
    """A finished task the journal still holds (a run killed before its checkpoint) whose row in the
    store differs from the record: the row is dropped and the record stays in the journal, which the next
    run replays."""
    with h5py.File(old, "r+") as f:
        row = int(np.flatnonzero(f["tasks/status"][:] == 1)[5])
        tid = f["tasks/id"][row].decode()
        scalars = {n: float(f[f"scalars/{n}"][row]) for n in f["scalars"]}
        hists = {"h/" + h: f[f"histograms/{h}/counts"][row] for h in f["histograms"]}
        meta = {"type": "task", "index": row, "id": tid, "status": 1, "attempts": int(f["tasks/attempts"][row]),
                "wall": 1.0, "rank": 1, "host": "h", "message": "", "traceback": "", "run_id": None,
                "scalars": scalars}
        f["scalars/A_G"][row] = scalars["A_G"] + 0.01  # the row no longer what the task gave
    with open(str(old) + ".journal", "ab") as fh:
        fh.write(encode_record(meta, hists))
    code, out, err = _cli("verify", old)
    assert code == 1 and "scalars/A_G differs from the journal's record of the task at 1 row(s)" in out, out
    code, out, err = _cli("verify", old, "--repair")
    assert code == 0 and "1 task(s) are pending again" in out, out
    with h5py.File(old, "r") as f:
        assert f["tasks/status"][row] == 0
    assert Path(str(old) + ".journal").read_bytes().endswith(encode_record(meta, hists))


def test_a_store_written_with_block_checksums_says_so(tmp_path):
    """A new store carries the attribute that tells it from an older one; without its checksums group
    (a damaged link) its readers refuse it instead of reading it unchecked."""
    spec = tmp_path / "s.yaml"
    spec.write_text("name: t\nseed: 1\ngrid: {N_G: [16], E_G: [1.0e-3], seeds: 2}\nobservables: [scalars]\n")
    code, out, err = _cli("run", spec, "--out", tmp_path / "s.h5", "--launcher", "inline", "--task-function",
                          "synthetic", "--quiet")
    assert code == 0, err
    with h5py.File(tmp_path / "s.h5", "r+") as f:
        assert f.attrs["block_checksums"] == "written with every block since the store was created"
        f.move("checksums", "checksumz")
    code, out, err = _cli("export", tmp_path / "s.h5", "--out", tmp_path / "x.csv")
    assert code == 2 and "have no block checksums" in err and NOTE not in err, err
