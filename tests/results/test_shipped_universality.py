"""data/universality.h5 and data/universality-1024.h5 (campaigns/universality.yaml and
universality-1024.yaml) are complete and sound, and give docs/UNIVERSALITY.md's tables and the
README's as the commands the page prints make them: `campaign reduce` over every energy, at overlaps
up to 1% and at the default window (its `systems.md`), and experiments/universality.py's summary of
every window (each system's row with `x`, and the test of one `beta_Z`)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import campaign_cli, complete_and_sound

ROOT = Path(__file__).resolve().parents[2]
STORES = [ROOT / "data" / "universality.h5", ROOT / "data" / "universality-1024.h5"]
DOC = (ROOT / "docs" / "UNIVERSALITY.md").read_text()


def _tables(text: str) -> list:
    """Every markdown table of ``text``: its lines, from the header to the last row."""
    tables, current = [], []
    for line in text.splitlines():
        if line.startswith("|"):
            current.append(line.rstrip())
        elif current:
            tables.append(current)
            current = []
    return tables + ([current] if current else [])


def _doc_table(header: str, after: str) -> list:
    """The first table of the page after the text ``after`` whose header line is ``header``."""
    return next(t for t in _tables(DOC[DOC.index(after):]) if t[0] == header)


@pytest.mark.slow
def test_the_stores_are_complete_and_sound():
    complete_and_sound(STORES[0], 9760)
    complete_and_sound(STORES[1], 1220)


SYSTEMS = ("| system | N_G | alpha | sizes | A_G* | beta_E | beta_Z | beta_Z/(2 alpha) | "
           "beta_E - beta_Z/(2 alpha) [sigma] | beta_Z - beta_Z(ref) [sigma] | Psi_O* |")


@pytest.mark.slow
@pytest.mark.parametrize("option, after", [(("--fit-all",), "## Fitted over every energy"),
                                           (("--fit-overlap", "0.01"), "At 1% (`campaign reduce"),
                                           ((), "At 0.1%, the default")])
def test_reduce_gives_the_pages_systems_tables(tmp_path, option, after):
    campaign_cli("reduce", *STORES, *option, "--out", tmp_path, check=True)
    printed = _tables((tmp_path / "systems.md").read_text())
    assert [_doc_table(SYSTEMS, after)] == printed


@pytest.mark.slow
def test_the_experiment_gives_the_pages_summary_and_the_readme_row(tmp_path):
    run = subprocess.run([sys.executable, str(ROOT / "experiments" / "universality.py"), *map(str, STORES)],
                         capture_output=True, text=True, check=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    out = run.stdout
    summary = out[out.index("## Every window"):]
    rows, common = _tables(summary)[:2]
    assert rows == _doc_table(rows[0], "## Fitted at one distance")
    assert common == _doc_table(common[0], "## Fitted at one distance")
    # the README's row per window: beta_Z of the four systems and the test of one value, as printed
    readme = (ROOT / "README.md").read_text()
    table = next(t for t in _tables(readme) if t[0].startswith("| fitted over | beta_Z: alpha = 2"))
    cells = lambda line: [c.strip() for c in line.split("|")[1:-1]]  # noqa: E731
    by_window, window = {}, None
    for r in map(cells, rows[2:]):
        window = r[0] or window
        by_window.setdefault(window, {})[r[1]] = r
    shared = {cells(line)[0]: cells(line) for line in common[2:]}
    names = {"every energy": "every energy", "overlaps <= 1%": "typical overlap <= 0.01",
             "overlaps <= 0.3%": "typical overlap <= 0.003", "overlaps <= 0.1% (default)": "typical overlap <= 0.001"}
    assert [cells(line)[0] for line in table[2:]] == list(names)
    for line in table[2:]:
        c = cells(line)
        w = by_window[names[c[0]]]
        assert c[1:5] == [w[s][4] for s in ("default", "hertz", "alpha3", "poly20")]
        assert c[6:9] == [w[s][3] for s in ("default", "hertz", "alpha3")]
        mean, _, p = shared[names[c[0]]][1:]
        assert c[5] == (f"no (p = {p})" if float(p) < 0.05 else f"{mean} (p = {p})")
