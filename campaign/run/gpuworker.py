"""A GPU worker's event loop: the GPU is never left idle while there is work for it.

``campaign.run.worker.worker_loop`` hands a GPU worker's messages to ``GpuLoop.serve`` when its
task function has ``start_batch`` (launch: on a GPU it returns at once), ``finish_batch`` (the
packings of a launch that has ended) and ``analyse`` (one packing's summary tuple); optionally
``batch_done`` (whether a launch has ended, never waiting; without it a launch ends when
``start_batch`` returns, as the emulation's does), ``slots`` (blocks the device holds at once for
a launch) and ``clock`` (a packing's block-seconds and FIRE steps, for the step budget).

The loop, round after round, never blocking while there is something to do:

1. takes every message waiting (tasks, the master's stop) without blocking;
2. collects the launches that have ended (``batch_done``) and queues their packings for analysis;
3. launches the waiting tasks of one ``batch_key`` (variant, N_G, protocol) as one batch when it
   is *due*: full (``limit`` tasks, ``--gpu-batch``), or no task has come for ``settle`` seconds
   (the master sends a batch's tasks back to back: a launch of one packing while the others are
   on their way would run alone), or its first task has waited ``gather`` seconds while tasks
   kept coming. It does not wait for the launches in flight to end: up to ``in_flight`` launches
   run at once, each on a stream of its own, so that a launch's blocks fill the SMs that an
   earlier launch's tail leaves idle;
4. analyses one finished packing on this process's core and sends its result, then goes round
   again (so that a launch that ends, or a task that comes, is seen between two analyses);
5. runs a task that cannot share a launch (a CPU task the master gives a GPU worker once no GPU
   task waits) by itself, once no packing waits for its analysis;
6. blocks waiting for the master only when nothing is in flight, waiting or unanalysed: every
   result is sent before the worker would wait.

The master keeps ``(in_flight + 1) x limit`` tasks outstanding at a GPU worker
(``campaign.run.comm``): the launches in flight and the next batch gathering.

**Stop and go.** With a deadline (``context["deadline"]``, epoch seconds, and ``context["margin"]``:
``campaign run --time-limit`` or ``SLURM_JOB_END_TIME``) every launch gets a step budget, the FIRE
steps each of its packings may take (``StepBudget``): the time left before the deadline less the
margin, over the block step time measured on this worker's earlier packings of that N_G (their
device clock's block-seconds over their FIRE steps) times the waves of blocks the launch and those
in flight make on the device's resident slots; a short probe budget (``PROBE_STEPS``) before any
was measured. A packing that reaches its budget comes back suspended: while there is time for at
least ``MIN_STEPS`` more steps it is launched again from its state here, else it goes to the
master as ``("suspended", index, attempt, record)`` (``record``: its arrays and counters; the
master saves it in the store and the next run resumes it). A task that would get fewer than
``MIN_STEPS`` steps is not launched: it goes back the same way with ``record`` None (nothing to
save). The finished packing is the one of an uninterrupted search, bit for bit.

A fault of a launch (out of memory, a lost device) fails that launch's tasks with its reason; a
packing that fails alone (a ``BlockOverflow``) or whose analysis fails fails alone.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field

#: launches a GPU worker keeps running at once (each on a stream of its own)
IN_FLIGHT = 3
#: seconds without a new task after which a partial batch is launched
SETTLE = 0.1
#: seconds a partial batch waits at most for more tasks while tasks keep coming
GATHER = 2.0
#: FIRE steps of a launch made before this worker has measured a block step at that N_G
PROBE_STEPS = 1000
#: fewest FIRE steps worth a launch; a packing that cannot get them before the deadline goes back
MIN_STEPS = 100
#: fraction of the time left a launch's budget plans for (its estimate's error, the collection)
SAFETY = 0.8


def is_suspended(item) -> bool:
    """Whether a launch's item is a suspended packing (``kernels.gpu.batch.Suspended``: its
    ``arrays()`` and ``steps``), not a finished one's tuple or the exception that failed it."""
    return callable(getattr(item, "arrays", None)) and hasattr(item, "steps")


