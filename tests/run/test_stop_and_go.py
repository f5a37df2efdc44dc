"""Stop and go (docs/GPU.md): GPU packings stopped at a step budget before a run's deadline, kept in
the store (``/checkpoints``), and ended by the next run with the bits of an uninterrupted run.

The store's side on its own (journal first, crash, damage, verify, repair); the master with a fake
GPU worker whose results depend on the state each task went on from; real worker processes under
``--time-limit`` with the synthetic stand-in's stop and go (``CAMPAIGN_SYNTHETIC_STEPS``: no numba,
so each run starts in seconds; its ``search_end`` depends on the state too), locally and under
``mpiexec -n 3``; the kernels' own stop and go through the block's emulation, with the master, the
store and the GPU worker's loop in this process (the emulation compiles once per process: about a
minute), the first run's deadline counted in FIRE steps, not seconds, so that where it stops does
not depend on the machine's speed; and the CUDA kernel's own under numba's CUDA simulator."""

import json
import os
import queue
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest

from campaign.run.gpuworker import StepBudget
from campaign.run.master import Master
from campaign.run.walltime import GPU_MIN_SECONDS, Deadline
from campaign.storage.checksums import CHECKPOINT_KEYS
from campaign.storage.store import Store
from helpers import SKIP_RUN_DATASETS, assert_same_contents, cuda_missing, store_contents, synthetic_run

ROOT = Path(__file__).resolve().parents[2]
MPIEXEC = Path(sys.executable).parent / "mpiexec"

GPU_SPEC = """\
name: sg
seed: 4
grid: {N_G: [64], E_G: [1.0e-3, 1.0e-6], seeds: 6}
protocol: {device: gpu}
observables: [scalars, connectivity]
"""

#: what differs between a resumed run and an uninterrupted one: the run's timing, and how the
#: packings were launched (the device's clock, the synthetic batch sizes)
DEVICE = ("scalars/device_start", "scalars/device_end", "scalars/device_seconds", "scalars/device_launches",
          "scalars/batch_size")
SKIP = SKIP_RUN_DATASETS + DEVICE + tuple("checksums/" + k.replace("/", ".") for k in DEVICE)


def _record(n, steps, seed=0):
    rng = np.random.default_rng(seed)
    arrays = {"positions": rng.random((n, 2)), "velocities": rng.random((2, n)), "reference": rng.random((2, n)),
              "state": rng.random(12)}
    return {"arrays": arrays, "steps": steps, "force_evaluations": steps + 3, "device_seconds": 0.25 * steps,
            "launches": 2}


def _same(a, b):
    assert set(a) == set(b) and all(np.array_equal(a[k], b[k]) and a[k].dtype == b[k].dtype for k in a)


def _summary(store, i):
    from campaign.run.worker import SyntheticTask, run_task

    ctx = dict(store.spec.worker_context(), task_function="synthetic")
    ctx["edges"] = {h: list(e) for h, e in store.edges.items()}
    return run_task(SyntheticTask(), dict(store.tasks[i].payload(), attempt=1), ctx)


def test_the_store_keeps_a_suspended_packing_until_its_task_finishes(tmp_path):
    spec, tasks, ctx, store = synthetic_run(tmp_path, GPU_SPEC)
    rec = _record(64, 500)
    store.suspend(3, rec)
    assert store.has_suspended(3) and not store.has_suspended(4)
    _same(store.suspended(3), rec["arrays"])  # staged, before any write
    store.close()
    with h5py.File(tmp_path / "s.h5", "r") as f:
        g = f[f"checkpoints/{tasks[3].id}"]
        assert sorted(g) == sorted(CHECKPOINT_KEYS) and int(g.attrs["steps"]) == 500
        assert f["tasks/status"][3] == 0  # still pending
    store = Store(tmp_path / "s.h5", spec, tasks, store.edges)
    _same(store.suspended(3), rec["arrays"])  # read back, checked against its checksum
    assert store.suspended_counts() == {"tasks": 1, "steps": 500}
    again = _record(64, 900, seed=1)  # a later stop of the same packing replaces it
    store.suspend(3, again)
    store.flush(force=True)
    _same(store.suspended(3), again["arrays"])
    store.record(3, _summary(store, 3), 1)  # finished: its checkpoint goes with the row's commit
    store.close()
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert f["tasks/status"][3] == 1 and len(f["checkpoints"]) == 0
    store = Store(tmp_path / "s.h5", spec, tasks, store.edges)
    assert store.suspended(3) is None and not store.has_suspended(3)
    store.suspend(3, rec)  # a done task is not suspended again
    assert not store.has_suspended(3)
    store.close()


