"""SLURM scripts: golden files, shell syntax, chains, option errors.

The golden scripts are the examples users read in slurm/examples/. After an intended change to
the template, regenerate them with ``UPDATE_GOLDEN=1 python -m pytest tests/test_slurm.py``
and review the diff.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from campaign.cli import main as cli_main
from campaign.errors import UserError
from campaign.run.slurm import SlurmOptions, chain_commands, parse_time

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "slurm" / "examples"
PAPER = REPO / "campaigns" / "paper.yaml"

GOLDEN = {
    "paper-srun.sbatch": ["--nodes", "4", "--ntasks-per-node", "32", "--time", "24:00:00",
                          "--partition", "compute", "--account", "jamming"],
    "paper-mpiexec.sbatch": ["--nodes", "2", "--ntasks-per-node", "16", "--time", "2-00:00:00",
                             "--launcher", "mpiexec", "--warn", "600"],
    "paper-short.sbatch": ["--nodes", "1", "--ntasks-per-node", "8", "--time", "00:30:00"],
}


def _render(args, tmp_path, name="x.sbatch"):
    out = tmp_path / name
    rc = cli_main(["slurm", str(PAPER.relative_to(REPO)), *args, "--out", str(out),
                   "--results", "results/paper.h5"])
    assert rc == 0
    return out.read_text()


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_golden_scripts(name, tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)  # the script holds absolute paths: make them the repository's
    text = _render(GOLDEN[name], tmp_path).replace(str(REPO), "<REPO>")
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
