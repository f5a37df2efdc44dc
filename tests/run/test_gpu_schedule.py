"""A GPU worker's event loop (campaign.run.gpuworker) on a fake clock: what it launches and when,
with a fake task function that records every launch; and its step budget."""

import math

import numpy as np
import pytest

from campaign.run import gpuworker
from campaign.run.gpuworker import GpuLoop, StepBudget
from campaign.run.worker import batch_key


class World:
    """The master's messages on a fake clock: ``script`` is ``[(time, message), ...]``; the loop's
    ``sleep`` advances the clock, a blocking ``recv`` jumps to the next message."""

    def __init__(self, script):
        self.t = 0.0
        self.script = sorted(script, key=lambda x: x[0])
        self.sent = []  # (time, message)

    def clock(self):
        return self.t

    def now(self):
        return 1000.0 + self.t  # epoch seconds

    def sleep(self, dt):
        assert dt > 0
        self.t += dt

    def poll(self):
        return bool(self.script) and self.script[0][0] <= self.t

    def recv(self):
        assert self.script, "the loop blocked waiting for a message that will never come"
        t, msg = self.script.pop(0)
        self.t = max(self.t, t)
        return msg

    def send(self, msg):
        self.sent.append((self.t, msg))


class FakeGpu:
    """A task function whose launches take ``duration`` seconds of the fake clock and whose
    analysis ``analysis`` seconds; each packing needs ``need[index]`` FIRE steps of ``step``
    seconds (a launch with a budget lasts budget x step x packings, as the emulation's)."""

    def __init__(self, world, duration=1.0, analysis=0.01, step=None, need=None):
        self.world, self.duration, self.analysis = world, duration, analysis
        self.step, self.need = step, need or {}
        self.launches = []  # dicts: start, end, size, budget, resumed

    def start_batch(self, payloads, context, budget=None, resume=None):
        resume = resume or [None] * len(payloads)
        items = []
        longest = 0
        for p, r in zip(payloads, resume):
            done = r.steps if r is not None else 0
            left = self.need.get(p["index"], 1) - done
            run = left if budget is None else min(left, budget)
            longest = max(longest, run)
            items.append(Halted(p, done + run) if run < left else ("packing", p["index"], done + run))
        t = self.world.t
        end = t + (self.duration if self.step is None else self.step * longest * len(payloads))
        launch = {"start": t, "end": end, "size": len(payloads), "budget": budget,
                  "resumed": sum(r is not None for r in resume), "items": items}
        self.launches.append(launch)
        return launch

    def batch_done(self, launch):
        return self.world.t >= launch["end"]

    def finish_batch(self, launch):
        assert self.world.t >= launch["end"], "collected before it ended: the loop would have waited"
        return [x if isinstance(x, Halted) else (x,) for x in launch["items"]]

    def clock(self, item):
        steps = item.steps if isinstance(item, Halted) else item[0][2]
        return steps * self.step, steps

    def analyse(self, payload, context, item):
        self.world.t += self.analysis
        return {"steps": float(item[2])}, {}, None


class Halted:
    """A packing stopped at its budget (what kernels.gpu.batch.Suspended offers the loop)."""

    def __init__(self, payload, steps):
        self.payload, self.steps = payload, steps
        self.force_evaluations = steps
        self.device_clock = {"seconds": 0.0, "launches": 1}

    def arrays(self):
        return {"positions": np.full((4, 2), float(self.steps))}


def task(i, n=64):
    return ("task", {"id": f"t{i}", "index": i, "N": n, "E": 1e-6, "seed": i, "variant": "gpu",
                     "protocol": {"device": "gpu"}, "attempt": 1})


def summary(payload, context, rank, got, wall):
    return {"index": payload["index"], "ok": not isinstance(got, Exception), "got": got}


def serve(world, fn, limit, context=None, **kw):
    loop = GpuLoop(fn, context or {}, 1, world.recv, world.send, world.poll, summary,
                   lambda p: summary(p, {}, 1, ({}, {}, None), 0.0), batch_key, limit=limit,
                   clock=world.clock, now=world.now, sleep=world.sleep, **kw)
    loop.serve()
    return loop


def results(world):
    return {m[1] for _, m in world.sent if m[0] == "result"}


def test_a_batch_is_gathered_before_its_launch():
    """Tasks that come one after the other, each within the settle window of the last, go out in
    one launch: never a launch of one while the rest of the batch is on its way."""
    world = World([(0.03 * k, task(k)) for k in range(7)] + [(30.0, ("stop",))])
    fn = FakeGpu(world)
    serve(world, fn, limit=16)
    assert [x["size"] for x in fn.launches] == [7]
    assert fn.launches[0]["start"] >= 0.18  # after the last task came
    assert results(world) == set(range(7))


def test_a_full_batch_goes_at_once_and_the_rest_after_the_window():
    world = World([(0.0, task(k)) for k in range(10)] + [(30.0, ("stop",))])
    fn = FakeGpu(world)
    serve(world, fn, limit=4)
    assert [x["size"] for x in fn.launches] == [4, 4, 2]
    assert fn.launches[0]["start"] == 0.0  # full: no waiting
    assert results(world) == set(range(10))


