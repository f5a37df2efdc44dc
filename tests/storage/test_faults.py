"""Faults a cluster throws at a campaign, for real: a disk that fills before and during a run,
HDF5 itself meeting the full disk, an output on a read-only file system, a dead master seen by
`campaign status`, worker processes and MPI ranks killed with SIGKILL.

The file systems are real tmpfs mounts (this needs root, as CI runs; elsewhere those tests
skip), filled with a plain file; every mount is removed when its test ends, whatever happens.
Every case ends, once the fault is cleared, in a store equal to an uninterrupted run's, and no
output of a faulty run has a traceback.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers import (SKIP_DATASETS, durable_packings, mpich_segments, processes, remove_segments_of_killed_jobs,
                     store_data_and_attrs)

ROOT = Path(__file__).resolve().parents[2]
MPIEXEC = Path(sys.executable).parent / "mpiexec"
# 240 tasks keeping their configurations: about 3 MB at the journal's peak and 1.4 MB in the store.
SPEC = """\
name: faults
seed: 5
grid: {N_G: [64, 128], E_G: [1.0e-3, 1.0e-6], seeds: 60}
observables: [scalars, connectivity, void_areas]
store: {configurations: true}
"""
DISK = "4000k"  # the uninterrupted run fits in it


def _can_mount():
    if os.geteuid() != 0:
        return "mounting a tmpfs needs root (CI runs as root)"
    return None


needs_root = pytest.mark.skipif(_can_mount() is not None, reason=str(_can_mount()))
pytestmark = pytest.mark.slow  # real runs into full, nearly full and read-only file systems: .ci/run


@contextlib.contextmanager
def tmpfs(path: Path, size: str, ro=False):
    """A real tmpfs of ``size`` at ``path`` for the block; unmounted afterwards whatever happens."""
    path.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}" + (",ro" if ro else ""), "tmpfs", str(path)],
                   check=True, capture_output=True)
    try:
        yield path
    finally:
        if subprocess.run(["umount", str(path)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(path)], capture_output=True)  # a process still holds a file


def _free(path) -> int:
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def _fill(disk: Path, leave: int) -> Path:
    """A filler file that leaves ``leave`` bytes free on ``disk``."""
    filler = disk / "filler"
    size = max(0, _free(disk) - leave)
    with open(filler, "ab") as fh:
        fh.write(b"\0" * size)
    return filler


def _env(**extra):
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", PYTHONPATH=f"{ROOT}{os.pathsep}{ROOT / 'tests'}")
    env.pop("CAMPAIGN_NO_RESERVE", None)
    env.update(extra)
    return env


def _run(spec, out, *extra, n=None, env=None, timeout=120):
    cmd = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet", *extra]
    if n is not None:
        cmd = [str(MPIEXEC), "-n", str(n)] + cmd
    elif "--launcher" not in extra:
        cmd += ["--workers", "2"]
    return subprocess.run(cmd, env=env or _env(), capture_output=True, text=True, timeout=timeout)


def _status(out, *extra):
    return subprocess.run([sys.executable, "-m", "campaign", "status", str(out), *extra], env=_env(),
                          capture_output=True, text=True, timeout=60)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The spec and one uninterrupted run of it, on an ordinary disk."""
    tmp = tmp_path_factory.mktemp("faults")
    spec = tmp / "spec.yaml"
    spec.write_text(SPEC)
    ref = tmp / "ref.h5"
    r = _run(spec, ref, "--launcher", "inline")
    assert r.returncode == 0, r.stderr
    return spec, ref


def _assert_equal(out, ref, skip=()):
    a, _ = store_data_and_attrs(out)
    b, _ = store_data_and_attrs(ref)
    assert sorted(a) == sorted(b)
    for name in a:
        if name not in SKIP_DATASETS and name not in skip:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def _assert_consistent(out):
    """The store walks with h5py from top to bottom, the journal holds no task twice (durable_packings
    asserts it), and every task of the journal is one of the spec's."""
    with h5py.File(out, "r", locking=False) as f:
        names = []
        f.visititems(lambda name, obj: names.append(name) or (obj[()] if isinstance(obj, h5py.Dataset) else None))
        status = f["tasks/status"][:]
    durable = durable_packings(out)
    assert all(0 <= i < len(status) for i in durable)
    return durable


def _assert_stop_paragraph(r, disk, kept=True):
    err = r.stderr
    assert r.returncode == 3, err
    assert err.count("campaign run: out of space") == 1, err  # one paragraph (under MPI too)
    assert "Traceback" not in err and "internal error" not in err, err
    assert "out of space" in err and "No space left on device" in err, err
    assert f"on the file system {disk} (tmpfs" in err and "free" in err, err  # the file system, its space
    assert "rerun the same command to resume: " in err and "needed" in err, err
    if kept:
        assert "kept everything it had finished" in err, err