def test_a_suspended_packing_survives_a_crash_in_the_journal(tmp_path):
    """The journal takes the suspended packing before the HDF5 file does: a run that dies before
    writing it (here: abandoned, as after a fault) leaves it to the next start, which replays it."""
    spec, tasks, ctx, store = synthetic_run(tmp_path, GPU_SPEC)
    rec = _record(64, 321, seed=5)
    store.suspend(7, rec)
    store.abandon()
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert "checkpoints" not in f or tasks[7].id not in f["checkpoints"]
    store = Store(tmp_path / "s.h5", spec, tasks, store.edges)
    _same(store.suspended(7), rec["arrays"])
    store.close()
    store = Store(tmp_path / "s.h5", spec, tasks, store.edges)  # now from the file
    _same(store.suspended(7), rec["arrays"])
    store.close()


def test_a_damaged_checkpoint_is_ignored_and_verify_and_repair_say_so(tmp_path):
    """A checkpoint whose bytes changed after they were written is not resumed (its task starts
    over, the run says so); `campaign verify` names it, and `--repair` leaves it out while it
    carries the intact ones over."""
    spec, tasks, ctx, store = synthetic_run(tmp_path, GPU_SPEC)
    good, bad = _record(64, 100, 1), _record(64, 200, 2)
    store.suspend(1, good)
    store.suspend(2, bad)
    store.record(0, _summary(store, 0), 1)
    store.close()
    path = tmp_path / "s.h5"
    with h5py.File(path, "r+") as f:
        ds = f[f"checkpoints/{tasks[2].id}/velocities"]
        v = ds[()]
        v[1, 5] = np.nextafter(v[1, 5], 2.0)  # one ulp
        ds[...] = v
    logs = []
    store = Store(path, spec, tasks, store.edges, log=logs.append)
    assert store.suspended(2) is None and any("checkpoints/" + tasks[2].id in m and "starts over" in m for m in logs)
    _same(store.suspended(1), good["arrays"])
    store.close()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "campaign", "verify", str(path), "--json"], env=env,
                       capture_output=True, text=True, timeout=120)
    report = json.loads(r.stdout)
    assert r.returncode == 1 and [d["object"] for d in report["damage"]] == [f"checkpoints/{tasks[2].id}"]
    assert report["tasks_lost"] == 0 and report["repairable"]
    r = subprocess.run([sys.executable, "-m", "campaign", "verify", str(path), "--repair"], env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    with h5py.File(path, "r") as f:
        assert sorted(f["checkpoints"]) == [tasks[1].id] and f["tasks/status"][0] == 1
    r = subprocess.run([sys.executable, "-m", "campaign", "verify", str(path)], env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    store = Store(path, spec, tasks, store.edges)
    _same(store.suspended(1), good["arrays"])
    store.close()


def test_a_gpu_task_goes_out_while_the_minimum_time_is_left(tmp_path):
    """A task that would not finish before the deadline is not dispatched, unless it is a GPU
    worker's (it stops at a step budget): that one goes while GPU_MIN_SECONDS are left."""
    spec, tasks, ctx, store = synthetic_run(tmp_path, GPU_SPEC)
    clock = {"t": 0.0}
    wall = Deadline(store, tasks, end=100.0, margin=10.0, clock=lambda: clock["t"])
    each = wall.model().task_seconds(tasks[0])
    ahead = [tasks[1]] * int(np.ceil(4 * GPU_MIN_SECONDS / each))  # queued at its worker before it
    clock["t"] = 90.0 - 2 * GPU_MIN_SECONDS  # about half of what they need is left
    assert wall(tasks[0]) and not wall(tasks[0], ahead) and wall(tasks[0], ahead, suspendable=True)
    clock["t"] = 90.0 - GPU_MIN_SECONDS / 2
    assert not wall(tasks[0], suspendable=True)
    store.close()


def _digest(arrays):
    """A number that changes with any bit of a suspended packing's arrays."""
    return float(zlib.crc32(b"".join(np.ascontiguousarray(arrays[k]).tobytes() for k in sorted(arrays))))


class GpuComm:
    """A GPU worker that stops every task of ``stop`` after ``steps`` steps the first time it gets
    it. A task's result depends on the state its search went on from (a scalar, ``went_on_from``,
    its digest): the state a resumed task brings (what the store kept), else the one its search
    passes through at ``steps`` steps (``_record``'s), so that a store comparison with an
    uninterrupted run sees a task resumed from other bits."""

    launcher = "fake"

    def __init__(self, store, stop, steps=77):
        from campaign.run.comm import gpu_capacity

        self.store, self.stop, self.steps = store, set(stop), steps
        self.n_workers = 1
        self.capacity = {1: gpu_capacity(4)}
        self.inbox = []
        self.resumed = []

    def send(self, w, payload):
        self.inbox.append(payload)

    def recv(self, timeout=None):
        if not self.inbox:
            return None
        p = self.inbox.pop(0)
        i = p["index"]
        if "resume" in p:
            state = p["resume"]
            self.resumed.append(i)
        elif i in self.stop:
            return 1, ("suspended", i, p["attempt"], _record(p["N"], self.steps, seed=i))
        else:
            state = _record(p["N"], self.steps, seed=i)["arrays"]
        summary = _summary(self.store, i)
        summary["scalars"]["went_on_from"] = _digest(state)
        return 1, ("result", i, p["attempt"], summary)

    def close(self, abandon=False):
        pass


def test_the_master_keeps_suspended_packings_and_the_next_run_resumes_them(tmp_path):
    stop = {0, 5, 11}
    spec, tasks, ctx, store = synthetic_run(tmp_path, GPU_SPEC)
    out = Master(GpuComm(store, stop), store, tasks).run()
    assert out["stopped"] == "wall time" and out["suspended"] == 3 and out["done"] == len(tasks) - 3
    assert {i for i in range(len(tasks)) if store.has_suspended(i)} == stop
    assert np.all((store.status == 0) == np.isin(np.arange(len(tasks)), sorted(stop)))
    assert int(store.attempts[0]) == 0
    store.close()
    store = Store(tmp_path / "s.h5", spec, tasks, store.edges)
    comm = GpuComm(store, stop)
    out = Master(comm, store, tasks).run()
    assert out["done"] == 3 and out["stopped"] is None and sorted(comm.resumed) == sorted(stop)
    store.close()
    _, _, _, ref = synthetic_run(tmp_path, GPU_SPEC, "ref.h5")
    Master(GpuComm(ref, ()), ref, tasks).run()
    ref.close()
    assert_same_contents(store_contents(tmp_path / "s.h5"), store_contents(tmp_path / "ref.h5"))


# --------------------------------------------------------------------------- real processes

SYNTH = """\
name: sg
seed: 4
grid: {N_G: [4096], E_G: [1.0e-3, 1.0e-6], seeds: 6}
protocol: {device: gpu}
observables: [scalars]
"""


def _run(cmd, env, timeout=240):
    t0 = time.monotonic()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    return r, time.monotonic() - t0


@pytest.mark.slow  # campaigns of the emulated block under a time limit; the deadline test below is quick
@pytest.mark.parametrize("launch", ["local", "mpi"])
def test_gpu_packings_stop_at_the_time_limit_and_the_next_run_ends_them(tmp_path, launch):
    """`campaign run --time-limit` with a GPU worker whose searches (the synthetic stand-in's:
    4000 x (1 + seed % 3) steps of 0.2 ms for each GPU worker, slept) cannot all finish: the run stops before its
    limit, exits 0 and keeps the suspended searches in the store (their state as large as a
    packing's at N_G 4096, 196 kB); `campaign status` shows them; the next run resumes them
    and the store ends equal to an uninterrupted run's (each search's ``search_end`` depends on
    every bit of the state it went on from)."""
    spec = tmp_path / "g.yaml"
    spec.write_text(SYNTH)
    gpus = 2 if launch == "mpi" else 1  # under mpiexec every worker rank is a GPU worker
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", CAMPAIGN_SYNTHETIC_STEPS=f"2e-4:{4000 * gpus}",
               PYTHONPATH=str(ROOT))
    base = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(tmp_path / "g.h5"), "--gpus", "1",
            "--gpu-batch", "4"]
    pre = [str(MPIEXEC), "-n", "3"] if launch == "mpi" else []
    workers = [] if launch == "mpi" else ["--workers", "2"]
    limit, margin = 12.0, 1.0
    r, took = _run(pre + base + workers + ["--time-limit", str(limit), "--margin", str(margin)], env)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "stopped at their step budget" in r.stderr and "Resume with" in r.stderr, r.stderr[-2000:]
    with h5py.File(tmp_path / "g.h5", "r") as f:
        status = f["tasks/status"][:]
        kept = {k: int(f["checkpoints"][k].attrs["steps"]) for k in f.get("checkpoints", {})}
        kept_launches = {k: int(f["checkpoints"][k].attrs["launches"]) for k in f.get("checkpoints", {})}
        ids = f["tasks/id"][:].astype(str)
    assert kept and all(s > 0 for s in kept.values())
    assert all(status[list(ids).index(k)] == 0 for k in kept)
    st = subprocess.run([sys.executable, "-m", "campaign", "status", str(tmp_path / "g.h5"), "--json"], env=env,
                        capture_output=True, text=True, timeout=60)
    got = json.loads(st.stdout)["suspended"]
    assert got == {"tasks": len(kept), "steps": sum(kept.values())}
    text = subprocess.run([sys.executable, "-m", "campaign", "status", str(tmp_path / "g.h5")], env=env,
                          capture_output=True, text=True, timeout=60).stdout
    assert f"suspended GPU packings: {len(kept)}" in text, text
    r, _ = _run(pre + base + workers, env)
    assert r.returncode == 0, r.stderr[-3000:]
    ref = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(tmp_path / "ref.h5"), "--workers", "1",
           "--launcher", "inline"]
    r, _ = _run(ref, env)
    assert r.returncode == 0, r.stderr[-3000:]
    with h5py.File(tmp_path / "g.h5", "r") as f:
        assert np.all(f["tasks/status"][:] == 1) and len(f["checkpoints"]) == 0
        launches = f["scalars/device_launches"][:]
    # each kept search went on from its state: more launches than it had when it was kept
    assert all(launches[list(ids).index(k)] > n for k, n in kept_launches.items())
    # the reference ran each task alone, in the master (no launches: no batch_size, no device_launches)
    a, b = store_contents(tmp_path / "g.h5"), store_contents(tmp_path / "ref.h5")
    only = {k.split("@")[0] for k in set(a) ^ set(b)}
    assert only <= set(SKIP) | {"scalars"}, only
    for k in set(a) & set(b):
        if k.split("@")[0] in SKIP or k in ("scalars@names", "scalars@crc32"):
            continue
        x, y = np.asarray(a[k]), np.asarray(b[k])
        assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), k


