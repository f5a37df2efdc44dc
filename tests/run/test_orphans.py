"""Workers end within seconds when their master dies (docs/STORE.md, "Workers die with their master").

The quick suite: a local `campaign run` whose two workers compute, its master SIGKILLed; the workers'
exit is awaited on their pid file descriptors, and it comes within 10 s both as the run is (the kernel's
PR_SET_PDEATHSIG and the watcher thread) and with the kernel's request left out (the watcher thread
alone, as on systems without it). The rest is slow:

A real `campaign run` (synthetic tasks of several seconds each) is killed with SIGKILL while its workers
compute; 10 s later no worker process is alive; a rerun completes the campaign with the bits of an
uninterrupted run. Locally (two worker processes) and under `mpiexec -n 3`, there with Hydra's own
clean-up disabled. And under `mpiexec -n 3` with a wrapper shell between Hydra and each task, the master
killed at moments of the start-up, before and after it sends the workers their settings: Hydra ends
the other tasks of a task killed by a signal by itself, -disable-auto-cleanup or not, but not those of
a wrapper that exits with a status, so that there the workers' own watch is what ends them.
"""

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from helpers import mpich_segments, processes, remove_segments_of_killed_jobs

ROOT = Path(__file__).resolve().parents[2]
MPIEXEC = Path(sys.executable).parent / "mpiexec"
SPEC = """\
name: orphans
seed: 11
grid: {N_G: [16, 32], E_G: [1.0e-3], seeds: 3}
observables: [scalars, connectivity]
"""
SKIP = ("tasks/wall", "tasks/rank", "tasks/host", "checksums/tasks.wall", "checksums/tasks.rank",
        "checksums/tasks.host")


def _env(delay):
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", PYTHONPATH=str(ROOT))
    env.pop("CAMPAIGN_SYNTHETIC_DELAY", None)
    if delay:
        env["CAMPAIGN_SYNTHETIC_DELAY"] = delay
    return env


def _alive(pids):
    out = []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat", "rb") as fh:
                if fh.read().rsplit(b")", 1)[-1].split()[0] not in (b"Z", b"X"):
                    out.append(pid)
        except OSError:
            pass
    return out


def _processes_of(out):
    """pid -> environment's PMI_RANK (or None) of every process running `campaign run ... OUT`."""
    got = {}
    for pid, args, env in processes():
        if b"campaign" in b" ".join(args) and str(out).encode() in args or (
                b"--multiprocessing-fork" in args and env.get(b"CAMPAIGN_ORPHAN_TAG") == str(out).encode()):
            got[pid] = env[b"PMI_RANK"].decode() if b"PMI_RANK" in env else None
    return got


#: `campaign run` with its local workers' request to the kernel (PR_SET_PDEATHSIG) left out: each worker
#: process imports this file as its main module (multiprocessing's spawn), so that only the watcher thread
#: of campaign.run.worker.die_with_parent can end it; each writes its pid into $ORPHANS_MARKS when it asks
WATCHER_ONLY = """\
import os
import sys

import campaign.run.worker


def no_kernel_request(sig=None):
    open(os.path.join(os.environ["ORPHANS_MARKS"], str(os.getpid())), "w").close()
    return False


campaign.run.worker._parent_death_signal = no_kernel_request
if __name__ == "__main__":
    from campaign import cli

    sys.exit(cli.main(sys.argv[1:]))
"""


