"""benchmarks/gpu_session.sh, the prepared GPU session (docs/GPU.md), run dry on the CPU: every mode
at tiny sizes (``GPU_SESSION_DRY=1``), the block under numba's CUDA simulator (bench, ncu) or its
emulation (campaign), so that a typo in the script or in ``benchmarks/bench_gpu.py`` fails here and
not in a rare GPU session. What each mode writes is read back: one JSON object a line in
``OUT/MODE.jsonl`` as it is measured, the record ``docs/GPU.md`` describes.

The campaign mode runs three times on one store (the synthetic stand-in's stop and go, its steps
slept, so that where each run stops does not depend on the machine's speed): ended by a SIGTERM
(the running packings abandoned, the store kept), stopped by ``campaign run
--time-limit`` (the packings kept suspended in the store), then to the end; and once with the
block's emulation, whose packings give the device time and its lower bound.

All slow (about three minutes on two cores): ``pytest --full`` (CI)."""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import pytest

from helpers import cuda_missing, require_cuda

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "gpu_session.sh"

pytestmark = pytest.mark.slow

#: what a stand-in for the lean FIRE kernel (the yardstick, lean_fire.py) prints per batch: the
#: line bench_gpu.py reads; it records how it was called beside itself
STANDIN = textwrap.dedent("""\
    import sys
    from pathlib import Path
    argv = sys.argv[1:]
    (Path(__file__).parent / "calls.txt").open("a").write(" ".join(argv) + "\\n")
    tpb = int(argv[argv.index("--tpb") + 1])
    steps = int(argv[argv.index("--steps") + 1])
    size, *batches = [a for k, a in enumerate(argv) if not a.startswith("--") and argv[k - 1] not in ("--tpb", "--steps")]
    for b in map(int, batches):
        print(f"N={size} B={b} TPB={tpb} steps={steps}: {40.0 + b:.1f} us per batch step, {(40.0 + b) / b:.3f} us per "
              "packing-step; E start->end copy0 1.0e-05")
    """)


def _env(**extra):
    """The session's environment: this interpreter, dry sizes, no package index, no ``ncu`` on the
    PATH (the ncu mode's skip is what is tested), the tests' numba cache (conftest)."""
    path = [d for d in os.environ.get("PATH", "").split(os.pathsep) if d and not (Path(d) / "ncu").exists()]
    env = dict(os.environ, PYTHON=sys.executable, GPU_SESSION_DRY="1", GPU_SESSION_INSTALL="0",
               PIP_NO_INDEX="1", PATH=os.pathsep.join(path))
    for k in ("NUMBA_ENABLE_CUDASIM", "CAMPAIGN_GPU_BACKEND", "CAMPAIGN_TASK_FUNCTION", "CAMPAIGN_SYNTHETIC_STEPS",
              "GPU_SESSION_STORE", "GPU_SESSION_SPEC", "GPU_SESSION_LIMIT", "GPU_SESSION_TIME_LIMIT"):
        env.pop(k, None)
    env.update(extra)
    return env


def _session(mode, out, env, *args, timeout=400):
    r = subprocess.run(["bash", str(SCRIPT), mode, str(out), *args], env=env, capture_output=True, text=True,
                       timeout=timeout)
    return r, r.stdout + r.stderr


def _lines(path):
    """Every line of a JSON-lines file, each one JSON object."""
    return [json.loads(line) for line in Path(path).read_text().splitlines()]


def _lines_so_far(path):
    """The complete lines of a JSON-lines file another process is writing (none before it exists)."""
    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        return []
    return [json.loads(line) for line in text.split("\n")[:-1]]


def _kinds(rows, kind):
    return [r for r in rows if r["kind"] == kind]