# --------------------------------------------------------------------------- the kernels' own

KERNEL_SPEC = """\
name: kg
seed: 7
grid: {N_G: [256], E_G: [1.0e-12, 1.0e-4], seeds: 8}
protocol: {device: gpu, gpu_threads: 16}
observables: [scalars, connectivity]
store: {configurations: true}
"""


class ThreadComm:
    """One GPU worker (``worker_loop``) in a thread of this process: the emulation compiled here
    serves every run."""

    launcher = "thread"

    def __init__(self, context):
        from campaign.run.comm import gpu_capacity, gpu_context
        from campaign.run.worker import worker_loop

        self.n_workers = 1
        self.capacity = {1: gpu_capacity(context["gpu_batch"])}
        self.down, self.up = queue.Queue(), queue.Queue()
        ctx = gpu_context(dict(context, warm_up=False), 0)
        self.thread = threading.Thread(target=worker_loop, args=(self.down.get, lambda m: self.up.put((1, m)), ctx,
                                                                 1, lambda: not self.down.empty()), daemon=True)
        self.thread.start()
        assert self.up.get(timeout=60)[1][0] == "ready"

    def send(self, w, payload):
        self.down.put(("task", payload))

    def recv(self, timeout=None):
        try:
            return self.up.get(timeout=timeout)
        except queue.Empty:
            return None

    def close(self, abandon=False):
        self.down.put(("stop",))
        self.thread.join(60)


