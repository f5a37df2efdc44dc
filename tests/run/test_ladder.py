"""The energy-ladder protocol: chained tasks, the master's dependency scheduling, and the kernel.

A ladder variant reaches each energy of the grid from the same seed's packing at the next
higher energy (``kernels.jam(..., start=...)``) instead of from random positions.
"""

import numpy as np
import pytest

from campaign.errors import UserError
from campaign.run.master import Master
from campaign.plan.parse import parse_spec
from campaign.storage.store import DONE, FAILED, PENDING, Store
from campaign.plan.tasks import expand, task_cost
from campaign.run.worker import SyntheticTask
from helpers import LADDER_SPEC, FakeComm, synthetic_run

SPEC = LADDER_SPEC


def _setup(tmp_path, text=SPEC, name="s.h5"):
    return synthetic_run(tmp_path, text, name)


# ---------------------------------------------------------------------------- spec and tasks

def test_parents_are_the_same_seed_one_energy_up():
    spec = parse_spec(SPEC)
    tasks = expand(spec)
    for t in tasks:
        if t.variant == "default":
            assert t.parent is None and t.parent_E is None
            continue
        higher = [e for e in spec.E if e > t.E]
        if not higher:
            assert t.parent is None  # the chain's top starts from random positions
            continue
        p = tasks[t.parent]
        assert (p.variant, p.N, p.seed, p.E) == (t.variant, t.N, t.seed, min(higher))
        assert t.parent_E == p.E
        # a step down one rung costs less than a packing made from random at the same energy
        assert 0 < task_cost(t) < task_cost(tasks[t.index - len(spec.E) * len(spec.seeds) * len(spec.N)])


def test_start_is_validated_and_random_is_the_default():
    base = parse_spec(SPEC.replace("variants: [{name: ladder, start: ladder}]\n", ""))
    explicit = parse_spec(SPEC.replace("[{name: ladder, start: ladder}]", "[]").replace(
        "observables:", "protocol: {start: random}\nobservables:"))
    assert [t.id for t in expand(base)] == [t.id for t in expand(explicit)]
    with pytest.raises(UserError, match="unknown start 'cascade'; expected one of random, ladder"):
        parse_spec(SPEC.replace("start: ladder", "start: cascade"))


# ---------------------------------------------------------------------------- master

def test_every_step_starts_from_its_parents_packing(tmp_path):
    spec, tasks, ctx, store = _setup(tmp_path)
    comm = FakeComm(ctx, 3)
    master = Master(comm, store, tasks, retries=0)
    out = master.run()
    assert out == {"done": len(tasks), "failed": 0, "abandoned": 0, "stopped": None, "remaining": 0}
    order = {p["index"]: k for k, (_, p) in enumerate(comm.sent)}
    ladder = [t for t in tasks if t.parent is not None]
    assert len(ladder) == 2 * 3 * 3
    for t in ladder:
        payload = comm.sent[order[t.index]][1]
        parent_cfg = store.configuration(t.parent)
        assert parent_cfg is not None  # kept by the store although the spec stores no configurations
        np.testing.assert_array_equal(payload["start"]["positions"], parent_cfg["positions"])
        assert store.read("scalars/start_checksum", t.index) == float(np.sum(parent_cfg["positions"]))
        assert order[t.parent] < order[t.index]
    for t in tasks:
        if t.parent is None:
            assert "start" not in comm.sent[order[t.index]][1]
            assert np.isnan(store.read("scalars/start_checksum", t.index))
    # only parents are asked for their configuration; the default variant keeps none
    asked = {p["index"] for _, p in comm.sent if p.get("return_configuration")}
    assert asked == {t.parent for t in ladder}
    assert master.configs == {}  # each parent's packing is dropped once its child is done
    store.close()


def test_a_failed_parent_fails_its_chain_below_and_nothing_else(tmp_path, monkeypatch):
    spec, tasks, ctx, store = _setup(tmp_path)
    victim = next(t for t in tasks if t.variant == "ladder" and t.N == 32 and t.seed == 1 and t.E == 1e-4)
    monkeypatch.setenv("CAMPAIGN_SYNTHETIC_FAIL", victim.id[:12])
    out = Master(FakeComm(ctx, 2), store, tasks, retries=1).run()
    below = [t for t in tasks if t.variant == "ladder" and t.N == 32 and t.seed == 1 and t.E < 1e-4]
    assert len(below) == 2
    assert out["failed"] == 3 and out["done"] == len(tasks) - 3 and out["remaining"] == 0
    assert store.status[victim.index] == FAILED
    for t in below:
        assert store.status[t.index] == FAILED
        assert b"ladder parent" in store.read("tasks/error", t.index)
    store.close()


