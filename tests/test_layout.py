"""The code's shape: the kernels' imports form no circle (every import, also those inside
functions), and the kernels import nothing from the orchestration."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imports(package):
    out = {}
    for f in sorted((ROOT / package).glob("*.py")):
        deps = set()
        for node in ast.walk(ast.parse(f.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            for name in names:
                top, _, rest = name.partition(".")
                if top in ("kernels", "campaign"):
                    deps.add((top, rest.split(".")[0]))
        out[f.stem] = deps
    return out


def test_kernels_imports_form_no_circle():
    graph = {m: {d for p, d in deps if p == "kernels" and d} for m, deps in _imports("kernels").items()}
    state = {}

    def visit(m, path):
        state[m] = "open"
        for d in sorted(graph.get(m, ())):
            assert state.get(d) != "open", "import circle: " + " -> ".join(path + [d])
            if d not in state:
                visit(d, path + [d])
        state[m] = "done"

    for m in graph:
        if m not in state:
            visit(m, [m])


def test_kernels_do_not_import_the_orchestration():
    for m, deps in _imports("kernels").items():
        assert not any(p == "campaign" for p, _ in deps), m