class StepClock(StepBudget):
    """A GPU worker's deadline counted in FIRE steps instead of seconds (``campaign.run.gpuworker``
    builds its ``StepBudget`` from the run's deadline; a test puts this one in its place): its clock is
    the FIRE steps the worker's launches took (each launch's packings' steps so far: what ``learn``
    hears), one step one unit of time, and the deadline is ``LIMIT`` of them. The same budgets, the
    same stops, whatever the machine's speed."""

    LIMIT = 23000  # the probe launch's 1000 steps of 8 packings, then 0.8 x 15000 / 8 = 1500 steps more each

    def __init__(self, deadline=None, margin=0.0, now=None):
        super().__init__(self.LIMIT, 0.0, now=lambda: self.spent)
        self.spent = 0.0

    def learn(self, n, seconds, steps):
        self.spent += steps
        super().learn(n, steps, steps)


def _kernel_run(tmp_path, name, steps=False, gpu=True):
    """A run of KERNEL_SPEC into ``name`` (the same store goes on) on a GPU worker (else on a CPU
    worker, in the master: ``InlineComm``); with ``steps``, a deadline of ``StepClock.LIMIT`` FIRE
    steps. Returns the master's outcome."""
    import campaign.run.gpuworker
    from campaign.run.comm import InlineComm
    from campaign.plan.parse import load_spec
    from campaign.plan.tasks import expand, warm_ups
    from campaign.run.worker import KernelTask

    path = tmp_path / "k.yaml"
    path.write_text(KERNEL_SPEC)
    spec = load_spec(path)
    tasks = expand(spec)
    ctx = dict(spec.worker_context(), task_function="kernels", protocol_warmups=warm_ups(tasks), gpus=1,
               gpu_batch=8, deadline=None, margin=0.0)
    edges = KernelTask().histogram_edges(ctx)
    ctx["edges"] = {h: [float(x) for x in e] for h, e in edges.items()}
    store = Store(tmp_path / name, spec, tasks, edges)
    with pytest.MonkeyPatch.context() as mp:
        if steps:
            mp.setattr(campaign.run.gpuworker, "StepBudget", StepClock)
        comm = ThreadComm(ctx) if gpu else InlineComm(ctx)
        try:
            out = Master(comm, store, tasks).run()
        finally:
            comm.close()
    store.close()
    return out


