"""The release metadata agree: the package version (``campaign.__version__``, the installed
distribution, ``campaign --version``, the ``package_version`` a run writes into its store),
CITATION.cff, CHANGELOG.md's latest entry and the store format it names; LICENSE is the MIT
text. The rule behind the versions: docs/DEVELOPMENT.md, "Versions and the changelog"."""

import datetime
import json
import re
from importlib import metadata
from pathlib import Path

import h5py
import pytest
import yaml

import campaign
from campaign import cli
from campaign.storage.store import FORMAT_VERSION, SCHEMA

ROOT = Path(__file__).resolve().parents[2]
SEMVER = re.compile(r"^(0|[1-9]\d*)\.(0|[1-9]\d*)\.(0|[1-9]\d*)$")
#: a released entry's heading: ``## [X.Y.Z] - YYYY-MM-DD`` (Keep a Changelog); ``[Unreleased]`` is not one
HEADING = re.compile(r"^## \[(?P<version>[^\]]+)\] - (?P<date>\d{4}-\d{2}-\d{2})\s*$", re.M)


def _changelog():
    """The released entries of CHANGELOG.md, newest first: dicts of version, date, body, and the
    store format and schema named in the body's first paragraph."""
    text = (ROOT / "CHANGELOG.md").read_text()
    heads = list(HEADING.finditer(text))
    assert heads, "CHANGELOG.md has no released entry (## [X.Y.Z] - YYYY-MM-DD)"
    entries = []
    for k, m in enumerate(heads):
        end = heads[k + 1].start() if k + 1 < len(heads) else len(text)
        # the next heading of level 2 (a later [Unreleased] or link section) also ends the body
        nxt = re.search(r"^## ", text[m.end():end], re.M)
        body = text[m.end(): m.end() + nxt.start()] if nxt else text[m.end():end]
        first = body.strip().split("\n\n")[0]
        fmt = re.search(r"[Ss]tore format (\d+)", first)
        schema = re.search(r"schema `([^`]+)`", first)
        entries.append({"version": m.group("version"), "date": m.group("date"), "body": body,
                        "format": int(fmt.group(1)) if fmt else None,
                        "schema": schema.group(1) if schema else None})
    return entries


def _citation():
    return yaml.safe_load((ROOT / "CITATION.cff").read_text())


def _key(version):
    m = SEMVER.match(version)
    assert m, f"{version!r} is not MAJOR.MINOR.PATCH"
    return tuple(int(x) for x in m.groups())


def test_package_version_is_semver():
    _key(campaign.__version__)


def test_changelog_latest_entry_is_the_package_version():
    latest = _changelog()[0]
    assert latest["version"] == campaign.__version__, (
        f"CHANGELOG.md's latest entry is {latest['version']}, the package is {campaign.__version__}: "
        "add an entry for the new version (docs/DEVELOPMENT.md, 'Versions and the changelog')")
    datetime.date.fromisoformat(latest["date"])


def test_changelog_latest_entry_names_the_current_store_format():
    latest = _changelog()[0]
    assert latest["format"] == FORMAT_VERSION and latest["schema"] == SCHEMA, (
        f"CHANGELOG.md's latest entry ({latest['version']}) names store format {latest['format']}, schema "
        f"{latest['schema']!r}; the code writes format {FORMAT_VERSION}, schema {SCHEMA!r}: a format change "
        "needs a new minor version and its entry")


def test_changelog_entries_follow_the_rule():
    """Newest first, dates never increasing, every entry names its store format, and a change of
    the store's format or schema between two entries is a minor (or major) version."""
    entries = _changelog()
    for e in entries:
        assert e["format"] is not None and e["schema"], f"{e['version']}: no 'Store format N, schema `...`'"
    for new, old in zip(entries, entries[1:]):
        kn, ko = _key(new["version"]), _key(old["version"])
        assert kn > ko, f"{new['version']} listed above {old['version']}"
        assert new["date"] >= old["date"], f"{new['version']} dated before {old['version']}"
        if (new["format"], new["schema"]) != (old["format"], old["schema"]):
            assert kn[2] == 0 and kn[:2] != ko[:2], (
                f"{new['version']} changes the store format ({old['format']} -> {new['format']}) but is "
                "not a minor version")
        assert "What to do" in new["body"] or new is entries[-1], f"{new['version']}: no 'What to do'"


def test_citation_is_cff_1_2_and_names_the_version():
    cff = _citation()
    for key in ("cff-version", "message", "title", "authors"):  # required by CFF 1.2
        assert cff.get(key), f"CITATION.cff: no {key!r}"
    assert cff["cff-version"] == "1.2.0"
    assert all(isinstance(a, dict) and (a.get("name") or a.get("family-names")) for a in cff["authors"])
    assert str(cff["version"]) == campaign.__version__
    assert str(cff["date-released"]) == _changelog()[0]["date"]
    assert cff["license"] == "MIT"


