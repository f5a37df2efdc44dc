"""The reducer's sections go through one registry: every output lists them in its order, and a
section's result is ``red.<name>``."""

import json

import pytest

from campaign.report.sectionplots import SECTION_FIGURES
from campaign.report.writing import write_outputs
from campaign.results import reduce as R
from campaign.results.sections import Group, Section
from synthetic_store import SyntheticCampaign, write_store


def test_the_registry_names_each_section_once_and_every_order_holds_them_all():
    names = [sec.name for sec in R.SECTIONS]
    assert names == ["tradeoff", "systems", "response", "protocols"]
    assert all(isinstance(sec, Section) for sec in R.SECTIONS)
    for output in (*R.ORDER, "json"):
        assert sorted(sec.name for sec in R.in_order(output)) == sorted(names), output
        assert set(R.ORDER.get(output, ())) <= set(names)
    assert [s.name for s in R.in_order("console")] == ["systems", "tradeoff", "response", "protocols"]
    assert [s.name for s in R.in_order("json")] == names
    assert set(SECTION_FIGURES) <= set(names)


def test_every_section_says_nothing_of_an_empty_result():
    for sec in R.SECTIONS:
        empty = sec.empty()
        assert sec.console(empty) == "" and sec.files(empty) == {} and sec.reduced(empty) == {}, sec.name
        assert all(text == "" for text in sec.tables(empty).values()), sec.name


def test_a_reduction_holds_each_sections_result_under_its_name(tmp_path):
    camp = SyntheticCampaign(N=(64, 128), E=(1e-3, 1e-6, 1e-9, 1e-12), seeds=3, variants=("default", "loose"))
    write_store(tmp_path / "c.h5", camp)
    red = R.reduce_campaign([tmp_path / "c.h5"], R.Settings(n_boot=20))
    assert list(red.sections) == [sec.name for sec in R.SECTIONS]
    assert red.tradeoff is red.sections["tradeoff"] and [r["variant"] for r in red.tradeoff] == ["default", "loose"]
    assert red.protocols.jamming_sizes and set(red.protocols.jamming_limits) == {"default", "loose"}
    with pytest.raises(AttributeError):
        red.variants  # noqa: B018: the records' old name, summary.json's key only
    written = [p.name for p in write_outputs(red, tmp_path / "out")]
    # the reducer's tables, the tables of every reduction (empty or not), summary.json, the sections' own files
    assert written.index("width_scaling.csv") < written.index("variants.csv") < written.index("jamming.csv") \
        < written.index("summary.json") < written.index("protocols.md") < written.index("reduced.h5")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert list(summary) == ["fit_rule", "rows", "extrapolated", "variants", "systems", "jamming", "protocols",
                             "status", "notes"]
    assert summary["protocols"]["jamming"].keys() == red.protocols.jamming_limits.keys()


def test_a_group_without_columns_holds_groups():
    assert Group().columns is None and Group().attrs == {}
