"""campaign run [SPEC] [--out FILE]: run (or resume) a campaign.

Under ``mpiexec -n K`` rank 0 is the master and ranks 1..K-1 are workers;
without a launcher the master drives ``--workers`` local processes. Rerunning
the same spec on the same file resumes it.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
import traceback
from pathlib import Path

HELP = "run or resume a campaign (no SPEC: the packaged quickstart)"


def configure(parser):
    parser.add_argument("spec", nargs="?", default=None,
                        help="campaign spec (YAML); default: the packaged quickstart")
    parser.add_argument("--out", default=None, help="HDF5 store (default: the spec's 'output')")
    parser.add_argument("--workers", type=int, default=None,
                        help="local worker processes when not under mpiexec (default: the cores)")
    parser.add_argument("--new", action="store_true",
                        help="start the store afresh: delete FILE and its journal first (needed when "
                             "FILE was written by a different spec)")
    parser.add_argument("--retries", type=int, default=None,
                        help="extra attempts for a failing task (default: the spec's run.retries, else 2)")
    parser.add_argument("--retry-failed", action="store_true",
                        help="also rerun tasks recorded as failed by earlier runs")
    parser.add_argument("--launcher", choices=("auto", "mpi", "local", "inline"), default="auto",
                        help="auto: MPI under an MPI launcher, else local processes (inline: no workers)")
    parser.add_argument("--grace", type=float, default=20.0,
                        help="seconds to wait for running tasks after SIGINT/SIGTERM (default 20)")
    parser.add_argument("--numba-cache", default=None,
                        help="numba cache directory (default: $NUMBA_CACHE_DIR, else "
                             "~/.cache/jamming-campaign/numba)")
    parser.add_argument("--time-limit", default=None, metavar="T",
                        help="wall time of this run, seconds or [D-]HH:MM:SS: tasks that would not finish "
                             "before it (minus --margin) are not started, and the run exits 0, resumable; counted "
                             "from CAMPAIGN_JOB_START (epoch seconds) when the batch script sets it "
                             "(SLURM_JOB_END_TIME, when set, limits it too)")
    parser.add_argument("--margin", type=float, default=60.0, metavar="SECONDS",
                        help="time kept free before the limit for collecting results and writing (default 60)")
    parser.add_argument("--quiet", action="store_true", help="no progress line")
    parser.add_argument("--gpus", type=int, default=0, metavar="K",
                        help="GPU workers: locally the first K workers own GPUs 0..K-1; under mpiexec "
                             "every worker rank owns one of its node's K GPUs (device: gpu tasks run "
                             "in batches, one thread block each; docs/GPU.md)")
    parser.add_argument("--gpu-batch", type=int, default=None, metavar="B",
                        help="tasks of one variant and N_G per GPU launch (default 256)")
    # testing hook: the per-task function ("kernels", "synthetic" or "module:attr")
    parser.add_argument("--task-function", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--depth", type=int, default=2, help=argparse.SUPPRESS)


def _log(msg):
    print(msg, file=sys.stderr, flush=True)


def _set_numba_cache(args):
    if args.numba_cache:
        os.environ["NUMBA_CACHE_DIR"] = str(Path(args.numba_cache).expanduser().resolve())
    else:
        os.environ.setdefault("NUMBA_CACHE_DIR", str(Path.home() / ".cache" / "jamming-campaign" / "numba"))
    try:
        Path(os.environ["NUMBA_CACHE_DIR"]).mkdir(parents=True, exist_ok=True)
    except OSError:
        pass


def main(args) -> int:
    # SLURM's USR1 warning may come while the tasks start and the kernels compile: remember it for
    # the master (which then starts no task) instead of dying of it.
    args.warned = []
    signal.signal(signal.SIGUSR1, lambda signum, frame: args.warned.append(signum))
    from campaign.run.launch import launched_tasks, mpi_env_detected, split_launch_error

    # First, before anything heavy is imported: a launcher started several tasks that must form one
    # MPI world, and nothing connects them (srun without --mpi, or --launcher local/inline).
    split = launched_tasks()[0] > 1
    use_mpi = args.launcher == "mpi" or (args.launcher == "auto" and mpi_env_detected())
    if split and not use_mpi:
        _refuse_split_launch(split_launch_error(1) + ("" if args.launcher == "auto" else
                                                      f" (--launcher {args.launcher} makes each task a master.)"))
    if use_mpi:  # a worker ends with its master from now on: while MPI starts, before the settings come
        from campaign.run.launch import watch_first_rank

        watch_first_rank()

    from campaign.errors import UserError
    from campaign.run.walltime import deadline

    args.deadline = deadline(time.time(), args.time_limit)
    if args.margin < 0:
        raise UserError(f"--margin must be >= 0 seconds; got {args.margin:g}")
    from campaign.plan import calibration

    calibration.active()  # the dispatch order and --time-limit price tasks: a bad calibration file stops here
    _set_numba_cache(args)
    if args.task_function is None:
        args.task_function = os.environ.get("CAMPAIGN_TASK_FUNCTION") or "kernels"
    # a campaign with precision targets decides its rounds with the reducer (the run wing does not reduce)
    from campaign.precision.planner import Planner

    args.planner = Planner
    if use_mpi:
        MPI = _start_mpi()
        comm = MPI.COMM_WORLD
        refused = split_launch_error(comm.Get_size())
        if refused:
            _refuse_split_launch(refused)
        if comm.Get_size() > 1:
            if comm.Get_rank() != 0:
                from campaign.run.engine import mpi_worker

                return mpi_worker(comm)
            return _mpi_master(args, comm, MPI)
    from campaign.run.engine import run_campaign

    return run_campaign(args)


def _start_mpi():
    """mpi4py's MPI, started (``MPI_Init_thread``, as mpi4py starts it: every thread level, errors as
    exceptions, finalised at exit) without holding the interpreter: MPI's start waits for every task of
    the job, the master included, and the watch of the master (``watch_first_rank``, a thread) must run
    meanwhile. mpi4py's own start holds the interpreter throughout; it is the fallback."""
    import atexit
    import ctypes

    import mpi4py

    mpi4py.rc.initialize = False
    from mpi4py import MPI

    if MPI.Is_initialized():
        return MPI
    try:
        init = ctypes.CDLL(MPI.__file__).MPI_Init_thread  # a foreign call: the interpreter is released
    except (OSError, AttributeError):
        MPI.Init_thread()
        return MPI
    provided = ctypes.c_int()
    if init(None, None, ctypes.c_int(MPI.THREAD_MULTIPLE), ctypes.byref(provided)) != 0 or not MPI.Is_initialized():
        raise RuntimeError("MPI_Init_thread failed")
    for comm in (MPI.COMM_SELF, MPI.COMM_WORLD):
        comm.Set_errhandler(MPI.ERRORS_RETURN)  # mpi4py's default: a failed call raises MPI.Exception
    atexit.register(lambda: MPI.Is_finalized() or MPI.Finalize())
    return MPI


