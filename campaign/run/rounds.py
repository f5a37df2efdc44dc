"""The rounds of a campaign with precision targets, on the master's side (docs/PRECISION.md).

A precision campaign's task table holds seeds ``0 .. max_seeds - 1`` of every cell; only the seeds
its decisions give out run. Decision ``k`` (``campaign.precision.allocation``, reached through the
``planner`` that ``campaign run`` hands in: the run wing does not reduce) says, per cell, how many
seeds rounds ``0 .. k`` hold (``allocated``) and how many more the next round starts with
(``early``). It is made when every task of rounds ``0 .. k - 1`` is finished, from those tasks only,
and kept in the store (``Store.record_round``) before any of its tasks goes out; a resumed run
reads the decisions made and makes the next one when its round is complete, so a campaign's tasks
and store are the same whatever the launcher, the workers or an interruption.

While round ``k``'s last tasks run, the master gives its idle workers the early seeds of round
``k + 1`` (decided with round ``k``), and while it makes decision ``k + 1`` (seconds: the reducer's
bootstrap) it goes on serving them: the store's rows are read in the master's thread, the decision
is made in another (``start``, then ``poll``). No worker waits for a decision as long as the early
seeds last. They always run, whatever the next decision says, so the store does not depend on when
a worker asked for work.
"""

from __future__ import annotations

import threading

import numpy as np

from campaign.storage.layout import PENDING

#: decisions that end a campaign (``campaign.precision.allocation.ACTIONS``, the others go on)
STOPS = ("met", "budget", "max_seeds", "unreachable", "limited")


class Rounds:
    """The master's view of the rounds: which tasks are given out, which are due before the next
    decision, and the decisions themselves (``planner.pilot()``, ``planner.decide(k, store, given,
    through)``, each returning a decision's record)."""

    def __init__(self, store, tasks, planner, log=None, settings=None):
        self.store, self.tasks, self.planner = store, tasks, planner
        self.log = log or (lambda msg: None)
        self.cells = planner.cells
        self.settings = settings if settings is not None else planner.settings
        self.T = len(tasks)
        self.records = self._valid_prefix(store.rounds())
        if not self.records:
            self._keep(planner.pilot())
        self._masks()
        self.queued = np.zeros(self.T, bool)  # the tasks handed to the master (``allowed``, ``_hand``)
        self._thread = self._result = None

    # ---- the decisions kept
    def _valid_prefix(self, recs) -> list:
        """The decisions 0, 1, ... that belong to this campaign's cells, up to the first missing one."""
        out = []
        C = self.cells.C
        for k in range(len(recs)):
            r = recs.get(k)
            if r is None or len(r.get("allocated", ())) != C or len(r.get("early", ())) != C:
                break
            if out and any(a < b for a, b in zip(r["allocated"], out[-1]["early"])):
                break  # not a continuation of the decision before: made again
            out.append(r)
        if len(out) < len(recs):
            self.log(f"campaign: {len(recs) - len(out)} round decision(s) of the store do not follow from the ones "
                     "before; they are made again")
        return out

    def _keep(self, record):
        self.store.record_round(record)
        self.records.append(record)
        if record.get("message"):
            self.log(f"\ncampaign: {record['message']}")

    def _masks(self):
        last = self.records[-1]
        self.through = self.cells.tasks_of(last["allocated"])  # the rounds decided so far
        self.given = self.cells.tasks_of(last["early"])        # ... with the next round's early seeds
        self.open = int(np.count_nonzero(self.through & (self.store.status == PENDING)))

    @property
    def round(self) -> int:
        return int(self.records[-1]["round"])

    @property
    def stopped(self) -> bool:
        """The last decision ended the campaign, and the spec's settings are those it was made with
        (a resumed run with other targets or another budget decides again)."""
        last = self.records[-1]
        return last["action"] in STOPS and last.get("settings") == self.settings

    # ---- what the master asks
    def allowed(self) -> np.ndarray:
        """The tasks that may run now (bool per task): the decided rounds (the early seeds come
        when the master has nothing else to give). They count as handed to the master."""
        self.queued = self.through.copy()
        return self.through.copy()

    def pending_given(self) -> int:
        """Tasks given out and not finished (the campaign's remaining work as decided so far)."""
        return int(np.count_nonzero(self.given & (self.store.status == PENDING)))

    def finished(self, i: int):
        """Task ``i`` has its final outcome."""
        if self.through[i]:
            self.open -= 1

    def _hand(self, mask) -> list:
        fresh = mask & ~self.queued & (self.store.status == PENDING)
        self.queued |= fresh
        return np.flatnonzero(fresh).tolist()

    def dry(self) -> list:
        """The master has no task left to give: the next round's early seeds."""
        return self._hand(self.given)

    def _due(self) -> bool:
        return self.open <= 0 and not self.stopped

    def _inputs(self):
        last = self.records[-1]
        return (int(last["round"]) + 1, np.asarray(last["early"], np.int64), np.asarray(last["allocated"], np.int64),
                last)

    def advance(self) -> list:
        """Make the next decisions (here, waiting for them) while every task of the rounds decided is
        finished; the tasks they give out (with the early seeds not handed out yet), as indices."""
        while self._due():
            k, given, through, last = self._inputs()
            self._keep(self.planner.decide(k, self.store, given, through, self.settings, last))
            self._masks()
        return self._hand(self.through)

    @property
    def busy(self) -> bool:
        """A decision is being made."""
        return self._thread is not None

    def start(self):
        """When every task of the rounds decided is finished: read their rows (here) and make the next
        decision in a thread of its own; ``poll`` collects it."""
        if self._thread is not None or not self._due():
            return
        k, given, through, last = self._inputs()
        snap = self.planner.snapshot(self.store, through)
        box = {}

        def work():
            try:
                box["record"] = self.planner.decide_snapshot(k, snap, given, self.settings, last)
            except BaseException as exc:  # noqa: BLE001 - raised again in the master's thread
                box["error"] = exc

        self._result = box
        self._thread = threading.Thread(target=work, name=f"campaign-decision-{k}", daemon=True)
        self._thread.start()

    def poll(self) -> list:
        """A decision made in its thread: kept (``Store.record_round``, in the master's thread), its
        tasks handed out, and the next one started if it is due at once; [] while none is ready."""
        if self._thread is None or self._thread.is_alive():
            return []
        self._thread.join()
        box, self._thread, self._result = self._result, None, None
        if "error" in box:
            raise box["error"]
        self._keep(box["record"])
        self._masks()
        self.start()
        return self._hand(self.through)
