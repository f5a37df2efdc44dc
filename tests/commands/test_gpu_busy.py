"""The GPUs' busy fraction `campaign status` reports (campaign.commands.status.GpuBusy), on a store
whose GPU packings have device clocks and runs chosen by hand."""

import datetime
import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

from campaign.commands.status import run_spans
from campaign.run.worker import SyntheticTask, run_task
from helpers import synthetic_run

ROOT = Path(__file__).resolve().parents[2]

SPEC = """\
name: busy
seed: 2
grid: {N_G: [32], E_G: [1.0e-4, 1.0e-6], seeds: 5}
protocol: {device: gpu}
observables: [scalars]
"""

T0 = 1.9e9  # epoch seconds


def iso(t):
    return datetime.datetime.fromtimestamp(t, datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S%z")


#: (host column, rank, device start - T0, end - T0, block-seconds, resident slots)
PACKINGS = [
    # GPU 1 in run A: window 10..50 on 2 slots (80 slot-seconds), 60 block-seconds
    ("n1 cuda:X", 1, 10, 30, 20, 2), ("n1 cuda:X", 1, 10, 20, 10, 2), ("n1 cuda:X", 1, 20, 50, 30, 2),
    # GPU 1 in run B (1000..1100): one packing resumed from run A (its clock starts there and holds
    # 25 block-seconds of both runs, at most 30 of them in this window) and one of its own:
    # window 1000..1040 on 2 slots (80), 25 + 30 block-seconds
    ("n1 cuda:X", 1, 40, 1030, 25, 2), ("n1 cuda:X", 1, 1010, 1040, 30, 2),
    # GPU 2 (another worker) in run A: 5 of 10 seconds on 1 slot
    ("n1 cuda:X", 2, 0, 10, 5, 1),
    # an emulated GPU: always busy
    ("n2 emulation", 3, 60, 70, 10, 1),
]


def _store(tmp_path):
    spec, tasks, ctx, store = synthetic_run(tmp_path, SPEC)
    for i, (host, rank, s, e, b, slots) in enumerate(PACKINGS):
        summary = run_task(SyntheticTask(), dict(tasks[i].payload(), attempt=1), ctx, rank)
        summary["scalars"].update(device_start=T0 + s, device_end=T0 + e, device_seconds=b, device_slots=slots,
                                  device_launches=1)
        summary["host"] = host
        store.record(i, summary, 1)
    cpu = run_task(SyntheticTask(), dict(tasks[9].payload(), attempt=1), ctx, 4)  # a CPU packing: no clock
    store.record(9, dict(cpu, host="n3"), 1)
    store.close()
    runs = [{"start": iso(T0), "end": iso(T0 + 100)}, {"start": iso(T0 + 1000), "end": iso(T0 + 1100)}]
    with h5py.File(tmp_path / "s.h5", "r+") as f:
        f.attrs["runs"] = json.dumps(runs)
    return tmp_path / "s.h5"


def test_status_reports_each_devices_busy_fraction(tmp_path):
    path = _store(tmp_path)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "campaign", "status", str(path), "--json"], env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    busy = json.loads(r.stdout)["gpu_busy"]
    assert set(busy) == {"cuda:X", "emulation"}
    x = busy["cuda:X"]
    assert x["block_seconds"] == pytest.approx(60 + 55 + 5)
    assert x["slot_seconds"] == pytest.approx(80 + 80 + 10)
    assert x["busy_fraction"] == pytest.approx(120 / 170)
    assert (x["gpus"], x["runs"], x["packings"]) == (2, 2, 6)
    assert busy["emulation"]["busy_fraction"] == pytest.approx(1.0)
    text = subprocess.run([sys.executable, "-m", "campaign", "status", str(path)], env=env, capture_output=True,
                          text=True, timeout=60).stdout
    assert f"GPU busy on cuda:X: {100 * 120 / 170:.1f}%" in text, text


def test_run_spans_close_a_run_without_an_end_at_the_next_start():
    runs = [{"start": iso(T0), "end": None}, {"start": iso(T0 + 500), "end": iso(T0 + 600)},
            {"start": iso(T0 + 900), "end": None}]
    spans = run_spans(json.dumps(runs))
    assert spans[0] == (T0, T0 + 500) and spans[1] == (T0 + 500, T0 + 600)
    assert spans[2][0] == T0 + 900 and spans[2][1] == float("inf")
    assert run_spans("not json") == []
