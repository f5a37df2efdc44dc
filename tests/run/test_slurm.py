"""SLURM scripts: golden files, shell syntax, chains, option errors.

The golden scripts are the examples users read in slurm/examples/. After an intended change to
the template, regenerate them with ``UPDATE_GOLDEN=1 python -m pytest tests/run/test_slurm.py``
and review the diff.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from campaign.cli import main as cli_main
from campaign.errors import UserError
from campaign.run.slurm import SlurmOptions, chain_commands, parse_time

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "slurm" / "examples"
PAPER = REPO / "campaigns" / "paper.yaml"
GPU_LARGE = REPO / "campaigns" / "gpu-equivalence-large.yaml"  # a spec with device: gpu tasks

GOLDEN = {
    "paper-srun.sbatch": ["--nodes", "4", "--ntasks-per-node", "32", "--time", "24:00:00",
                          "--partition", "compute", "--account", "jamming"],
    "paper-mpiexec.sbatch": ["--nodes", "2", "--ntasks-per-node", "16", "--time", "2-00:00:00",
                             "--launcher", "mpiexec", "--warn", "600"],
    "paper-short.sbatch": ["--nodes", "1", "--ntasks-per-node", "8", "--time", "00:30:00"],
    "gpu-srun.sbatch": ["--nodes", "2", "--gpus-per-node", "4", "--cpus-per-task", "8", "--time", "02:00:00",
                        "--partition", "gpu", "--account", "jamming"],
}
GOLDEN_SPEC = {"gpu-srun.sbatch": GPU_LARGE}


def _render(args, tmp_path, name="x.sbatch", spec=PAPER):
    out = tmp_path / name
    rc = cli_main(["slurm", str(spec.relative_to(REPO)), *args, "--out", str(out),
                   "--results", f"results/{spec.stem}.h5"])
    assert rc == 0
    return out.read_text()


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_golden_scripts(name, tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)  # the script holds absolute paths: make them the repository's
    text = _render(GOLDEN[name], tmp_path, spec=GOLDEN_SPEC.get(name, PAPER)).replace(str(REPO), "<REPO>")
    golden = EXAMPLES / name
    if os.environ.get("UPDATE_GOLDEN"):
        golden.write_text(text)
    assert text == golden.read_text()


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_golden_scripts_are_valid_bash(name):
    subprocess.run(["bash", "-n", str(EXAMPLES / name)], check=True)


def test_script_reflects_options(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)
    text = _render(["--nodes", "3", "--ntasks-per-node", "5", "--time", "1-02:03:04", "--warn", "77"], tmp_path)
    assert "#SBATCH --nodes=3\n" in text and "#SBATCH --ntasks-per-node=5\n" in text
    assert "#SBATCH --time=1-02:03:04\n" in text and "#SBATCH --signal=USR1@77\n" in text
    assert "--partition" not in text and "--account" not in text
    assert "--time-limit 1-02:03:04 --margin 107" in text  # the warning + SLURM's 30 s check period
    assert "--time-limit 1-02:03:04 --margin 5\n" in _render(["--time", "1-02:03:04", "--margin", "5"], tmp_path)
    assert f"SPEC={PAPER}" in text and f"OUT={REPO / 'results' / 'paper.h5'}" in text


@pytest.mark.parametrize("text,seconds", [("00:00:01", 1), ("01:02:03", 3723), ("2-00:00:00", 172800),
                                          ("100:00:00", 360000)])
def test_parse_time(text, seconds):
    assert parse_time(text) == seconds


@pytest.mark.parametrize("text", ["", "1:00", "00:60:00", "00:00:00", "1h", "-1:00:00", "a-01:00:00"])
def test_parse_time_refuses(text):
    with pytest.raises(UserError):
        parse_time(text)


@pytest.mark.parametrize("kwargs", [{"nodes": 0}, {"ntasks_per_node": 0}, {"nodes": 1, "ntasks_per_node": 1},
                                    {"launcher": "aprun"}, {"partition": "a b"}, {"account": "x;rm"},
                                    {"time": "soon"}, {"time": "00:01:00", "warn_seconds": 60},
                                    {"time": "00:01:00", "margin_seconds": -1}])
def test_bad_options_refused(kwargs):
    with pytest.raises(UserError):
        SlurmOptions(**kwargs).checked()


def test_bad_option_exits_2(tmp_path, capsys):
    assert cli_main(["slurm", str(PAPER), "--time", "forever"]) == 2
    assert "HH:MM:SS" in capsys.readouterr().err
    assert cli_main(["slurm", str(PAPER), "--chain", "3"]) == 2  # a chain needs a script file


def test_chain_submits_with_afterany_dependencies(tmp_path):
    """Run the printed chain against a stand-in sbatch that records its arguments."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    log = tmp_path / "sbatch.log"
    fake = bindir / "sbatch"
    fake.write_text('#!/bin/bash\necho "$@" >> "%s"\nn=$(wc -l < "%s")\necho "$((1000 + n));cluster"\n'
                    % (log, log))
    fake.chmod(0o755)
    script = tmp_path / "job.sbatch"
    script.write_text("#!/bin/bash\n")
    env = {**os.environ, "PATH": f"{bindir}:{os.environ['PATH']}"}
    out = subprocess.run(["bash", "-c", chain_commands(script, 4)], env=env, capture_output=True,
                         text=True, check=True).stdout
    calls = log.read_text().splitlines()
    assert calls[0] == f"--parsable {script}"
    assert calls[1:] == [f"--parsable --dependency=afterany:{1000 + k} {script}" for k in (1, 2, 3)]
    assert out.split() == ["submitted", "1001;cluster", "submitted", "1002;cluster",
                           "submitted", "1003;cluster", "submitted", "1004;cluster"]