def _refuse_split_launch(message):
    """Every task of a split launch says why and exits 2. srun --kill-on-bad-exit ends the step when
    the first one exits; a pause lets the others (slower to start on a loaded node) reach this point
    and report too."""
    from campaign.errors import UserError

    if "SLURM_STEP_NUM_TASKS" in os.environ:
        time.sleep(3.0)
    raise UserError(message)


def _mpi_master(args, comm, MPI) -> int:
    from campaign.errors import UserError, WriteFault

    from campaign.run.engine import run_campaign

    state = {"sent": False}
    try:
        return run_campaign(args, comm, MPI, state)
    except UserError:
        if not state["sent"]:
            comm.bcast(None, root=0)
            raise
        traceback.print_exc()
        comm.Abort(2)
    except WriteFault:  # a full disk: the engine stopped the workers (or aborted the job when busy)
        if not state["sent"]:
            comm.bcast(None, root=0)
        raise
    except SystemExit:
        raise
    except BaseException:  # noqa: BLE001 - a master fault aborts the whole job instead of hanging it
        traceback.print_exc()
        _log("campaign run: internal error on the MPI master; aborting the job")
        sys.stderr.flush()
        time.sleep(0.5)  # let the launcher forward the message before MPI_Abort tears the job down
        comm.Abort(1)
    return 1
