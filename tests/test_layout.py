"""The code's shape: neither the kernels' nor the orchestration's imports form a circle
(every import counts, also those inside functions), the kernels import nothing from
the orchestration, no module imports its own package's ``__init__`` (nothing runs back up),
and ``campaign``'s wings import only from themselves and the wings before them on the data's
path: plan -> storage -> run | results -> commands -> cli (docs/DEVELOPMENT.md, "The house")."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


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
#: imports the other). ``errors`` and ``version`` serve every wing.
WINGS = {"errors": 0, "version": 0, "plan": 1, "storage": 2, "run": 3, "results": 3, "commands": 4,
         "cli": 5, "__main__": 6, "": 6}


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


def test_no_module_is_over_900_lines():
    """A module a reader can hold in mind: the kernels and the orchestration cut by responsibility."""
    long = {str(f.relative_to(ROOT)): n for package in ("kernels", "campaign")
            for f in sorted((ROOT / package).rglob("*.py")) if (n := len(f.read_text().splitlines())) > 900}
    assert long == {}