def test_citation_references_the_paper():
    refs = _citation().get("references") or []
    papers = [r for r in refs if r.get("type") == "article"]
    assert len(papers) == 1, "CITATION.cff: one article among the references (Ramola & Chakraborty)"
    paper = papers[0]
    assert paper["title"] in (ROOT / "README.md").read_text()  # the paper the README says it reproduces
    assert [(a["given-names"], a["family-names"]) for a in paper["authors"]] == [
        ("Kabir", "Ramola"), ("Bulbul", "Chakraborty")]


# The MIT licence as published by the Open Source Initiative (https://opensource.org/license/mit),
# less the copyright line, whitespace-normalised.
MIT = """Permission is hereby granted, free of charge, to any person obtaining a copy of this software and
associated documentation files (the "Software"), to deal in the Software without restriction, including
without limitation the rights to use, copy, modify, merge, publish, distribute, sublicense, and/or sell
copies of the Software, and to permit persons to whom the Software is furnished to do so, subject to the
following conditions: The above copyright notice and this permission notice shall be included in all
copies or substantial portions of the Software. THE SOFTWARE IS PROVIDED "AS IS", WITHOUT WARRANTY OF
ANY KIND, EXPRESS OR IMPLIED, INCLUDING BUT NOT LIMITED TO THE WARRANTIES OF MERCHANTABILITY, FITNESS FOR
A PARTICULAR PURPOSE AND NONINFRINGEMENT. IN NO EVENT SHALL THE AUTHORS OR COPYRIGHT HOLDERS BE LIABLE
FOR ANY CLAIM, DAMAGES OR OTHER LIABILITY, WHETHER IN AN ACTION OF CONTRACT, TORT OR OTHERWISE, ARISING
FROM, OUT OF OR IN CONNECTION WITH THE SOFTWARE OR THE USE OR OTHER DEALINGS IN THE SOFTWARE."""


def test_license_is_the_mit_text():
    text = (ROOT / "LICENSE").read_text()
    first, _, rest = text.strip().partition("\n")
    assert first.strip() == "MIT License"
    copyright_line = re.search(r"^Copyright \(c\) (\d{4}(-\d{4})?) (.+)$", text, re.M)
    assert copyright_line, "LICENSE: no 'Copyright (c) YEAR HOLDER' line"
    body = text[copyright_line.end():]
    assert " ".join(body.split()) == " ".join(MIT.split())
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^license = \{text = "MIT"\}', pyproject, re.M)


def test_pyproject_reads_the_version_from_the_package():
    """One source of truth: pyproject.toml has no version of its own."""
    tomllib = pytest.importorskip("tomllib")
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" not in data["project"] and "version" in data["project"]["dynamic"]
    assert data["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "campaign.version.__version__"}


def test_installed_distribution_has_the_package_version():
    # A source tree's own jamming_campaign.egg-info (a build's by-product, on sys.path when pytest
    # runs from the checkout) is not an installation; what pip installed is.
    dists = [d for d in metadata.distributions(name="jamming-campaign")
             if Path(d.locate_file("")).resolve() != ROOT]
    if not dists:
        pytest.skip("jamming-campaign is not installed (run from a source tree)")
    dist = dists[0]  # the one importlib.metadata.version() reports
    if dist.version != campaign.__version__:
        direct = json.loads(dist.read_text("direct_url.json") or "{}")
        if direct.get("dir_info", {}).get("editable"):
            pytest.skip(f"editable install made at version {dist.version}; its metadata is frozen at install "
                        f"time: pip install -e . again to record {campaign.__version__}")
    assert dist.version == campaign.__version__


def test_campaign_version_option(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.split() == ["campaign", campaign.__version__]


def test_a_run_records_the_version_and_the_store_format(tmp_path):
    """One task of the cheap synthetic task function through `campaign run`, inline."""
    spec = tmp_path / "one.yaml"
    spec.write_text("name: one\nseed: 3\ngrid: {N_G: [16], E_G: [1.0e-3], seeds: 1}\nobservables: [scalars]\n")
    out = tmp_path / "one.h5"
    assert cli.main(["run", str(spec), "--out", str(out), "--launcher", "inline", "--quiet",
                     "--task-function", "synthetic"]) == 0
    with h5py.File(out, "r") as f:
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        assert f["tasks/status"][:].tolist() == [1]
    assert attrs["package_version"] == campaign.__version__
    assert int(attrs["format_version"]) == FORMAT_VERSION == _changelog()[0]["format"]
    assert attrs["schema"] == SCHEMA == _changelog()[0]["schema"]
