"""The HDF5 store and its journal: layout, commit marker, refusal, locking, rebuild."""

import json

import h5py
import numpy as np
import pytest

from campaign.errors import UserError
from campaign.plan.parse import parse_spec
from campaign.storage.store import DONE, FAILED, PENDING, Store, encode_record, read_journal, scan_journal
from campaign.plan.tasks import expand
from campaign.run.worker import SyntheticTask, run_task

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
    ctx = dict(spec.worker_context(), task_function="synthetic", bins={})
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


def _assert_same(a, b, skip=("tasks/wall", "tasks/rank", "tasks/host", "checksums/tasks.wall", "checksums/tasks.rank",
                             "checksums/tasks.host")):
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


def _fill_killed(out, spec, tasks, fn, ctx, edges, rows):
    """Like _fill, but the run is cut off after its last flush (no closing checkpoint)."""
    st = Store(out, spec, tasks, edges)
    for i in rows:
        st.record(i, _summary(fn, tasks[i], ctx, fail=(i % 7 == 3)), attempts=1)
    st.flush(force=True)
    st.abandon()


def test_view_damaged_by_a_killed_run_is_rebuilt_from_the_journal(tmp_path):
    """Rows recorded since the last checkpoint are in the journal: whatever happened to
    the store, reopening gives back exactly the uninterrupted run's file."""
    spec, tasks, fn, ctx, edges = _setup()
    ref = tmp_path / "ref.h5"
    _fill(ref, spec, tasks, fn, ctx, edges, range(0, len(tasks), 2))
    expected = _contents(ref)
    for damage in ("garbage", "truncate", "delete"):
        out = tmp_path / f"{damage}.h5"
        _fill_killed(out, spec, tasks, fn, ctx, edges, range(0, len(tasks), 2))
        raw = out.read_bytes()
        if damage == "garbage":
            out.write_bytes(raw[:200] + b"\x00" * 4000 + raw[4200:])
        elif damage == "truncate":
            out.write_bytes(raw[: len(raw) // 3])
        else:
            out.unlink()
        Store(out, spec, tasks, edges, log=lambda m: None).close()
        _assert_same(_contents(out), expected)


def test_a_failed_write_step_poisons_the_handle_and_closing_writes_nothing(tmp_path):
    """What failed belongs to the handle HDF5 writes through (``GuardedFile.poisoned``), set by the
    write step that failed: no later step may write through it, and abandoning the store writes
    nothing more to the file, which the next start opens as it was."""
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    st = Store(out, spec, tasks, edges)
    st.record(0, _summary(fn, tasks[0], ctx), attempts=1)
    st.flush(force=True)
    before = out.read_bytes()
    with pytest.raises(RuntimeError, match="boom"):
        with st.space.write_step(st.io, 0, "a step that fails", len(st.scalar_names)):
            st.f.attrs["half_written"] = 1
            raise RuntimeError("boom")
    assert st.io.poisoned and st.io.failed is None
    with pytest.raises(RuntimeError, match="failed a write before"):
        with st.space.write_step(st.io, 0, "a later step", len(st.scalar_names)):
            pass
    st.abandon()
    assert out.read_bytes() == before
    st = Store(out, spec, tasks, edges)
    assert st.finished(0) and not st.io.poisoned and "half_written" not in st.f.attrs
    st.close()


def test_checkpoint_leaves_only_the_header_in_the_journal(tmp_path):
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    _fill(out, spec, tasks, fn, ctx, edges, range(len(tasks)))
    recs, _ = read_journal((tmp_path / "s.h5.journal").read_bytes())
    kinds = [m["type"] for m, _ in recs]
    assert kinds[0] == "header" and "task" not in kinds and kinds[-1] == "checkpoint"
    assert recs[-1][0]["committed"] == len(tasks)


def test_a_chunk_torn_while_rewriting_a_block_loses_nothing(tmp_path, monkeypatch):
    """Adding a row to a block whose other rows were checkpointed rewrites their compressed
    chunks; those rows are put back into the journal first. Tear such a chunk (as a SIGKILL
    in the middle of the write would): the store is salvaged block by block and the journal
    gives back every row of the torn block."""
    import campaign.storage.store as S

    monkeypatch.setattr(S, "BLOCK_ROWS", 4)
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    _fill(out, spec, tasks, fn, ctx, edges, [0, 1, 4, 5, 8, 9])  # blocks 0, 1, 2; checkpointed
    _fill_killed(out, spec, tasks, fn, ctx, edges, [6])           # block 1 rewritten, then killed
    recs, _ = read_journal((tmp_path / "s.h5.journal").read_bytes())
    assert sorted(m["index"] for m, _ in recs if m["type"] == "task") == [4, 5, 6]
    with h5py.File(out, "r") as f:
        info = f["histograms/alpha_v/counts"].id.get_chunk_info_by_coord((4, 0))
    with open(out, "r+b") as fh:
        fh.seek(info.byte_offset)
        fh.write(b"\xff" * info.size)
    logged = []
    st = Store(out, spec, tasks, edges, log=logged.append)
    assert any("salvaging" in m for m in logged) and not any("run again" in m for m in logged)
    assert [int(i) for i in np.flatnonzero(st.status != PENDING)] == [0, 1, 4, 5, 6, 8, 9]
    st.close()
    ref = tmp_path / "ref.h5"
    _fill(ref, spec, tasks, fn, ctx, edges, [0, 1, 4, 5, 6, 8, 9])
    _assert_same(_contents(out), _contents(ref))


def test_lost_store_after_a_checkpoint_is_counted_and_rerun(tmp_path):
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    _fill(out, spec, tasks, fn, ctx, edges, [1, 3, 4])
    out.unlink()
    logged = []
    st = Store(out, spec, tasks, edges, log=logged.append)
    assert any(m.startswith("campaign: at least 3 finished task(s) were only in the missing store") for m in logged)
    assert not any(st.finished(i) for i in range(len(tasks)))
    st.close()


def test_lost_journal_the_store_is_the_record(tmp_path):
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    _fill(out, spec, tasks, fn, ctx, edges, [1, 3, 4])
    expected = _contents(out)
    (tmp_path / "s.h5.journal").unlink()
    st = Store(out, spec, tasks, edges)
    assert [i for i in range(len(tasks)) if st.finished(i)] == [1, 3, 4]
    st.close()
    _assert_same(_contents(out), expected)
    recs, _ = read_journal((tmp_path / "s.h5.journal").read_bytes())
    assert recs[0][0]["spec_hash"] == spec.hash and not [m for m, _ in recs if m["type"] == "task"]


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
    st.flush(force=True)
    st.abandon()  # killed after its flush: the records are still in the journal
    ref = tmp_path / "ref.h5"
    st = Store(ref, spec, tasks, edges)
    for i in (0, 2, 5):
        st.record(i, _summary(fn, tasks[i], ctx), 1)
    st.close()
    expected = _contents(ref)
    with h5py.File(out, "r+") as f:
        del f[f"configurations/{tasks[2].id}/radii"]
    logged = []
    st = Store(out, spec, tasks, edges, log=logged.append)
    assert any("replaying the journal" in m for m in logged)
    got = st.configuration(2)
    assert np.array_equal(got["radii"], _summary(fn, tasks[2], ctx)["configuration"]["radii"])
    st.close()
    _assert_same(_contents(out), expected)


def test_damage_inside_the_journal_keeps_every_intact_record():
    recs = [({"type": "task", "i": k}, {"h": np.arange(50 + k, dtype=np.int64)}) for k in range(6)]
    blobs = [encode_record(m, a) for m, a in recs]
    data = b"".join(blobs)
    start = [sum(len(b) for b in blobs[:k]) for k in range(6)]
    # a flipped byte inside record 2: records 0, 1, 3, 4, 5 survive
    flipped = bytearray(data)
    flipped[start[2] + 40] ^= 0x01
    got, end, damaged = scan_journal(bytes(flipped))
    assert [m["i"] for m, _ in got] == [0, 1, 3, 4, 5] and end == len(data)
    assert damaged == [(start[2], len(blobs[2]), 1)]
    # record 3 cut short in the middle (its tail is gone; the next records follow directly)
    cut = data[:start[3] + 30] + data[start[4]:]
    got, end, damaged = scan_journal(cut)
    assert [m["i"] for m, _ in got] == [0, 1, 2, 4, 5] and end == len(cut)
    assert damaged == [(start[3], 30, 1)]
    # two records' bytes overwritten, magic and all: both counted from what is left of them
    wiped = data[:start[1]] + b"\x00" * (start[3] - start[1]) + data[start[3]:]
    got, _, damaged = scan_journal(wiped)
    assert [m["i"] for m, _ in got] == [0, 3, 4, 5] and damaged[0][:2] == (start[1], start[3] - start[1])


@pytest.mark.parametrize("damage", ["flip", "cut"])
def test_resume_from_a_damaged_journal_reruns_only_the_lost_tasks(tmp_path, damage):
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    rows = [0, 2, 4, 6, 8]
    _fill_killed(out, spec, tasks, fn, ctx, edges, rows)
    out.unlink()  # the store is gone too: the journal alone says what was done
    jpath = tmp_path / "s.h5.journal"
    data = jpath.read_bytes()
    recs, _ = read_journal(data)
    offsets, pos = [], 0
    while pos < len(data):  # record boundaries
        n = int.from_bytes(data[pos + 4:pos + 8], "little")
        offsets.append(pos)
        pos += 12 + n
    k = next(j for j, (m, _) in enumerate(recs) if m.get("type") == "task" and m["index"] == 4)
    a, b = offsets[k], offsets[k + 1]
    if damage == "flip":
        data = data[:a + 50] + bytes([data[a + 50] ^ 0x80]) + data[a + 51:]
    else:
        data = data[:a + (b - a) // 2] + data[b:]
    jpath.write_bytes(data)
    logged = []
    st = Store(out, spec, tasks, edges, log=logged.append)
    assert any("about 1 record(s) lost; kept 4 intact task record(s)" in m for m in logged), logged
    assert [i for i in range(len(tasks)) if st.finished(i)] == [0, 2, 6, 8]
    st.record(4, _summary(fn, tasks[4], ctx), attempts=1)  # the lost task, run again
    st.close()
    ref = tmp_path / "ref.h5"
    _fill(ref, spec, tasks, fn, ctx, edges, [0, 2, 6, 8])
    st = Store(ref, spec, tasks, edges)
    st.record(4, _summary(fn, tasks[4], ctx), attempts=1)
    st.close()
    _assert_same(_contents(out), _contents(ref))


def _old_format_store(path, spec, tasks):
    """A store as the previous layout wrote it: dense datasets, no format_version attribute."""
    T = len(tasks)
    with h5py.File(path, "w") as f:
        f.attrs.update(schema="jamming-campaign/1", name=spec.name, spec_hash=spec.hash, spec_yaml=spec.text,
                       runs="[]")
        g = f.create_group("tasks")
        g["id"] = np.array([t.id.encode() for t in tasks], "S32")
        g["status"] = np.ones(T, np.int8)
        for name in ("variant", "host", "error"):
            g[name] = np.zeros(T, "S8")
        for name in ("N", "seed", "attempts", "rank"):
            g[name] = np.ones(T, np.int64)
        for name in ("E", "wall"):
            g[name] = np.ones(T)
        f.create_group("scalars")["A_G"] = np.full(T, 250.0)  # an absolute area, as it was
        f.create_group("histograms")


def test_a_store_of_the_old_format_is_refused_by_every_command(tmp_path, capsys):
    from campaign import cli

    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "old.h5"
    _old_format_store(out, spec, tasks)
    with pytest.raises(UserError, match="store format 1") as exc:
        Store(out, spec, tasks, edges)
    msg = str(exc.value)
    assert "fractions of the box area" in msg and "half-plane" in msg and "--out NEW.h5" in msg
    (tmp_path / "s.yaml").write_text(SPEC)
    for argv in (["status", str(out)], ["reduce", str(out), "--out", str(tmp_path / "r")],
                 ["run", str(tmp_path / "s.yaml"), "--out", str(out), "--task-function", "synthetic",
                  "--launcher", "inline"]):
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "store format 1" in err and "Run the spec again into a new file" in err and "Traceback" not in err
    # validate checks the spec (exit 0) and says why its output cannot be resumed
    (tmp_path / "o.yaml").write_text(SPEC + f"output: {out}\n")
    assert cli.main(["validate", str(tmp_path / "o.yaml")]) == 0
    assert "exists but cannot be resumed" in capsys.readouterr().out
    # --new replaces it
    assert cli.main(["run", str(tmp_path / "s.yaml"), "--out", str(out), "--task-function", "synthetic",
                     "--launcher", "inline", "--new"]) == 0
    with h5py.File(out, "r") as f:
        assert f.attrs["format_version"] == 2


def test_synthetic_bins_are_the_kernels_default_bins():
    from kernels.analysis import DEFAULT_BINS

    from campaign.run.worker import SYNTHETIC_BINS

    from kernels.names import DEFAULT_OBSERVABLES, OBSERVABLES

    # the contact network's histograms (the linear response's fall back on 10 synthetic bins)
    network = {h for o in DEFAULT_OBSERVABLES for h in OBSERVABLES[o]}
    assert SYNTHETIC_BINS == {h: len(e) - 1 for h, e in DEFAULT_BINS.items() if h in network}


RESERVE_SPEC = """\
name: reserve
seed: 8
grid: {N_G: [64, 128], E_G: [1.0e-3, 1.0e-6], seeds: 80}
observables: [scalars, connectivity, void_areas, contact_angles]
store: {configurations: true}
"""


@pytest.mark.parametrize("every", [pytest.param(1, marks=pytest.mark.slow), 10, 1000])
def test_reservations_cover_every_write_step(tmp_path, monkeypatch, every):
    """Every HDF5 write step reserves at least what the file then grows by (the estimate of
    docs/STORE.md, "Out of space"), and not wildly more: a full disk is met before HDF5 writes,
    and a nearly full one still takes a campaign that fits. Tasks in random order (blocks written
    many times, chunks rewritten), configurations kept, every 17th task failed; flushed after every
    task, every 10, or once at the end. Two blocks of rows (BLOCK_ROWS 256, 320 tasks). A step that
    adds one row to a block reserves the block's whole compressed chunks (HDF5 may place a rewritten
    chunk at the end of the file), so no step reserves more than twice the finished store."""
    spec, tasks, fn, ctx, edges = _setup(RESERVE_SPEC)
    out = tmp_path / "r.h5"
    st = Store(out, spec, tasks, edges)
    for k, i in enumerate(np.random.default_rng(every).permutation(len(tasks))):
        st.record(int(i), _summary(fn, tasks[i], ctx, fail=(k % 17 == 0)), attempts=1)
        if k % every == 0:
            st.flush(force=True)
    st.close()
    steps = st.space_log
    assert len(steps) >= 4 and all(grew <= need for need, grew in steps), steps
    assert max(need for need, _ in steps) <= 2 * out.stat().st_size + (512 << 10), (steps, out.stat().st_size)
    if every == 1000:  # one step writes every row: the estimate is close to what it takes
        need, grew = max(steps)
        assert grew <= need <= 2 * grew, steps


def test_salvage_drops_a_failed_row_whose_failure_record_is_gone(tmp_path, monkeypatch):
    """A SIGKILL while a failure record is added can tear the ``failures`` group's index and take
    the link of an earlier, committed record with it. Salvaging such a store keeps no row that says
    failed without its record (the traceback would be lost for good): the task is pending again, and
    running it again gives the uninterrupted run's record."""
    import campaign.storage.store as S

    monkeypatch.setattr(S, "BLOCK_ROWS", 4)
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    _fill(out, spec, tasks, fn, ctx, edges, [0, 1, 3])  # 3 fails; checkpointed
    with h5py.File(out, "r+") as f:
        del f[f"failures/{tasks[3].id}"]
    _fill_killed(out, spec, tasks, fn, ctx, edges, [8, 9, 10])  # in the journal; 10 fails
    with h5py.File(out, "r") as f:
        info = f["histograms/alpha_v/counts"].id.get_chunk_info_by_coord((8, 0))
    with open(out, "r+b") as fh:  # a torn chunk of block 2: the store is salvaged when it is opened
        fh.seek(info.byte_offset)
        fh.write(b"\xff" * info.size)
    logged = []
    st = Store(out, spec, tasks, edges, log=logged.append)
    assert any("salvaging" in m for m in logged)
    assert not any("lost their failure record" in m for m in logged), logged  # salvage dropped it itself
    assert [int(i) for i in np.flatnonzero(st.status != PENDING)] == [0, 1, 8, 9, 10]
    for i in (3,):
        st.record(i, _summary(fn, tasks[i], ctx, fail=(i % 7 == 3)), attempts=1)
    st.close()
    ref = tmp_path / "ref.h5"
    _fill(ref, spec, tasks, fn, ctx, edges, [0, 1, 3, 8, 9, 10])
    _assert_same(_contents(out), _contents(ref))
    with h5py.File(out, "r") as f:
        assert f[f"failures/{tasks[3].id}"].attrs["traceback"] == "Tb..."


def test_a_failed_row_without_its_record_runs_again(tmp_path):
    """The same loss in a store that opens without salvage: the row is pending again (said so), and
    running it again gives the uninterrupted run's record, not one without its traceback."""
    spec, tasks, fn, ctx, edges = _setup()
    out = tmp_path / "s.h5"
    _fill(out, spec, tasks, fn, ctx, edges, [0, 1, 3, 10])  # 3 and 10 fail
    with h5py.File(out, "r+") as f:
        del f[f"failures/{tasks[3].id}"]
    logged = []
    st = Store(out, spec, tasks, edges, log=logged.append)
    assert any("1 failed task(s) have lost their failure record" in m for m in logged), logged
    assert [int(i) for i in np.flatnonzero(st.status != PENDING)] == [0, 1, 10]
    st.record(3, _summary(fn, tasks[3], ctx, fail=True), attempts=1)
    st.close()
    ref = tmp_path / "ref.h5"
    _fill(ref, spec, tasks, fn, ctx, edges, [0, 1, 3, 10])
    _assert_same(_contents(out), _contents(ref))
