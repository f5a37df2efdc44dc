"""The HDF5 store and its journal: layout, commit marker, refusal, locking, rebuild."""

import json

import h5py
import numpy as np
import pytest

from campaign.errors import UserError
from campaign.spec import parse_spec
from campaign.store import DONE, FAILED, PENDING, Store, encode_record, read_journal
from campaign.tasks import expand
from campaign.worker import SyntheticTask, run_task

SPEC = """\
name: st
seed: 3
grid: {N_G: [16, 24], E_G: [1.0e-3, 1.0e-5], seeds: 3}
observables: [scalars, connectivity, void_areas]
"""


def _setup(text=SPEC):
    spec = parse_spec(text)
    tasks = expand(spec)
    fn = SyntheticTask()
    ctx = {"task_function": "synthetic", "system": spec.system.canonical(), "observables": list(spec.observables),
           "histograms": list(spec.histograms), "bins": {}, "configurations": spec.configurations}
    edges = fn.histogram_edges(ctx)
    ctx["edges"] = edges
    return spec, tasks, fn, ctx, edges


def _summary(fn, task, ctx, fail=False):
    s = run_task(fn, dict(task.payload(), attempt=1), ctx, rank=1)
    if fail:
        s.update(ok=False, scalars={}, histograms={}, error={"message": "RuntimeError: boom", "traceback": "Tb..."})
    return s


def _contents(path):
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
            for k, v in obj.attrs.items():
                if k not in ("runs", "start_time", "end_time", "hosts", "versions", "git_commit"):
                    out[f"{name}@{k}"] = v
        f.visititems(visit)
        for k, v in f.attrs.items():
            if k not in ("runs", "start_time", "end_time", "hosts", "versions", "git_commit"):
                out[f"@{k}"] = v
    return out


def _assert_same(a, b, skip=("tasks/wall", "tasks/rank", "tasks/host")):
    assert set(a) == set(b)
    for k in a:
        if k in skip:
            continue
        x, y = np.asarray(a[k]), np.asarray(b[k])
        assert x.dtype == y.dtype and x.shape == y.shape, k
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), k


def test_journal_round_trip_and_torn_tails():
    recs = [({"type": "task", "i": k, "x": float("nan") if k == 1 else 0.1 * k},
             {"h": np.arange(k + 3, dtype=np.int64), "p": np.random.default_rng(k).random((k + 1, 2))})
            for k in range(4)]
    blobs = [encode_record(m, a) for m, a in recs]
    data = b"".join(blobs)
    got, n = read_journal(data)
    assert n == len(data) and len(got) == 4
    for (m, a), (gm, ga) in zip(recs, got):
        assert gm["i"] == m["i"] and (gm["x"] == m["x"] or np.isnan(m["x"]))
        assert all(np.array_equal(a[k], ga[k]) and a[k].dtype == ga[k].dtype for k in a)
    head = len(data) - len(blobs[-1])
    for cut in range(head, len(data)):  # every torn tail of the last record is ignored
        got, n = read_journal(data[:cut])
        assert len(got) == 3 and n == head
    flipped = bytearray(data)
    flipped[head + 20] ^= 0xFF  # a corrupted byte fails the checksum
    got, n = read_journal(bytes(flipped))
    assert len(got) == 3 and n == head


def test_layout_commit_marker_and_reopen(tmp_path):
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    st = Store(out, spec, tasks, edges)
    st.record(5, _summary(fn, tasks[5], ctx), attempts=1)
    st.record(2, _summary(fn, tasks[2], ctx, fail=True), attempts=3)
    with h5py.File(out, "r", locking=False) as f:  # nothing committed before a flush
        assert f["tasks/status"][5] == PENDING
    st.flush(force=True)
    with h5py.File(out, "r", locking=False) as f:
        assert f["tasks/status"][5] == DONE and f["tasks/status"][2] == FAILED
    st.close()
    T = len(tasks)
    with h5py.File(out, "r") as f:
        assert f.attrs["schema"] == "jamming-campaign/1" and f.attrs["spec_hash"] == spec.hash
        assert f.attrs["spec_yaml"] == SPEC and f.attrs["name"] == "st"
        runs = json.loads(f.attrs["runs"])
        assert len(runs) == 1 and runs[0]["start"] and runs[0]["end"]
        assert f["tasks/id"].dtype == "S32" and f["tasks/id"].shape == (T,)
        assert [x.decode() for x in f["tasks/id"][:]] == [t.id for t in tasks]
        assert list(f["tasks/N"][:]) == [t.N for t in tasks] and list(f["tasks/E"][:]) == [t.E for t in tasks]
        assert f["tasks/variant"].asstr()[0] == "default"
        assert list(f["tasks/attempts"][[2, 5]]) == [3, 1]
        assert f["tasks/error"][2].decode() == "RuntimeError: boom"
        assert f["failures"][tasks[2].id].attrs["traceback"] == "Tb..."
        assert set(f["histograms"]) == {"z_g", "z_v", "alpha_v"}
        for h, e in edges.items():
            assert np.array_equal(f[f"histograms/{h}/edges"][:], e)
            c = f[f"histograms/{h}/counts"]
            assert c.shape == (T, len(e) - 1) and c.dtype == np.int64
            assert c[5].sum() == tasks[5].N and c[0].sum() == 0
        s = f["scalars/phi"][:]
        assert np.isnan(s[[0, 2]]).all() and np.isfinite(s[5])
    st = Store(out, spec, tasks, edges)  # resume: finished rows are known
    assert st.finished(5) and st.finished(2) and not st.finished(0)
    st.close()


