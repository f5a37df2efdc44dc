"""docs/GPU.md and docs/SPEED_ACCURACY.md quote `campaign reduce` of stores shipped in data/
(gpu-equivalence.h5, gpu-equivalence-large.h5, speed-accuracy.h5): each store is complete and
sound, and the pages' tables are what the reducer prints, entry for entry (the commands the pages
print, run as a user runs them)."""

import hashlib
import json
import re
from pathlib import Path

import pytest

from helpers import campaign_cli as _campaign, complete_and_sound as _complete_and_sound

ROOT = Path(__file__).resolve().parents[2]


def _cells(line: str) -> list:
    return [c.strip() for c in line.split("|")[1:-1]]


def _table(text: str, header: str) -> list:
    """The rows of the first markdown table in ``text`` whose header line starts with ``header``,
    each a dict from the header's names to the cells as printed."""
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith(header))
    names = _cells(lines[i])
    rows = []
    for ln in lines[i + 2:]:
        if not ln.startswith("|"):
            break
        rows.append(dict(zip(names, _cells(ln))))
    return rows


def _by_variant(rows: list) -> dict:
    """Rows keyed by their first cell, the reference's mark `` (ref)`` dropped."""
    return {next(iter(r.values())).replace(" (ref)", ""): r for r in rows}


def _reduced(tmp_path, store, *extra):
    """`campaign reduce STORE [extra]`: the console's variants table, protocols.md's values per
    variant and differences from the reference, and table.md's rows per variant and size."""
    out = tmp_path / "red"
    run = _campaign("reduce", store, *extra, "--out", out, check=True)
    protocols = (out / "protocols.md").read_text()
    sizes, name = {}, None
    for ln in (out / "table.md").read_text().splitlines():
        if ln.startswith("Variant `"):
            name = ln.split("`")[1]
        elif name and ln.startswith("| ") and not ln.startswith("| N_G |"):
            c = _cells(ln)
            sizes.setdefault(name, {})[c[0]] = c[1:]
    return {"console": _by_variant(_table(run.stdout, "| variant | packings | FE/packing |")),
            "values": _by_variant(_table(protocols[protocols.index("## N_G -> inf per variant"):], "| variant | A_G*")),
            "diffs": _by_variant(_table(protocols, "| variant | corr |")),
            "sizes": sizes}


#: the console's variants-table columns the pages quote: page's name -> console's name
PER_PACKING = {"packings": "packings", "cost (FE)": "cost (FE)", "d(E_G/E)": "d(E_G/E)", "dA_G": "dA_G",
               "dDelta_Z": "dDelta_Z", "dPsi_O": "dPsi_O", "max bias / spread": "max bias/spread"}
QUANTITIES = ("A_G*(E_G=0)", "beta_E", "A_G*(Delta Z=0)", "beta_Z", "Psi_O*", "phi_J", "N_R/N")


def _gpu_section() -> str:
    text = (ROOT / "docs" / "GPU.md").read_text()
    return text[text.index("## Evidence on a CPU machine"):text.index("## The block step")]


def _gpu_per_packing_row(doc: str, store: str, console: dict):
    row = next(r for r in _table(doc, "| store | packings |") if r["store"] == f"`data/{store}`")
    got = console["gpu"]
    assert {k: row[k] for k in PER_PACKING} == {k: got[v] for k, v in PER_PACKING.items()}, store
    assert row["d(contacts)"] == got["d(iso excess)"], store


@pytest.mark.slow
def test_gpu_equivalence_store_gives_gpu_md(tmp_path):
    """data/gpu-equivalence.h5 (campaigns/gpu-equivalence.yaml) is complete and sound, and
    docs/GPU.md's tables are what `campaign reduce data/gpu-equivalence.h5` prints: the block against
    the CPU packing by packing (the variants table), the N_G -> inf rows of both and their paired
    differences (protocols.md); every size's row is the CPU's to the last digit, as the page says."""
    store = ROOT / "data" / "gpu-equivalence.h5"
    _complete_and_sound(store, 864)
    red = _reduced(tmp_path, store)
    doc = _gpu_section()
    _gpu_per_packing_row(doc, "gpu-equivalence.h5", red["console"])
    rows = {r["variant"]: r for r in _table(doc, "| variant | A_G*(E_G=0) |")}
    assert [rows["default (CPU)"][q] for q in QUANTITIES] == [red["values"]["default"][q] for q in QUANTITIES]
    assert [rows["gpu"][q] for q in QUANTITIES] == [red["values"]["gpu"][q] for q in QUANTITIES]
    assert [rows["gpu minus CPU"][q] for q in QUANTITIES] == [red["diffs"]["gpu"][q] for q in QUANTITIES]
    sizes = red["sizes"]
    assert {n: r[:5] for n, r in sizes["gpu"].items() if n != "N_G -> inf"} == \
        {n: r[:5] for n, r in sizes["default"].items() if n != "N_G -> inf"}