def test_submit_without_sbatch_is_a_user_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PATH", str(tmp_path))  # no sbatch here
    assert shutil.which("sbatch") is None
    rc = cli_main(["slurm", str(PAPER), "--out", str(tmp_path / "j.sbatch"), "--chain", "2", "--submit"])
    assert rc == 2
    assert "sbatch" in capsys.readouterr().err


def test_packaged_template_is_installed():
    from importlib import resources
    assert "{launch}" in resources.files("campaign").joinpath("templates/campaign.sbatch").read_text()


# ---------------------------------------------------------------------------------- split launches

SPLIT_SPEC = """\
name: split
seed: 3
grid: {N_G: [16], E_G: [1.0e-3], seeds: 3}
observables: [scalars]
"""

# What each launcher leaves in a task's environment when it started K tasks that MPI did not join.
SPLIT_ENVIRONMENTS = {
    "srun without PMI": {"SLURM_STEP_NUM_TASKS": "3", "SLURM_PROCID": "1", "SLURM_NTASKS": "3"},
    "Hydra / PMI": {"PMI_SIZE": "4", "PMI_RANK": "2"},
    "Open MPI": {"OMPI_COMM_WORLD_SIZE": "2", "OMPI_COMM_WORLD_RANK": "0"},
}
LAUNCH_VARIABLES = ("SLURM_STEP_NUM_TASKS", "SLURM_PROCID", "SLURM_NTASKS", "PMI_SIZE", "PMI_RANK", "PMI_FD",
                    "PMI_PORT", "PMIX_RANK", "PMIX_SIZE", "OMPI_COMM_WORLD_SIZE", "OMPI_COMM_WORLD_RANK",
                    "HYDRA_CONTROL_FD", "MPI_LOCALNRANKS")


def _run_env(extra):
    env = {k: v for k, v in os.environ.items() if k not in LAUNCH_VARIABLES}
    env.update(CAMPAIGN_TASK_FUNCTION="synthetic", PYTHONPATH=str(REPO), **extra)
    return env


def _files(directory):
    return {p.name: p.read_bytes() for p in sorted(Path(directory).iterdir()) if p.is_file()}


