"""Transports between the master and its workers, behind one small interface.

The master loop (campaign.run.master) only ever calls::

    comm.n_workers                  # workers are numbered 1..n_workers
    comm.send(worker, payload)      # one task (a dict, see Task.payload)
    comm.recv(timeout) -> None | (worker, ("result", index, attempt, summary))
                                    #              | (worker, ("dead", reason))
    comm.wait_ready() -> set         # block until every worker has loaded its task function;
                                    # returns the workers that died meanwhile
    comm.close(abandon=False)       # stop the workers (abandon: do not wait for them)
    comm.abort(code)                # a master fault: end the whole job now

Implementations:

* ``InlineComm``: the master runs each task itself when it sends it (tests, ``-n 1``).
* ``LocalComm``: worker processes started with multiprocessing's ``spawn``
  context (numba and ``fork`` do not mix), one duplex pipe each.
* ``MPIComm``: rank 0 is the master, ranks 1..K-1 the workers (mpi4py, pickled
  messages); ``mpi_worker`` is the worker side.
"""

from __future__ import annotations

import collections
import os
import socket
import sys
import time

from campaign.run import worker as _worker
from campaign.run.launch import mpi_env_detected  # noqa: F401 - where it used to live

TAG_TASK, TAG_STOP, TAG_RESULT = 1, 2, 3


class InlineComm:
    launcher = "inline"

    def __init__(self, context: dict):
        self.context = context
        self.fn = _worker.resolve(context.get("task_function"))
        self.n_workers = 1
        self.results = collections.deque()
        self.hosts = [socket.gethostname()]

    def wait_ready(self):
        return set()

    def send(self, worker, payload):
        summary = _worker.run_task(self.fn, payload, self.context, rank=0)
        self.results.append((worker, ("result", payload["index"], payload.get("attempt", 1), summary)))

    def recv(self, timeout=None):
        return self.results.popleft() if self.results else None

    def close(self, abandon=False):
        self.results.clear()

    def abort(self, code=1):
        raise SystemExit(code)


def _local_main(conn, context, rank):
    import multiprocessing

    parent = multiprocessing.parent_process()
    # a killed master must not leave this process computing: it ends with the master (SIGKILL by the
    # kernel on Linux, else the watcher of the parent's sentinel), its task pending in the store
    _worker.die_with_parent(parent.pid if parent is not None else None, getattr(parent, "sentinel", None))
    def recv():
        try:
            return conn.recv()
        except (EOFError, OSError):  # the master is gone: stop quietly
            return None

    def send(msg):
        try:
            conn.send(msg)
        except (BrokenPipeError, OSError):
            raise SystemExit(0) from None

    def poll():
        try:
            return conn.poll(0)
        except (EOFError, OSError):
            return True  # the next recv says the master is gone

    outbox = _Outbox(conn) if context.get("gpu_device") is not None else None
    try:
        _worker.worker_loop(recv, outbox.send if outbox else send, context, rank, poll)
    finally:
        if outbox is not None:
            outbox.close()


class _Outbox:
    """A GPU worker's sends to the master, made by a thread of their own: the worker never blocks
    on a send, so that it always reads what the master sends it. Both send large messages (a
    suspended packing's state, a task resumed from one, stored configurations): a worker blocked
    sending into a full pipe while the master blocks sending into the worker's would wait forever."""

    def __init__(self, conn):
        import queue
        import threading

        self.conn, self.queue = conn, queue.SimpleQueue()
        self.thread = threading.Thread(target=self._run, name="campaign-outbox", daemon=True)
        self.thread.start()

    def send(self, msg):
        self.queue.put(msg)

    def _run(self):
        while True:
            msg = self.queue.get()
            if msg is None:
                return
            try:
                self.conn.send(msg)
            except (BrokenPipeError, OSError):
                os._exit(0)  # the master is gone: its tasks stay pending in the store

    def close(self):
        """Send what is queued, then end the thread."""
        self.queue.put(None)
        self.thread.join()


def gpu_context(context: dict, device: int | None) -> dict:
    """A worker's context: a GPU worker owns ``device`` (``CUDA_VISIBLE_DEVICES`` is set before
    CUDA starts) and runs batches of ``context["gpu_batch"]`` tasks; any other runs one at a time."""
    if device is None:
        out = dict(context, gpu_batch=1, gpu_device=None)
        if int(context.get("gpus") or 0):  # the GPU workers run the device: gpu tasks: no need to compile them
            cpu = [p for p in context.get("protocol_warmups") or () if dict(p).get("device") != "gpu"]
            out["protocol_warmups"] = cpu or [{}]
        return out
    return dict(context, gpu_device=int(device))