@contextlib.contextmanager
def _removing_segments(before):
    try:
        yield
    finally:
        remove_segments_of_killed_jobs(before)


# --------------------------------------------------------------------------- a full disk

@needs_root
@pytest.mark.parametrize("launcher", ["local", "mpi"])
def test_disk_fills_during_a_run_then_resumes(tmp_path, reference, launcher):
    """The disk fills in the middle of a run: exit 3, one paragraph, nothing lost, the store
    consistent; a rerun on the still-full disk stops the same way and changes nothing in the store;
    once the filler is gone the rerun completes to an uninterrupted run's store."""
    spec, ref = reference
    n = 3 if launcher == "mpi" else None
    segments = mpich_segments()  # MPI_Abort(3) leaves the job's shared memory behind
    with tmpfs(tmp_path / "disk", DISK) as disk, _removing_segments(segments):
        filler = _fill(disk, 1 << 20)
        out = disk / "out.h5"
        r = _run(spec, out, n=n, env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.002"))
        _assert_stop_paragraph(r, disk)
        kept = _assert_consistent(out)
        assert 0 < len(kept) < 240, r.stderr  # it stopped part-way
        assert not (Path(str(out) + ".progress.json").exists()
                    and json.loads(Path(str(out) + ".progress.json").read_text())["active"])
        st = _status(out)
        assert st.returncode == 0 and "no run is writing it" in st.stdout, st.stdout + st.stderr
        before = out.read_bytes()
        r = _run(spec, out, n=n)  # still full: stops before starting a task
        _assert_stop_paragraph(r, disk, kept=False)
        assert "No task was started" in r.stderr
        assert out.read_bytes() == before  # the store untouched
        assert _assert_consistent(out).keys() >= kept.keys()
        filler.unlink()
        r = _run(spec, out, n=n)
        assert r.returncode == 0, r.stderr
        _assert_equal(out, ref)


@needs_root
def test_disk_full_before_a_run(tmp_path, reference):
    """No room for even a new store: exit 3 before any task starts, no store left behind; once
    there is room the run completes."""
    spec, ref = reference
    with tmpfs(tmp_path / "disk", "1500k") as disk:
        filler = _fill(disk, 8 << 10)
        out = disk / "sub" / "out.h5"
        r = _run(spec, out)
        _assert_stop_paragraph(r, disk, kept=False)
        assert "No task was started" in r.stderr
        assert not out.exists() and not Path(str(out) + ".tmp").exists()
        filler.unlink()
    with tmpfs(tmp_path / "disk", DISK) as disk:
        out = disk / "out.h5"
        assert _run(spec, out).returncode == 0
        _assert_equal(out, ref)


@needs_root
def test_hdf5_itself_meets_the_full_disk(tmp_path, reference):
    """Past every reservation (CAMPAIGN_NO_RESERVE=1: as on a file system without fallocate whose
    free space another writer takes), a write of HDF5's fails in the middle of replaying the
    journal: no segmentation fault (HDF5 never sees the failure: the rest of the step goes to an
    in-memory overlay), exit 3, the journal whole, the store as it was before the step; a rerun on
    the still-full disk stops before writing; once there is room the rerun completes to an
    uninterrupted run's store."""
    spec, ref = reference
    with tmpfs(tmp_path / "disk", DISK) as disk:
        filler = _fill(disk, 1 << 20)
        out = disk / "out.h5"
        r = _run(spec, out, env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.002"))
        _assert_stop_paragraph(r, disk)  # the journal filled: finished tasks in the journal only
        journal = Path(str(out) + ".journal")
        records = durable_packings(out)
        assert records
        # a little room: less than the replay needs, more than the reservations would ask
        with open(filler, "r+b") as fh:
            fh.truncate(filler.stat().st_size - (24 << 10))
        r = _run(spec, out, env=_env(CAMPAIGN_NO_RESERVE="1"))
        assert r.returncode == 3 and r.returncode != -signal.SIGSEGV, r.stderr
        assert "Traceback" not in r.stderr and "may be left damaged" in r.stderr, r.stderr
        assert durable_packings(out).keys() >= records.keys()  # the journal still holds every finished task
        state = out.read_bytes(), journal.read_bytes()
        r = _run(spec, out)  # still full: stops before writing (the reservations are back)
        assert r.returncode == 3 and "Traceback" not in r.stderr and "No task was started" in r.stderr, r.stderr
        store, log = out.read_bytes(), journal.read_bytes()
        # unchanged, but for the bytes past the file's end of allocation that the failed step had
        # written before the disk filled (closing the file cuts them off)
        assert log == state[1] and store == state[0][:len(store)]
        _assert_consistent(out)
        assert not Path(str(out) + ".tmp").exists()
        filler.unlink()
        r = _run(spec, out)
        assert r.returncode == 0, r.stderr
        _assert_equal(out, ref)


# --------------------------------------------------------------------------- an output that cannot be written

@needs_root
def test_read_only_output_is_refused_before_any_worker_starts(tmp_path, reference):
    spec, ref = reference
    warm = tmp_path / "warm.log"
    env = _env(WARM_LOG=str(warm))
    probe = ["--task-function", "test_cli_engine:WarmProbe"]  # logs every warm-up (master and workers)
    with tmpfs(tmp_path / "ro", "1m", ro=True) as ro:
        for out, n in ((ro / "out.h5", None), (ro / "new" / "dir" / "out.h5", None), (ro / "out.h5", 3)):
            r = _run(spec, out, *probe, n=n, env=env, timeout=60)
            assert r.returncode == 2, r.stderr
            assert "Read-only file system" in r.stderr and str(out.parent if n or "new" not in str(out)
                                                               else ro / "new") in r.stderr, r.stderr
            assert "Traceback" not in r.stderr and r.stderr.count("\n") <= 2, r.stderr
            assert not warm.exists()  # refused before anything started
    # a store whose file system became read-only between two runs
    with tmpfs(tmp_path / "disk", DISK) as disk:
        out = disk / "out.h5"
        r = _run(spec, out, "--time-limit", "1", "--margin", "0", env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.05"))
        assert r.returncode == 0, r.stderr
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        r = _run(spec, out)
        assert r.returncode == 2 and "Read-only file system" in r.stderr and "Traceback" not in r.stderr, r.stderr
        subprocess.run(["mount", "-o", "remount,rw", str(disk)], check=True)
        r = _run(spec, out)
        assert r.returncode == 0, r.stderr
        _assert_equal(out, ref)


@needs_root
def test_other_commands_on_a_full_or_read_only_disk(tmp_path, reference):
    """campaign reduce writing its tables into a full tmpfs: exit 3, one paragraph; into a read-only
    one: exit 2; never a traceback."""
    spec, ref = reference
    with tmpfs(tmp_path / "disk", "200k") as disk:
        _fill(disk, 8 << 10)
        r = subprocess.run([sys.executable, "-m", "campaign", "reduce", str(ref), "-o", str(disk / "red")],
                           env=_env(), capture_output=True, text=True, timeout=120)
        assert r.returncode == 3 and "out of space" in r.stderr and "No space left on device" in r.stderr, r.stderr
        assert "Traceback" not in r.stderr and r.stderr.strip().count("\n") == 0, r.stderr
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        r = subprocess.run([sys.executable, "-m", "campaign", "reduce", str(ref), "-o", str(disk / "red2")],
                           env=_env(), capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and "Read-only file system" in r.stderr and "Traceback" not in r.stderr, r.stderr


# --------------------------------------------------------------------------- a dead writer

def _wait_for(predicate, timeout=30.0, what="a condition"):
    t0 = time.monotonic()
    while not predicate():
        assert time.monotonic() - t0 < timeout, f"waited {timeout:.0f} s for {what}"
        time.sleep(0.05)


def _started(out, at_least=1):
    return lambda: len(_durable_quiet(out)) >= at_least


def _durable_quiet(out):
    try:
        return durable_packings(out)
    except (OSError, AssertionError, KeyError):
        return {}


def test_status_tells_a_live_writer_from_a_dead_one(tmp_path, reference):
    spec, ref = reference
    out = tmp_path / "out.h5"
    p = subprocess.Popen([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet",
                          "--workers", "2"], env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.05"), stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        _wait_for(_started(out, 4), what="the run's first tasks")
        live = json.loads(_status(out, "--json").stdout)
        assert live["live"] and live["writer"]["state"] == "running" and live["writer"]["judged_by"] == "pid"
        assert live["writer"]["pid"] == p.pid
        assert f"a run is writing it (pid {p.pid} on" in _status(out).stdout
    finally:
        os.killpg(p.pid, signal.SIGKILL)  # the master and its workers, as the OOM killer or a node failure would
        p.wait(timeout=30)
    dead = json.loads(_status(out, "--json").stdout)
    assert not dead["live"] and dead["writer"] == dict(dead["writer"], state="dead", judged_by="pid", pid=p.pid)
    text = _status(out).stdout
    assert f"no run is writing it: the run that was (pid {p.pid} on" in text and "rerunning it resumes" in text
    assert "finished task(s) are in its journal only so far" in text or dead["done"] > 0
    sidecar = Path(str(out) + ".progress.json")
    info = json.loads(sidecar.read_text())
    # the pid now belongs to another process (pid reuse): a live pid with another start time is dead
    sidecar.write_text(json.dumps(dict(info, pid=os.getpid(), pid_start=1)))
    assert json.loads(_status(out, "--json").stdout)["writer"]["state"] == "dead"
    # another host: judged by the progress file's age (60 s)
    for age, state, live in ((5, "running", True), (120, "dead", False)):
        sidecar.write_text(json.dumps(dict(info, host="elsewhere-node-17", updated=time.time() - age)))
        got = json.loads(_status(out, "--json").stdout)
        assert (got["live"], got["writer"]["state"], got["writer"]["judged_by"]) == (live, state, "age"), got
    text = _status(out).stdout
    assert "has not updated its progress file for 0:02:0" in text and "(more than 60 s)" in text, text
    r = _run(spec, out)
    assert r.returncode == 0, r.stderr
    _assert_equal(out, ref)
    assert "no run is writing it (last run ended" in _status(out).stdout


# --------------------------------------------------------------------------- killed workers

def _ranks(out):
    """{MPI rank: pid} of the processes running `campaign run ... --out OUT` under mpiexec."""
    return {int(env[b"PMI_RANK"]): pid for pid, cmd, env in processes()
            if str(out).encode() in cmd and b"campaign" in cmd and b"PMI_RANK" in env}


def test_worker_rank_killed_under_mpiexec(tmp_path, reference):
    """SIGKILL of a worker rank (as the out-of-memory killer does): the launcher ends the job (MPI's
    rule), the store stays consistent, status sees no live writer, and the rerun completes."""
    spec, ref = reference
    out = tmp_path / "out.h5"
    cmd = [str(MPIEXEC), "-n", "3", sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet"]
    segments = mpich_segments()
    p = subprocess.Popen(cmd, env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.05"), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _wait_for(_started(out, 6), what="the MPI run's first tasks")
        ranks = _ranks(out)
        assert set(ranks) == {0, 1, 2}, ranks
        os.kill(ranks[1], signal.SIGKILL)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
        remove_segments_of_killed_jobs(segments)
    assert p.returncode != 0, err
    kept = _assert_consistent(out)
    assert 0 < len(kept) < 240
    st = json.loads(_status(out, "--json").stdout)
    assert not st["live"] and st["writer"]["state"] in ("dead", "ended"), st
    r = _run(spec, out, n=3)
    assert r.returncode == 0, r.stderr
    _assert_equal(out, ref)


def test_local_worker_killed_the_run_goes_on(tmp_path, reference):
    """Without MPI the master outlives a killed worker process: its tasks are retried by the others."""
    spec, ref = reference
    out = tmp_path / "out.h5"
    p = subprocess.Popen([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--workers", "2"],
                         env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.03"), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, start_new_session=True)
    try:
        _wait_for(_started(out, 4), what="the run's first tasks")
        children = subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True, text=True).stdout.split()
        workers = [int(c) for c in children if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]
        assert workers, children
        os.kill(workers[0], signal.SIGKILL)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
    assert p.returncode == 0, err
    assert "died (exit code -9)" in err and "240 done, 0 failed" in err, err
    _assert_equal(out, ref, skip=("tasks/attempts", "checksums/tasks.attempts"))
    with h5py.File(out, "r") as f:
        attempts = f["tasks/attempts"][:]
    assert 1 <= (attempts == 2).sum() <= 16 and ((attempts == 1) | (attempts == 2)).all()  # the killed one's tasks


def test_an_exhausted_quota_is_out_of_space_like_a_full_disk(tmp_path):
    """EDQUOT takes the full disk's path (exit 3, the same paragraph). A real quota cannot be
    exhausted on these machines: their kernel is built without CONFIG_QUOTA (ext4 refuses to
    mount with its quota feature, tmpfs refuses usrquota), so the error is built here as the
    operating system and HDF5 report it."""
    import errno

    from campaign.storage import faults

    path = tmp_path / "x.h5"
    for exc in (OSError(errno.EDQUOT, os.strerror(errno.EDQUOT)),
                RuntimeError(f"Can't write data (file write failed: ..., errno = {errno.EDQUOT}, "
                             "error message = 'Disk quota exceeded', ...)")):
        fault = faults.write_fault(exc, path, "writing a block of the store")
        assert isinstance(fault, faults.OutOfSpace) and fault.errno == errno.EDQUOT
        text = faults.stop_paragraph(fault, path, counts={"done": 3, "failed": 0, "pending": 2}, total=5)
        assert "out of space" in text and "Disk quota exceeded" in text
        assert "raise the quota" in text and "rerun the same command" in text
