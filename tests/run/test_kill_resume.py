"""Crash safety: SIGKILL the master at random moments, rerun, and get an uninterrupted run's file.

Each round starts a real `campaign run` process (synthetic tasks with small
delays, alternately inline and with two local worker processes), kills it with
SIGKILL after a random time (from interpreter start-up to a little past the end of the
run, or, every other round, while it works; estimated from an uninterrupted run and the
work left),
and checks the durable record (the store's committed rows and the journal's
records since its last checkpoint): nothing finished is ever lost and no task is
recorded twice. A last run completes the campaign; every dataset must then equal an
uninterrupted run's (run-dependent columns aside: wall time, rank, host).
"""

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from campaign.plan.parse import parse_spec
from campaign.plan.tasks import expand
from helpers import SKIP_DATASETS, durable_packings, store_data_and_attrs

ROOT = Path(__file__).resolve().parents[2]
SPEC = """\
name: kill
seed: 99
grid: {N_G: [16, 32, 48], E_G: [1.0e-3, 1.0e-6], seeds: 6}
variants: [{name: loose, force_tolerance: 1.0e-3}]
observables: [scalars, connectivity, void_areas]
store: {configurations: true}
"""
DELAY = "0.005*N"


def _env():
    return dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", PYTHONPATH=str(ROOT),
                CAMPAIGN_SYNTHETIC_DELAY=DELAY, CAMPAIGN_SYNTHETIC_FAIL="seed:4")


def _cmd(spec, out, inline):
    return [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet"] + (
        ["--launcher", "inline"] if inline else ["--workers", "2"])


def _kill_rounds(tmp_path, rounds, seed, spec_text=SPEC):
    spec = tmp_path / "s.yaml"
    spec.write_text(spec_text)
    tasks = expand(parse_spec(spec_text))
    total, failing = len(tasks), sum(t.seed == 4 for t in tasks)
    ref = tmp_path / "ref.h5"
    t0 = time.monotonic()
    r = subprocess.run(_cmd(spec, ref, inline=True), env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    span = time.monotonic() - t0
    t0 = time.monotonic()  # a run with nothing left to do: start-up and shut-down only
    r = subprocess.run(_cmd(spec, ref, inline=True), env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    idle = min(time.monotonic() - t0, span)
    out = tmp_path / "k.h5"
    rng = random.Random(seed)
    finished = {}  # index -> run that computed it (None: known from the store only)
    killed_mid_run = 0
    for k in range(rounds):
        p = subprocess.Popen(_cmd(spec, out, inline=k % 2 == 0), env=_env(), stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)
        # kill within the time this run should take (start-up plus its share of the work left),
        # every other round while it works: start-up takes most of a run of these short tasks
        work = (span - idle) * (total - len(finished)) / total
        if k % 4 < 2:
            time.sleep(rng.uniform(0.0, 1.2) * (idle + work))
        else:
            time.sleep(0.8 * idle + rng.uniform(0.0, 1.2) * work)
        done_before = p.poll() is not None
        try:
            os.killpg(p.pid, signal.SIGKILL)  # the master and its workers, whatever they are doing
        except ProcessLookupError:
            pass
        p.wait(timeout=30)
        durable = durable_packings(out)
        assert finished.keys() <= durable.keys(), "a finished task was lost"
        for i, run in durable.items():  # computed again by a later run: recorded twice
            assert i not in finished or run is None or finished[i] == run, "a finished task was recorded twice"
        killed_mid_run += (not done_before) and len(durable) > len(finished)
        for i, run in durable.items():
            finished.setdefault(i, run)
        if len(finished) == total:  # finished: start over to keep killing runs mid-way
            for suffix in ("", ".journal", ".progress.json"):
                Path(str(out) + suffix).unlink(missing_ok=True)
            finished = {}
    r = subprocess.run(_cmd(spec, out, inline=False), env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    durable = durable_packings(out)
    assert len(durable) == total
    for i, run in durable.items():
        assert i not in finished or run is None or finished[i] == run, "a finished task was recorded twice"
    a, a_attrs = store_data_and_attrs(ref)
    b, b_attrs = store_data_and_attrs(out)
    assert set(a) == set(b) and a_attrs.keys() == b_attrs.keys()
    for name in a:
        if name not in SKIP_DATASETS:
            x, y = a[name], b[name]
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name
    for k in a_attrs:
        assert np.array_equal(a_attrs[k], b_attrs[k]), k
    with h5py.File(out, "r") as f:
        st = f["tasks/status"][:]
        assert (st == 1).sum() == total - failing and (st == 2).sum() == failing
    return killed_mid_run


def test_sigkill_at_random_moments_then_resume(tmp_path):
    killed = _kill_rounds(tmp_path, rounds=20, seed=20261121)
    assert killed >= 2  # some kills did land in the middle of runs that were making progress


@pytest.mark.slow
def test_sigkill_many_more_times(tmp_path):
    _kill_rounds(tmp_path, rounds=100, seed=7)


@pytest.mark.slow
def test_sigkill_without_task_delays(tmp_path, monkeypatch):
    """Tasks of microseconds: the master spends its time in the journal and HDF5 writes."""
    monkeypatch.setattr(sys.modules[__name__], "DELAY", "0")
    _kill_rounds(tmp_path, rounds=60, seed=11, spec_text=SPEC.replace("seeds: 6", "seeds: 100"))
