"""`campaign run`, `campaign status` and `campaign validate` from the command line."""

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest

from campaign import cli
from campaign.storage.progress import Progress

ROOT = Path(__file__).resolve().parents[2]
SPEC = """\
name: cli
seed: 9
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 3}
observables: [scalars, connectivity]
run: {retries: 1}
"""


def _spec(tmp_path, text=SPEC, name="s.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _env(**extra):
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", PYTHONPATH=str(ROOT))
    env.update(extra)
    return env


def _run_cli(*argv):
    return cli.main(["run", *argv, "--task-function", "synthetic"])


def test_run_status_and_resume(tmp_path, capsys):
    spec, out = _spec(tmp_path), tmp_path / "o.h5"
    assert _run_cli(str(spec), "--out", str(out), "--launcher", "inline") == 0
    err = capsys.readouterr().err
    assert "12 done, 0 failed, 0 pending of 12 tasks" in err and "\r" not in err  # quiet: not a terminal
    assert cli.main(["status", str(out)]) == 0
    text = capsys.readouterr().out
    assert "done 12  failed 0  running 0  remaining 0" in text
    assert "no run is writing it" in text
    assert text.count("default ") == 4  # one line per (variant, N, E)
    size = (tmp_path / "o.h5.journal").stat().st_size
    assert _run_cli(str(spec), "--out", str(out), "--launcher", "inline") == 0  # resume: nothing to do
    assert "this run: 0 done" in capsys.readouterr().err
    with h5py.File(out, "r") as f:
        assert len(json.loads(f.attrs["runs"])) == 2
        versions = json.loads(f.attrs["versions"])
        for key in ("python", "numpy", "numba", "h5py", "mpi4py", "mpi_library"):
            assert versions[key] and versions[key] != "not installed", key
        assert f.attrs["spec_yaml"] == spec.read_text() and len(f.attrs["spec_hash"]) == 32
        assert f.attrs["git_commit"] and f.attrs["package_version"] == __import__("campaign").__version__
        assert json.loads(f.attrs["hosts"]) and f.attrs["start_time"] <= f.attrs["end_time"]
    assert (tmp_path / "o.h5.journal").stat().st_size - size < 4096  # two run records, no task records


def test_other_spec_refused_unless_new(tmp_path, capsys):
    out = tmp_path / "o.h5"
    assert _run_cli(str(_spec(tmp_path)), "--out", str(out), "--launcher", "inline") == 0
    other = _spec(tmp_path, SPEC.replace("seed: 9", "seed: 10"), "t.yaml")
    capsys.readouterr()
    assert _run_cli(str(other), "--out", str(out), "--launcher", "inline") == 2
    err = capsys.readouterr().err
    assert "different spec" in err and "--new" in err and "Traceback" not in err
    assert _run_cli(str(other), "--out", str(out), "--launcher", "inline", "--new") == 0
    with h5py.File(out, "r") as f:
        assert f.attrs["spec_yaml"] == other.read_text()


def test_failures_listed_by_status(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("CAMPAIGN_SYNTHETIC_FAIL", "seed:2")
    out = tmp_path / "o.h5"
    assert _run_cli(str(_spec(tmp_path)), "--out", str(out), "--launcher", "inline") == 0
    assert "4 failed" in capsys.readouterr().err
    assert cli.main(["status", str(out), "--tracebacks"]) == 0
    text = capsys.readouterr().out
    assert "failures (4):" in text and text.count("attempts=2") == 4
    assert "synthetic failure" in text and "Traceback (most recent call last)" in text
    assert cli.main(["status", str(out), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["done"] == 8 and data["failed"] == 4 and len(data["failures"]) == 4
    assert {f["seed"] for f in data["failures"]} == {2}
    assert sum(g["failed"] for g in data["groups"]) == 4
    # failed tasks are finished: a plain rerun leaves them, --retry-failed runs them again
    monkeypatch.delenv("CAMPAIGN_SYNTHETIC_FAIL")
    assert _run_cli(str(_spec(tmp_path)), "--out", str(out), "--launcher", "inline") == 0
    assert "8 done, 4 failed" in capsys.readouterr().err
    assert _run_cli(str(_spec(tmp_path)), "--out", str(out), "--launcher", "inline", "--retry-failed") == 0
    assert "12 done, 0 failed" in capsys.readouterr().err
    with h5py.File(out, "r") as f:
        assert len(f["failures"]) == 0


def test_status_user_errors(tmp_path, capsys):
    assert cli.main(["status", str(tmp_path / "missing.h5")]) == 2
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = 1
    assert cli.main(["status", str(tmp_path / "other.h5")]) == 2
    assert "not a campaign store" in capsys.readouterr().err


def test_run_without_spec_runs_the_packaged_quickstart(tmp_path):
    r = subprocess.run([sys.executable, "-m", "campaign", "run", "--launcher", "inline"], cwd=tmp_path,
                       env=_env(), capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    with h5py.File(tmp_path / "results" / "quickstart.h5", "r") as f:
        assert f.attrs["name"] == "quickstart" and (f["tasks/status"][:] == 1).sum() == 288


def test_bad_options_exit_2(tmp_path):
    spec = _spec(tmp_path)
    assert _run_cli(str(spec), "--workers", "0") == 2
    assert _run_cli(str(tmp_path / "nope.yaml")) == 2


def test_status_while_running_and_sigterm_then_resume(tmp_path):
    spec, out = _spec(tmp_path, SPEC.replace("seeds: 3", "seeds: 30")), tmp_path / "o.h5"
    cmd = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--workers", "2"]
    p = subprocess.Popen(cmd, env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.1"), stderr=subprocess.PIPE, text=True)
    try:
        seen = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            time.sleep(0.5)
            r = subprocess.run([sys.executable, "-m", "campaign", "status", str(out), "--json"], env=_env(),
                               capture_output=True, text=True, timeout=30)
            if r.returncode == 0:
                data = json.loads(r.stdout)
                if data["live"] and 0 < data["done"] < 80:
                    seen = data
                    break
        assert seen is not None, "status never saw the run in progress"
        assert seen["running"] >= 1 and seen["eta_seconds"] > 0
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 143, err
    assert "Resume with: campaign run" in err and "no new tasks" in err
    with h5py.File(out, "r") as f:
        done = int((f["tasks/status"][:] == 1).sum())
    assert 0 < done < 120
    r = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert f"this run: {120 - done} done" in r.stderr


def test_progress_line_on_a_terminal():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    s = Tty()
    p = Progress(10, stream=s)
    p.update(done=3, failed=1, running=2, remaining=4, cost_remaining=4.0, finished_now=4, cost_now=4.0, force=True)
    p.finish()
    text = s.getvalue()
    assert text.startswith("\r") and "done 3  failed 1  running 2  remaining 4" in text
    assert "packings/h" in text and "ETA" in text


class WarmProbe:
    """A task function that logs who warms up and when (see the test below)."""

    def __init__(self):
        from campaign.run.worker import SyntheticTask

        self.inner = SyntheticTask()

    def histogram_edges(self, context):
        return self.inner.histogram_edges(context)

    def warm_up(self, context):
        with open(os.environ["WARM_LOG"], "a") as f:
            f.write(f"{os.getpid()} {time.monotonic()}\n")
        time.sleep(0.3)  # a "compilation" that takes a while

    def run(self, payload, context):
        return self.inner.run(payload, context)


@pytest.mark.parametrize("launcher", ["local", pytest.param("mpi", marks=pytest.mark.slow)])
def test_kernels_are_compiled_once_by_the_master_before_any_worker_starts(tmp_path, launcher):
    mpiexec = Path(sys.executable).parent / "mpiexec"
    log, out = tmp_path / "warm.log", tmp_path / "o.h5"
    cmd = [sys.executable, "-m", "campaign", "run", str(_spec(tmp_path)), "--out", str(out),
           "--task-function", "test_cli_engine:WarmProbe"]
    cmd = [str(mpiexec), "-n", "3"] + cmd if launcher == "mpi" else cmd + ["--workers", "2"]
    env = _env(WARM_LOG=str(log), PYTHONPATH=f"{ROOT}{os.pathsep}{Path(__file__).resolve().parent}")  # WarmProbe's module
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    with h5py.File(out, "r") as f:
        master = json.loads(f.attrs["runs"])[-1]["pid"]
    entries = [(int(p), float(t)) for p, t in (line.split() for line in log.read_text().splitlines())]
    assert entries[0][0] == master  # the master warms the cache first ...
    workers = entries[1:]
    assert len(workers) == 2 and master not in {p for p, _ in workers}
    assert all(t >= entries[0][1] + 0.3 for _, t in workers)  # ... and the workers only load it afterwards


def test_a_full_disk_at_the_progress_file_says_what_the_write_needed(tmp_path, monkeypatch):
    """The progress file's write on a full file system stops the run (OutOfSpace) with the bytes it
    wanted, so that the stop paragraph says what the step needed whichever write met the full disk."""
    import errno

    from campaign.errors import OutOfSpace

    p = Progress(10, sidecar=tmp_path / "out.h5.progress.json", stream=io.StringIO(), enabled=False)
    written = []

    def full(self, text, *a, **k):
        written.append(text)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full)
    with pytest.raises(OutOfSpace) as got:
        p.write_sidecar()
    assert got.value.needed == len(written[-1].encode()) > 0
