"""data/newton.h5 (campaigns/newton.yaml, configurations kept) and data/pressure-route.h5
(campaigns/pressure-route.yaml) are complete and sound, and give the tables of docs/NEWTON.md
("What it changes in the packings") and docs/PRESSURE_ROUTE.md ("Equivalence with the O'Hern
route") entry for entry as `campaign reduce` prints them (the commands the pages print, run as a
user runs them)."""

import csv
from pathlib import Path

import pytest

from helpers import campaign_cli as _campaign, complete_and_sound as _complete_and_sound

ROOT = Path(__file__).resolve().parents[2]


def _cells(line: str) -> list:
    return [c.strip() for c in line.split("|")[1:-1]]


def _table(text: str, header: str) -> list:
    """The rows (lists of cells) of the markdown table in ``text`` whose header line starts with ``header``."""
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith(header))
    rows = []
    for ln in lines[i + 2:]:
        if not ln.startswith("|"):
            break
        rows.append(_cells(ln))
    return rows


def _variant_row(printed: str, variant: str) -> dict:
    """The row of ``variant`` in the "Variants against" table `campaign reduce` prints: column -> cell."""
    text = printed[printed.index("Variants against"):]
    head = _cells(next(ln for ln in text.splitlines() if ln.startswith("| variant |")))
    row = next(r for r in _table(text, "| variant |") if r[0] == variant)
    return dict(zip(head, row))


def _paired_row(protocols_md: str, variant: str) -> list:
    """The row of ``variant`` in protocols.md's differences from the reference (paired errors)."""
    text = protocols_md[protocols_md.index("Each variant minus"):]
    return next(r for r in _table(text, "| variant | corr |") if r[0] == variant)


def _reduce(tmp_path, store: Path, *extra):
    """`campaign reduce STORE [extra] --out DIR`: what it prints and the directory it wrote."""
    out = tmp_path / store.stem
    run = _campaign("reduce", store, *extra, "--out", out, check=True)
    return run.stdout, out


def _section(path: Path, start: str, end: str) -> str:
    text = path.read_text()
    return text[text.index(start):text.index(end)]


@pytest.mark.slow
def test_newton_store_gives_the_endgame_tables(tmp_path):
    """`campaign reduce data/newton.h5` gives docs/NEWTON.md's packing-by-packing table (the row
    `newton` of "Variants against 'default'") and its N_G -> inf differences (protocols.md, paired)."""
    store = ROOT / "data" / "newton.h5"
    _complete_and_sound(store, 1152)
    printed, out = _reduce(tmp_path, store)
    v = _variant_row(printed, "newton")
    doc = _section(ROOT / "docs" / "NEWTON.md", "## What it changes in the packings", "## Limits")
    table = {r[0]: r[1] for r in _table(doc, "| | endgame - FIRE |")}
    assert table == {
        "E_G / E (where in the window)": v["d(E_G/E)"],
        "A_G": v["dA_G"],
        "Delta Z": v["dDelta_Z"],
        "Psi_O": v["dPsi_O"],
        "contacts - (2 N_G - 1)": v["d(iso excess)"],
        "largest bias / packing-to-packing spread": v["max bias/spread"],
        "cost: force evaluations / seconds": f"{v['cost (FE)']} / {v['cost (s)']}",
    }
    protocols = (out / "protocols.md").read_text()
    assert _table(doc, "| variant | corr |") == [_paired_row(protocols, "newton")]
    # the prose: no difference of the limits beyond 1.3 of its errors, none significant
    pairs = list(csv.DictReader((out / "protocols.csv").open()))
    assert round(max(abs(float(p["z"])) for p in pairs), 1) == 1.3 and "no difference exceeds 1.3" in doc
    assert not any(p["significant"] == "True" for p in pairs)


@pytest.mark.slow
def test_pressure_route_store_gives_the_equivalence_tables(tmp_path):
    """`campaign reduce data/pressure-route.h5 --fit-all` gives docs/PRESSURE_ROUTE.md's table of
    paired deviations, its N_G -> inf differences (protocols.md, paired) and the N = 512 fits it
    quotes (table.md)."""
    store = ROOT / "data" / "pressure-route.h5"
    _complete_and_sound(store, 640)
    printed, out = _reduce(tmp_path, store, "--fit-all")
    v = _variant_row(printed, "pressure")
    doc = _section(ROOT / "docs" / "PRESSURE_ROUTE.md", "## Equivalence with the O'Hern route",
                   "## Status of the 2x target")
    table = {r[0]: r[1] for r in _table(doc, "| quantity | pressure - ohern |")}
    assert table == {
        "force evaluations (summed over the same packings)": f"ratio {v['cost (FE)']}",
        "E_G / E (where in the window)": v["d(E_G/E)"],
        "A_G": v["dA_G"],
        "Delta Z": v["dDelta_Z"],
        "Psi_O": v["dPsi_O"],
        "isostatic excess (contacts)": v["d(iso excess)"],
    }
    protocols = (out / "protocols.md").read_text()
    assert _table(doc, "| variant | corr |") == [_paired_row(protocols, "pressure")]
    fits = (out / "table.md").read_text()
    d = _cells(next(ln for ln in fits[fits.index("Variant `default`"):].splitlines() if ln.startswith("| 512 |")))
    p = _cells(next(ln for ln in fits[fits.index("Variant `pressure`"):].splitlines() if ln.startswith("| 512 |")))
    quoted = " ".join(doc.split())
    assert (f"N = 512: A_G* {p[1]} against {d[1]}, beta_E {p[2]} against {d[2]}, beta_Z {p[4]} against {d[4]}; "
            f"Psi_O* {p[5]} against {d[5]})") in quoted