@pytest.fixture(scope="module")
def partly_done_store(tmp_path_factory):
    """A real store, stopped by its wall time part-way (inline: one process, no workers): the first
    task (3 s) starts within the 2 s limit, no other fits after it."""
    directory = tmp_path_factory.mktemp("split")
    spec = directory / "split.yaml"
    spec.write_text(SPLIT_SPEC)
    out = directory / "split.h5"
    first = subprocess.run([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet",
                            "--launcher", "inline", "--time-limit", "2", "--margin", "0"],
                           env=_run_env({"CAMPAIGN_SYNTHETIC_DELAY": "3"}), capture_output=True, text=True,
                           timeout=120)
    assert first.returncode == 0, first.stderr
    return spec, out


@pytest.mark.parametrize("name,launcher", [(name, "auto") for name in sorted(SPLIT_ENVIRONMENTS)]
                         + [("srun without PMI", "mpi"), ("srun without PMI", "local")])
def test_split_launch_is_refused_before_the_store(name, launcher, partly_done_store, tmp_path):
    """K > 1 tasks said by the launcher, a world of 1 seen by MPI: exit 2, the store byte for byte as it was."""

    spec, original = partly_done_store
    store = tmp_path / "store"
    shutil.copytree(original.parent, store, ignore=shutil.ignore_patterns("*.yaml"))
    out = store / original.name
    before = _files(store)
    status = json.loads(subprocess.run([sys.executable, "-m", "campaign", "status", str(out), "--json"],
                                       env=_run_env({}), capture_output=True, text=True, check=True).stdout)
    assert (status["done"], status["remaining"]) == (1, 2)
    got = subprocess.run([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet",
                          "--workers", "1", "--launcher", launcher], env=_run_env(SPLIT_ENVIRONMENTS[name]),
                         capture_output=True, text=True, timeout=120)
    assert got.returncode == 2, got.stderr
    assert "split launch" in got.stderr and "srun --mpi=pmi2" in got.stderr and "Traceback" not in got.stderr
    assert _files(store) == before


def test_one_task_or_one_world_is_not_a_split_launch(tmp_path):
    spec = tmp_path / "split.yaml"
    spec.write_text(SPLIT_SPEC)
    out = tmp_path / "one.h5"
    got = subprocess.run([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet",
                          "--workers", "1"], env=_run_env({"SLURM_STEP_NUM_TASKS": "1", "SLURM_NTASKS": "4"}),
                         capture_output=True, text=True, timeout=120)
    assert got.returncode == 0, got.stderr
    from campaign.run.launch import launched_tasks, split_launch_error

    assert launched_tasks({}) == (1, None)
    assert launched_tasks({"SLURM_NTASKS": "8"})[0] == 1  # the allocation, not a step: one process
    assert launched_tasks({"SLURM_STEP_NUM_TASKS": "2", "PMI_SIZE": "64"})[0] == 64  # Hydra over srun proxies
    assert launched_tasks({"PMI_SIZE": "x"})[0] == 1
    assert split_launch_error(64, {"PMI_SIZE": "64"}) is None
    assert split_launch_error(1, {"PMI_SIZE": "64"}) is not None


# ---------------------------------------------------------------------------------- GPU jobs

GPU_SPEC = """\
name: gpujob
seed: 3
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 3}
protocol: {device: gpu}
observables: [scalars]
"""


def _sbatch_lines(text):
    return dict(line[len("#SBATCH --"):].split("=", 1) for line in text.splitlines() if line.startswith("#SBATCH --"))


def _launch_line(text):
    return [line for line in text.splitlines() if "python -m campaign run" in line][0]


@pytest.mark.parametrize("nodes,gpus,cpus,launcher", [(1, 4, None, "srun"), (3, 4, 8, "srun"), (2, 1, 2, "srun-pmix"),
                                                      (1, 8, 4, "mpiexec"), (3, 2, None, "mpiexec")])
