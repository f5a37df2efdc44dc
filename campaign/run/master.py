"""The master loop: dynamic scheduling, retries, signals, progress.

It talks to a ``comm`` (campaign.run.comm: inline, local processes or MPI) and a
``store`` (campaign.storage.store) and knows nothing else about either. Tasks go out
most expensive first (campaign.plan.tasks.cost), ``depth`` (2) per worker at a time
so that a worker never waits for the master between two tasks (more when tasks
are only milliseconds long). A ladder step, which carries its parent's packing, goes
only to a worker with nothing in flight: sends are blocking, and a large one to a busy
worker would wait for that worker while it waits to send its result.

* A failed task (an error record from its worker, or a worker that died under
  it) goes back into the queue until it has had ``1 + retries`` attempts; then
  it is recorded as failed and the campaign goes on.
* ``can_dispatch(task, ahead) -> bool``: a hook asked before each dispatch, with
  the tasks already queued at that worker; ``False`` stops dispatching (the next
  task would not fit in the wall time left: campaign.run.walltime). A ``device: gpu``
  task for a GPU worker is asked with ``suspendable=True``: it may stop at a step budget.
* Stop and go (GPU workers, docs/GPU.md): a worker hands back a packing it stopped at
  its step budget as ``("suspended", index, attempt, record)``; the store keeps its
  state (``Store.suspend``), the task stays pending and is not dispatched again in this
  run, and a task with a kept state goes out with it (``payload["resume"]``), to a CPU
  worker only when nothing is in flight there (a large payload, as a ladder step's).
* First SIGINT/SIGTERM/SIGUSR1 (SLURM's warning before the time limit): stop
  dispatching, collect the running tasks for up to
  ``grace`` seconds; a second signal (or the end of the grace time) abandons
  them. Either way the store is flushed and closed, and resuming is a rerun.
* Ladder chains (``Task.parent``): a task waits until its parent is done and is sent
  with the parent's configuration (``payload["start"]``); a parent is asked to return
  its configuration (``payload["return_configuration"]``), which the store keeps, so a
  resumed run continues the chains. When a parent fails for good, its descendants are
  recorded as failed with the reason.
* Rounds (a campaign with precision targets, ``campaign.run.rounds``): only the tasks its
  decisions gave out run; when every task of the rounds decided is finished, the next decision
  gives out more (or ends the campaign), and a worker that would wait meanwhile gets the next
  round's early seeds.
"""

from __future__ import annotations

import heapq
import signal
import time
from collections import deque

import numpy as np

from campaign.storage.layout import DONE, FAILED, PENDING
from campaign.plan.tasks import task_cost


