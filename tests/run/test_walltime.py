"""Wall-time awareness: deadlines, the dispatch predicate, and a SLURM job run locally.

The last test runs the body of a script written by `campaign slurm` (mpiexec launcher) with
SLURM's environment set by hand: a first job runs out of time and stops cleanly (exit 0), a
second job completes the file, and the result equals one uninterrupted run's.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from campaign.errors import UserError
from campaign.plan.parse import parse_spec
from campaign.storage.store import DONE
from campaign.plan.tasks import expand
from campaign.run.walltime import Deadline, deadline, parse_limit
from helpers import SKIP_DATASETS, store_data_and_attrs

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
SPEC = """\
name: walltime
seed: 5
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 5}
observables: [scalars, connectivity]
"""


@pytest.mark.parametrize("text,seconds", [("90", 90.0), ("2.5", 2.5), ("00:01:30", 90.0), ("1-00:00:00", 86400.0)])
def test_parse_limit(text, seconds):
    assert parse_limit(text) == seconds


@pytest.mark.parametrize("text", ["0", "-5", "nan", "inf", "soon", "1:30"])
def test_parse_limit_refuses(text):
    with pytest.raises(UserError):
        parse_limit(text)


def test_time_limit_counts_from_the_job_start():
    """The batch script records its start: what srun, imports and MPI set-up take is spent, not added."""
    assert deadline(1000.0, "60", {"CAMPAIGN_JOB_START": "990"}) == 1050.0
    assert deadline(1000.0, "60", {"CAMPAIGN_JOB_START": "1010"}) == 1060.0  # a clock in the future: ignored
    assert deadline(1000.0, "60", {"CAMPAIGN_JOB_START": "soon"}) == 1060.0
    assert deadline(1000.0, None, {"CAMPAIGN_JOB_START": "990"}) is None
    assert deadline(1000.0, "60", {"CAMPAIGN_JOB_START": "990", "SLURM_JOB_END_TIME": "1040"}) == 1040.0


def test_deadline_is_the_earliest_limit():
    assert deadline(1000.0, None, {}) is None
    assert deadline(1000.0, "60", {}) == 1060.0
    assert deadline(1000.0, None, {"SLURM_JOB_END_TIME": "1500"}) == 1500.0
    assert deadline(1000.0, "00:10:00", {"SLURM_JOB_END_TIME": "1500"}) == 1500.0
    assert deadline(1000.0, "60", {"SLURM_JOB_END_TIME": "1500"}) == 1060.0
    assert deadline(1000.0, "60", {"SLURM_JOB_END_TIME": "garbage"}) == 1060.0


class _Store:
    def __init__(self, n):
        self.status = np.zeros(n, dtype=np.int8)
        self.wall = np.full(n, np.nan)


def test_predicate_counts_the_task_and_the_ones_queued_before_it():
    tasks = expand(parse_spec(SPEC))
    store = _Store(len(tasks))
    cell = [t for t in tasks if (t.N, t.E) == (16, 1e-3)]
    for t in cell[:4]:  # every finished packing of this cell took 10 s
        store.status[t.index], store.wall[t.index] = DONE, 10.0
    task, others = cell[4], [t for t in tasks if t.N == 32]
    now = [0.0]
    wall = Deadline(store, tasks, end=100.0, margin=20.0, clock=lambda: now[0])
    per_task = wall.model().task_seconds(task)
    assert 9.0 < per_task < 12.0  # learnt from the store, not the static guess
    assert all(wall.model().task_seconds(t) > per_task for t in others)  # larger N costs more
    assert wall(task)                                       # 80 s left
    assert not wall(task, ahead=others[:7])                 # 7 larger tasks queued before it
    now[0] = 80.0 - 0.5 * per_task
    assert not wall(task)                                   # half a task's time left
    now[0] = 80.0 - 1.5 * per_task
    assert wall(task) and not wall(task, ahead=others[:1])


def _env(**extra):
    return dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", PYTHONPATH=str(ROOT),
                PATH=f"{BIN}:{os.environ['PATH']}", **extra)


def _status(path):
    return json.loads(subprocess.run([sys.executable, "-m", "campaign", "status", str(path), "--json"], env=_env(),
                                     capture_output=True, text=True, check=True).stdout)


@pytest.mark.slow
def test_sigusr1_stops_cleanly_and_the_rerun_completes(tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    out = tmp_path / "s.h5"
    cmd = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--workers", "2", "--quiet"]
    proc = subprocess.Popen(cmd, env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.3"), stderr=subprocess.PIPE, text=True)
    journal = Path(str(out) + ".journal")
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60 and (not journal.exists() or journal.stat().st_size < 2000):
        time.sleep(0.05)
    proc.send_signal(signal.SIGUSR1)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "stopped (SIGUSR1)" in err and "Resume with" in err
    assert subprocess.run(cmd, env=_env(), capture_output=True, timeout=60).returncode == 0
    assert _status(out)["done"] == 20


@pytest.mark.slow
def test_slurm_script_body_runs_out_of_time_then_a_second_job_completes(tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    script = tmp_path / "job.sbatch"
    out = tmp_path / "out.h5"
    subprocess.run([sys.executable, "-m", "campaign", "slurm", str(spec), "--launcher", "mpiexec",
                    "--nodes", "1", "--ntasks-per-node", "3", "--time", "00:10:00", "--warn", "1", "--margin", "1",
                    "--results", str(out), "--out", str(script)], env=_env(), check=True, capture_output=True)
    slurm = {"SLURM_JOB_ID": "4242", "SLURM_NTASKS": "3", "SLURM_JOB_NUM_NODES": "1", "TMPDIR": str(tmp_path),
             "CAMPAIGN_SYNTHETIC_DELAY": "0.5"}
    # First job: the allocation ends 6 s from now; 20 tasks of 0.5 s on 2 workers need 5 s of
    # work plus start-up, so it runs out of time part-way through.
    first = subprocess.run(["bash", str(script)], capture_output=True, text=True, timeout=120,
                           env=_env(**slurm, SLURM_JOB_END_TIME=str(int(time.time()) + 6)))
    assert first.returncode == 0, first.stderr
    assert "stopped (wall time)" in first.stderr and "task(s) left" in first.stderr
    after_first = _status(out)
    assert 0 < after_first["done"] < 20 and after_first["remaining"] == 20 - after_first["done"]
    assert after_first["remaining_core_hours"] > 0
    # Second job of the chain: plenty of time.
    second = subprocess.run(["bash", str(script)], capture_output=True, text=True, timeout=120,
                            env=_env(**slurm, SLURM_JOB_END_TIME=str(int(time.time()) + 3600)))
    assert second.returncode == 0, second.stderr
    # A third job finds nothing left and exits at once.
    t0 = time.monotonic()
    third = subprocess.run(["bash", str(script)], capture_output=True, text=True, timeout=120,
                           env=_env(**slurm, SLURM_JOB_END_TIME=str(int(time.time()) + 3600)))
    assert third.returncode == 0 and time.monotonic() - t0 < 30
    assert "this run: 0 done" in third.stderr
    # The same as one uninterrupted run.
    ref = tmp_path / "ref.h5"
    subprocess.run([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(ref), "--launcher", "inline",
                    "--quiet"], env=_env(), check=True, capture_output=True, timeout=120)
    got, got_attrs = store_data_and_attrs(out)
    want, want_attrs = store_data_and_attrs(ref)
    assert sorted(got) == sorted(want)
    for name in want:
        if name not in SKIP_DATASETS:
            np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    assert got_attrs.keys() == want_attrs.keys()