def test_different_spec_refused_unless_new(tmp_path):
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    st = Store(out, spec, tasks, edges)
    st.record(0, _summary(fn, tasks[0], ctx), 1)
    st.close()
    spec2, tasks2, fn2, ctx2, edges2 = _setup(SPEC.replace("seed: 3", "seed: 4"))
    with pytest.raises(UserError, match="different spec"):
        Store(out, spec2, tasks2, edges2)
    out.unlink()  # only the journal left: still refused
    with pytest.raises(UserError, match="different spec"):
        Store(out, spec2, tasks2, edges2)
    st = Store(out, spec2, tasks2, edges2, new=True)
    assert not st.finished(0)
    st.close()


def test_one_writer_at_a_time(tmp_path):
    spec, tasks, fn, ctx, edges = _setup()
    st = Store(tmp_path / "s.h5", spec, tasks, edges)
    with pytest.raises(UserError, match="another run is writing"):
        Store(tmp_path / "s.h5", spec, tasks, edges)
    st.close()
    Store(tmp_path / "s.h5", spec, tasks, edges).close()


def _fill(out, spec, tasks, fn, ctx, edges, rows):
    st = Store(out, spec, tasks, edges)
    for i in rows:
        st.record(i, _summary(fn, tasks[i], ctx, fail=(i % 7 == 3)), attempts=1)
    st.close()


def test_rebuild_from_journal_when_view_is_damaged_or_missing(tmp_path):
    spec, tasks, fn, ctx, edges = _setup()
    ref = tmp_path / "ref.h5"
    _fill(ref, spec, tasks, fn, ctx, edges, range(0, len(tasks), 2))
    expected = _contents(ref)
    for damage in ("garbage", "truncate", "delete"):
        out = tmp_path / f"{damage}.h5"
        _fill(out, spec, tasks, fn, ctx, edges, range(0, len(tasks), 2))
        raw = out.read_bytes()
        if damage == "garbage":
            out.write_bytes(raw[:200] + b"\x00" * 4000 + raw[4200:])
        elif damage == "truncate":
            out.write_bytes(raw[: len(raw) // 3])
        else:
            out.unlink()
        Store(out, spec, tasks, edges, log=lambda m: None).close()
        _assert_same(_contents(out), expected)


def test_lost_journal_is_rebuilt_from_the_view(tmp_path):
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    _fill(out, spec, tasks, fn, ctx, edges, [1, 3, 4])
    expected = _contents(out)
    (tmp_path / "s.h5.journal").unlink()
    Store(out, spec, tasks, edges).close()  # re-journals the finished rows
    out.write_bytes(b"not hdf5")
    Store(out, spec, tasks, edges, log=lambda m: None).close()
    _assert_same(_contents(out), expected)


def test_unreadable_view_without_journal_is_refused(tmp_path):
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    out.write_bytes(b"junk" * 100)
    with pytest.raises(UserError, match="unreadable"):
        Store(out, spec, tasks, edges)


def test_failed_then_done_drops_the_failure_record(tmp_path):
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    st = Store(out, spec, tasks, edges)
    st.record(3, _summary(fn, tasks[3], ctx, fail=True), 2)
    st.close()
    st = Store(out, spec, tasks, edges)
    st.record(3, _summary(fn, tasks[3], ctx), 1)
    st.close()
    with h5py.File(out, "r") as f:
        assert f["tasks/status"][3] == DONE and tasks[3].id not in f["failures"]
        assert f["tasks/error"][3] == b""


def test_configurations_only_when_asked(tmp_path):
    text = SPEC + "store: {configurations: true}\n"
    spec, tasks, fn, ctx, edges = _setup(text)
    out = tmp_path / "c.h5"
    st = Store(out, spec, tasks, edges)
    s = _summary(fn, tasks[1], ctx)
    st.record(1, s, 1)
    st.close()
    with h5py.File(out, "r") as f:
        g = f[f"configurations/{tasks[1].id}"]
        assert np.array_equal(g["positions"][:], s["configuration"]["positions"])
        assert g["positions"].shape == (tasks[1].N, 2) and g["species"].dtype == np.int32
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "n.h5"
    _fill(out, spec, tasks, fn, ctx, edges, [1])
    with h5py.File(out, "r") as f:
        assert "configurations" not in f


def test_torn_configuration_group_is_rebuilt_from_the_journal(tmp_path):
    """A SIGKILL during a flush can leave a configuration group half written (or unreadable)
    while every other dataset reads fine: the view is damaged and is rebuilt, not used."""
    text = SPEC + "store: {configurations: true}\n"
    spec, tasks, fn, ctx, edges = _setup(text)
    out = tmp_path / "c.h5"
    st = Store(out, spec, tasks, edges)
    for i in (0, 2, 5):
        st.record(i, _summary(fn, tasks[i], ctx), 1)
    st.close()
    expected = _contents(out)
    with h5py.File(out, "r+") as f:
        del f[f"configurations/{tasks[2].id}/radii"]
    logged = []
    st = Store(out, spec, tasks, edges, log=logged.append)
    assert any("rebuilding it from its journal" in m for m in logged)
    got = st.configuration(2)
    assert np.array_equal(got["radii"], _summary(fn, tasks[2], ctx)["configuration"]["radii"])
    st.close()
    _assert_same(_contents(out), expected)