def test_gpu_job_has_a_worker_per_gpu_and_the_master_beside_them(tmp_path, nodes, gpus, cpus, launcher):
    """--gpus-per-node G on N nodes: N x G GPU workers and the master, G GPUs per node, G + 1 task slots
    per node (the master's node holds G workers too), C cores per rank; srun told C again, and the
    ranks spread evenly (the per-node count unset) over several nodes; mpiexec G per node in turn."""
    spec = tmp_path / "g.yaml"
    spec.write_text(GPU_SPEC)
    script = tmp_path / "g.sbatch"
    assert cli_main(["slurm", str(spec), "--nodes", str(nodes), "--gpus-per-node", str(gpus), "--launcher", launcher,
                     *(["--cpus-per-task", str(cpus)] if cpus else []), "--out", str(script), "--no-estimate"]) == 0
    text = script.read_text()
    subprocess.run(["bash", "-n", str(script)], check=True)
    opts = _sbatch_lines(text)
    c = cpus or 1
    assert int(opts["nodes"]) == nodes and int(opts["gpus-per-node"]) == gpus and int(opts["cpus-per-task"]) == c
    assert int(opts["ntasks"]) == nodes * gpus + 1 and int(opts["ntasks-per-node"]) == gpus + 1
    assert "gpus-per-task" not in opts and "gpu-bind" not in text
    launch = _launch_line(text)
    assert launch.endswith(f" --gpus {gpus}") and f"OMP_NUM_THREADS={c} " in text
    if launcher == "mpiexec":
        assert launch.startswith(f'mpiexec -n "$SLURM_NTASKS" -ppn {gpus} ') and "unset SLURM_NTASKS_PER_NODE" not in text
    else:
        assert launch.startswith("srun ") and f" --cpus-per-task={c} " in launch
        assert ("unset SLURM_NTASKS_PER_NODE\n" + launch in text) == (nodes > 1)


def test_cpu_job_is_unchanged_by_the_gpu_options(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)
    text = _render(["--nodes", "2", "--ntasks-per-node", "16"], tmp_path)
    opts = _sbatch_lines(text)
    assert (opts["nodes"], opts["ntasks-per-node"], opts["cpus-per-task"]) == ("2", "16", "1")
    assert "ntasks" not in opts and "gpus-per-node" not in opts and "--gpus" not in _launch_line(text)


@pytest.mark.parametrize("kwargs", [{"gpus_per_node": -1}, {"gpus_per_node": 4, "ntasks_per_node": 5},
                                    {"cpus_per_task": 4}, {"gpus_per_node": 1, "cpus_per_task": 0}])
def test_bad_gpu_options_refused(kwargs):
    with pytest.raises(UserError):
        SlurmOptions(**kwargs).checked()


def _campaign(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "campaign", *args], env=_run_env({}),
                          capture_output=True, text=True, timeout=120, cwd=cwd)


def _one_paragraph(stderr, command):
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert "Traceback" not in stderr and len(lines) == 1 and lines[0].startswith(f"campaign {command}: "), stderr
    return lines[0]


def test_gpu_job_of_a_spec_without_gpu_tasks_is_refused(tmp_path):
    """campaigns/paper-8192.yaml has no device: gpu task: a GPU job of it (its GPU workers would run
    CPU tasks) is refused with one paragraph, exit 2, no script written; `--ntasks-per-node` beside
    --gpus-per-node too."""
    got = _campaign("slurm", str(REPO / "campaigns" / "paper-8192.yaml"), "--gpus-per-node", "1", "--partition",
                    "gpu", "--nodes", "1", "--out", str(tmp_path / "x.sbatch"))
    assert got.returncode == 2 and not (tmp_path / "x.sbatch").exists()
    assert "no `device: gpu` task" in _one_paragraph(got.stderr, "slurm")
    got = _campaign("slurm", str(GPU_LARGE), "--gpus-per-node", "4", "--ntasks-per-node", "32", "--no-estimate")
    assert got.returncode == 2 and "--ntasks-per-node" in _one_paragraph(got.stderr, "slurm")


