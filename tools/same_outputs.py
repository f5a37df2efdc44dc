"""Every output a user reads, made by two commits from the same stores, compared byte for byte.

    python tools/same_outputs.py --base REV [--head REV] [--stores DIR ...] [--keep DIR]

For a change meant to leave behaviour alone (a move of code, a new layout): both commits are
checked out into temporary git worktrees, and each runs, from the same input stores, the
commands whose outputs the documentation quotes:

* ``campaign reduce`` of every shipped store (``data/*.h5``) and of every store found in the
  ``--stores`` directories (the docs' campaigns: ``results/paper-small.h5`` ...), alone, with
  ``--fit-all``, with ``--json``, and in the groups the docs reduce together
  (``GROUPS``); the tables (md, csv, tex), every CSV, ``summary.json`` and the ``/reduced``
  group;
* ``campaign plot`` of the same (every figure, PNG);
* ``campaign status``, ``campaign verify``, ``campaign export`` (CSV) of each store,
  ``campaign draw`` of a store that keeps configurations, ``campaign validate`` of every spec
  under ``campaigns/``.

Text, CSV, JSON and PNG files must be equal byte for byte; an HDF5 output (``reduced.h5``) equal
in every dataset and attribute but its ``generated`` time; a command's stdout and exit code
equal too (stderr, which carries timings, is not compared). Prints one line per output that
differs and exits 1 if any does, 0 if every output is the same.
"""

from __future__ import annotations

import argparse
import filecmp
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: stores the docs reduce together (by file name); each store is also reduced alone
GROUPS = [
    ("protocols.h5", "protocols-more.h5"),
    ("paper-small.h5", "paper-large.h5"),
    ("paper-small.h5", "paper-large.h5", "paper-8192-cpu.h5"),
    ("universality.h5", "universality-1024.h5"),
    ("response.h5", "response-1024.h5"),
]
#: variations of ``campaign reduce`` run on every store and group
REDUCE_OPTIONS = ([], ["--fit-all"], ["--boot", "50", "--json"])
#: timings and clocks in stdout that legitimately differ from run to run
VOLATILE = ("wrote ", "seconds", " s)", "rate")
#: a duration closing a line that says more (`campaign verify`'s "read ... in 0.4 s"): the line is
#: compared, its clock is not
DURATION = re.compile(r" in [0-9.]+ s$")


def run(code: Path, args, cwd: Path, log):
    """``python -m campaign ARGS`` with the package of worktree ``code``: (exit code, stdout)."""
    env = dict(os.environ, PYTHONPATH=str(code), NUMBA_CACHE_DIR=str(cwd.parent / f".numba-{code.name}"),
               MPLBACKEND="Agg")
    p = subprocess.run([sys.executable, "-m", "campaign", *map(str, args)], cwd=cwd, env=env,
                       capture_output=True, text=True)
    log.write(f"$ campaign {' '.join(map(str, args))}\n(exit {p.returncode})\n{p.stderr[-2000:]}\n")
    out = "\n".join(DURATION.sub(" in ... s", line) for line in p.stdout.splitlines()
                    if not any(v in line for v in VOLATILE))
    return p.returncode, out


def jobs(stores, specs):
    """(name, arguments, output directory or file relative to the job folder) for every command."""
    by_name = {p.name: p for p in stores}
    out = []
    sets = [(p.stem, [p]) for p in stores]
    sets += [("+".join(Path(n).stem for n in g), [by_name[n] for n in g]) for g in GROUPS
             if all(n in by_name for n in g)]
    for name, files in sets:
        for i, opts in enumerate(REDUCE_OPTIONS):
            out.append((f"reduce-{name}-{i}", ["reduce", *files, *opts, "--out", f"reduce-{name}-{i}"]))
        out.append((f"plot-{name}", ["plot", *files, "--out", f"plot-{name}"]))
    for p in stores:
        out.append((f"status-{p.stem}", ["status", p]))
        out.append((f"verify-{p.stem}", ["verify", p]))
        out.append((f"export-{p.stem}", ["export", p, "--out", f"export-{p.stem}.csv"]))
        with h5py.File(p, "r") as f:
            has_conf = "configurations" in f and len(f["configurations"]) > 0
        if has_conf:
            out.append((f"draw-{p.stem}", ["draw", p, "--out", f"draw-{p.stem}.png"]))
    for s in specs:
        out.append((f"validate-{s.stem}", ["validate", s]))
    return out