@pytest.mark.parametrize("then", ["gpu worker", pytest.param("cpu worker", marks=pytest.mark.slow)])
def test_kernel_packings_stopped_at_a_step_budget_end_with_an_uninterrupted_runs_bits(tmp_path, monkeypatch, then):
    """The block's own stop and go through the GPU worker's loop, the master and the store: a run
    whose deadline is counted in FIRE steps (``StepClock``; a search at E_G 1e-12 takes 20 000 to
    30 000 of them) stops the searches that do not finish (the probe launch, a second launch from
    their state at the budget the steps left give), keeps them, and the next run ends them, on a GPU
    worker or emulated on a CPU worker; the store then holds the bits of an uninterrupted run's
    (configurations included), only the device's clock differs."""
    monkeypatch.setenv("CAMPAIGN_GPU_BACKEND", "emulate")
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")  # the worker sets it: restored after the test
    whole = _kernel_run(tmp_path, "ref.h5")
    assert whole["done"] == 16
    first = _kernel_run(tmp_path, "k.h5", steps=True)
    assert first.get("suspended", 0) >= 1 and first["stopped"] == "wall time", first
    with h5py.File(tmp_path / "k.h5", "r") as f:
        kept = {k: int(g.attrs["launches"]) for k, g in f["checkpoints"].items()}
        steps = {k: int(g.attrs["steps"]) for k, g in f["checkpoints"].items()}
        ids = list(f["tasks/id"][:].astype(str))
    # each kept search went beyond the probe launch: launched again from its state in the worker
    assert kept and all(n >= 2 for n in kept.values()) and all(s > 1000 for s in steps.values()), (kept, steps)
    second = _kernel_run(tmp_path, "k.h5", gpu=then == "gpu worker")
    assert second["done"] == 16 - first["done"]
    with h5py.File(tmp_path / "k.h5", "r") as f:
        assert np.all(f["tasks/status"][:] == 1) and len(f["checkpoints"]) == 0
        launches = f["scalars/device_launches"][:]
        slots = f["scalars/device_slots"][:]
        start, end, busy = (f[f"scalars/device_{k}"][:] for k in ("start", "end", "seconds"))
    # each kept search went on from its state (its clock counts the first run's launches too)
    assert all(launches[ids.index(k)] > n for k, n in kept.items()) and np.all(slots == 1)
    # block-seconds within the first start and last end (epoch seconds in float64: 0.2 us apart)
    assert np.all(start < end) and np.all((busy > 0) & (busy <= end - start + 1e-6))
    assert_same_contents_but(store_contents(tmp_path / "k.h5"), store_contents(tmp_path / "ref.h5"))


def assert_same_contents_but(a, b):
    assert set(a) == set(b), sorted(set(a) ^ set(b))
    for k in a:
        if k in SKIP:
            continue
        x, y = np.asarray(a[k]), np.asarray(b[k])
        assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), k