def _throwaway_python(tmp_path):
    """A virtual environment that sees this one's packages (a .pth) but installs into its own
    prefix: the session's ``pip install --no-deps --no-build-isolation -e .`` may run there without
    touching the environment that runs the tests."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    site = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    outer = [p for p in sys.path if p and Path(p).is_dir() and Path(p).resolve() != ROOT]
    Path(site, "outer.pth").write_text("\n".join(outer) + "\n")
    return python


def test_bench_mode_runs_dry_under_the_cuda_simulator(tmp_path, request):
    """bench: the kernel against its emulation (the same bits, also stopped and resumed), the lean
    kernel at 512 threads, the FIRE-step table (each threads x registers kernel at every batch), a
    whole cell; every line written as it was measured; the project installed in a throwaway
    environment with no package index, or run from the checkout where that install fails."""
    require_cuda(request.config, cuda_missing())
    yard = tmp_path / "yard"
    yard.mkdir()
    (yard / "lean_fire.py").write_text(STANDIN)
    out = tmp_path / "out"
    env = _env(NUMBA_ENABLE_CUDASIM="1", PYTHON=str(_throwaway_python(tmp_path)))
    env.pop("GPU_SESSION_INSTALL")
    r, text = _session("bench", out, env, str(yard))
    assert r.returncode == 0, text[-4000:]
    rows = _lines(out / "bench.jsonl")
    (session,) = _kinds(rows, "session")
    assert session["dry"] == 1 and "gpu" in session
    installed = session["install"] == "editable"
    assert installed or session["install"].startswith(("the editable install failed", "installed, but another")), session
    assert ("the project is installed in place" if installed else f"with PYTHONPATH={ROOT}") in text
    assert (out / "pip.log").exists()
    (start,) = _kinds(rows, "start")
    assert start["device"] == "cuda-simulator" and start["backend"] == "cuda"

    (check,) = _kinds(rows, "check_packing")
    assert check["bitwise_equal"] and check["gpu_status"] == check["emulation_status"] == "converged"
    (resumed,) = _kinds(rows, "check_resumed")
    assert resumed["bitwise_equal"] and resumed["launches"] >= 2 and resumed["device_clock_in_host_window"]

    base = _kinds(rows, "baseline")
    assert [(b["N"], b["batch"], b["threads"]) for b in base] == [(16, 1, 512), (16, 2, 512)]
    assert [b["us_per_block_step"] for b in base] == [41.0, 42.0] and base[1]["us_per_step_per_packing"] == 21.0
    assert (yard / "calls.txt").read_text().split() == ["16", "1", "2", "--steps", "3", "--tpb", "512"]

    steps = _kinds(rows, "step")
    assert [(s["threads"], s["max_registers"], s["batch"]) for s in steps] == [
        (2, 64, 1), (2, 64, 2), (2, 128, 1), (2, 128, 2)]
    for s in steps:
        assert s["N"] == 16 and s["start"] == "random" and s["registers"] == 0 and s["slots"] == 1
        assert s["us_per_step_per_packing"] > 0 and s["us_per_block_step"] == pytest.approx(s["us_per_step_per_packing"])
    (cell,) = _kinds(rows, "cell")
    assert cell["converged"] == 1 and 0.0 < cell["busy_fraction"] <= 1.0 + 1e-6 and cell["slots"] == 1
    assert rows.index(check) < rows.index(base[0]) < rows.index(steps[0]) < rows.index(cell)
    assert _kinds(rows, "end")[0]["exit"] == 0 and _kinds(rows, "ended")[0]["exit"] == 0

    record = json.loads((out / "bench.json").read_text())
    assert record["device"] == "cuda-simulator"
    assert [{k: s[k] for k in ("N", "batch", "threads", "registers", "us_per_step_per_packing", "us_per_block_step")}
            for s in record["steps"]] == [{k: s[k] for k in ("N", "batch", "threads", "registers",
                                                            "us_per_step_per_packing", "us_per_block_step")}
                                          for s in steps]
    assert record["baseline"][0]["threads"] == 512 and record["cells"][0]["converged"] == 1
    assert record["check"]["resumed"]["bitwise_equal"]


def test_campaign_mode_ends_killed_stopped_or_done_and_resumes_its_store(tmp_path):
    """campaign, three commands on one store (GPU_SESSION_STORE): the first ended by a SIGTERM while
    it runs packings (its record written, the running packings abandoned, nothing done), the second stopped
    by campaign run --time-limit (exit 0, its packings kept suspended in the store), the third
    going on from them to the end."""
    spec = tmp_path / "spec.yaml"
    spec.write_text("name: gpu-session-stop\nseed: 5\ngrid: {N_G: [64], E_G: [1.0e-3], seeds: 2}\n"
                    "protocol: {device: gpu}\nobservables: [scalars]\n")
    store = tmp_path / "keep" / "s.h5"
    # seed 0: 2000 steps, seed 1: 4000, of 2 ms each (12 s in all, one packing after the other)
    env = _env(GPU_SESSION_SPEC=str(spec), GPU_SESSION_STORE=str(store), CAMPAIGN_TASK_FUNCTION="synthetic",
               CAMPAIGN_SYNTHETIC_STEPS="0.002:2000")

    # the first: a SIGTERM to the script once the campaign runs packings (as a job's end sends it)
    a = tmp_path / "a"
    proc = subprocess.Popen(["bash", str(SCRIPT), "campaign", str(a)], env=dict(env, GPU_SESSION_GRACE="1"),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 120
    while not any(x["kind"] == "campaign_progress" and x["running"] for x in _lines_so_far(a / "campaign.jsonl")):
        assert proc.poll() is None and time.monotonic() < deadline, "the campaign never ran a packing"
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    text = proc.communicate(timeout=120)[0]
    assert proc.returncode == 143, text[-4000:]
    assert "signal: stopping the campaign mode" in text
    rows = _lines(a / "campaign.jsonl")
    (rec,) = _kinds(rows, "campaign")
    assert rec["interrupted"] == "SIGTERM" and rec["returncode"] == 143 and not rec["resumed"]
    assert rec["tasks"] == 2 and rec["packings"] == 0 and rec["pending"] == 2 and rec["store"] == str(store)
    assert _kinds(rows, "stopped")[0]["signal"] == "SIGTERM" and _kinds(rows, "ended")[0]["exit"] == 143

    r, text = _session("campaign", tmp_path / "b", dict(env, GPU_SESSION_TIME_LIMIT="8", GPU_SESSION_MARGIN="1"))
    assert r.returncode == 0, text[-4000:]
    assert "this run goes on from it" in text
    (rec,) = _kinds(_lines(tmp_path / "b" / "campaign.jsonl"), "campaign")
    assert rec["resumed"] and rec["interrupted"] is None and rec["returncode"] == 0 and rec["time_limit_s"] == 8.0
    assert rec["packings"] < 2 and rec["suspended"] >= 1 and rec["packings"] + rec["pending"] == 2
    with h5py.File(store, "r") as f:
        assert len(f["checkpoints"]) == rec["suspended"]

    r, text = _session("campaign", tmp_path / "c", env)
    assert r.returncode == 0, text[-4000:]
    (rec,) = _kinds(_lines(tmp_path / "c" / "campaign.jsonl"), "campaign")
    assert rec["resumed"] and rec["packings"] == rec["tasks"] == 2 and rec["pending"] == rec["suspended"] == 0
    assert json.loads((tmp_path / "c" / "campaign.json").read_text())["campaign"]["packings"] == 2
    with h5py.File(store, "r") as f:
        assert list(f["tasks/status"][:]) == [1, 1] and len(f.get("checkpoints", {})) == 0


def test_campaign_mode_with_the_blocks_emulation_records_the_device_time(tmp_path):
    """campaign with the block itself (its emulation; the dry spec: two packings of 16 disks): the
    record docs/GPU.md describes, with the busy fraction and the lower bound on the device's time,
    max(longest packing, block-seconds / slots), from the store's device clocks."""
    out = tmp_path / "out"
    r, text = _session("campaign", out, _env(GPU_SESSION_BACKEND="emulate"))
    assert r.returncode == 0, text[-4000:]
    rows = _lines(out / "campaign.jsonl")
    (rec,) = _kinds(rows, "campaign")
    assert _kinds(rows, "start")[0]["device"] == "emulation"
    assert rec["spec"] == str(out / "dry-campaign.yaml") and rec["store"] == str(out / "campaign.h5")
    assert rec["packings"] == rec["tasks"] == rec["finished_gpu_packings"] == 2 and rec["returncode"] == 0
    assert rec["wall_s"] > 0 and 0.0 < rec["busy_fraction"] <= 1.0 + 1e-6 and rec["slots"] == 1
    with h5py.File(out / "campaign.h5", "r") as f:
        seconds = f["scalars/device_seconds"][:]
        assert f["tasks/host"][0].decode().endswith(" emulation")
    assert rec["longest_packing_s"] == max(seconds) and rec["block_seconds"] == pytest.approx(sum(seconds))
    assert rec["lower_bound_s"] == max(max(seconds), rec["block_seconds"] / rec["slots"]) > 0
    assert json.loads((out / "campaign.json").read_text())["campaign"]["lower_bound_s"] == rec["lower_bound_s"]