class Master:
    def __init__(self, comm, store, tasks, *, retries=2, depth=2, progress=None, can_dispatch=None,
                 grace=20.0, redo_failed=False, log=None, rounds=None):
        self.comm, self.store, self.tasks = comm, store, tasks
        self.retries, self.depth, self.progress = retries, depth, progress
        self.can_dispatch, self.grace = can_dispatch, grace
        self.log = log or (lambda msg: None)
        T = len(tasks)
        self.rounds = rounds
        status = np.asarray(store.status)
        todo = (status == PENDING) | ((status == FAILED) if redo_failed else False)
        if rounds is not None:  # the tasks the decisions gave out (a decision due now is made first)
            allowed = rounds.allowed()
            allowed[rounds.advance()] = True
            todo &= allowed
        self.costs = np.fromiter((task_cost(t) for t in tasks), np.float64, T)
        self.children = {}
        parent = np.full(T, -1, np.int64)
        for t in tasks:
            if t.parent is not None:
                self.children.setdefault(t.parent, []).append(t.index)
                parent[t.index] = t.parent
        self.configs = {}  # parent index -> its configuration, while its children need it
        self._woken = False  # a child became ready: offer it to every worker
        # a task runs once its parent is done; a parent that failed for good fails its chain below
        has_parent = parent >= 0
        waits = np.zeros(T, bool)
        waits[has_parent] = status[parent[has_parent]] != DONE
        self.blocked = set(np.flatnonzero(todo & waits).tolist())
        # the queues: the ready tasks most expensive first (ties in canonical order). With GPU
        # workers (comm.capacity) device: gpu tasks have their own queue, which only GPU workers take
        # from while one is alive; a GPU worker takes CPU tasks when no GPU task waits
        ready = np.flatnonzero(todo & ~waits)
        self.capacity = dict(getattr(comm, "capacity", {}))  # GPU workers: tasks per batch
        self.on_gpu = np.zeros(T, bool)
        if self.capacity:
            self.on_gpu = np.fromiter((dict(t.protocol).get("device") == "gpu" for t in tasks), bool, T)
        order = ready[np.lexsort((ready, -self.costs[ready]))]
        self.queues = {False: _Queue(order[~self.on_gpu[order]], self.costs),
                       True: _Queue(order[self.on_gpu[order]], self.costs)}
        self.cost_remaining = float(self.costs[todo].sum())
        self.attempts = np.zeros(T, np.int32)
        self.n_done = self.n_failed = 0
        self._orphans = [int(i) for i in sorted(self.blocked) if not todo[parent[i]]
                         and status[parent[i]] == FAILED]
        self.in_flight = {w: deque() for w in range(1, comm.n_workers + 1)}
        self.alive = set(self.in_flight) - set(getattr(comm, "dead", ()))
        self.n_suspended = 0         # packings GPU workers handed back at their step budget
        self.gpu_time_up = False     # a GPU worker said no launch fits before the deadline
        self.stop_reason = None      # why dispatching stopped early (signal name, wall time, ...)
        self.stop_since = None
        self.signals = 0
        self._finished, self._cost, self._last_progress = 0, 0.0, 0.0
        self.mean_wall = None  # running mean of the workers' task times (sets the dispatch depth)

    # ---- signals
    def on_signal(self, signum, frame=None):
        """What SIGINT, SIGTERM and SIGUSR1 do (also called for a signal that came before the
        master started): stop dispatching, then wait for the running tasks up to the grace time."""
        self.signals += 1
        name = signal.Signals(signum).name
        if self.signals == 1:
            # a warning that comes after the wall-time stop (SLURM's USR1 while the last tasks
            # finish) starts the grace period but does not rename why the run stopped
            self.stop_reason = self.stop_reason or name
            self.stop_since = time.monotonic()
            running = sum(len(q) for q in self.in_flight.values())
            self.log(f"\ncampaign: {name}: no new tasks; waiting up to {self.grace:g} s for {running} running "
                     f"task(s) (send it again to abandon them)")
        else:
            self.log(f"\ncampaign: {name} again: abandoning the running tasks")

    def _install_signals(self):
        old = {}
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1):
            try:
                old[sig] = signal.signal(sig, self.on_signal)
            except ValueError:  # not the main thread
                pass
        return old

    # ---- the queue
    def _queued(self):
        return self.queues[False].queued() + self.queues[True].queued()

    def _queue_for(self, w):
        """The queue worker ``w`` takes from now: a GPU worker its GPU tasks, then CPU tasks; a CPU
        worker CPU tasks, and GPU tasks (emulated) only when no GPU worker is left."""
        if w in self.capacity:
            return self.queues[bool(self.queues[True].queued()) and not self.gpu_time_up]
        if not self.queues[False].queued() and not (self.alive & set(self.capacity)):
            return self.queues[True]
        return self.queues[False]

    def _push(self, i):
        self.queues[bool(self.on_gpu[i])].push(i)

    def _give(self, indices):
        """Tasks a round's decision gave out: into the queues."""
        for i in indices:
            self._push(int(i))
            self.cost_remaining += float(self.costs[i])
        if indices:
            self._woken = True

    def _next_round(self):
        """With rounds: when every task of the rounds decided is finished, the next decision (made
        beside this loop: ``_round_made`` collects it)."""
        if self.rounds is not None and self.rounds.open <= 0 and self.stop_reason is None:
            self.rounds.start()

    def _round_made(self):
        """A decision made: its tasks into the queues and out to every worker."""
        if self.rounds is None:
            return
        got = self.rounds.poll()
        if got and self.stop_reason is None:
            self._give(got)
            self._woken = False
            for v in sorted(self.alive):
                self._dispatch(v)

    # ---- scheduling
    def _depth(self):
        """Tasks kept at a worker: ``depth``, more when tasks are so short that a worker
        would otherwise wait for the master (about 20 ms of work queued, at most 16), and
        one at the end of the queue, so that no task waits behind another while a worker
        is idle."""
        depth = self.depth
        if self.mean_wall is not None and self.mean_wall > 0:
            depth = max(depth, min(16, 1 + int(0.02 / self.mean_wall)))
        if self._queued() < depth * len(self.alive):
            return 1
        return depth

    def _gpu_share(self, w):
        """Tasks outstanding at GPU worker ``w``: its capacity (a batch per launch in flight and one
        gathering), but no more than its share of the GPU tasks left, so that every GPU worker
        gets batches when there are fewer tasks than capacity."""
        gpu = [v for v in self.capacity if v in self.alive]
        held = sum(len(self.in_flight[v]) for v in gpu)
        share = -(-(self.queues[True].queued() + held) // max(1, len(gpu)))
        return max(1, min(self.capacity[w], share))

    def _dispatch(self, w):
        q = self.in_flight[w]
        if self.rounds is not None and not self._queued() and self.stop_reason is None:
            self._give(self.rounds.dry())  # nothing else to give: the next round's early seeds
        queue = self._queue_for(w)
        gpu = w in self.capacity and queue is self.queues[True]
        # a GPU worker keeps batches in flight (it runs the tasks of one variant and N_G together)
        depth = self._gpu_share(w) if gpu else self._depth()
        while len(q) < depth and queue.queued() and self.stop_reason is None:
            i = queue.peek()
            task = self.tasks[i]
            if (task.parent is not None or (not gpu and self.store.has_suspended(i))) and q:
                # a ladder step carries its parent's packing, a suspended task its state (hundreds of
                # kB at N_G 8192): only to a worker waiting for work. A busy worker sends its result
                # before it reads again, so a payload beyond the pipe's buffer (or MPI's eager limit)
                # sent to it now would block this send while the worker blocks sending its result
                # here: a deadlock. (A GPU worker sends without blocking: campaign.run.comm._Outbox.)
                return
            suspendable = gpu and bool(self.on_gpu[i])
            if self.can_dispatch is not None and not (
                    self.can_dispatch(task, [self.tasks[j] for j in q], suspendable=True) if suspendable
                    else self.can_dispatch(task, [self.tasks[j] for j in q])):
                self.stop_reason = "wall time"
                self.log("\ncampaign: the next task would not fit in the time left; no new tasks")
                return
            queue.pop()
            attempt = int(self.attempts[i]) + 1
            self.attempts[i] = attempt
            payload = task.payload()
            payload["attempt"] = attempt
            if task.parent is not None:
                start = self.configs.get(task.parent)
                if start is None:
                    start = self.store.configuration(task.parent)
                if start is None:
                    self._fail(i, f"the configuration of its ladder parent (task {self.tasks[task.parent].id}) "
                                  "is not in the store; rerun the parent with --redo-failed after removing it, "
                                  "or start afresh with --new")
                    continue
                payload["start"] = start
            if i in self.children:
                payload["return_configuration"] = True
            state = self.store.suspended(i)
            if state is not None:  # a packing stopped at a step budget by an earlier run: on from there
                payload["resume"] = state
            q.append(i)
            self.comm.send(w, payload)

    def _fail(self, i, message, rank=-1):
        """Record task ``i`` as failed without running it (and its descendants)."""
        summary = {"id": self.tasks[i].id, "ok": False, "scalars": {}, "histograms": {}, "configuration": None,
                   "wall": float("nan"), "rank": rank, "host": "", "error": {"message": message, "traceback": ""}}
        self._outcome(i, self.retries + 1, summary)

    def _release(self, i, summary):
        """A final outcome of task ``i``: unblock its children or fail them; free its parent's data."""
        parent = self.tasks[i].parent
        if parent is not None and all(self.store.finished(c) for c in self.children[parent]):
            self.configs.pop(parent, None)
        for c in self.children.get(i, ()):
            if c not in self.blocked:
                continue
            self.blocked.discard(c)
            cfg = summary.get("configuration") if summary["ok"] else None
            if summary["ok"] and cfg is not None:
                self.configs[i] = cfg
                self._push(c)
                self._woken = True
            elif summary["ok"]:
                self._fail(c, f"its ladder parent (task {self.tasks[i].id}) returned no configuration")
            else:
                self._fail(c, f"its ladder parent (task {self.tasks[i].id}) failed")

    def _outcome(self, i, attempt, summary):
        cost = float(self.costs[i])
        if summary["ok"] or attempt > self.retries:
            self.store.record(i, summary, attempt)
            if self.rounds is not None:
                self.rounds.finished(i)
            self.cost_remaining -= cost
            if summary["ok"]:
                self.n_done += 1
            else:
                self.n_failed += 1
            self._release(i, summary)
            self._next_round()
            return 1, cost
        self._push(i)  # retry later
        return 0, 0.0

    def _running(self):
        return sum(len(q) for q in self.in_flight.values())

    def _tick(self, finished=0, cost=0.0, force=False):
        self.store.maybe_flush()
        if self.progress is None:
            return
        self._finished += finished
        self._cost += cost
        now = time.monotonic()
        if force or now - self._last_progress >= 0.2:
            c = self.store.counts_by_status()
            running = self._running()
            pending = c["pending"] if self.rounds is None else self.rounds.pending_given()
            self.progress.update(done=c["done"], failed=c["failed"], running=running,
                                 remaining=max(0, pending - running), cost_remaining=self.cost_remaining,
                                 finished_now=self._finished, cost_now=self._cost, force=True)
            self._finished, self._cost, self._last_progress = 0, 0.0, now

    def run(self) -> dict:
        old = self._install_signals()
        try:
            for i in self._orphans:
                self.blocked.discard(i)
                self._fail(i, f"its ladder parent (task {self.tasks[self.tasks[i].parent].id}) failed")
            for w in sorted(self.alive):
                self._dispatch(w)
            while self._running() or (self.rounds is not None and self.rounds.busy and self.stop_reason is None):
                if self.signals >= 2 or (self.stop_since is not None
                                         and time.monotonic() - self.stop_since > self.grace):
                    break
                self._round_made()
                if not self._running():  # waiting for a decision only
                    time.sleep(0.02)
                    continue
                got = self.comm.recv(timeout=0.05 if self.rounds is not None and self.rounds.busy else 0.25)
                if got is None:
                    self._tick()
                    continue
                w, msg = got
                finished, cost = 0, 0.0
                if msg[0] == "result":
                    _, i, attempt, summary = msg
                    try:
                        self.in_flight[w].remove(i)
                    except ValueError:
                        continue  # not ours (cannot happen with these comms); ignore
                    wall = summary.get("wall")
                    if wall is not None and wall == wall:
                        self.mean_wall = wall if self.mean_wall is None else 0.9 * self.mean_wall + 0.1 * wall
                    finished, cost = self._outcome(i, attempt, summary)
                    if w in self.alive:
                        self._dispatch(w)
                    if self._woken:
                        self._woken = False
                        for v in sorted(self.alive):
                            self._dispatch(v)
                elif msg[0] == "suspended":
                    _, i, attempt, record = msg
                    try:
                        self.in_flight[w].remove(i)
                    except ValueError:
                        continue
                    self.attempts[i] -= 1  # not an attempt that failed: the task stays pending
                    if record is not None:
                        self.store.suspend(i, record)
                    self.n_suspended += 1
                    self.gpu_time_up = True  # the worker has no time for a launch: send it no GPU task
                    if w in self.alive:
                        self._dispatch(w)
                elif msg[0] == "dead":
                    self.alive.discard(w)
                    lost = list(self.in_flight[w])
                    self.in_flight[w].clear()
                    if self.alive:
                        self.log(f"\ncampaign: {msg[1]}; its {len(lost)} task(s) go back into the queue "
                                 f"({len(self.alive)} worker(s) left)")
                    for i in lost:
                        err = {"message": msg[1], "traceback": ""}
                        summary = {"id": self.tasks[i].id, "ok": False, "scalars": {}, "histograms": {},
                                   "configuration": None, "wall": float("nan"), "rank": w, "host": "",
                                   "error": err}
                        f, c = self._outcome(i, int(self.attempts[i]), summary)
                        finished, cost = finished + f, cost + c
                    if not self.alive:
                        self.stop_reason = self.stop_reason or "no worker left"
                        self.log(f"\ncampaign: {msg[1]}; no worker left")
                        break
                    for v in sorted(self.alive):
                        self._dispatch(v)
                self._tick(finished, cost)
            abandoned = self._running()
            self._tick(force=True)
            if self.n_suspended and self.stop_reason is None:
                self.stop_reason = "wall time"  # GPU workers stopped their packings before the deadline
            out = {"done": self.n_done, "failed": self.n_failed, "abandoned": abandoned,
                   "stopped": self.stop_reason,
                   "remaining": self._queued() + abandoned + len(self.blocked) + self.n_suspended}
            if self.n_suspended:
                out["suspended"] = self.n_suspended  # handed back at their step budget, kept in the store
            return out
        finally:
            for sig, handler in old.items():
                signal.signal(sig, handler)


class _Queue:
    """Tasks waiting to be dispatched, most expensive first (ties by index): a sorted array read
    from its head, plus a small heap for retries and ladder steps that became ready."""

    def __init__(self, order, costs):
        self.order, self.costs, self.head, self.extra = order, costs, 0, []

    def queued(self):
        return len(self.order) - self.head + len(self.extra)

    def peek(self):
        """The next task to dispatch (index), or None."""
        best = self.extra[0] if self.extra else None
        if self.head < len(self.order):
            i = int(self.order[self.head])
            if best is None or (-self.costs[i], i) < best:
                return i
        return None if best is None else best[1]

    def pop(self):
        i = self.peek()
        if self.extra and self.extra[0][1] == i:
            heapq.heappop(self.extra)
        else:
            self.head += 1
        return i

    def push(self, i):
        heapq.heappush(self.extra, (-float(self.costs[i]), int(i)))