def gpu_capacity(gpu_batch: int) -> int:
    """Tasks the master keeps outstanding at a GPU worker: a batch for each launch it keeps in
    flight and one more gathering (``campaign.run.gpuworker``)."""
    from campaign.run.gpuworker import IN_FLIGHT

    return (IN_FLIGHT + 1) * int(gpu_batch)


class LocalComm:
    """Worker processes on this machine (no MPI)."""

    launcher = "local"

    def __init__(self, context: dict, n_workers: int, gpus: int = 0):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        self.n_workers = n_workers
        self.conns, self.procs = {}, {}
        # workers 1..gpus own GPU 0..gpus-1 and take batches of gpu_batch tasks: the master keeps a batch
        # outstanding at each for every launch in flight and one gathering (campaign.run.gpuworker)
        self.capacity = {w: gpu_capacity(context.get("gpu_batch") or 1) for w in range(1, min(gpus, n_workers) + 1)}
        for w in range(1, n_workers + 1):
            parent, child = ctx.Pipe(duplex=True)
            wctx = gpu_context(context, w - 1 if w in self.capacity else None)
            p = ctx.Process(target=_local_main, args=(child, wctx, w), name=f"campaign-worker-{w}",
                            daemon=True)
            p.start()
            child.close()
            self.conns[w], self.procs[w] = parent, p
        self.hosts = [socket.gethostname()]
        self._by_conn = {c: w for w, c in self.conns.items()}

    def wait_ready(self):
        waiting, dead = set(self.conns), set()
        while waiting:
            got = self.recv(timeout=None)
            if got is None:
                continue
            w, msg = got
            waiting.discard(w)
            if msg[0] == "dead":
                dead.add(w)
        return dead

    def send(self, worker, payload):
        try:
            self.conns[worker].send(("task", payload))
        except (BrokenPipeError, OSError, KeyError):
            pass  # the worker died; recv reports it

    def recv(self, timeout=None):
        from multiprocessing.connection import wait

        if not self.conns:
            if timeout:
                time.sleep(timeout)
            return None
        ready = wait(list(self.conns.values()), timeout)
        if not ready:
            return None
        conn = ready[0]
        w = self._by_conn[conn]
        try:
            return w, conn.recv()
        except (EOFError, OSError):
            proc = self.procs[w]
            proc.join(1.0)
            del self.conns[w]
            return w, ("dead", f"worker process {w} (pid {proc.pid}) died (exit code {proc.exitcode})")

    def close(self, abandon=False):
        for w, conn in list(self.conns.items()):
            try:
                conn.send(("stop",))
            except (BrokenPipeError, OSError):
                pass
        deadline = time.monotonic() + (0.0 if abandon else 10.0)
        for p in self.procs.values():
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.terminate()
                p.join(5.0)
        for conn in self.conns.values():
            conn.close()
        self.conns.clear()

    def abort(self, code=1):
        self.close(abandon=True)
        raise SystemExit(code)


class _Backoff:
    """Poll without burning a core: spin briefly, then sleep longer and longer (at most 0.2 ms).

    A waiting rank costs a few percent of a core; the short cap keeps the latency of a
    message far below the time the master needs per task (the throughput target is
    thousands of tasks per second) even when several ranks share a core.
    """

    def __init__(self):
        self.n = 0

    def wait(self):
        self.n += 1
        if self.n > 50:
            time.sleep(min(2e-4, 1e-5 * (self.n - 50)))

    def reset(self):
        self.n = 0


class MPIComm:
    """Master side of MPI: rank 0; workers are ranks 1..size-1."""

    launcher = "mpi"

    def __init__(self, comm):
        from mpi4py import MPI

        self.MPI = MPI
        self.comm = comm
        self.n_workers = comm.Get_size() - 1
        self.hosts = []
        self._status = MPI.Status()
        self.capacity = {}  # GPU workers and their batch size: set_capacity

    def wait_ready(self):
        for _ in range(self.n_workers):
            self.recv(timeout=None)
        return set()

    def set_capacity(self, gpu_batch: int):
        """Every worker rank owns a GPU (``campaign run --gpus``) and takes batches of ``gpu_batch``
        (as many outstanding as ``LocalComm``'s GPU workers: ``gpu_capacity``)."""
        self.capacity = {w: gpu_capacity(gpu_batch) for w in range(1, self.n_workers + 1)}

    def send(self, worker, payload):
        self.comm.send(payload, dest=worker, tag=TAG_TASK)

    def recv(self, timeout=None):
        deadline = None if timeout is None else time.monotonic() + timeout
        backoff = _Backoff()
        while True:
            msg = self.comm.improbe(source=self.MPI.ANY_SOURCE, tag=TAG_RESULT, status=self._status)
            if msg is not None:
                return self._status.Get_source(), msg.recv()
            if deadline is not None and time.monotonic() >= deadline:
                return None
            backoff.wait()

    def close(self, abandon=False):
        for w in range(1, self.n_workers + 1):
            self.comm.send(None, dest=w, tag=TAG_STOP)

    def abort(self, code=1):
        sys.stderr.flush()
        self.comm.Abort(code)


