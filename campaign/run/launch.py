"""What the launcher of this process says: MPI or not, and how many tasks it started.

Standard library only: ``campaign run`` asks before it imports anything heavy, so that all tasks of
a refused launch reach the refusal within moments of each other.
"""

from __future__ import annotations

import os
import time


def mpi_env_detected() -> bool:
    """True when this process was started by an MPI launcher (mpiexec, srun with PMI)."""
    keys = ("PMI_RANK", "PMI_SIZE", "PMIX_RANK", "OMPI_COMM_WORLD_SIZE", "MPI_LOCALNRANKS", "PMI_FD",
            "HYDRA_CONTROL_FD")
    return any(k in os.environ for k in keys)


# Variables in which a launcher says how many tasks it started, and which one it is.
_TASK_COUNTS = (("SLURM_STEP_NUM_TASKS", "srun"), ("PMI_SIZE", "a PMI launcher such as Hydra's mpiexec"),
                ("OMPI_COMM_WORLD_SIZE", "Open MPI's mpirun"), ("PMIX_SIZE", "a PMIx launcher"))
_TASK_RANKS = ("SLURM_PROCID", "PMI_RANK", "OMPI_COMM_WORLD_RANK", "PMIX_RANK")


def launched_tasks(environ=None) -> tuple[int, str | None]:
    """How many tasks the launcher of this process says it started, and which launcher said so.

    (1, None) when no launcher variable says more than one. Under Hydra's mpiexec inside a SLURM
    job, srun starts one proxy per node (SLURM_STEP_NUM_TASKS = nodes) and PMI_SIZE counts the
    ranks: the largest count is the one that matters.
    """
    environ = os.environ if environ is None else environ
    best, who = 1, None
    for key, name in _TASK_COUNTS:
        try:
            k = int(environ.get(key, ""))
        except ValueError:
            continue
        if k > best:
            best, who = k, f"{key}={k}, set by {name}"
    return best, who


def split_launch_error(world: int, environ=None) -> str | None:
    """The message refusing a split launch, or None: the launcher started K > 1 tasks, MPI sees ``world``.

    Each task would then be a master of its own (a world of 1 runs local workers): several masters
    on one file. Every task refuses before it opens the store.
    """
    k, who = launched_tasks(environ)
    if k <= 1 or world > 1:
        return None
    environ = os.environ if environ is None else environ
    rank = next((f" (task {environ[r]})" for r in _TASK_RANKS if r in environ), "")
    return (f"split launch: the launcher says {k} tasks were started ({who}), but this one{rank} is alone "
            f"in its MPI world, so every task would be a master of its own. The launcher did not connect the "
            "tasks to the MPI library: under SLURM start them with `srun --mpi=pmi2` (the MPICH the "
            "package installs; `srun --mpi=list` shows what the cluster offers; `campaign slurm` "
            "writes it), or with the MPI library's own mpiexec; an Open MPI or site MPI needs the srun "
            "--mpi type it was built for (see slurm/README.md). Nothing was written.")


# The rank a launcher gives each task, by launcher (Hydra's mpiexec and srun with PMI, srun, Open MPI, PMIx).
_RANK_VARS = ("PMI_RANK", "SLURM_PROCID", "OMPI_COMM_WORLD_RANK", "PMIX_RANK")


def _stat(pid):
    """(state, parent pid) of process ``pid`` from /proc, or None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            fields = fh.read().rsplit(b")", 1)[-1].split()
        return fields[0], int(fields[1])
    except (OSError, IndexError, ValueError):
        return None


def _environ(pid) -> dict:
    try:
        with open(f"/proc/{pid}/environ", "rb") as fh:
            return dict(kv.split(b"=", 1) for kv in fh.read().split(b"\0") if b"=" in kv)
    except OSError:
        return {}


def _alive(pid) -> bool:
    st = _stat(pid)
    return st is not None and st[0] not in (b"Z", b"X")


def _ranks_below(key: bytes, launcher: int) -> dict:
    """pid -> rank (bytes) of the processes below ``launcher`` (the launcher's process that started this
    task) whose environment holds the rank variable ``key``: the job's tasks on this host, and any
    wrapper between a task and the launcher."""
    parent = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            st = _stat(d)
            if st is not None and st[0] not in (b"Z", b"X"):
                parent[int(d)] = st[1]
    found = {}
    for pid in parent:
        p, seen = pid, 0
        while p in parent and p != launcher and seen < 64:
            p, seen = parent[p], seen + 1
        if p == launcher and pid != launcher:
            rank = _environ(pid).get(key)
            if rank is not None:
                found[pid] = rank
    return found


def watch_first_rank(interval: float = 0.5, look_for: float = 10.0) -> bool:
    """A worker task of an MPI launch ends when the master (rank 0) on its host is gone, from its very
    start: while MPI starts, while it waits for the settings the master broadcasts, and after (where
    ``campaign.run.comm.watch_master`` watches the master by the pid the settings name). Otherwise a
    master killed before it sent them leaves its workers waiting for ever where the launcher does not
    end the job's other tasks by itself (a wrapper script between the launcher and the master, Hydra's
    ``-disable-auto-cleanup``, srun without ``--kill-on-bad-exit``). Linux (/proc); standard library
    only, before MPI starts.

    The master is found as the processes with rank 0 below the launcher's process that started this
    one (the nearest ancestor without a rank variable: Hydra's proxy, slurmstepd); a thread looks
    for them for up to ``look_for`` seconds (rank 0 runs on another host when none is found: its
    launcher ends the job there), then every ``interval`` seconds whether one is still alive, and
    ends this process (``os._exit``) when none is, or when the launcher's process is gone. A master
    killed before this process looked is told apart from one on another host by Hydra's count of the
    job's tasks on this host (``MPI_LOCALNRANKS``): fewer are alive. Returns whether it watches."""
    import threading

    key = next((k for k in _RANK_VARS if k in os.environ), None)
    if key is None or os.environ[key] == "0" or not os.path.isdir("/proc"):
        return False
    key_b = key.encode()
    launcher, hops = os.getppid(), 0
    while launcher > 1 and key_b in _environ(launcher) and hops < 64:
        st = _stat(launcher)
        launcher, hops = (st[1] if st else 1), hops + 1
    if launcher <= 1:
        return False

    local = os.environ.get("MPI_LOCALNRANKS", "")  # Hydra: how many of the job's tasks run on this host

    def watch():
        t0, master, short = time.monotonic(), set(), 0
        while True:
            if not master and time.monotonic() - t0 < look_for:
                ranks = _ranks_below(key_b, launcher)
                master = {pid for pid, rank in ranks.items() if rank == b"0"}
                # twice in a row: a task the launcher has forked but not yet started has no rank variable
                short = short + 1 if not master and local.isdigit() and len(set(ranks.values())) < int(local) else 0
                if short >= 2:
                    os._exit(0)  # a task of this host (the master, not seen yet) is gone already
            if not _alive(launcher) or (master and not any(_alive(p) for p in master)):
                os._exit(0)
            if not master and time.monotonic() - t0 >= look_for:
                return  # the master runs on another host
            time.sleep(interval)

    threading.Thread(target=watch, name="campaign-first-rank-watch", daemon=True).start()
    return True
