"""The stores shipped in data/ are complete and sound, and give the numbers the docs quote from them
(the commands the docs print, run as a user runs them)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _campaign(*args, **kw):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return subprocess.run([sys.executable, "-m", "campaign", *map(str, args)], env=env, capture_output=True,
                          text=True, timeout=600, **kw)


def _row(text: str, n: int) -> list:
    """The cells of the table row of size ``n`` in a markdown ``text`` (the first such row)."""
    line = next(ln for ln in text.splitlines() if ln.startswith(f"| {n} |"))
    return [c.strip() for c in line.split("|")[2:-1]]


def _complete_and_sound(store: Path, tasks: int):
    """`campaign status`: every one of ``tasks`` done; `campaign verify`: no damage."""
    status = json.loads(_campaign("status", store, "--json", check=True).stdout)
    assert (status["done"], status["failed"], status["remaining"]) == (tasks, 0, 0)
    verify = _campaign("verify", store)
    assert verify.returncode == 0 and "no damage" in verify.stdout + verify.stderr, verify.stdout + verify.stderr


@pytest.mark.slow
def test_the_8192_store_is_complete_sound_and_gives_the_documented_row(tmp_path):
    """data/paper-8192-cpu.h5 (the chain of docs/CLUSTERS.md): every task done, `campaign verify`
    clean, and `campaign reduce` (default range and --fit-all) gives docs/PAPER.md's 8192 row, entry
    for entry as printed, and the README's."""
    store = ROOT / "data" / "paper-8192-cpu.h5"
    _complete_and_sound(store, 104)
    got = {}
    for name, extra in (("default", ()), ("all", ("--fit-all",))):
        _campaign("reduce", store, *extra, "--out", tmp_path / name, check=True)
        got[name] = _row((tmp_path / name / "table.md").read_text(), 8192)   # A_G*(E), beta_E, A_G*(Z), beta_Z, Psi_O*, range
    d, a = got["default"], got["all"]
    text = (ROOT / "docs" / "PAPER.md").read_text()
    section = text[text.index("### N_G = 8192, on CPUs"):]
    doc = _row(section, 8192)
    assert doc == ["0.4461(4)", f"{d[0]} [{a[0]}]", "0.284(4)", f"{d[1]} [{a[1]}]", "0.4460(3)",
                   f"{d[2]} [{a[2]}]", "1.001(3)", f"{d[3]} [{a[3]}]", f"{d[4]} [{a[4]}]"]
    readme = _row((ROOT / "README.md").read_text(), 8192)
    assert readme == ["0.4461(4)", d[0], "0.284(4)", f"{d[1]} [{a[1]}]", "1.001(3)", f"{d[3]} [{a[3]}]", "-", d[4]]


def _bare(cell: str) -> str:
    """A table cell's value as printed: bold and the reducer's undetermined mark dropped, a remark after it too."""
    return cell.replace("**", "").replace("*", "").split(" ")[0]


@pytest.mark.slow
def test_paper_small_store_gives_the_finite_size_table(tmp_path):
    """data/paper-small.h5 (campaigns/paper-small.yaml, no configurations) is complete and sound, and
    docs/PAPER.md's finite-size table (N_G 64..1024 and N_G -> inf, the default range) is what
    `campaign reduce data/paper-small.h5` gives, entry for entry."""
    store = ROOT / "data" / "paper-small.h5"
    _complete_and_sound(store, 1300)
    _campaign("reduce", store, "--out", tmp_path / "red", check=True)
    table = (tmp_path / "red" / "table.md").read_text()
    text = (ROOT / "docs" / "PAPER.md").read_text()
    doc = text[text.index("## The finite-size table"):text.index("### To N_G = 4096")]
    for n in (64, 128, 256, 512, 1024, "N_G -> inf"):
        got = [_bare(c) for c in _row(table, n)]          # A_G*(E), beta_E, A_G*(Z), beta_Z, Psi_O*, range
        cells = [_bare(c) for c in _row(doc, n)]         # paper, ours per entry; Psi_O* ours alone
        assert [cells[1], cells[3], cells[5], cells[7], cells[8]] == got[:5], n