def h5_same(a: Path, b: Path):
    """The first difference between two HDF5 files (datasets, attributes; ``generated`` skipped)."""
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        names_a, names_b = [], []
        fa.visit(names_a.append)
        fb.visit(names_b.append)
        if names_a != names_b:
            return f"objects differ: {sorted(set(names_a) ^ set(names_b))[:5]}"
        for name in ["/", *names_a]:
            oa, ob = fa[name], fb[name]
            ka = {k for k in oa.attrs if k != "generated"}
            kb = {k for k in ob.attrs if k != "generated"}
            if ka != kb:
                return f"{name}: attributes {sorted(ka ^ kb)}"
            for k in sorted(ka):
                if not _equal(oa.attrs[k], ob.attrs[k]):
                    return f"{name}: attribute {k}"
            if isinstance(oa, h5py.Dataset) and not _equal(oa[()], ob[()]):
                return f"{name}: values"
    return ""


def _equal(x, y):
    x, y = np.asarray(x), np.asarray(y)
    if x.shape != y.shape or x.dtype != y.dtype:
        return False
    if x.dtype.kind == "f":
        return bool(np.array_equal(x, y, equal_nan=True))
    return bool(np.array_equal(x, y))


def compare(a: Path, b: Path):
    """Lines naming every file that differs between two job folders."""
    out = []
    fa = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    fb = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for rel in sorted(set(fa) ^ set(fb)):
        out.append(f"{rel}: only in {'base' if rel in fa else 'head'}")
    for rel in sorted(set(fa) & set(fb)):
        if rel.suffix == ".h5":
            why = h5_same(a / rel, b / rel)
            if why:
                out.append(f"{rel}: {why}")
        elif not filecmp.cmp(a / rel, b / rel, shallow=False):
            out.append(f"{rel}: bytes differ")
    return out


def worktree(rev: str, where: Path) -> Path:
    if rev == "WORKTREE":  # the checkout as it stands, uncommitted changes included
        return ROOT
    path = where / rev.replace("/", "_")
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--force", str(path), rev],
                   check=True, capture_output=True)
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", required=True, help="the commit before the change")
    ap.add_argument("--head", default="WORKTREE", help="the commit after it (default: the checkout as it is)")
    ap.add_argument("--stores", nargs="*", default=[], metavar="DIR",
                    help="more directories of stores to reduce (the docs' campaigns' results/)")
    ap.add_argument("--only", nargs="*", default=None, metavar="JOB",
                    help="run only the jobs whose names start with these")
    ap.add_argument("--keep", metavar="DIR", help="keep the outputs here (default: a temporary directory)")
    a = ap.parse_args(argv)
    stores = sorted((ROOT / "data").glob("*.h5"))
    for d in a.stores:
        stores += sorted(p for p in Path(d).glob("*.h5") if "_reduced" not in str(p))
    specs = sorted((ROOT / "campaigns").glob("*.yaml"))
    todo = [j for j in jobs(stores, specs) if a.only is None or j[0].startswith(tuple(a.only))]
    tmp = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="same_outputs_"))
    tmp.mkdir(parents=True, exist_ok=True)
    trees = tmp / "trees"
    trees.mkdir(exist_ok=True)
    code = {side: worktree(rev, trees) for side, rev in (("base", a.base), ("head", a.head))}
    differ = []
    try:
        for name, args in todo:
            results = {}
            for side in ("base", "head"):
                cwd = tmp / side / name
                shutil.rmtree(cwd, ignore_errors=True)
                cwd.mkdir(parents=True)
                with open(tmp / f"{side}.log", "a") as log:
                    results[side] = run(code[side], args, cwd, log)
            lines = compare(tmp / "base" / name, tmp / "head" / name)
            if results["base"] != results["head"]:
                lines.insert(0, f"exit {results['base'][0]} -> {results['head'][0]}, stdout "
                             + ("same" if results["base"][1] == results["head"][1] else "differs"))
            print(f"{name}: " + ("same" if not lines else "DIFFERS"), flush=True)
            for line in lines:
                print(f"    {line}", flush=True)
            differ += lines
    finally:
        for side, path in code.items():
            if path != ROOT:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(path)],
                               capture_output=True)
        if not a.keep:
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"{len(todo)} commands, {len(differ)} outputs differ")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
