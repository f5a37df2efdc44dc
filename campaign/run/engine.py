"""A campaign run, from the spec to the store: expand the tasks, open the store, compile
the kernels once per node, start the workers (MPI ranks, local processes or none), let the
master schedule the tasks, close the store and say how it ended.

``campaign run`` (``campaign/commands/run.py``) parses the command line, checks the launch
(one MPI world or none) and calls ``run_campaign`` on the master; MPI workers call
``mpi_worker``. The scheduling itself is ``campaign.run.master``; the file is ``campaign.storage.store``.
"""

from __future__ import annotations

import os
import platform
import signal
import socket
import subprocess
import sys
import time
import traceback
from pathlib import Path

#: tasks a GPU worker runs in one launch (``campaign run --gpu-batch``): one thread block each; an
#: H100 runs 132-528 blocks of 256 threads at once (docs/GPU.md)
GPU_BATCH = 256


def _log(msg):
    print(msg, file=sys.stderr, flush=True)


def _compiled() -> str:
    """What the warm-up compiled and what it loaded from the numba cache (``kernels.compiled``):
    a campaign compiles only the kernels its protocol and observables use."""
    if "kernels" not in sys.modules:  # a task function without the kernels
        return "no kernels"
    from kernels.compiled import compile_report

    return compile_report().summary()


def _git_commit() -> str:
    here = Path(__file__).resolve().parent
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5)
        if out.returncode == 0 and out.stdout.strip():
            return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return "unknown"


