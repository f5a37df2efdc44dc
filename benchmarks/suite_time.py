"""The README's two commands, timed as a new user meets them: a fresh clone, a fresh HOME (no
pip cache, no numba cache), a fresh virtual environment.

    python benchmarks/suite_time.py                    # both commands, each in its own fresh clone
    python benchmarks/suite_time.py --only quickstart  # the first (install, quickstart, reduce)
    python benchmarks/suite_time.py --only tests --durations 20   # the second, with pytest's slowest
    python benchmarks/suite_time.py --ci --json suite.json        # and bash .ci/run (the full suite;
                                                                  # root, its SLURM cluster: ~an hour)

The commands are read from the README's first code block (its first line: install and the
quickstart campaign; its second: install the test extra and run the quick suite), cloned from
this repository's HEAD (``--ref``) and run verbatim; each part of a command (between ``&&``) is
timed on its own, in order, stopping at the first that fails, as ``&&`` would. ``--ci`` also times
``bash .ci/run`` (every test, the SLURM cluster included) in a clone of its own. The table gives
wall-clock seconds per part and the command's total; the quickstart's "kernels ready" line (its
numba compilation) and pytest's closing line are quoted. Numbers are only worth quoting from a
quiet machine (nothing else running: ``uptime`` near 0).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Environment variables a fresh user does not have: caches, the caller's venv, the CI cluster.
DROP = ("NUMBA_CACHE_DIR", "VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME", "CAMPAIGN_TEST_SLURM", "PYTEST_ADDOPTS",
        "XDG_CACHE_HOME", "XDG_CONFIG_HOME", "XDG_DATA_HOME", "PIP_CACHE_DIR", "CONDA_PREFIX", "CI")


def readme_commands(readme: Path) -> list:
    """The lines of the README's first fenced code block (its commands)."""
    text = readme.read_text()
    m = re.search(r"```(?:bash|sh)?\n(.*?)```", text, re.S)
    if not m:
        raise SystemExit(f"{readme}: no code block")
    return [line.strip() for line in m.group(1).splitlines() if line.strip() and not line.startswith("#")]


def fresh_clone(repo: Path, ref: str, where: Path) -> Path:
    clone = where / "clone"
    subprocess.run(["git", "clone", "--quiet", "--no-hardlinks", str(repo), str(clone)], check=True)
    subprocess.run(["git", "-C", str(clone), "checkout", "--quiet", "--detach", ref], check=True)
    return clone


def fresh_env(home: Path, durations: int | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in DROP}
    home.mkdir(parents=True, exist_ok=True)
    env["HOME"] = str(home)
    if durations is not None:
        env["PYTEST_ADDOPTS"] = f"--durations={durations}"
    return env


def run_command(name: str, command: str, repo: Path, ref: str, keep: bool, durations: int | None,
                log_dir: Path) -> dict:
    """Run one README command verbatim in a fresh clone with a fresh HOME: a record of its parts."""
    where = Path(tempfile.mkdtemp(prefix=f"suite-{name}-"))
    clone = fresh_clone(repo, ref, where)
    env = fresh_env(where / "home", durations)
    parts = [p.strip() for p in command.split("&&")]
    record = {"name": name, "command": command, "parts": [], "ok": True}
    log = log_dir / f"suite-{name}.log"
    t_all = time.monotonic()
    with open(log, "w") as fh:
        for part in parts:
            fh.write(f"$ {part}\n")
            fh.flush()
            t0 = time.monotonic()
            proc = subprocess.run(["bash", "-c", part], cwd=clone, env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL)
            seconds = time.monotonic() - t0
            fh.write(proc.stdout)
            fh.write(f"[exit {proc.returncode}, {seconds:.1f} s]\n")
            record["parts"].append({"command": part, "seconds": round(seconds, 1), "exit": proc.returncode})
            for line in proc.stdout.splitlines():
                if "kernels ready in" in line:
                    record["kernels_ready"] = line.strip()
                if re.search(r"\d+ (passed|failed|error)", line) and ("=" in line or " in " in line):
                    record["pytest"] = line.strip(" =")
            if proc.returncode != 0:
                record["ok"] = False
                break
    record["seconds"] = round(time.monotonic() - t_all, 1)
    record["log"] = str(log)
    if keep:
        record["clone"] = str(clone)
    else:
        shutil.rmtree(where, ignore_errors=True)
    return record


def machine() -> dict:
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    return {"python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count(),
            "load_before": [round(x, 2) for x in load] if load else None}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ref", default="HEAD", help="the commit to clone (default: HEAD)")
    ap.add_argument("--only", choices=("quickstart", "tests"), help="time one of the two commands")
    ap.add_argument("--ci", action="store_true", help="also time bash .ci/run (every test; root, ~an hour)")
    ap.add_argument("--durations", type=int, metavar="N",
                    help="pytest's N slowest tests in the log (PYTEST_ADDOPTS=--durations=N)")
    ap.add_argument("--keep", action="store_true", help="keep the clones (their paths in the JSON)")
    ap.add_argument("--logs", help="where the commands' logs go (default: a new temporary directory)")
    ap.add_argument("--json", metavar="FILE", help="write the results as JSON")
    a = ap.parse_args(argv)

    ref = subprocess.run(["git", "-C", str(ROOT), "rev-parse", a.ref], check=True, capture_output=True,
                         text=True).stdout.strip()
    commands = readme_commands(ROOT / "README.md")
    todo = [("quickstart", commands[0]), ("tests", commands[1])]
    if a.only:
        todo = [t for t in todo if t[0] == a.only]
    if a.ci:
        todo.append(("ci", "bash .ci/run"))
    log_dir = Path(a.logs).resolve() if a.logs else Path(tempfile.mkdtemp(prefix="suite-logs-"))
    log_dir.mkdir(parents=True, exist_ok=True)
    result = {"commit": ref, "machine": machine(), "commands": []}
    print(f"commit {ref[:10]}, {result['machine']['cpus']} cpus, load {result['machine']['load_before']}",
          flush=True)
    load = result["machine"]["load_before"]
    if load and load[0] > 0.5:
        print("warning: the machine is busy (load above 0.5): these times are inflated, not figures to quote",
              flush=True)
    for name, command in todo:
        rec = run_command(name, command, ROOT, ref, a.keep, a.durations, log_dir)
        result["commands"].append(rec)
        print(f"\n{name}: {rec['seconds']:.1f} s{'' if rec['ok'] else '  FAILED'}  ({rec['log']})")
        for part in rec["parts"]:
            print(f"  {part['seconds']:8.1f} s  {part['command']}" + ("" if part["exit"] == 0 else
                                                                     f"  [exit {part['exit']}]"))
        for key in ("kernels_ready", "pytest"):
            if key in rec:
                print(f"  {rec[key]}")
        sys.stdout.flush()
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    result["machine"]["load_after"] = [round(x, 2) for x in load] if load else None
    print("\n| command | seconds | result |\n|---|---|---|")
    for rec in result["commands"]:
        print(f"| {rec['name']} | {rec['seconds']:.0f} | {rec.get('pytest', 'ok' if rec['ok'] else 'FAILED')} |")
    if a.json:
        Path(a.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0 if all(r["ok"] for r in result["commands"]) else 1


if __name__ == "__main__":
    sys.exit(main())