def _strip_gpu_block(o):
    if isinstance(o, dict):
        return {k: _strip_gpu_block(v) for k, v in o.items() if k != "gpu_block"}
    return [_strip_gpu_block(v) for v in o] if isinstance(o, list) else o


@pytest.mark.slow
def test_gpu_equivalence_large_store_gives_gpu_md(tmp_path):
    """data/gpu-equivalence-large.h5 (made with 0.2.7) is complete; `campaign verify` finds it sound
    (its stored spec read without the ``gpu_block`` 0.3.0 added hashes to its spec_hash); and
    docs/GPU.md quotes `campaign reduce
    data/gpu-equivalence-large.h5`: its row of the packing-by-packing table, no finite-size fit in
    the default range, and phi_J (the same for both) with its paired difference."""
    import h5py

    from campaign.plan.parse import parse_spec
    from campaign.plan.spec import canonical_json

    store = ROOT / "data" / "gpu-equivalence-large.h5"
    status = json.loads(_campaign("status", store, "--json", check=True).stdout)
    assert (status["done"], status["failed"], status["remaining"]) == (128, 0, 0)
    verify = _campaign("verify", store)
    said = verify.stdout + verify.stderr
    assert verify.returncode == 0 and "no damage" in said, said
    with h5py.File(store, "r") as f:
        text, stored = (x.decode() if isinstance(x, bytes) else str(x) for x in (f.attrs["spec_yaml"], f.attrs["spec_hash"]))
    canonical = _strip_gpu_block(parse_spec(text).canonical())
    assert hashlib.blake2b(canonical_json(canonical).encode(), digest_size=16).hexdigest() == stored
    red = _reduced(tmp_path, store)
    doc = _gpu_section()
    _gpu_per_packing_row(doc, "gpu-equivalence-large.h5", red["console"])
    for v in ("default", "gpu"):
        assert set(red["sizes"][v]["N_G -> inf"][:5]) == {"--"}, v
    phi = red["values"]["default"]["phi_J"]
    assert red["values"]["gpu"]["phi_J"] == phi
    prose = " ".join(doc.split())
    assert f"is phi_J {phi} for both, paired difference {red['diffs']['gpu']['phi_J']}." in prose


def _unbold(cell: str) -> str:
    return cell[2:-2] if len(cell) > 4 and cell.startswith("**") and cell.endswith("**") else cell


@pytest.mark.slow
def test_speed_accuracy_store_gives_the_tables(tmp_path):
    """data/speed-accuracy.h5 (campaigns/speed-accuracy.yaml re-run with 0.3.0, no configurations)
    is complete and sound, and docs/SPEED_ACCURACY.md's tables are what `campaign reduce
    data/speed-accuracy.h5 --fit-all` prints: per variant, the packing-by-packing columns of the
    variants table and the paired differences of A_G*(E_G=0) and beta_E (protocols.md; the reference
    its own values), every variant once; and the table of significant differences lists exactly
    those protocols.md marks. The seconds column is the first run's timing, not checked."""
    store = ROOT / "data" / "speed-accuracy.h5"
    _complete_and_sound(store, 11340)
    red = _reduced(tmp_path, store, "--fit-all")
    text = (ROOT / "docs" / "SPEED_ACCURACY.md").read_text()
    assert "measured packing by packing over 11340 packings" in text
    doc = text[:text.index("## The fast protocol")]
    cols = dict(PER_PACKING, **{"d(contacts - (2N_G-1))": "d(iso excess)", "front": "front"})
    seen = []
    for row in _table(doc, "| variant | packings | cost (FE) |"):
        v = re.search(r"`([^`]+)`", row["variant"]).group(1)
        seen.append(v)
        got = red["console"][v]
        assert {k: _unbold(row[k]) for k in cols} == {k: got[c] for k, c in cols.items()}, v
        if v == "default":
            want = [f"({red['values'][v]['A_G*(E_G=0)']})", f"({red['values'][v]['beta_E']})"]
        else:
            want = [red["diffs"][v]["A_G*(E_G=0)"], red["diffs"][v]["beta_E"]]
        assert [row["dA_G*(E=0)"], row["dbeta_E"]] == want, v
    assert sorted(seen) == sorted(red["console"]) and len(seen) == len(set(seen))
    significant = {(f"`{v}`", q, c[:-3]) for v, r in red["diffs"].items() for q, c in r.items() if c.endswith(" **")}
    listed = [(r["variant"], r["quantity"], r["difference (z, Holm's p)"])
              for r in _table(doc, "| variant | quantity | difference")]
    assert significant and sorted(listed) == sorted(significant) and len(listed) == len(significant)
