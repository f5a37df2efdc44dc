"""The README stays a front door (at most 15 000 characters) and every relative link of the
documentation reaches a file, and a heading when it names one."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "slurm" / "README.md"]


def _anchors(path):
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to hyphens."""
    out = set()
    for line in path.read_text().splitlines():
        m = re.match(r"#+\s+(.*)", line)
        if m:
            out.add(re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-"))
    return out


def test_readme_is_short():
    assert len((ROOT / "README.md").read_text()) <= 15_000


@pytest.mark.parametrize("page", [p for p in PAGES if p.exists()], ids=lambda p: p.name)
def test_relative_links_resolve(page):
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    bad = []
    for link in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+://", link) or link.startswith("mailto:"):
            continue
        path, _, anchor = link.partition("#")
        target = (page.parent / path).resolve() if path else page
        if not target.exists():
            bad.append(f"{link}: no such file")
        elif anchor and target.suffix == ".md" and anchor not in _anchors(target):
            bad.append(f"{link}: no heading #{anchor}")
    assert not bad, f"{page.relative_to(ROOT)}: {bad}"


# --------------------------------------------------------------------------- documents named anywhere

_SKIP_DIRS = {"__pycache__", "jamming_campaign.egg-info"}
#: Files the reducer writes next to its output (campaign/report/writing.py), not documents of
#: this repository: named in the docs and the code as outputs. Each must still be a name the
#: results package writes (test_output_names_are_written), so that this list cannot outlive them.
REDUCER_OUTPUTS = {"table.md", "systems.md", "protocols.md"}
_MD_NAME = re.compile(r"(?<![\w./-])((?:[\w.-]+/)*[\w.-]*\w\.md)\b")
#: Addresses of other projects' files (a link to a URL is not a file of this repository).
_URL = re.compile(r"[a-z][a-z0-9+.-]*://\S+")


def _citing_files():
    out = []
    for p in sorted(ROOT.rglob("*")):
        rel = p.relative_to(ROOT).parts
        if p.suffix not in {".py", ".md", ".yaml", ".sbatch"} or not p.is_file():
            continue
        if any(part.startswith(".") or part in _SKIP_DIRS for part in rel):
            continue  # .git, the virtual environment, caches, build metadata
        out.append(p)
    return out


def _md_names(path):
    return set(_MD_NAME.findall(_URL.sub(" ", path.read_text(errors="replace"))))


def test_citing_files_are_found():
    files = {p.relative_to(ROOT).as_posix() for p in _citing_files()}
    for expected in ("README.md", "docs/CONTRACTS.md", "kernels/network.py", "tests/project/test_docs.py",
                     "campaigns/ci.yaml"):
        assert expected in files
    assert not any(f.startswith((".venv/", ".git/")) for f in files)


def test_md_name_pattern():
    text = ("see ``docs/PHYSICS.md``, [STORE.md](STORE.md#x), ../CHANGELOG.md and "
            "https://example.org/other/README.md; not PHYSICS.mdx")
    found = set(_MD_NAME.findall(_URL.sub(" ", text)))
    assert found == {"docs/PHYSICS.md", "STORE.md", "../CHANGELOG.md"}


def test_output_names_are_written():
    code = "".join(p.read_text() for wing in ("results", "report") for p in (ROOT / "campaign" / wing).glob("*.py"))
    for name in REDUCER_OUTPUTS:
        assert f'"{name}"' in code or f"'{name}'" in code, name


def test_every_named_document_exists():
    """Every ``*.md`` named in code (.py) or docs (.md, .yaml, .sbatch) is a file of the
    repository, relative to the naming file, to docs/ or to the repository root."""
    bad = []
    for path in _citing_files():
        for name in sorted(_md_names(path) - REDUCER_OUTPUTS):
            if not any((base / name).is_file() for base in (path.parent, ROOT / "docs", ROOT)):
                bad.append(f"{path.relative_to(ROOT)}: {name}")
    assert not bad, bad


# --------------------------------------------------------------------------- the module table

def _module_table():
    """The module paths the first column of CONTRACTS.md's layout table names: a cell's
    backticked ``dir/file.py`` sets the directory its following bare ``file.py`` names use."""
    text = (ROOT / "docs" / "CONTRACTS.md").read_text()
    section = text.split("## Package layout and ownership of names", 1)[1].split("\n## ", 1)[0]
    named = set()
    for line in section.splitlines():
        if not line.startswith("| `") and not line.startswith("| **`"):
            continue
        folder = None
        for token in re.findall(r"`([^`]+)`", line.split("|")[1]):
            if "/" in token:
                folder = token.rsplit("/", 1)[0]
                name = token
            elif folder is not None:
                name = f"{folder}/{token}"
            else:
                continue
            if name.endswith(".py"):
                named.add(name)
    return named


def test_module_table_names_every_module():
    on_disk = {p.relative_to(ROOT).as_posix()
               for pkg in ("kernels", "campaign") for p in (ROOT / pkg).rglob("*.py")
               if p.name not in {"__init__.py", "__main__.py"} and "__pycache__" not in p.parts}
    table = _module_table()
    assert {"kernels/space.py", "campaign/plan/tasks.py"} <= on_disk
    assert not on_disk - table, f"modules missing from docs/CONTRACTS.md: {sorted(on_disk - table)}"
    assert not table - on_disk, f"docs/CONTRACTS.md names modules that do not exist: {sorted(table - on_disk)}"


# --------------------------------------------------------------------------- tests import no test module

def _imported_modules(path):
    import ast

    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.add(node.module)
        elif isinstance(node, ast.ImportFrom) and node.level:
            out |= {f".{node.module or ''}.{a.name}".replace("..", ".") for a in node.names}
    for text in re.findall(r"^\s*(?:from\s+(\S+)\s+import|import\s+(\S+))", path.read_text(), re.M):
        out |= {t for t in text if t}  # also imports inside strings (subprocess harnesses)
    return out


def _is_test_module(name):
    return re.fullmatch(r"(?:\.?tests\.|\.)?test_\w+", name) is not None


def test_test_module_names_are_recognised():
    assert _is_test_module("test_master") and _is_test_module("tests.test_master")
    assert _is_test_module(".test_master")
    assert not _is_test_module("tests.helpers") and not _is_test_module("references")
    assert not _is_test_module("pytest") and not _is_test_module("kernels.test_x.y")


def test_no_test_module_imports_another():
    bad = {p.name: sorted(m for m in _imported_modules(p) if _is_test_module(m))
           for p in sorted((ROOT / "tests").rglob("*.py"))}
    bad = {k: v for k, v in bad.items() if v}
    assert not bad, f"shared code belongs in tests/helpers.py or tests/references.py: {bad}"


# --------------------------------------------------------------------------- the README's commands

def test_ci_runs_the_readmes_full_suite_command():
    """CI runs what the README calls the full suite, every test (``--full``), with the CUDA
    compiler libraries; the README's second command is the quick suite (no ``--full``, no GPU
    toolkit)."""
    readme = " ".join((ROOT / "README.md").read_text().split())
    full = re.search(r"runs every test: `([^`]+)`", readme)
    assert full, "the README names the full-suite command"
    command = full.group(1)
    assert "--full" in command and ".[test,cuda]" in command, command
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert command in ci, f".ci/run does not run the README's full-suite command {command!r}"
    block = re.search(r"```bash\n(.*?)```", (ROOT / "README.md").read_text(), re.S).group(1).splitlines()
    assert block[1].endswith("pip install '.[test]' && .venv/bin/python -m pytest -q -n auto --dist loadfile"), block[1]