def test_resume_continues_the_chains_from_stored_packings(tmp_path):
    text = SPEC.replace("variants: [{name: ladder, start: ladder}]", "protocol: {start: ladder}")
    spec, tasks, ctx, store = _setup(tmp_path, text)
    assert all(t.parent is not None for t in tasks if t.E < 1e-2)
    budget = {"n": 9}

    def can_dispatch(task, ahead):
        budget["n"] -= 1
        return budget["n"] >= 0

    out = Master(FakeComm(ctx, 2), store, tasks, can_dispatch=can_dispatch).run()
    assert out["stopped"] == "wall time" and 0 < out["remaining"] < len(tasks)
    store.close()
    # a new process: the parents' packings come from the file, not from memory
    store = Store(tmp_path / "s.h5", spec, tasks, SyntheticTask().histogram_edges(ctx))
    resumed = [t for t in tasks if t.parent is not None and store.status[t.index] == PENDING
               and store.status[t.parent] == DONE]
    assert resumed, "the interruption should leave a chain half done"
    comm = FakeComm(ctx, 2)
    out = Master(comm, store, tasks).run()
    assert out["remaining"] == 0 and all(store.status == DONE)
    sent = {p["index"]: p for _, p in comm.sent}
    for t in resumed:
        np.testing.assert_array_equal(sent[t.index]["start"]["positions"], store.configuration(t.parent)["positions"])
    store.close()


# ---------------------------------------------------------------------------- kernel

def test_jam_from_a_packing_reaches_the_lower_window_deterministically():
    import kernels

    top = kernels.jam(64, 1e-4, 11)
    steps = []
    for E in (1e-6, 1e-9):
        p = kernels.jam(64, E, 0, start=top if not steps else steps[-1])
        assert p.status == "converged"
        assert E <= p.energy <= E * 1.1
        assert p.force_residual <= 1e-6
        np.testing.assert_array_equal(p.species, top.species)
        assert p.settings["start"] == "packing"
        steps.append(p)
    again = kernels.jam(64, 1e-6, 99, start=(top.positions, top.radii, top.species))
    assert again.positions.tobytes() == steps[0].positions.tobytes()  # the seed is not used
    # decompressing: smaller disks at the lower energy, the same disks otherwise
    assert np.all(steps[0].radii < top.radii)
    np.testing.assert_allclose(steps[0].radii / top.radii, steps[0].radii[0] / top.radii[0], rtol=1e-12)


@pytest.mark.parametrize("start, match", [
    ((np.zeros((5, 2)), np.ones(64), np.zeros(64)), r"start: expected positions \(64, 2\)"),
    ((np.zeros((64, 2)), -np.ones(64), np.zeros(64)), "positive finite radii"),
    ((np.full((64, 2), np.nan), np.ones(64), np.zeros(64)), "finite positions"),
    ("ladder", "start: expected None, a Packing"),
])
def test_bad_start_is_refused(start, match):
    import kernels

    with pytest.raises(ValueError, match=match):
        kernels.jam(64, 1e-6, 0, start=start)


def test_start_packing_from_another_box_is_refused():
    import kernels

    p = kernels.jam(32, 1e-3, 0, box=(2.0, 1.0))
    with pytest.raises(ValueError, match=r"start: expected a packing in the box \[1.0, 1.0\]"):
        kernels.jam(32, 1e-5, 0, start=p)


def test_a_large_ladder_start_never_deadlocks_a_busy_worker(tmp_path, monkeypatch):
    """A ladder step carries its parent's packing (hundreds of kB at N_G 8192), more than a
    pipe's buffer or MPI's eager limit. Sent to a worker still busy with a task, it blocked the
    master in its send while the worker blocked sending its result (a large configuration too)
    to the master: both waited forever (seen at N_G 8192). Real worker processes, packings of
    20000 disks (480 kB), each task 0.2 s."""
    import threading

    from campaign.run.comm import LocalComm

    monkeypatch.setenv("CAMPAIGN_SYNTHETIC_DELAY", "0.2")
    spec, tasks, ctx, store = _setup(tmp_path, SPEC.replace("N_G: [16, 32]", "N_G: [20000]")
                                     .replace("seeds: 3", "seeds: 2"))
    comm = LocalComm(ctx, 1)
    out = {}
    try:
        assert comm.wait_ready() == set()
        t = threading.Thread(target=lambda: out.update(Master(comm, store, tasks, retries=0).run()), daemon=True)
        t.start()
        t.join(60)
        assert not t.is_alive(), "the master and its worker are deadlocked"
    finally:
        if out:
            comm.close()
        else:  # deadlocked: kill the worker so that the test process can go on
            for p in comm.procs.values():
                p.kill()
    assert out == {"done": len(tasks), "failed": 0, "abandoned": 0, "stopped": None, "remaining": 0}
    store.close()
