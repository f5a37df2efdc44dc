"""The master loop without MPI: scheduling, retries, failures, signals, worker death."""

import os
import signal

import h5py
import numpy as np
import pytest

from campaign.run.comm import InlineComm, LocalComm
from campaign.run.master import Master
from campaign.storage.store import DONE, FAILED
from campaign.plan.tasks import task_cost
from campaign.run.worker import SyntheticTask
from helpers import FakeComm, synthetic_run

SPEC = """\
name: m
seed: 5
grid: {N_G: [16, 32, 48], E_G: [1.0e-3, 1.0e-6], seeds: 4}
variants: [{name: loose, force_tolerance: 1.0e-3}]
observables: [scalars, connectivity, contact_angles]
"""


def _setup(tmp_path, name="s.h5"):
    return synthetic_run(tmp_path, SPEC, name)


def _reference_scalars(task, ctx):
    scal, hists, _ = SyntheticTask().run(dict(task.payload(), attempt=1), ctx)
    return scal, hists


def test_inline_run_records_every_task(tmp_path):
    spec, tasks, ctx, store = _setup(tmp_path)
    out = Master(InlineComm(ctx), store, tasks, retries=1).run()
    assert out == {"done": len(tasks), "failed": 0, "abandoned": 0, "stopped": None, "remaining": 0}
    store.close()
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert (f["tasks/status"][:] == DONE).all() and (f["tasks/attempts"][:] == 1).all()
        for t in tasks[::5]:
            scal, hists = _reference_scalars(t, ctx)
            for k, v in scal.items():
                assert f[f"scalars/{k}"][t.index] == v
            for h, c in hists.items():
                assert np.array_equal(f[f"histograms/{h}/counts"][t.index], c)


@pytest.mark.parametrize("wall, depth", [(1.0, 2), (1e-4, 16)])
def test_dispatch_depth_follows_task_length(tmp_path, wall, depth):
    spec, tasks, ctx, store = _setup(tmp_path)
    comm = FakeComm(ctx, 2, wall=wall)
    Master(comm, store, tasks, depth=2).run()
    store.close()
    assert comm.max_queue == depth  # 2 for real packings; up to 16 for millisecond tasks


def test_no_task_waits_behind_another_at_the_end(tmp_path):
    spec, tasks, ctx, store = _setup(tmp_path)
    comm = FakeComm(ctx, 2)
    Master(comm, store, tasks, depth=2).run()
    store.close()
    assert max(comm.queued_before) == 1  # prefetching while the queue is long ...
    assert comm.queued_before[-3:] == [0, 0, 0]  # ... and only to idle workers at its end


def test_dispatch_is_most_expensive_first_and_keeps_workers_fed(tmp_path):
    spec, tasks, ctx, store = _setup(tmp_path)
    comm = FakeComm(ctx, 3, wall=1.0)
    Master(comm, store, tasks, retries=0, depth=2).run()
    store.close()
    costs = [task_cost(tasks[p["index"]]) for _, p in comm.sent]
    assert costs == sorted(costs, reverse=True)
    assert sorted(p["index"] for _, p in comm.sent) == list(range(len(tasks)))
    assert {w for w, _ in comm.sent[:6]} == {1, 2, 3}  # the first round goes to every worker, twice


def test_failures_are_recorded_retried_and_the_campaign_goes_on(tmp_path, monkeypatch):
    monkeypatch.setenv("CAMPAIGN_SYNTHETIC_FAIL", "seed:1")
    monkeypatch.setenv("CAMPAIGN_SYNTHETIC_FLAKY", "seed:2")
    spec, tasks, ctx, store = _setup(tmp_path)
    comm = FakeComm(ctx, 2)
    out = Master(comm, store, tasks, retries=2).run()
    store.close()
    bad = [t for t in tasks if t.seed == 1]
    assert out["failed"] == len(bad) and out["done"] == len(tasks) - len(bad)
    with h5py.File(tmp_path / "s.h5", "r") as f:
        st, att = f["tasks/status"][:], f["tasks/attempts"][:]
        for t in tasks:
            if t.seed == 1:
                assert st[t.index] == FAILED and att[t.index] == 3
                rec = f["failures"][t.id].attrs
                assert "synthetic failure" in rec["message"] and "Traceback" in rec["traceback"]
                assert rec["attempts"] == 3 and rec["host"]
                assert np.isnan(f["scalars/phi"][t.index])
            else:
                assert st[t.index] == DONE
                assert att[t.index] == (2 if t.seed == 2 else 1)
    # each failing task was sent exactly 1 + retries times
    sent = [p["index"] for _, p in comm.sent]
    assert all(sent.count(t.index) == 3 for t in bad)


def test_no_retries_means_one_attempt(tmp_path, monkeypatch):
    monkeypatch.setenv("CAMPAIGN_SYNTHETIC_FLAKY", "seed:2")
    spec, tasks, ctx, store = _setup(tmp_path)
    out = Master(FakeComm(ctx, 2), store, tasks, retries=0).run()
    assert out["failed"] == sum(t.seed == 2 for t in tasks)
    store.close()


