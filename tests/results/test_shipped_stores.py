"""The stores shipped in data/ are complete and sound, and give the numbers the docs quote from them
(the commands the docs print, run as a user runs them)."""

from pathlib import Path

import pytest

from helpers import campaign_cli as _campaign, complete_and_sound as _complete_and_sound, sound as _sound

ROOT = Path(__file__).resolve().parents[2]


def _row(text: str, n: int) -> list:
    """The cells of the table row of size ``n`` in a markdown ``text`` (the first such row)."""
    line = next(ln for ln in text.splitlines() if ln.startswith(f"| {n} |"))
    return [c.strip() for c in line.split("|")[2:-1]]


@pytest.mark.slow
def test_the_8192_store_is_complete_sound_and_gives_the_documented_row(tmp_path):
    """data/paper-8192-cpu.h5 (the chain of docs/CLUSTERS.md): every task done, `campaign verify`
    clean, and `campaign reduce` (default range and --fit-all) gives docs/PAPER.md's 8192 row, entry
    for entry as printed."""
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


def _reduced_rows(tmp_path, name, stores, sizes):
    """`campaign reduce STORES` with the default range and with --fit-all: per size of ``sizes``, the
    table's cells (A_G*(E), beta_E, A_G*(Z), beta_Z, Psi_O*) as printed, bold and marks dropped."""
    out = {}
    for fit, extra in (("default", ()), ("all", ("--fit-all",))):
        _campaign("reduce", *stores, *extra, "--out", tmp_path / f"{name}-{fit}", check=True)
        table = (tmp_path / f"{name}-{fit}" / "table.md").read_text()
        out[fit] = {n: [_bare(c) for c in _row(table, n)[:5]] for n in sizes}
    return out


@pytest.mark.slow
def test_paper_large_store_gives_the_table_to_4096(tmp_path):
    """data/paper-large.h5 (campaigns/paper-large.yaml, no configurations) is complete and sound, and
    docs/PAPER.md's table "To N_G = 4096" (1024, 2048, 4096 and N_G -> inf; default range and every
    energy) is what `campaign reduce data/paper-small.h5 data/paper-large.h5` gives, entry for entry."""
    _complete_and_sound(ROOT / "data" / "paper-large.h5", 624)
    sizes = (1024, 2048, 4096, "N_G -> inf")
    got = _reduced_rows(tmp_path, "to4096", [ROOT / "data" / "paper-small.h5", ROOT / "data" / "paper-large.h5"], sizes)
    text = (ROOT / "docs" / "PAPER.md").read_text()
    doc = text[text.index("### To N_G = 4096"):text.index("### N_G = 8192, on CPUs")]
    for n in sizes:
        c = [_bare(x) for x in _row(doc, n)]   # paper, default, every energy for A_G*(E), beta_E, beta_Z; Psi_O* default, every
        d, a = got["default"][n], got["all"][n]
        assert [c[1], c[2], c[4], c[5], c[7], c[8], c[9], c[10]] == [d[0], a[0], d[1], a[1], d[3], a[3], d[4], a[4]], n


@pytest.mark.slow
def test_the_row_to_infinity_with_8192(tmp_path):
    """The N_G -> inf row with the eighth size (docs/PAPER.md "N_G = 8192, on CPUs") and the README's
    table (1024, 4096, 8192 and N_G -> inf) are what `campaign reduce data/paper-small.h5
    data/paper-large.h5 data/paper-8192-cpu.h5` gives (default range, --fit-all in brackets)."""
    stores = [ROOT / "data" / f"{s}.h5" for s in ("paper-small", "paper-large", "paper-8192-cpu")]
    inf = "N_G -> inf"
    got = _reduced_rows(tmp_path, "to8192", stores, (1024, 4096, 8192, inf))
    d, a = got["default"][inf], got["all"][inf]
    text = (ROOT / "docs" / "PAPER.md").read_text()
    section = text[text.index("### N_G = 8192, on CPUs"):]
    doc = [x.replace("**", "") for x in _row(section, inf)]
    assert doc == ["0.446(1)", f"{d[0]} [{a[0]}]", "0.28(2)", f"{d[1]} [{a[1]}]", "0.446(1)",
                   f"{d[2]} [{a[2]}]", "1.00(1)", f"{d[3]} [{a[3]}]", f"{d[4]} [{a[4]}] (paper 0.369(1))"]
    readme = (ROOT / "README.md").read_text()
    paper = {1024: ("0.4454(2)", "0.284(3)", "1.001(2)", "-"), 4096: ("0.4461(2)", "0.284(3)", "1.001(2)", "-"),
             8192: ("0.4461(4)", "0.284(4)", "1.001(3)", "-"), inf: ("0.446(1)", "0.28(2)", "1.00(1)", "0.369(1)")}
    for n, p in paper.items():
        d, a = got["default"][n], got["all"][n]
        row = [x.replace("**", "") for x in _row(readme, n)]
        assert row == [p[0], d[0], p[1], f"{d[1]} [{a[1]}]", p[2], f"{d[3]} [{a[3]}]", p[3], d[4]], n


def _variant_rows(table: str) -> dict:
    """variant -> the rows (N_G or "N_G -> inf" -> cells) of a table.md holding several variants."""
    out, name = {}, None
    for line in table.splitlines():
        if line.startswith("Variant `"):
            name = line.split("`")[1]
        elif name and line.startswith("| ") and not line.startswith("| N_G |"):
            cells = [c.strip() for c in line.split("|")[1:-1]]
            key = cells[0] if cells[0].startswith("N_G") else int(cells[0])
            out.setdefault(name, {})[key] = [_bare(c) for c in cells[1:]]
    return out


@pytest.mark.slow
def test_paper_protocol_store_gives_the_protocol_table(tmp_path):
    """data/paper-protocol.h5 (campaigns/paper-protocol.yaml) is complete and sound, and docs/PAPER.md's
    table of section (c) (per variant the exponents per size and A_G*(E_G=0) for N_G -> inf, over every
    energy) is what `campaign reduce data/paper-protocol.h5 --fit-all` gives."""
    store = ROOT / "data" / "paper-protocol.h5"
    _complete_and_sound(store, 900)
    _campaign("reduce", store, "--fit-all", "--out", tmp_path / "red", check=True)
    got = _variant_rows((tmp_path / "red" / "table.md").read_text())
    text = (ROOT / "docs" / "PAPER.md").read_text()
    doc = text[text.index("### (c) The paper's protocol"):text.index("### The half-plane rattler rule")]
    for variant in ("default", "cg", "paper-protocol"):
        line = next(ln for ln in doc.splitlines() if ln.startswith(f"| {variant} |"))
        cells = [c.strip() for c in line.split("|")[1:-1]]
        g = got[variant]
        assert cells[3] == ", ".join(g[n][1] for n in (64, 128, 256)), variant
        assert cells[4] == ", ".join(g[n][3] for n in (64, 128, 256)), variant
        assert cells[5] == g["N_G -> inf"][0], variant
@pytest.mark.slow
@pytest.mark.parametrize("store", sorted(p.name for p in (ROOT / "data").glob("*.h5")))
def test_every_shipped_store_verifies_sound(store):
    """`campaign verify` finds no damage in any store in data/ (a store of an older version
    included: data/gpu-equivalence-large.h5 was written by 0.2.7)."""
    _sound(ROOT / "data" / store)
