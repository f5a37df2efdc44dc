"""A GPU worker's pipeline: the next batch runs on the GPU while this one is analysed.

The worker loop (``campaign.run.worker.worker_loop``) hands each batch of ``device: gpu`` tasks
(one ``batch_key``) to ``Pipeline.run``, whose task function has ``start_batch`` (launch: on a GPU
it returns at once), ``finish_batch`` (wait, the packings) and ``analyse`` (one packing's summary
tuple). For batch k+1 the pipeline launches it, then analyses batch k on this process's core and
sends its results while the GPU works, then waits for k+1 and keeps its packings until the next
batch or ``flush``. The worker loop flushes before it would block waiting for the master (no
message waiting), before any task that runs alone, and when it stops: results never wait on
tasks the master has not sent. The master keeps two batches in flight at a GPU worker
(``campaign.run.comm``), so that the next one is there to launch.

A fault of the launch or the wait (out of memory, a lost device) fails that batch's tasks with
its reason; a packing that fails alone (a ``BlockOverflow``) or whose analysis fails fails alone.
"""

from __future__ import annotations

import time


class Pipeline:
    def __init__(self, fn, context: dict, rank: int, send, summary):
        """``summary(payload, context, rank, got, wall)`` makes a task's summary from what the task
        function returned or the exception that failed it (``campaign.run.worker._summary``)."""
        self.fn, self.context, self.rank, self.send, self.summary = fn, context, rank, send, summary
        self.held = None  # (payloads, [(packing, seconds) | exception], seconds per task)

    def run(self, payloads: list) -> None:
        """Launch ``payloads``, analyse and send the batch held so far, then wait for these."""
        t0 = time.perf_counter()
        try:
            handle = self.fn.start_batch(payloads, self.context)
        except Exception as exc:  # noqa: BLE001 - the batch fails, the worker goes on
            handle = exc
        self.flush()
        got = handle
        if not isinstance(handle, Exception):
            try:
                got = self.fn.finish_batch(handle)
            except Exception as exc:  # noqa: BLE001
                got = exc
        if isinstance(got, Exception):
            got = [got] * len(payloads)
        self.held = (payloads, got, (time.perf_counter() - t0) / len(payloads))

    def flush(self) -> None:
        """Analyse the batch held and send its results."""
        if self.held is None:
            return
        payloads, got, share = self.held
        self.held = None
        for payload, item in zip(payloads, got):
            t0 = time.perf_counter()
            if not isinstance(item, Exception):
                try:
                    item = self.fn.analyse(payload, self.context, *item)
                except Exception as exc:  # noqa: BLE001 - that task fails, the batch goes on
                    item = exc
            summary = self.summary(payload, self.context, self.rank, item, share + time.perf_counter() - t0)
            self.send(("result", payload["index"], payload.get("attempt", 1), summary))
