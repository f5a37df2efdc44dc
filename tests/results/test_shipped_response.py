"""The response stores shipped in data/ (campaigns/response.yaml and campaigns/response-1024.yaml, no
configurations) are complete and sound, and give docs/RESPONSE.md's tables: `campaign reduce
data/response.h5 data/response-1024.h5`, run as a user runs it, its response_*.csv formatted as the
page prints them."""

import csv
import math
from pathlib import Path

import pytest

from helpers import campaign_cli as _campaign, complete_and_sound as _complete_and_sound

from campaign.results.tables import fmt_err

ROOT = Path(__file__).resolve().parents[2]
STORES = (ROOT / "data" / "response.h5", ROOT / "data" / "response-1024.h5")
SIZES = (64, 128, 256, 512)


@pytest.fixture(scope="module")
def reduced(tmp_path_factory):
    """The directory `campaign reduce data/response.h5 data/response-1024.h5` wrote (the page's command)."""
    out = tmp_path_factory.mktemp("response") / "red"
    _campaign("reduce", *STORES, "--out", out, check=True)
    return out


def _records(path: Path) -> list:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _num(s: str) -> float:
    return float(s) if s != "" else math.nan


def _printed(value, err) -> str:
    """The reducer's ``0.4416(2)``; an undetermined value as the page prints it, ``-``."""
    s = fmt_err(value, err)
    return "-" if s == "--" else s


def _page_rows(start: str, end: str) -> dict:
    """First cell -> the other cells (bold dropped) of the markdown table rows of docs/RESPONSE.md
    between the headings or phrases ``start`` and ``end``."""
    text = (ROOT / "docs" / "RESPONSE.md").read_text()
    i = text.index(start)
    section = text[i:text.index(end, i)]
    rows = {}
    for line in section.splitlines():
        if line.startswith("| ") and not line.startswith("|---"):
            cells = [c.strip().replace("**", "") for c in line.split("|")[1:-1]]
            rows[cells[0]] = cells[1:]
    return rows


@pytest.mark.slow
def test_the_response_stores_are_complete_and_sound():
    """data/response.h5: 2688 tasks done; data/response-1024.h5: 144; `campaign verify` clean."""
    _complete_and_sound(STORES[0], 2688)
    _complete_and_sound(STORES[1], 144)


@pytest.mark.slow
def test_the_fit_table_is_the_reduction(reduced):
    """The exponents of `G ~ p^beta`, `G ~ Delta Z^beta`, `omega_min ~ Delta Z^beta` (N_G 64..512)
    are response_fits.csv's, entry for entry as the reducer prints a value with its error."""
    fits = {(r["variant"], int(r["N_G"]), r["fit"]): r for r in _records(reduced / "response_fits.csv")}
    page = _page_rows("| fit (cells with >= 4 excess contacts)", "(O'Hern, Silbert")
    rows = {"harmonic: `G ~ p^beta`": ("default", "G_vs_p"),
            "harmonic: `G ~ Delta Z^beta`": ("default", "G_vs_dZ"),
            "Hertz: `G ~ p^beta`": ("hertz", "G_vs_p"),
            "Hertz: `G ~ Delta Z^beta`": ("hertz", "G_vs_dZ"),
            "`omega_min ~ Delta Z^beta` harmonic": ("default", "omega_min_vs_dZ"),
            "`omega_min ~ Delta Z^beta` Hertz": ("hertz", "omega_min_vs_dZ")}
    assert set(rows) <= set(page), sorted(page)
    for label, (variant, fit) in rows.items():
        got = [_printed(_num(fits[variant, n, fit]["exponent"]), _num(fits[variant, n, fit]["exponent_err"]))
               for n in SIZES]
        assert page[label][:4] == got, label


@pytest.mark.slow
def test_the_gap_and_force_exponents_are_the_reduction(reduced):
    """gamma, theta, theta_e pooled near jamming (N_G 256, 512, 1024) are response_exponents.csv's."""
    pooled = {(r["variant"], int(r["N_G"])): r for r in _records(reduced / "response_exponents.csv")}
    page = _page_rows("| exponent | N_G = 256", "(Charbonneau, Corwin")
    rows = {"`gamma`, harmonic": ("default", "gamma"), "`gamma`, Hertz": ("hertz", "gamma"),
            "`theta`, all contacts, harmonic": ("default", "theta"),
            "`theta`, all contacts, Hertz": ("hertz", "theta"),
            "`theta_e`, extended, harmonic": ("default", "theta_ext"),
            "`theta_e`, extended, Hertz": ("hertz", "theta_ext")}
    assert set(rows) <= set(page), sorted(page)
    for label, (variant, key) in rows.items():
        got = [_printed(_num(pooled[variant, n][key]), _num(pooled[variant, n][f"{key}_err"])) for n in (256, 512, 1024)]
        assert page[label][:3] == got, label


def _fraction(cells) -> str:
    """The fraction of packings with G < 0 over ``cells`` pooled, to 0.01 (``0`` when none, ``-``
    without cells)."""
    n = sum(int(c["n_moduli"]) for c in cells)
    if n == 0:
        return "-"
    f = sum(_num(c["frac_G_negative"]) * int(c["n_moduli"]) for c in cells) / n
    return "0" if f == 0 else f"{f:.2f}"


@pytest.mark.slow
def test_the_negative_shear_modulus_table_is_the_reduction(reduced):
    """Per harmonic N_G: the fraction of G < 0 below p s^2 N^2 = 0.01 and above 100 (cells pooled),
    and the cell of the largest fraction (the lower pressure on a tie) with its binomial error and
    its p s^2 N^2, from response_cells.csv."""
    cells = [c for c in _records(reduced / "response_cells.csv") if c["variant"] == "default"]
    page = _page_rows("**Negative G in a fixed box.**", "Packings made in a fixed box")
    for n in (64, 128, 256, 512, 1024):
        mine = sorted((c for c in cells if int(c["N"]) == n), key=lambda c: float(c["E"]))
        x = [_num(c["mean_p_s2"]) * n**2 for c in mine]
        frac = [_num(c["frac_G_negative"]) for c in mine]
        i = max(range(len(mine)), key=lambda k: (frac[k], -k))   # the first of the largest
        peak = f"{frac[i]:.2f}({round(_num(mine[i]['frac_G_negative_err']) * 100)})"
        got = [_fraction([c for c, xx in zip(mine, x) if xx < 0.01]), peak, f"{x[i]:.1f}",
               _fraction([c for c, xx in zip(mine, x) if xx > 100])]
        assert page[str(n)] == got, n