def mpi_worker(comm, context: dict) -> None:
    """Worker side of MPI: serve tasks from rank 0 until told to stop."""
    from mpi4py import MPI

    status = MPI.Status()
    rank = comm.Get_rank()

    probed = []  # a message matched by poll, received by the next recv

    def probe():
        msg = comm.improbe(source=0, tag=MPI.ANY_TAG, status=status)
        return None if msg is None else (msg, status.Get_tag())

    def recv():
        backoff = _Backoff()
        while True:
            got = probed.pop() if probed else probe()
            if got is not None:
                obj = got[0].recv()
                return ("stop",) if got[1] == TAG_STOP else ("task", obj)
            if sending:
                sent()
            backoff.wait()

    sending = []  # a GPU worker's sends in progress (isend): it never blocks on one (comm._Outbox)
    gpu = context.get("gpu_device") is not None or int(context.get("gpus") or 0) > 0

    def send(msg):
        if not gpu:
            comm.send(msg, dest=0, tag=TAG_RESULT)
            return
        sending.append(comm.isend(msg, dest=0, tag=TAG_RESULT))
        sent()

    def sent():
        sending[:] = [r for r in sending if not r.Test()]

    def poll():
        # MPI moves a message into reach only as its progress engine runs: a single probe right
        # after a receive can miss what is already on its way, so try for up to a millisecond
        sent()
        deadline = time.monotonic() + 1e-3
        while not probed:
            got = probe()
            if got is not None:
                probed.append(got)
            elif time.monotonic() > deadline:
                break
        return bool(probed)

    watch_master(context.get("master"))
    try:
        _worker.worker_loop(recv, send, rank_gpu(context, rank), rank, poll)
    finally:
        if sending:
            MPI.Request.Waitall(sending)


def rank_gpu(context: dict, rank: int) -> dict:
    """A worker rank's context under ``--gpus K``: every worker rank is a GPU worker, on GPU
    ``node_rank mod K`` of the GPUs it sees (the node's ranks share them in turn). The master is its
    node's rank 0 (the block layouts of srun and mpiexec), so K workers beside it still take K
    different GPUs. ``CUDA_VISIBLE_DEVICES`` is set at once, before anything (the node's warm-up)
    can start CUDA; the worker loop sets it again to the same device."""
    gpus = int(context.get("gpus") or 0)
    if not gpus or "gpu_device" in context:
        return context
    context = gpu_context(context, node_rank(rank) % gpus)
    os.environ["CUDA_VISIBLE_DEVICES"] = _worker.visible_device(context["gpu_device"])
    return context


def watch_master(master, interval: float = 0.5) -> None:
    """An MPI worker ends when its master does (its task stays pending in the store): with the
    launcher's process that started it (``die_with_parent``: mpiexec's proxy, or srun's step daemon,
    which end when the job does), and, on the master's host, as soon as the master's process is gone
    (``master``: [pid, host], a thread that looks every ``interval`` seconds). On other hosts the
    launcher ends the other ranks when one dies (Hydra's mpiexec and srun do)."""
    import threading

    _worker.die_with_parent()
    pid, host = (list(master) + [None, None])[:2] if master else (None, None)
    if not pid or host != socket.gethostname():
        return

    def watch():
        while not _worker.master_gone(pid, host):
            time.sleep(interval)
        os._exit(0)

    threading.Thread(target=watch, name="campaign-master-watch", daemon=True).start()


def node_rank(rank: int) -> int:
    """This process's rank among those of its node, as the launcher says (MPICH's hydra, Open
    MPI, srun), else its world rank."""
    for name in ("MPI_LOCALRANKID", "OMPI_COMM_WORLD_LOCAL_RANK", "SLURM_LOCALID", "PMI_LOCAL_RANK"):
        value = os.environ.get(name, "")
        if value.isdigit():
            return int(value)
    return rank