def _versions(mpi=None) -> dict:
    from importlib import metadata

    out = {"python": platform.python_version()}
    for dist in ("numpy", "numba", "h5py", "mpi4py", "mpich", "pyyaml", "scipy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    try:
        import h5py

        out["hdf5"] = h5py.version.hdf5_version
    except ImportError:
        pass
    if mpi is None:  # not under MPI: ask the library for its version without initialising it
        try:
            import mpi4py

            mpi4py.rc.initialize = mpi4py.rc.finalize = False
            from mpi4py import MPI as mpi
        except Exception:  # noqa: BLE001 - provenance is best effort
            mpi = None
    if mpi is not None:
        try:
            out["mpi_library"] = " ".join(mpi.Get_library_version().split())[:200]
        except Exception:  # noqa: BLE001
            pass
    return out


def provenance(launcher, n_workers, mpi=None) -> dict:
    from campaign.version import __version__

    return {"package_version": __version__, "git_commit": _git_commit(), "versions": _versions(mpi),
            "launcher": launcher, "workers": n_workers, "hosts": [socket.gethostname()],
            "argv": sys.argv[:], "pid": os.getpid()}


def mpi_worker(comm) -> int:
    from campaign.run.comm import mpi_worker as serve, rank_gpu

    context = comm.bcast(None, root=0)
    if context is None:  # the master refused to start (bad spec, refused file): it says why
        return 0
    comm.gather(socket.gethostname(), root=0)
    try:
        context = rank_gpu(context, comm.Get_rank())  # before the node's warm-up can start CUDA
        node_warm_up(comm, context, first_warms=True)
        serve(comm, context)
    except BaseException:  # noqa: BLE001 - a worker-side fault must not hang the job
        traceback.print_exc()
        sys.stderr.flush()
        comm.Abort(1)
    return 0


def node_warm_up(comm, context, first_warms):
    """One compilation per node: the node's lowest rank fills the numba cache, the others wait.

    On the master's node the master (rank 0, always first) has compiled already; on other nodes
    (possibly other CPUs, hence other cache entries) the first worker compiles while the rest of
    the node waits, instead of every rank compiling the same kernels at once.
    """
    from mpi4py import MPI

    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    try:
        if first_warms and node.Get_rank() == 0 and context.get("warm_up", True):
            from campaign.run.worker import resolve

            fn = resolve(context.get("task_function"))
            if hasattr(fn, "warm_up"):
                try:
                    fn.warm_up(context)
                except Exception:  # noqa: BLE001 - the tasks will report it
                    pass
        node.Barrier()
    finally:
        node.Free()


def _resume_command(args, out, mpi_comm) -> str:
    resume = " ".join(["campaign", "run"] + ([args.spec] if args.spec else []) + ["--out", str(out)])
    return ("mpiexec -n K " + resume) if mpi_comm is not None else resume


def _abandon(comm, store, progress):
    """After a fault: stop the workers without waiting, close the store as it is (a poisoned
    HDF5 handle is neutralised), and say in the progress file that nothing runs any more."""
    if comm is not None:
        try:
            comm.close(abandon=True)
        except Exception:  # noqa: BLE001
            pass
    store.abandon()
    if progress is not None:
        progress.stopped()


def run_campaign(args, mpi_comm=None, MPI=None, state=None) -> int:
    """Run (or resume) the campaign ``args`` describes (the options of ``campaign run``) on the
    master: with ``mpi_comm`` the MPI world's other ranks are the workers. Returns the exit code."""
    import numpy as np

    from campaign.run.comm import InlineComm, LocalComm, MPIComm
    from campaign.errors import UserError, WriteFault
    from campaign.storage.faults import check_writable, stop_paragraph
    from campaign.run.master import Master
    from campaign.storage.progress import Progress
    from campaign.plan.parse import load_spec
    from campaign.storage.layout import FAILED, PENDING
    from campaign.storage.store import Store
    from campaign.plan.tasks import energy_floor_problems, expand, warm_ups
    from campaign.run.worker import resolve

    state = state if state is not None else {}
    # the plan: the spec, what workers need of it, the tasks, their histograms' edges
    spec = load_spec(args.spec)
    gpu_batch = getattr(args, "gpu_batch", None)
    context = dict(spec.worker_context(), task_function=args.task_function, gpus=int(getattr(args, "gpus", 0) or 0),
                   gpu_batch=int(gpu_batch or 0) or GPU_BATCH)
    # a GPU worker's launches stop at a step budget before the deadline (campaign.run.gpuworker)
    context.update(deadline=getattr(args, "deadline", None), margin=float(getattr(args, "margin", 0.0) or 0.0))
    out = Path(args.out or spec.output)
    retries = spec.retries if args.retries is None else args.retries
    if retries < 0:
        raise UserError(f"--retries must be >= 0, got {retries}")
    if context["gpus"] < 0 or (gpu_batch is not None and gpu_batch < 1):
        raise UserError(f"--gpus must be >= 0 and --gpu-batch >= 1, got {args.gpus} and {args.gpu_batch}")
    if context["gpus"]:
        from campaign.run.slurm import refuse_without_gpu_tasks

        refuse_without_gpu_tasks(spec, f"--gpus {context['gpus']}", "run it without --gpus (a worker per core)")
    if mpi_comm is not None:
        launcher, n_workers = "mpi", mpi_comm.Get_size() - 1
    elif args.launcher == "inline":
        launcher, n_workers = "inline", 1
    else:
        n_workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
        if n_workers < 1:
            raise UserError(f"--workers must be at least 1, got {n_workers}")
        if context["gpus"] > n_workers:
            raise UserError(f"--gpus {args.gpus} needs as many workers (one per GPU), got --workers {n_workers}")
        launcher = "local"
    tasks = expand(spec)
    context["protocol_warmups"] = warm_ups(tasks)
    if args.task_function == "kernels":
        problems = energy_floor_problems(spec)
        if problems:
            raise UserError(f"{len(problems)} problem(s) in the spec:\n  " + "\n  ".join(problems))
    check_writable(out, new=args.new)  # before any worker starts: exit 2 naming the path and the reason
    fn = resolve(args.task_function)
    edges = fn.histogram_edges(context)
    context["edges"] = {h: [float(x) for x in e] for h, e in edges.items()}

    resume = _resume_command(args, out, mpi_comm)
    try:
        store = Store(out, spec, tasks, edges, new=args.new, provenance=provenance(launcher, n_workers, MPI),
                      log=_log)
    except WriteFault as fault:  # a full disk before anything started: the store is as it was
        fault.message = stop_paragraph(fault, out, resume=resume)
        raise
    comm = master = progress = rounds = None
    outcome = None
    workers_stopped = False  # told to stop after the master loop (MPI: they exit cleanly)
    try:
        if spec.precision is not None:  # the rounds: the decisions kept, and one due now
            from campaign.run.rounds import Rounds

            planner = getattr(args, "planner", None)
            if planner is None:
                raise RuntimeError("a campaign with precision targets needs the planner `campaign run` hands in")
            rounds = Rounds(store, tasks, planner(spec, tasks), log=_log)
            rounds.advance()
            todo = rounds.pending_given()
        else:
            todo = int(np.count_nonzero((store.status == PENDING) | ((store.status == FAILED) if args.retry_failed else False)))
        context["warm_up"] = bool(todo)
        c = store.counts_by_status()
        progress = Progress(len(tasks), sidecar=Path(str(out) + ".progress.json"),
                            enabled=None if not args.quiet else False)
        progress.begin(done=c["done"], failed=c["failed"], remaining=c["pending"])  # a heartbeat from now on
        if todo and hasattr(fn, "warm_up") and launcher != "inline":
            if sys.stderr.isatty() and not args.quiet:
                _log(f"campaign: compiling the kernels (once; cached in {os.environ.get('NUMBA_CACHE_DIR')})")
            t_warm, cpu_warm = time.monotonic(), time.process_time()
            # beside GPU workers, none of the device: gpu kernels: the CUDA kernel is compiled in memory,
            # not cached on disk, so the master's compilation would serve no worker, and it would hold a
            # CUDA context on a GPU that a worker uses (with no CPU protocol left it warms the default
            # one, whose analysis kernels the GPU workers load from the node's numba cache); a local
            # run's master compiles the analysis in a second process beside the search
            warm = dict(context, warm_helper=launcher == "local" and n_workers > 1)
            fn.warm_up(dict(warm, protocol_warmups=[p for p in context["protocol_warmups"] or [{}]
                                                    if p.get("device") != "gpu"]) if context["gpus"] else warm)
            if not args.quiet:  # the per-node start-up cost a job of a chain pays (docs: slurm/README.md)
                _log(f"campaign: kernels ready in {time.monotonic() - t_warm:.1f} s, "
                     f"{time.process_time() - cpu_warm:.1f} s of CPU: {_compiled()} "
                     f"(numba cache {os.environ.get('NUMBA_CACHE_DIR')})")
        if mpi_comm is not None:
            context["master"] = [os.getpid(), socket.gethostname()]  # workers on its host watch it
            mpi_comm.bcast(context, root=0)
            state["sent"] = True
            hosts = mpi_comm.gather(socket.gethostname(), root=0)
            store.run["hosts"] = sorted(set(hosts))
            node_warm_up(mpi_comm, context, first_warms=False)  # rank 0 has warmed its node already
            comm = MPIComm(mpi_comm)
            if context["gpus"]:
                comm.set_capacity(context["gpu_batch"])
        elif launcher == "inline" or todo == 0:  # nothing to do: no worker processes to start
            comm = InlineComm(context)
        else:
            comm = LocalComm(context, min(n_workers, max(1, todo)), gpus=context["gpus"])
        comm.dead = comm.wait_ready()  # workers have loaded (not compiled: see warm_up above) the kernels
        if getattr(comm, "capacity", None):
            progress.extra["gpu_workers"] = len(comm.capacity)  # campaign status shows them
        wall = None
        if args.deadline is not None:
            from campaign.run.walltime import Deadline

            wall = Deadline(store, tasks, args.deadline, args.margin)
        master = Master(comm, store, tasks, retries=retries, depth=max(1, args.depth), progress=progress,
                        grace=args.grace, redo_failed=args.retry_failed, log=_log, can_dispatch=wall, rounds=rounds)
        if getattr(args, "warned", None):
            master.on_signal(signal.SIGUSR1)
        t0, cpu0 = time.monotonic(), time.process_time()
        outcome = master.run()
        cpu = time.process_time() - cpu0
        ended = None  # a precision campaign that has ended: its last decision, the errors of every packing
        if rounds is not None and rounds.stopped and not rounds.pending_given():
            ended = (rounds.records[-1], rounds.planner.report(store, rounds.records[-1]["early"]))
        progress.finish()
        comm.close(abandon=outcome["abandoned"] > 0)
        comm, workers_stopped = None, True
        counts = store.counts_by_status()
        store.close(completed=outcome["done"], failed=outcome["failed"], stopped=outcome["stopped"],
                    suspended=outcome.get("suspended", 0),
                    seconds=round(time.monotonic() - t0, 3), master_cpu_seconds=round(cpu, 3))
    except WriteFault as fault:
        # A full disk (or a file system that failed) on the write path: stop at once. Everything
        # finished is in the journal, the store is consistent; the tasks in flight are given up.
        in_flight = master._running() if master is not None else 0
        _abandon(comm, store, progress)
        fault.message = stop_paragraph(fault, out, counts=store.counts_by_status(), total=len(tasks),
                                       need=store.space_needed(), resume=resume)
        if mpi_comm is not None and state.get("sent") and (in_flight or (comm is None and not workers_stopped)):
            _log(f"campaign run: {fault.message}")
            sys.stderr.flush()
            time.sleep(0.5)  # let the launcher forward the message before MPI_Abort ends the job
            mpi_comm.Abort(fault.exit_code)  # workers busy with tasks nobody will collect
            os._exit(fault.exit_code)  # MPICH's MPI_Abort can return before the launcher kills the job
        raise
    except BaseException:
        _abandon(comm, store, progress)
        raise
    if rounds is None:
        msg = (f"campaign: {out}: {counts['done']} done, {counts['failed']} failed, {counts['pending']} pending "
               f"of {len(tasks)} tasks (this run: {outcome['done']} done, {outcome['failed']} failed)")
    else:
        left = rounds.pending_given()
        msg = (f"campaign: {out}: {counts['done']} done, {counts['failed']} failed, {left} pending of the "
               f"{int(rounds.given.sum())} tasks rounds 0-{rounds.round} gave out ({len(tasks)} possible; this run: "
               f"{outcome['done']} done, {outcome['failed']} failed)")
    _log(msg)
    if ended is not None:
        last, report = ended
        _log(f"campaign: the campaign has ended ({last['action']}) after round {last['round']}: {last['message']}")
        _log("campaign: with every packing of the store: " + report.replace("\n", "\ncampaign:   "))
    if outcome.get("suspended"):
        _log(f"campaign: {outcome['suspended']} GPU packing(s) stopped at their step budget before the deadline; "
             "their state is in the store and the next run goes on from it")
    if counts["failed"]:
        _log(f"campaign: see the failures with: campaign status {out}")
    left = counts["pending"] if rounds is None else rounds.pending_given()
    if outcome["stopped"] is not None and left:
        from campaign.run.walltime import fit_from_store

        waiting = (store.status == PENDING) if rounds is None else (store.status == PENDING) & rounds.given
        pending = [tasks[i] for i in np.flatnonzero(waiting)]
        hours = fit_from_store(store, tasks).total_seconds(pending) / 3600.0
        _log(f"campaign: stopped ({outcome['stopped']}); {left} task(s) left, about {hours:.3g} "
             f"core-hours. Resume with: {resume}")
        # Running out of allocated time is the normal end of one job of a chain: success.
        code = {"SIGINT": 130, "SIGTERM": 143, "SIGUSR1": 0, "wall time": 0}.get(outcome["stopped"], 3)
        if mpi_comm is not None and outcome["abandoned"]:
            mpi_comm.Abort(code)  # workers still busy with abandoned tasks: do not wait for them
        return code
    return 0