def test_launches_overlap_and_results_go_out_while_the_gpu_runs():
    """A batch that comes while a launch runs is launched without waiting for it to end (up to
    ``in_flight`` launches), and the first launch's packings are analysed and sent while the
    second runs; a third batch waits for a free place when two are in flight."""
    script = [(0.0, task(k)) for k in range(4)]
    script += [(0.5, task(k)) for k in range(4, 8)]
    script += [(0.6, task(k)) for k in range(8, 12)]
    script += [(30.0, ("stop",))]
    world = World(script)
    fn = FakeGpu(world, duration=2.0, analysis=0.05)
    serve(world, fn, limit=4, in_flight=2)
    first, second, third = fn.launches
    assert [x["size"] for x in fn.launches] == [4, 4, 4]
    assert second["start"] < first["end"]  # in flight together
    assert third["start"] >= first["end"]  # at most two in flight
    sent_first = [t for t, m in world.sent if m[0] == "result" and m[1] < 4]
    assert len(sent_first) == 4 and max(sent_first) < second["end"]
    assert results(world) == set(range(12))


def test_it_sends_everything_before_it_waits_for_the_master():
    """The loop blocks on the master only with nothing in flight, waiting or unanalysed: the
    results of a launch are all sent before the next tasks come (World.recv would fail if the loop
    waited on a message that only comes after the results it holds)."""
    world = World([(0.0, task(k)) for k in range(3)] + [(100.0, task(3)), (200.0, ("stop",))])
    fn = FakeGpu(world, duration=1.0)
    serve(world, fn, limit=8)
    assert [x["size"] for x in fn.launches] == [3, 1]
    last_of_first = max(t for t, m in world.sent if m[0] == "result" and m[1] < 3)
    assert last_of_first < 100.0


def test_a_cpu_task_runs_alone_between_launches():
    cpu = ("task", {"id": "c", "index": 99, "N": 64, "E": 1e-6, "seed": 0, "variant": "default",
                    "protocol": {}, "attempt": 1})
    world = World([(0.0, task(0)), (0.0, task(1)), (0.0, cpu), (20.0, ("stop",))])
    fn = FakeGpu(world)
    serve(world, fn, limit=8)
    assert [x["size"] for x in fn.launches] == [2]
    assert results(world) == {0, 1, 99}


def test_the_step_budget_plans_for_the_time_left():
    """Budget = SAFETY x time left / (block step x waves), waves = the launch's packings and those
    still on the device over the resident slots; the probe before any measurement; nothing below
    MIN_STEPS; no budget without a deadline."""
    clock = {"t": 0.0}
    b = StepBudget(deadline=100.0, margin=10.0, now=lambda: clock["t"])
    assert StepBudget(None).steps(64, 8) is None
    assert b.steps(64, 8) == gpuworker.PROBE_STEPS
    b.learn(64, seconds=2.0, steps=4000)  # 0.5 ms a step
    b.slots[64] = 4
    # 90 s left, 6 + 2 packings on 4 slots: two waves of 0.5 ms steps
    assert b.steps(64, 6, ahead=2) == int(gpuworker.SAFETY * 90.0 / (2 * 0.5e-3))
    clock["t"] = 90.0 - 1e-3  # a millisecond left: not worth a launch
    assert b.steps(64, 6) == 0


def test_packings_stop_at_their_budget_and_go_on_or_go_back():
    """With a deadline: the first launch probes; a packing that reaches its budget goes on from its
    state here while there is time, and goes back to the master with its state when there is not;
    the others finish and are sent."""
    need = {0: 500, 1: 3000, 2: 10**7}  # FIRE steps each needs; task 2 cannot finish in time
    world = World([(0.0, task(k)) for k in range(3)] + [(1e6, ("stop",))])
    fn = FakeGpu(world, step=1e-3, need=need)
    context = {"deadline": 1000.0 + 60.0, "margin": 10.0}  # 50 s of work at most
    serve(world, fn, limit=8, context=context)
    assert fn.launches[0]["budget"] == gpuworker.PROBE_STEPS and fn.launches[0]["size"] == 3
    assert all(x["resumed"] == x["size"] for x in fn.launches[1:])  # every later launch goes on
    assert results(world) == {0, 1}
    back = [m for _, m in world.sent if m[0] == "suspended"]
    assert [m[1] for m in back] == [2]
    record = back[0][3]
    assert record["steps"] == record["arrays"]["positions"][0, 0] and record["steps"] < need[2]
    # every launch ended before the deadline less the margin
    assert max(x["end"] for x in fn.launches) <= 50.0 + 1e-9
    assert record["steps"] > 0.5 * 50.0 / 1e-3 * gpuworker.SAFETY  # most of the time went into it


def test_a_task_with_no_time_left_goes_back_untouched():
    world = World([(0.0, task(0)), (0.0, task(1)), (1e6, ("stop",))])
    fn = FakeGpu(world, step=1e-3)
    serve(world, fn, limit=8, context={"deadline": 1000.0 + 5.0, "margin": 10.0})  # already past
    assert fn.launches == []
    assert sorted((m[0], m[1], m[3]) for _, m in world.sent) == [("suspended", 0, None), ("suspended", 1, None)]


@pytest.mark.parametrize("fails", ["launch", "collect"])
def test_a_launch_that_fails_fails_its_tasks_and_the_worker_goes_on(fails):
    world = World([(0.0, task(0)), (0.0, task(1)), (5.0, task(2)), (30.0, ("stop",))])

    class Broken(FakeGpu):
        def start_batch(self, payloads, context, **kw):
            if fails == "launch" and payloads[0]["index"] == 0:
                raise RuntimeError("out of memory")
            return super().start_batch(payloads, context, **kw)

        def finish_batch(self, launch):
            if fails == "collect" and launch["items"][0][1] == 0:
                raise RuntimeError("lost device")
            return super().finish_batch(launch)

    serve(world, Broken(world), limit=8)
    ok = {m[1]: m[3]["ok"] for _, m in world.sent if m[0] == "result"}
    assert ok == {0: False, 1: False, 2: True}
    assert not math.isnan(world.t)