@pytest.mark.parametrize("launch", ["local", "mpi"])
def test_gpu_run_of_a_spec_without_gpu_tasks_is_refused(tmp_path, launch):
    """campaign run --gpus on a spec without device: gpu tasks: exit 2, one paragraph (the master's
    alone under MPI), before any file is written."""
    spec = tmp_path / "cpu.yaml"
    spec.write_text(GPU_SPEC.replace("protocol: {device: gpu}\n", ""))
    out = tmp_path / "cpu.h5"
    cmd = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(out), "--quiet", "--gpus", "1"]
    if launch == "mpi":
        cmd = [str(Path(sys.executable).parent / "mpiexec"), "-n", "3"] + cmd
    got = subprocess.run(cmd, env=_run_env({}), capture_output=True, text=True,
                         timeout=120)
    assert got.returncode == 2, got.stderr
    assert "no `device: gpu` task" in _one_paragraph(got.stderr, "run") and "--gpus 1" in got.stderr
    assert list(tmp_path.iterdir()) == [spec]
    ok = _campaign("run", str(spec), "--out", str(out), "--quiet", "--workers", "1")
    assert ok.returncode == 0, ok.stderr  # the same spec without --gpus runs


def _gpu_calibration(tmp_path):
    """The packaged calibration with GPU ratios, as `campaign calibrate --gpu` adds them."""
    from campaign.plan import calibration

    cal = calibration.packaged().with_gpu({"device": "cuda:Test GPU", "threads": 256, "batch": 132,
                                           "N": [16, 1024], "ratio": [0.5, 0.01]})
    path = tmp_path / "gpu-calibration.json"
    cal.save(path)
    return calibration.load(path), path


def _hours_and_wall(stderr):
    m = re.search(r"estimated ([0-9.,e+-]+) GPU-hours .* for (\d+) GPU worker\(s\).* about (\d+):(\d\d):(\d\d) of "
                  r"wall time.* longest task up to", stderr)
    assert m, stderr
    h, mi, se = (int(x) for x in m.group(3, 4, 5))
    return float(m.group(1).replace(",", "")), int(m.group(2)), 3600 * h + 60 * mi + se


@pytest.mark.parametrize("mixed", [False, True])
def test_gpu_job_is_priced_in_gpu_hours(tmp_path, capsys, mixed):
    """With a GPU calibration a GPU job's device: gpu tasks cost their GPU-seconds (CPU seconds times the
    measured ratio), its CPU tasks their core-seconds, shared by N x G GPU workers; the wall is at
    least a launch of the calibration's batch of the longest task."""
    from campaign.plan.parse import parse_spec
    from campaign.plan.tasks import expand

    text = GPU_SPEC.replace("N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 3", "N_G: [1024, 4096], E_G: [1.0e-3, "
                            "1.0e-12], seeds: 24")  # priced, never run: packings of minutes
    if mixed:
        text = text.replace("protocol: {device: gpu}\n", "variants: [{name: gpu, device: gpu}]\n")
    spec = tmp_path / "g.yaml"
    spec.write_text(text)
    cal, path = _gpu_calibration(tmp_path)
    tasks = expand(parse_spec(text))
    on_gpu = [t for t in tasks if dict(t.protocol).get("device") == "gpu"]
    shares = [cal.seconds(t.N, t.E, {}, t.exponent) * float(np.interp(np.log(t.N), np.log([16, 1024]), [0.5, 0.01]))
              for t in on_gpu]
    cpu = [cal.seconds(t.N, t.E, t.protocol, t.exponent) for t in tasks if t not in on_gpu]
    assert len(cpu) == (len(on_gpu) if mixed else 0)
    total = sum(shares) + sum(cpu)
    assert cli_main(["slurm", str(spec), "--nodes", "2", "--gpus-per-node", "3", "--time", "01:00:00",
                     "--calibration", str(path), "--out", str(tmp_path / "g.sbatch")]) == 0
    err = capsys.readouterr().err
    hours, workers, wall = _hours_and_wall(err)
    assert workers == 6 and "cuda:Test GPU" in err
    assert hours == pytest.approx(total / 3600, rel=0.05)
    longest = max([132 * x for x in shares] + cpu)  # a launch of 132 lasts 132 shares; a CPU task its own
    assert wall == pytest.approx(max(total / 6, longest), abs=1.5) and wall > 30
    assert ("CPU task(s)" in err) == mixed


