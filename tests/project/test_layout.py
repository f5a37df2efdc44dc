"""The code's shape: neither the kernels' nor the orchestration's imports form a circle
(every import counts, also those inside functions), the kernels import nothing from
the orchestration, no module imports its own package's ``__init__`` (nothing runs back up),
and ``campaign``'s wings import only from themselves and the wings before them on the data's
path: plan -> storage -> run | results -> precision | report -> commands -> cli (docs/DEVELOPMENT.md,
"The house")."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _graph(package):
    """Module -> the modules of ``kernels`` and ``campaign`` it imports (dotted names)."""
    out = {}
    for f in sorted((ROOT / package).rglob("*.py")):
        parts = f.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)  # a package by its name
        deps = set()
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                for a in node.names:  # ``from pkg import mod`` imports the module pkg.mod
                    sub = f"{node.module}.{a.name}"
                    is_module = (ROOT / sub.replace(".", "/")).with_suffix(".py").is_file() or \
                        (ROOT / sub.replace(".", "/") / "__init__.py").is_file()
                    deps.add(sub if is_module else node.module)
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
        out[name] = {d for d in deps if d.split(".")[0] in ("kernels", "campaign")}
    return out


def _assert_no_circle(graph):
    state = {}

    def visit(m, path):
        state[m] = "open"
        for d in sorted(graph.get(m, ())):
            if d not in graph:
                continue
            assert state.get(d) != "open", "import circle: " + " -> ".join(path + [d])
            if d not in state:
                visit(d, path + [d])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


def test_kernels_imports_form_no_circle():
    _assert_no_circle(_graph("kernels"))


def test_campaign_imports_form_no_circle():
    _assert_no_circle(_graph("campaign"))


def test_kernels_do_not_import_the_orchestration():
    for m, deps in _graph("kernels").items():
        assert not any(d.startswith("campaign") for d in deps), m


def test_the_circle_check_finds_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}}
    try:
        _assert_no_circle(graph)
    except AssertionError as e:
        assert "a -> b -> c -> a" in str(e)
    else:
        raise AssertionError("a circle went unnoticed")


#: campaign's wings in the order of the data's path; run and results are side by side (neither
#: imports the other), and so are precision (the rounds' decisions, which reduce the store and are
#: handed to a run by the commands) and report (what people read of a reduction). ``errors`` and
#: ``version`` serve every wing.
WINGS = {"errors": 0, "version": 0, "plan": 1, "storage": 2, "run": 3, "results": 3, "precision": 4,
         "report": 4, "commands": 5, "cli": 6, "__main__": 7, "": 7}


def _wing(module):
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""  # "": the package's own __init__


def _layering_violations(graph):
    out = []
    for m, deps in sorted(graph.items()):
        if not m.startswith("campaign"):
            continue
        w = _wing(m)
        for d in sorted(d for d in deps if d.split(".")[0] == "campaign"):
            dw = _wing(d)
            if dw != w and WINGS[dw] >= WINGS[w]:
                out.append(f"{m} ({w or 'campaign'}) imports {d} ({dw or 'campaign'})")
    return out


def test_campaign_is_in_wings():
    wings = [p.name for p in (ROOT / "campaign").iterdir() if (p / "__init__.py").is_file()]
    assert set(wings) == {w for w in WINGS if w and (ROOT / "campaign" / w).is_dir()}
    assert len(set(wings) - {"commands"}) >= 3
    loose = sorted(p.stem for p in (ROOT / "campaign").glob("*.py"))
    assert set(loose) <= {"__init__", "__main__", "cli", "errors", "version"}, loose
    for w in wings:  # a wing's __init__ only documents it: importing one module loads no other
        tree = ast.parse((ROOT / "campaign" / w / "__init__.py").read_text())
        assert not [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))], w


def test_wings_import_only_backwards():
    assert _layering_violations(_graph("campaign")) == []


def test_nothing_runs_back_up():
    """No module imports its own package's (or a parent package's) ``__init__``."""
    for package in ("kernels", "campaign"):
        for m, deps in _graph(package).items():
            parents = {".".join(m.split(".")[:i]) for i in range(1, len(m.split(".")))}
            assert not deps & parents, f"{m} imports {sorted(deps & parents)}"


def test_the_layering_check_finds_a_backward_import():
    graph = {"campaign.plan.spec": {"campaign.storage.store"}, "campaign.results.reduce": {"campaign.run.engine"},
             "campaign.run.engine": {"campaign.storage.store", "campaign.errors"}}
    assert _layering_violations(graph) == [
        "campaign.plan.spec (plan) imports campaign.storage.store (storage)",
        "campaign.results.reduce (results) imports campaign.run.engine (run)"]


def test_every_wing_is_few_modules_of_at_most_800_lines():
    """Every folder of campaign/ (docs/DEVELOPMENT.md, "The house"): at most 15 modules, its __init__
    included, none over 800 lines, each cut by what it does (the writer, the layout, the reader, the
    scan ...)."""
    folders = sorted({f.parent for f in (ROOT / "campaign").rglob("*.py")})
    crowded = {d.relative_to(ROOT).as_posix(): n for d in folders if (n := len(list(d.glob("*.py")))) > 15}
    assert crowded == {}
    long = {f.relative_to(ROOT).as_posix(): n for f in sorted((ROOT / "campaign").rglob("*.py"))
            if (n := len(f.read_text().splitlines())) > 800}
    assert long == {}


def test_the_stored_spec_is_parsed_in_one_place():
    """A store's spec (its root attribute spec_yaml) is parsed by campaign.storage.layout.stored_spec
    alone: no other module of campaign/ calls the spec's parser or loads YAML (campaign.plan.parse,
    the parser itself, reads spec files)."""
    parsers = {f.relative_to(ROOT).as_posix() for f in sorted((ROOT / "campaign").rglob("*.py"))
               if re.search(r"\bparse_spec\(|\byaml\.(safe_)?load\(", f.read_text())}
    assert parsers == {"campaign/plan/parse.py", "campaign/storage/layout.py"}, parsers


def test_no_module_is_over_900_lines():
    """A module a reader can hold in mind: the kernels (and the orchestration, held tighter above) cut
    by responsibility."""
    long = {str(f.relative_to(ROOT)): n for package in ("kernels", "campaign")
            for f in sorted((ROOT / package).rglob("*.py")) if (n := len(f.read_text().splitlines())) > 900}
    assert long == {}


def run_walk(spec, out):
    """The walk of ``campaign run`` (docs/DEVELOPMENT.md, "The house"): the project functions
    ``run_campaign`` calls, to depth 3, each at its first call and in that order, outside the
    master's task loop (``Master.run``) and the writing of finished rows (``Store.flush``, which
    the loop or the close may do first, as time decides); comprehensions are not functions.
    Returns the modules of its stays: a stay is a run of consecutive functions of one module;
    every stay in a module left before is a return."""
    import sys

    from campaign import cli
    from campaign.run.engine import run_campaign
    from campaign.run.master import Master
    from campaign.storage.store import Store

    seen, stays, root = set(), [], []

    def profile(frame, event, arg):
        if event != "call":
            return
        if not root:
            if frame.f_code is run_campaign.__code__:
                root.append(frame)
            return
        depth, f = 0, frame
        while f is not None and f is not root[0]:
            if f.f_code in (Master.run.__code__, Store.flush.__code__) and f is not frame:
                return  # the task loop, the writing of rows
            f, depth = f.f_back, depth + 1
        module = frame.f_globals.get("__name__", "")
        key = (module, frame.f_code.co_qualname)
        if f is None or depth > 3 or not module.startswith(("campaign", "kernels")) or key in seen \
                or frame.f_code.co_name.startswith("<"):
            return  # comprehensions are expressions of their function (inlined since Python 3.12)
        seen.add(key)
        if not stays or stays[-1] != module:
            stays.append(module)

    # once without the profile: a cold numba cache compiles here, not under the profile (slow)
    assert cli.main(["run", str(spec), "--out", f"{out}.warm.h5", "--workers", "1", "--quiet"]) == 0
    sys.setprofile(profile)
    try:
        code = cli.main(["run", str(spec), "--out", str(out), "--workers", "1", "--quiet"])
    finally:
        sys.setprofile(None)
    assert code == 0
    return stays


def test_the_walk_of_campaign_run_returns_to_few_modules(tmp_path):
    """A reader following a run from its arguments to its workers and back meets each module in
    few separate stays: at most 18 returns to a module left before (20 before the store's start
    took its journal, one look at its file and the state it gives in one function; 31 before the
    run gathered its plan, the spec, its tasks, the energy check, the output's check and the
    workers' context, before touching the store; the spec computed its hash once; the store
    recorded the master's peak memory itself)."""
    spec = tmp_path / "tiny.yaml"
    spec.write_text("name: tiny\nseed: 1\ngrid: {N_G: [16], E_G: [1.0e-4], seeds: 2}\n")
    stays = run_walk(spec, tmp_path / "tiny.h5")
    walk = " -> ".join(stays)
    assert len(set(stays)) >= 12, walk  # the walk does reach the store, the master and the workers
    assert {"campaign.plan.spec", "campaign.storage.store", "campaign.run.master", "campaign.run.comm"} <= set(stays)
    assert len(stays) - len(set(stays)) <= 18, walk
