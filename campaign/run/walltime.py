"""Wall-time awareness: stop dispatching tasks that would not finish before the allocation ends.

The deadline is the earliest of ``SLURM_JOB_END_TIME`` (epoch seconds; SLURM sets it in the
job's environment) and the run's start plus ``--time-limit``. A task is dispatched only if,
by the learned cost model (campaign.plan.costmodel), it and the tasks already queued at its worker
finish before ``deadline - margin``. The model is refitted from the store's finished rows as
results come in, so estimates follow what this machine actually takes.

A ``device: gpu`` task for a GPU worker stops at a step budget instead (stop and go:
``campaign.run.gpuworker``): it is dispatched whatever its cost while at least
``GPU_MIN_SECONDS`` are left before ``deadline - margin``; what it does not finish is kept in the
store and the next run goes on from there.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np

from campaign.plan.costmodel import CostModel
from campaign.errors import UserError
from campaign.run.slurm import parse_time
from campaign.storage.layout import DONE


#: seconds before ``deadline - margin`` a GPU task still goes out: time to launch, run some
#: steps and hand the packing back
GPU_MIN_SECONDS = 2.0


def parse_limit(text) -> float:
    """``--time-limit``: seconds (a number) or SLURM's ``[D-]HH:MM:SS``."""
    try:
        seconds = float(text)
    except (TypeError, ValueError):
        return float(parse_time(text))
    if not (math.isfinite(seconds) and seconds > 0):
        raise UserError(f"--time-limit must be a positive number of seconds or [D-]HH:MM:SS; got {text!r}")
    return seconds


def job_start(start: float, environ) -> float:
    """When the allocation's clock started: ``CAMPAIGN_JOB_START`` (epoch seconds, set by the batch
    script `campaign slurm` writes, as its first command) when it is set and not later than ``start``,
    else ``start``. Everything between the two (srun starting the tasks, Python imports, MPI set-up)
    is spent from the job's wall time, not added after it."""
    try:
        began = float(environ.get("CAMPAIGN_JOB_START", ""))
    except ValueError:
        return start
    return began if math.isfinite(began) and began <= start else start


def deadline(start: float, time_limit=None, environ=None) -> float | None:
    """Epoch seconds at which the allocation ends, or None when nothing limits the run.

    ``--time-limit`` counts from the job's start (``job_start``), not from this process's."""
    environ = os.environ if environ is None else environ
    candidates = []
    if time_limit is not None:
        candidates.append(job_start(start, environ) + parse_limit(time_limit))
    end = environ.get("SLURM_JOB_END_TIME")
    if end:
        try:
            candidates.append(float(end))
        except ValueError:
            pass  # not ours to refuse: SLURM's variable, unusable; --time-limit still applies
    return min(candidates) if candidates else None


def fit_rows(tasks, status, wall) -> CostModel:
    """The cost model learnt from the finished rows of a task table (status, wall seconds)."""
    done = np.flatnonzero(np.asarray(status) == DONE)
    if done.size == 0:
        return CostModel.prior()
    chosen = [tasks[i] for i in done]
    return CostModel.fit([t.N for t in chosen], [t.E for t in chosen], np.asarray(wall)[done],
                         [dict(t.protocol) for t in chosen], [t.parent_E for t in chosen],
                         [t.exponent for t in chosen])


def fit_from_store(store, tasks) -> CostModel:
    return fit_rows(tasks, store.status, store.wall)


def remaining_seconds(tasks, status, wall) -> tuple[float, int]:
    """Estimated CPU seconds of the tasks not done yet, and how many finished tasks taught it."""
    model = fit_rows(tasks, status, wall)
    left = [t for t in tasks if status[t.index] != DONE]
    return model.total_seconds(left), model.n_points


class Deadline:
    """The master's ``can_dispatch(task, ahead)`` predicate for a deadline (epoch seconds)."""

    def __init__(self, store, tasks, end: float, margin: float, clock=time.time, refit_seconds=2.0):
        self.store, self.tasks = store, tasks
        self.end, self.margin, self.clock = end, margin, clock
        self.refit_seconds = refit_seconds
        self._model, self._fitted_at, self._n_done = None, -math.inf, -1

    def model(self) -> CostModel:
        now = self.clock()
        if self._model is None or now - self._fitted_at >= self.refit_seconds:
            n_done = int(np.count_nonzero(self.store.status == DONE))
            if n_done != self._n_done:
                self._model, self._n_done = fit_from_store(self.store, self.tasks), n_done
            self._fitted_at = now
        return self._model

    def left(self) -> float:
        return self.end - self.margin - self.clock()

    def __call__(self, task, ahead=(), suspendable=False) -> bool:
        """Whether ``task`` (behind the tasks ``ahead`` at its worker) finishes in the time left;
        a ``suspendable`` one (a GPU worker's: it stops at a step budget) whether the minimum is left."""
        if suspendable:
            return self.left() >= GPU_MIN_SECONDS
        model = self.model()
        need = model.task_seconds(task) + sum(model.task_seconds(t) for t in ahead)
        return need <= self.left()