def test_gpu_job_without_a_gpu_calibration_says_so(tmp_path, capsys):
    spec = tmp_path / "g.yaml"
    spec.write_text(GPU_SPEC)
    assert cli_main(["slurm", str(spec), "--gpus-per-node", "2", "--out", str(tmp_path / "g.sbatch")]) == 0
    err = capsys.readouterr().err
    assert "no GPU calibration" in err and "12 `device: gpu` task(s)" in err
    assert "advice" not in err.replace("no advice", "") and "job(s)" not in err
    assert cli_main(["slurm", str(spec), "--ntasks-per-node", "4", "--out", str(tmp_path / "c.sbatch")]) == 0
    assert "CPU emulation in a CPU job" in capsys.readouterr().err  # a CPU job of GPU tasks says what it does


def test_a_worker_rank_takes_a_gpu_of_its_own(monkeypatch):
    """Under MPI with --gpus G the master is its node's rank 0 and the G workers beside it ranks 1..G:
    each worker takes a different one of the GPUs SLURM listed for the node, and sets
    CUDA_VISIBLE_DEVICES to it at once; a rank SLURM bound to one GPU keeps it."""
    from campaign.run.comm import rank_gpu

    for name in ("MPI_LOCALRANKID", "OMPI_COMM_WORLD_LOCAL_RANK", "PMI_LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)

    def device(local, visible, gpus):
        monkeypatch.setenv("SLURM_LOCALID", str(local))
        monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)
        context = rank_gpu({"gpus": gpus}, 100 + local)
        assert os.environ["CUDA_VISIBLE_DEVICES"] == _worker_visible(context)
        return os.environ["CUDA_VISIBLE_DEVICES"]

    for visible in ("0,1,2,3", "4,5,6,7"):  # the job's GPUs on the node, as SLURM numbers them
        first = [device(k, visible, 4) for k in range(1, 5)]  # the master's node: local rank 0 is the master
        other = [device(k, visible, 4) for k in range(4)]
        assert sorted(first) == sorted(other) == visible.split(",")
    assert device(2, "3", 4) == "3"  # SLURM bound this rank to GPU 3
    assert rank_gpu({"gpus": 0}, 1) == {"gpus": 0}


def _worker_visible(context):
    from campaign.run.worker import visible_device

    return visible_device(context["gpu_device"])


def test_master_warms_no_gpu_kernel_beside_gpu_workers(tmp_path):
    """The master compiles no GPU kernel when GPU workers run them (it would hold a GPU beside them);
    the GPU worker warms its own (a local run; tests/run/test_slurm_cluster.py checks it under SLURM)."""
    spec = tmp_path / "g.yaml"
    spec.write_text(GPU_SPEC)
    probe = tmp_path / "probe"
    probe.mkdir()
    env = dict(_run_env({"CAMPAIGN_TEST_GPU_PROBE": str(probe)}), CAMPAIGN_TASK_FUNCTION="slurm_gpu_probe:ProbeTask",
               PYTHONPATH=f"{REPO}{os.pathsep}{REPO / 'tests'}")
    got = subprocess.run([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(tmp_path / "g.h5"), "--quiet",
                          "--workers", "1", "--gpus", "1"], env=env, capture_output=True, text=True, timeout=120)
    assert got.returncode == 0, got.stderr
    records = [json.loads(line) for path in probe.iterdir() for line in path.read_text().splitlines()]
    master = [r for r in records if r["gpu_device"] == "none"]
    worker = [r for r in records if r["gpu_device"] == 0]
    assert len(master) == 1 and master[0]["gpu_warm_ups"] == [], records
    assert worker and all(r["gpu_warm_ups"] for r in worker), records