class StepBudget:
    """The FIRE steps a launch's packings may take before ``deadline - margin`` (epoch seconds;
    ``deadline`` None: unbounded), from the block step time measured per N_G."""

    def __init__(self, deadline=None, margin=0.0, now=time.time):
        self.deadline, self.margin, self.now = deadline, float(margin or 0.0), now
        self.step = {}   # N -> seconds per FIRE step of one block (the last launch that ran it)
        self.slots = {}  # N -> blocks the device held at once in a launch of that N

    def learn(self, n, seconds, steps):
        """A launch of N_G ``n`` took ``seconds`` block-seconds for ``steps`` FIRE steps in all."""
        if steps > 0 and seconds > 0 and math.isfinite(seconds):
            self.step[n] = seconds / steps

    def left(self) -> float:
        return math.inf if self.deadline is None else self.deadline - self.margin - self.now()

    def steps(self, n, packings, ahead=0):
        """The budget of a launch of ``packings`` packings of N_G ``n`` with ``ahead`` packings of
        earlier launches still on the device: None (no deadline), 0 (not worth a launch), or the
        FIRE steps each packing may take."""
        if self.deadline is None:
            return None
        left = self.left()
        t = self.step.get(n)
        if t is None:
            return PROBE_STEPS if left > 0 else 0
        waves = math.ceil((packings + ahead) / max(1, self.slots.get(n, 1)))
        steps = int(SAFETY * left / (t * waves)) if left > 0 else 0
        return steps if steps >= MIN_STEPS else 0


@dataclass
class Launch:
    handle: object
    payloads: list
    started: float  # perf_counter at the launch


@dataclass
class Waiting:
    """Tasks of one batch key waiting for a launch: (payload, state to resume from or None)."""
    tasks: list = field(default_factory=list)
    since: float = 0.0  # monotonic time of its oldest task