def test_a_gpu_packing_run_alone_records_its_device_clock(monkeypatch):
    """A device: gpu task run by itself (a CPU worker emulating it) stores the device clock's
    scalars too: one launch on one slot, its block-seconds inside its start and end."""
    from campaign.run.worker import KernelTask, run_task

    monkeypatch.setenv("CAMPAIGN_GPU_BACKEND", "emulate")
    context = {"system": {"box": [1.0, 1.0], "potential": {"exponent": 2.0},
                          "species": [["A", 0.5, 1.4], ["B", 0.5, 1.0]]},
               "observables": ["scalars"], "histograms": [], "edges": {}}
    payload = {"id": "t", "index": 0, "N": 32, "E": 1e-4, "seed": 0, "entropy": [1, 2],
               "protocol": {"device": "gpu", "gpu_threads": 16}}
    t0 = time.time()
    s = run_task(KernelTask(), payload, context)["scalars"]
    assert (s["device_launches"], s["device_slots"]) == (1.0, 1.0)
    assert t0 <= s["device_start"] < s["device_end"] <= time.time()
    assert 0 < s["device_seconds"] <= s["device_end"] - s["device_start"] + 1e-6


def test_the_checkpoints_write_step_reserves_what_it_adds(tmp_path):
    """Writing suspended packings is a write step like any other: the file never grows by more than
    the step reserved first (docs/STORE.md, "Out of space"), nor does the store reserve wildly more."""
    spec, tasks, ctx, store = synthetic_run(tmp_path, GPU_SPEC)
    for rounds in range(3):  # new groups, then each replaced by a later stop
        for i in range(len(tasks)):
            store.suspend(i, _record(4096, 100 * (rounds + 1), seed=i + rounds))
        store.flush(force=True)
    steps = store.space_log
    assert len(steps) >= 3 and all(grew <= need for need, grew in steps), steps
    store.close()
    arrays = 4096 * 2 * 8 * 3 + 12 * 8  # one packing's four arrays
    assert max(need for need, _ in steps) <= 2 * len(tasks) * arrays + (512 << 10)


# --------------------------------------------------------------------------- the CUDA kernel's own

SIMULATED = """
import numpy as np
from kernels.gpu import Suspended, jam_batch

whole = jam_batch(16, [1e-3], [[3]], backend="cuda", threads=2)[0]
back, launches = None, 0
while True:  # stopped every 60 FIRE steps; each state through the arrays a store keeps
    got = jam_batch(16, [1e-3], [[3]], backend="cuda", threads=2, budget=60, resume=[back])[0]
    launches += 1
    assert launches <= 30, "no end in sight: the search ends in about 11 launches"
    if not isinstance(got, Suspended):
        break
    back = Suspended.from_arrays({k: np.array(a) for k, a in got.arrays().items()}, 1e-3)
assert whole.settings["device"] == got.settings["device"] == "cuda-simulator", got.settings["device"]
assert whole.status == got.status == "converged" and launches >= 5, (whole.status, got.status, launches)
assert got.settings["device_clock"]["launches"] == launches
assert whole.positions.tobytes() == got.positions.tobytes() and whole.radii.tobytes() == got.radii.tobytes()
assert (whole.energy, whole.pressure, whole.force_residual, whole.force_evaluations, whole.iterations) == (
    got.energy, got.pressure, got.force_residual, got.force_evaluations, got.iterations)
print("ok", launches, whole.force_evaluations)
"""


@pytest.mark.slow  # about a minute of numba's CUDA simulator (one Python thread per GPU thread)
@pytest.mark.skipif(cuda_missing() is not None, reason=str(cuda_missing()))
def test_the_cuda_kernel_stopped_and_resumed_ends_with_the_bits_of_an_uninterrupted_run():
    """The CUDA kernel itself (numba's CUDA simulator; 16 disks, 2 threads): a search stopped every 60 FIRE
    steps, its state kept as the store keeps it and launched again, ends with the bits of the same search
    run in one launch (positions, radii, energy, pressure, residual, steps); its clock counts the launches."""
    r = subprocess.run([sys.executable, "-c", SIMULATED], capture_output=True, text=True, timeout=600,
                       env=dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_ENABLE_CUDASIM="1"))
    assert r.returncode == 0 and r.stdout.startswith("ok"), r.stdout + r.stderr[-3000:]