def _children(pid):
    """The pids of the processes whose parent is ``pid``."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_bytes().rsplit(b")", 1)[-1].split()[1]) == pid:
                    out.append(int(d.name))
            except (OSError, IndexError, ValueError):
                pass
    return out


def _until(what, seen, limit):
    """Look for the state ``seen()`` says (a true value when it is there) every 20 ms, at most
    ``limit`` seconds; returns it."""
    end = time.monotonic() + limit
    while True:
        got = seen()
        if got or time.monotonic() > end:
            assert got, f"not seen in {limit} s: {what}"
            return got
        time.sleep(0.02)


@pytest.mark.skipif(not sys.platform.startswith("linux") or not hasattr(os, "pidfd_open"),
                    reason="reads /proc; waits on pid file descriptors")
@pytest.mark.parametrize("how", ["as it runs", "watcher alone"])
def test_a_killed_local_master_leaves_no_worker(tmp_path, how):
    """A local run's master SIGKILLed once its progress file says its two workers hold tasks (each
    computes for a minute): both workers end within 10 s, as the run is (the kernel's signal and the
    watcher thread) and with the watcher thread alone (each worker is seen to leave the kernel's
    request out)."""
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    out, marks = tmp_path / "o.h5", tmp_path / "marks"
    marks.mkdir()
    (tmp_path / "watcher_only.py").write_text(WATCHER_ONLY)
    main = ["-m", "campaign"] if how == "as it runs" else [str(tmp_path / "watcher_only.py")]
    p = subprocess.Popen([sys.executable, *main, "run", str(spec), "--out", str(out), "--workers", "2", "--quiet"],
                         env=dict(_env("60"), ORPHANS_MARKS=str(marks)), stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, start_new_session=True)
    pidfds = []
    try:
        progress = Path(str(out) + ".progress.json")

        def computing():  # the master dispatches once every worker said it is ready: tasks in flight
            try:
                state = json.loads(progress.read_text())
            except (OSError, ValueError):
                return None
            workers = [pid for pid in _children(p.pid)
                       if b"--multiprocessing-fork" in Path(f"/proc/{pid}/cmdline").read_bytes()]
            return workers if state.get("running", 0) >= 2 and len(workers) == 2 else None

        workers = _until("two workers computing", lambda: p.poll() is None and computing() or p.poll() is not None,
                         60)
        assert p.poll() is None, p.stderr.read().decode()[-2000:]
        if how == "watcher alone":  # each worker left the kernel's request out
            assert sorted(int(m.name) for m in marks.iterdir()) == sorted(workers), (list(marks.iterdir()), workers)
        pidfds = [os.pidfd_open(pid) for pid in workers]
        os.kill(p.pid, signal.SIGKILL)
        assert p.wait(timeout=30) == -signal.SIGKILL  # the master's death, seen
        t0, left = time.monotonic(), list(pidfds)
        while left and time.monotonic() - t0 < 10:  # a pid file descriptor is readable once its process ended
            ended, _, _ = select.select(left, [], [], 10 - (time.monotonic() - t0))
            left = [fd for fd in left if fd not in ended]
        assert not left and not _alive(workers), f"workers {_alive(workers)} still alive 10 s after the master's death"
    finally:
        for fd in pidfds:
            os.close(fd)
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except OSError:
            pass
        p.wait(timeout=30)
        p.stderr.close()


def _datasets(path):
    with h5py.File(path, "r") as f:
        got = {}
        f.visititems(lambda k, o: got.__setitem__(k, o[()]) if isinstance(o, h5py.Dataset) else None)
    return got


def _kill_and_resume(tmp_path, launch):
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    ref, out = tmp_path / "ref.h5", tmp_path / "o.h5"
    base = [sys.executable, "-m", "campaign", "run", str(spec), "--quiet"]
    r = subprocess.run(base + ["--out", str(ref), "--launcher", "inline"], env=_env(None), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    env = dict(_env("20"), CAMPAIGN_ORPHAN_TAG=str(out))
    p = subprocess.Popen(launch(base + ["--out", str(out)]), env=env, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # until the workers compute (the progress file says so)
            procs = _processes_of(out)
            if len(procs) >= 3 and Path(str(out) + ".progress.json").exists():
                break
            time.sleep(0.5)
        time.sleep(3)
        procs = _processes_of(out)
        argv = {pid: Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0") for pid in procs}
        masters = [pid for pid, rank in procs.items() if rank in (None, "0") and pid != p.pid
                   and b"--multiprocessing-fork" not in argv[pid]
                   and b"python" in Path(argv[pid][0].decode()).name.encode()]  # not its wrapper shell
        if not masters:
            masters = [p.pid]
        master = min(masters)
        workers = [pid for pid in procs if pid != master]
        assert len(workers) >= 2, procs
        os.kill(master, signal.SIGKILL)
        t0 = time.monotonic()
        while _alive(workers) and time.monotonic() - t0 < 10:
            time.sleep(0.2)
        assert not _alive(workers), f"workers {_alive(workers)} still alive 10 s after the master's death"
        gone = time.monotonic() - t0
    finally:
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except OSError:
            pass
        p.wait(timeout=30)
    r = subprocess.run(base + ["--out", str(out), "--workers", "2"], env=_env(None), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    a, b = _datasets(out), _datasets(ref)
    assert set(a) == set(b)
    for k in a:
        if k not in SKIP:
            assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), k
    return gone


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_local_workers_die_with_a_killed_master(tmp_path):
    gone = _kill_and_resume(tmp_path, lambda cmd: cmd + ["--workers", "2"])
    print("workers gone", round(gone, 2), "s after the SIGKILL")
    assert gone < 10


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux") or not MPIEXEC.exists(), reason="reads /proc; mpiexec")
def test_mpi_workers_die_with_a_killed_master(tmp_path):
    # Hydra's clean-up off and a wrapper shell between it and each task (Hydra ends the other tasks of one
    # killed by a signal whatever the option says): the workers' own watch of the master ends them
    gone = _kill_and_resume(tmp_path, lambda cmd: [str(MPIEXEC), "-disable-auto-cleanup", "-n", "3", "sh", "-c",
                                                   '"$@"; exit $?', "sh"] + cmd)
    print("workers gone", round(gone, 2), "s after the SIGKILL")
    assert gone < 10


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux") or not MPIEXEC.exists(), reason="reads /proc; mpiexec")
def test_mpi_workers_die_with_a_master_killed_while_starting(tmp_path):
    """`mpiexec -n 3`, the master SIGKILLed at moments of the start-up: while MPI starts, while it plans
    (the workers wait for its settings), as its progress file appears (it sends the settings next) and
    just after: 10 s later no worker is alive. Each task is started by a shell that waits for it (as a
    site's wrapper script does), and Hydra's clean-up is off: Hydra then sees the master's shell exit
    with a status, not a signal, and ends no other task by itself (without the wrapper it ends them
    all whatever -disable-auto-cleanup says), so that the workers' own watch is what ends them."""
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    phases, segments = [], mpich_segments()  # the killed jobs' shared memory is removed below
    for k, moment in enumerate(("seen", "planning", "progress", "after")):
        out = tmp_path / f"o{k}.h5"
        cmd = [str(MPIEXEC), "-disable-auto-cleanup", "-n", "3", "sh", "-c", '"$@"; exit $?', "sh", sys.executable,
               "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet"]
        p = subprocess.Popen(cmd, env=_env("20"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             start_new_session=True)
        progress = Path(str(out) + ".progress.json")
        try:
            deadline, master, seen = time.monotonic() + 60, None, None
            while time.monotonic() < deadline:
                procs = _ranked(out)
                master = next((pid for pid, (rank, py) in procs.items() if rank == "0" and py), None)
                seen = seen or (time.monotonic() if master else None)
                ready = {"seen": master is not None, "planning": seen and time.monotonic() - seen > 1.0,
                         "progress": progress.exists(), "after": progress.exists()}[moment]
                if ready:
                    break
                time.sleep(0.01)
            if moment == "after":
                time.sleep(0.3)
            procs = _ranked(out)
            workers = [pid for pid, (rank, _) in procs.items() if rank != "0"]
            assert master is not None and len(workers) >= 2, procs
            phases.append(progress.exists())
            os.kill(master, signal.SIGKILL)
            t0 = time.monotonic()
            while _alive(workers) and time.monotonic() - t0 < 10:
                time.sleep(0.2)
            assert not _alive(workers), (f"workers {_alive(workers)} still alive 10 s after the master's death "
                                         f"({moment})")
            print(moment, "workers gone", round(time.monotonic() - t0, 2), "s after the SIGKILL")
        finally:
            for pid in [p.pid] + list(_ranked(out)):
                try:
                    os.kill(pid, signal.SIGKILL)
                except OSError:
                    pass
            p.wait(timeout=30)
            remove_segments_of_killed_jobs(segments)
    assert False in phases and True in phases  # killed before the settings were sent, and after


def _ranked(out):
    """pid -> (PMI_RANK, is it the Python process rather than its shell) of every task of the launch
    writing OUT."""
    got = {}
    for pid, args, env in processes():
        if str(out).encode() in args and b"PMI_RANK" in env:
            got[pid] = (env[b"PMI_RANK"].decode(), b"python" in Path(args[0].decode()).name.encode())
    return got
