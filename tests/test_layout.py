"""The code's shape: neither the kernels' nor the orchestration's imports form a circle
(every import counts, also those inside functions), and the kernels import nothing from
the orchestration. A task's path, spec -> tasks -> engine -> worker/master -> store, then
reads downward."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _graph(package):
    """Module -> the modules of ``kernels`` and ``campaign`` it imports (dotted names)."""
    out = {}
    for f in sorted((ROOT / package).rglob("*.py")):
        name = ".".join(f.relative_to(ROOT).with_suffix("").parts)
        deps = set()
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                if node.module in ("kernels", "campaign"):
                    deps.update(f"{node.module}.{a.name}" for a in node.names)
                else:
                    deps.add(node.module)
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