class GpuLoop:
    """The event loop of a GPU worker (module docstring). ``summary(payload, context, rank, got,
    wall)`` makes a task's summary (``campaign.run.worker._summary``), ``run_alone(payload)`` runs
    a task that shares no launch and returns its summary, ``key(payload)`` is the batch key (None:
    it runs alone). ``clock`` (monotonic), ``now`` (epoch) and ``sleep`` are the loop's time."""

    def __init__(self, fn, context, rank, recv, send, poll, summary, run_alone, key, *, limit,
                 in_flight=IN_FLIGHT, settle=SETTLE, gather=GATHER, clock=time.monotonic, now=time.time,
                 sleep=time.sleep):
        self.fn, self.context, self.rank = fn, context, rank
        self.recv, self.send, self.poll = recv, send, poll
        self.summary, self.run_alone, self.key = summary, run_alone, key
        self.limit, self.in_flight = max(1, int(limit)), max(1, int(in_flight))
        self.settle, self.gather = settle, gather
        self.clock, self.sleep = clock, sleep
        self.budget = StepBudget(context.get("deadline"), context.get("margin", 0.0), now)
        self.waiting: dict = {}       # batch key -> Waiting
        self.alone = deque()          # tasks that run by themselves
        self.running: list = []       # Launch, oldest first
        self.ready = deque()          # (payload, item, seconds of its launch's share)
        self.last_arrival = -math.inf
        self.stopping = False
        self.gone = False             # the master is gone: stop now

    # ---- the loop
    def serve(self) -> None:
        while True:
            self._receive()
            if self.gone:
                return
            self._collect()
            if not self.stopping:
                self._launch_due()
            if self.ready:
                self._analyse_one()
                continue
            if self.alone and not self.stopping:
                payload = self.alone.popleft()
                s = self.run_alone(payload)
                self.send(("result", payload["index"], payload.get("attempt", 1), s))
                continue
            if self.stopping and not self.running:
                return
            if not self.running and not self.waiting:
                self._take(self.recv())  # nothing to do until the master sends: everything was sent
                continue
            self.sleep(self._nap())

    def _nap(self) -> float:
        """How long to wait before looking again: until the next batch falls due, at most 2 ms."""
        nap = 2e-3
        now = self.clock()
        for w in self.waiting.values():
            nap = min(nap, max(0.0, self.last_arrival + self.settle - now), max(0.0, w.since + self.gather - now))
        return max(nap, 1e-4)

    def _receive(self):
        while not self.gone and self.poll():
            self._take(self.recv())

    def _take(self, msg):
        if msg is None:
            self.gone = True
            return
        if msg[0] == "stop":
            self.stopping = True
            return
        payload = msg[1]
        self.last_arrival = self.clock()
        key = self.key(payload)
        if key is None:
            self.alone.append(payload)
        else:
            self._wait(key, payload, None)

    def _wait(self, key, payload, state, front=False):
        w = self.waiting.get(key)
        if w is None:
            w = self.waiting[key] = Waiting(since=self.clock())
        if front:
            w.tasks.insert(0, (payload, state))
        else:
            w.tasks.append((payload, state))

    # ---- launching
    def _due(self, w, now) -> bool:
        return (len(w.tasks) >= self.limit or now - self.last_arrival >= self.settle
                or now - w.since >= self.gather)

    def _launch_due(self):
        now = self.clock()
        for key in sorted(self.waiting, key=lambda k: self.waiting[k].since):
            if len(self.running) >= self.in_flight:
                return
            w = self.waiting[key]
            if not self._due(w, now):
                continue
            batch, w.tasks = w.tasks[:self.limit], w.tasks[self.limit:]
            if not w.tasks:
                del self.waiting[key]
            else:
                w.since = now
            self._start(batch)

    def _start(self, batch):
        payloads = [p for p, _ in batch]
        resume = [s for _, s in batch]
        n = payloads[0]["N"]
        ahead = sum(len(launch.payloads) for launch in self.running)
        budget = self.budget.steps(n, len(payloads), ahead)
        if budget == 0:  # no time left for a launch: back to the master, saved if it has a state
            for payload, state in batch:
                self._suspend(payload, state)
            return
        t0 = time.perf_counter()
        try:
            kwargs = {} if budget is None and not any(s is not None for s in resume) else {
                "budget": budget, "resume": resume}
            handle = self.fn.start_batch(payloads, self.context, **kwargs)
        except Exception as exc:  # noqa: BLE001 - the launch fails, the worker goes on
            share = (time.perf_counter() - t0) / len(payloads)
            self.ready.extend((p, exc, share) for p in payloads)
            return
        if hasattr(self.fn, "slots"):
            try:
                self.budget.slots[n] = int(self.fn.slots(handle))
            except Exception:  # noqa: BLE001 - one slot: a conservative budget
                pass
        self.running.append(Launch(handle, payloads, t0))

    # ---- collecting
    def _ended(self, launch) -> bool:
        if not hasattr(self.fn, "batch_done"):
            return True
        try:
            return bool(self.fn.batch_done(launch.handle))
        except Exception:  # noqa: BLE001 - finish_batch reports the fault
            return True

    def _collect(self):
        for launch in [x for x in self.running if self._ended(x)]:
            self.running.remove(launch)
            try:
                got = self.fn.finish_batch(launch.handle)
            except Exception as exc:  # noqa: BLE001 - the launch's tasks fail with its reason
                got = [exc] * len(launch.payloads)
            share = (time.perf_counter() - launch.started) / len(launch.payloads)
            self._learn(launch.payloads[0]["N"], got)
            for payload, item in zip(launch.payloads, got):
                if is_suspended(item):
                    if self.budget.steps(payload["N"], 1) and not self.stopping:
                        self._wait(self.key(payload), payload, item, front=True)  # on from here
                    else:
                        self._suspend(payload, item)
                else:
                    self.ready.append((payload, item, share))

    def _learn(self, n, got):
        if not hasattr(self.fn, "clock"):
            return
        seconds = steps = 0.0
        for item in got:
            if isinstance(item, Exception):
                continue
            try:
                s, k = self.fn.clock(item)
            except Exception:  # noqa: BLE001 - a packing without a clock teaches nothing
                continue
            if s == s and k == k:
                seconds, steps = seconds + s, steps + k
        self.budget.learn(n, seconds, steps)

    def _suspend(self, payload, state):
        """Hand a task back to the master: its suspended state (saved in the store, resumed by the
        next run), or None when it did not run here."""
        record = None
        if state is not None:
            clock = dict(getattr(state, "device_clock", {}) or {})
            record = {"arrays": state.arrays(), "steps": int(state.steps),
                      "force_evaluations": int(getattr(state, "force_evaluations", 0)),
                      "device_seconds": float(clock.get("seconds", math.nan)),
                      "launches": int(clock.get("launches", 0)), "rank": self.rank}
        self.send(("suspended", payload["index"], payload.get("attempt", 1), record))

    # ---- analysing
    def _analyse_one(self):
        payload, item, share = self.ready.popleft()
        t0 = time.perf_counter()
        if not isinstance(item, Exception):
            try:
                item = self.fn.analyse(payload, self.context, *item)
            except Exception as exc:  # noqa: BLE001 - that task fails, the batch goes on
                item = exc
        summary = self.summary(payload, self.context, self.rank, item, share + time.perf_counter() - t0)
        self.send(("result", payload["index"], payload.get("attempt", 1), summary))