def test_ncu_mode_without_ncu_says_so_and_runs_the_command_it_would_profile(tmp_path, request):
    """ncu: without Nsight Compute on the PATH the mode is skipped with a line that says so (exit 0),
    and the dry run runs the launch it would have profiled, bare; an unknown mode is refused."""
    require_cuda(request.config, cuda_missing())
    out = tmp_path / "out"
    r, text = _session("ncu", out, _env(NUMBA_ENABLE_CUDASIM="1"))
    assert r.returncode == 0, text[-4000:]
    assert "ncu (Nsight Compute) is not on the PATH: the ncu mode is skipped" in text
    rows = _lines(out / "ncu.jsonl")
    assert [x["kind"] for x in rows] == ["session", "skipped", "ended"] and rows[-1]["exit"] == 0
    (step,) = _kinds(_lines(out / "ncu-app.jsonl"), "step")
    assert (step["N"], step["threads"], step["batch"]) == (16, 2, 2) and step["us_per_step_per_packing"] > 0
    r, text = _session("profile", tmp_path / "x", _env())
    assert r.returncode == 2 and "unknown mode profile" in text


def test_one_kernel_per_register_bound(request):
    """65536 registers an SM: 64 a thread let 1024 threads share it; a bound above what one block
    of nt threads may take comes to that (128 at 1024 threads is 64), and two bounds that come to
    the same are one kernel, compiled once (bench_gpu.py times it once)."""
    require_cuda(request.config, cuda_missing())
    code = textwrap.dedent("""\
        import sys
        sys.path.insert(0, "benchmarks")
        from kernels.gpu import device
        import bench_gpu
        b = device.register_bound
        assert device.REGISTER_FILE // device.DEFAULT_REGISTERS == 1024
        assert (b(512), b(512, 128), b(1024), b(1024, 128), b(256, 255), b(128, 255)) == (64, 128, 64, 64, 255, 255)
        assert device.kernel(512, 2.0) is device.kernel(512, 2.0, 64) is not device.kernel(512, 2.0, 128)
        assert device.kernel(1024, 2.0, 128) is device.kernel(1024, 2.0, 64)
        assert bench_gpu.kernels_to_time([512, 1024], [64, 128], "cuda") == [(512, 64), (512, 128), (1024, 64)]
        print("ok")
        """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT,
                       env=dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_ENABLE_CUDASIM="1"))
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-3000:]