def test_a_dead_worker_costs_an_attempt_and_others_take_over(tmp_path):
    spec, tasks, ctx, store = _setup(tmp_path)
    comm = FakeComm(ctx, 2, die={1: 3})
    out = Master(comm, store, tasks, retries=1).run()
    store.close()
    assert out["done"] == len(tasks) and out["failed"] == 0
    assert len(comm.lost) == 2 and all(w == 2 for w, _ in comm.sent[comm.died_at:])
    assert all(store.attempts[i] == 2 for i in comm.lost)
    assert (store.attempts == 1).sum() == len(tasks) - 2


def test_wall_time_hook_stops_dispatching(tmp_path):
    spec, tasks, ctx, store = _setup(tmp_path)
    allowed = iter(range(10))
    out = Master(FakeComm(ctx, 2), store, tasks, can_dispatch=lambda t, ahead: next(allowed, None) is not None).run()
    store.close()
    assert out["stopped"] == "wall time" and out["done"] == 10 and out["remaining"] == len(tasks) - 10


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_dispatch_and_collects_running_tasks(tmp_path, sig):
    spec, tasks, ctx, store = _setup(tmp_path)

    def hit(n):
        if n == 5:
            os.kill(os.getpid(), sig)

    messages = []
    out = Master(FakeComm(ctx, 2, on_result=hit), store, tasks, log=messages.append).run()
    store.close()
    # 4 tasks were in flight at the signal (2 workers x depth 2), minus the one just finished
    assert out["stopped"] == sig.name and out["abandoned"] == 0
    assert 5 <= out["done"] <= 8 and out["remaining"] == len(tasks) - out["done"]
    assert any("no new tasks" in m for m in messages)
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert int((f["tasks/status"][:] == DONE).sum()) == out["done"]


def _payload_content(path):
    with h5py.File(path, "r") as f:
        out = {k: f[f"scalars/{k}"][:] for k in f["scalars"]}
        out.update({f"h/{k}": f[f"histograms/{k}/counts"][:] for k in f["histograms"]})
        out.update({f"t/{k}": f[f"tasks/{k}"][:] for k in ("id", "status", "attempts", "error", "N", "E", "seed")})
    return out


def test_local_processes_give_the_inline_result(tmp_path):
    spec, tasks, ctx, store = _setup(tmp_path, "inline.h5")
    Master(InlineComm(ctx), store, tasks).run()
    store.close()
    spec, tasks, ctx, store = _setup(tmp_path, "local.h5")
    comm = LocalComm(ctx, 2)
    try:
        assert comm.wait_ready() == set()
        out = Master(comm, store, tasks).run()
    finally:
        comm.close()
    store.close()
    assert out["done"] == len(tasks)
    a, b = _payload_content(tmp_path / "inline.h5"), _payload_content(tmp_path / "local.h5")
    assert set(a) == set(b)
    for k in a:
        assert np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), k
    with h5py.File(tmp_path / "local.h5", "r") as f:
        assert set(f["tasks/rank"][:]) == {1, 2}


def test_a_crashing_local_worker_is_survived(tmp_path, monkeypatch):
    monkeypatch.setenv("CAMPAIGN_SYNTHETIC_CRASH", "seed:3")
    spec, tasks, ctx, store = _setup(tmp_path)
    spec_small = [t for t in tasks if t.N == 16 and t.variant == "default"]  # 8 tasks, two of them crash
    crashing = [t for t in spec_small if t.seed == 3]
    # use a store over all tasks but only run the small set (others count as done elsewhere)
    for t in tasks:
        if t not in spec_small:
            store.status[t.index] = DONE
    comm = LocalComm(ctx, 2)
    try:
        out = Master(comm, store, tasks, retries=0).run()
    finally:
        comm.close()
    assert out["failed"] >= len(crashing)
    for t in crashing:
        assert store.status[t.index] == FAILED
        assert "died" in store.read("tasks/error", t.index).decode()
    store.abandon()


def test_a_warning_after_the_wall_time_stop_keeps_the_reason(tmp_path):
    """SLURM's USR1 arriving while the master collects its last tasks after a wall-time stop
    (a real signal to this process) starts the grace period; the run still says it stopped
    for the wall time."""
    import os
    import signal

    spec, tasks, ctx, store = _setup(tmp_path)
    budget = {"left": 5}

    def can_dispatch(task, queued):
        budget["left"] -= 1
        return budget["left"] > 0

    class WarnedComm(InlineComm):
        def recv(self, timeout=None):
            if budget["left"] <= 0 and not getattr(self, "warned", False):
                self.warned = True
                os.kill(os.getpid(), signal.SIGUSR1)
            return super().recv(timeout)

    comm = WarnedComm(ctx)
    logs = []
    out = Master(comm, store, tasks, retries=1, can_dispatch=can_dispatch, log=logs.append).run()
    store.close()
    assert comm.warned and any("SIGUSR1" in m for m in logs)
    assert out["stopped"] == "wall time" and 0 < out["done"] < len(tasks)
