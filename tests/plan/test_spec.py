"""Spec loading and validation: every malformed case exits 2 naming the key path and line."""

import re
from pathlib import Path

import pytest

from campaign import cli
from campaign.plan import tasks
from campaign.errors import UserError
from campaign.plan.parse import load_spec, packaged_spec_text, parse_spec
from kernels.names import DEFAULT_OBSERVABLES

ROOT = Path(__file__).resolve().parents[2]
BAD = sorted((ROOT / "tests" / "bad_specs").glob("*.yaml"))

MINIMAL = """\
name: t
seed: 7
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 3}
"""


def _expectation(path):
    first = path.read_text().splitlines()[0]
    m = re.match(r"# expect: (.*?) \| line (\d+) \| (.*)$", first)
    assert m, f"{path.name}: first line must be '# expect: PATH | line N | FRAGMENT'"
    return m.group(1), int(m.group(2)), m.group(3)


def test_there_is_a_bad_spec_for_each_required_case():
    names = {p.stem for p in BAD}
    for case in ("wrong_type", "out_of_range", "unknown_key", "empty_grid", "duplicate_variants", "bad_syntax"):
        assert case in names


@pytest.mark.parametrize("path", BAD, ids=[p.stem for p in BAD])
def test_bad_spec_exits_2_naming_path_and_line(path, capsys):
    keypath, line, fragment = _expectation(path)
    assert cli.main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert f"{path}:{line}:" in err, err
    if keypath != "(none)":
        assert f":{line}: {keypath}: " in err, err
    assert fragment in err, err


def test_all_problems_are_reported_at_once():
    text = "name: t\nseed: x\ngrid: {N_G: [0], E_G: [2.0], seeds: 1}\nprotocl: {}\n"
    with pytest.raises(UserError) as exc:
        parse_spec(text, "s.yaml")
    msg = str(exc.value)
    assert "4 problem(s)" in msg
    for frag in ("s.yaml:2: seed:", "s.yaml:3: grid.N_G[0]:", "s.yaml:3: grid.E_G[0]:", "s.yaml:4: protocl:"):
        assert frag in msg


def test_minimal_spec_defaults():
    s = parse_spec(MINIMAL)
    assert s.N == (16, 32) and s.E == (1e-6, 1e-3) and s.seeds == (0, 1, 2)
    assert [v.name for v in s.variants] == ["default"]
    assert s.variants[0].protocol_dict == {"window": 0.1, "force_tolerance": 1e-6}
    assert s.observables == DEFAULT_OBSERVABLES
    assert s.system.box == (1.0, 1.0) and s.system.exponent == 2.0
    assert [(x.name, x.fraction, x.radius) for x in s.system.species] == [("A", 0.5, 1.4), ("B", 0.5, 1.0)]
    assert s.output == "results/t.h5" and s.retries == 2 and s.configurations is False
    assert s.n_tasks == 12


ISSUE_EXAMPLE = """\
name: quickstart
seed: 12345                     # campaign seed, mixed into every task's SeedSequence
system:
  box: [1.0, 1.0]
  species: [{name: A, fraction: 0.5, radius: 1.4}, {name: B, fraction: 0.5, radius: 1.0}]
  potential: {exponent: 2.0}
grid:                           # Cartesian product
  N_G: [64, 128]
  E_G: [1.0e-4, 1.0e-8, 1.0e-12] # also {log_range: [1.0e-15, 1.0e-3], per_decade: 1}
  seeds: 4                      # or {start: 100, count: 4}
protocol: {window: 0.1, force_tolerance: 1.0e-6}
variants:                       # optional: named overrides of protocol keys, each its own sub-campaign
  - {name: loose, force_tolerance: 1.0e-3}
observables: [scalars, contact_angles, contact_lengths, connectivity, edge_triangles, void_areas, fictitious, radial_grains, radial_contacts]
store: {configurations: false}
output: results/quickstart.h5
"""


def test_the_issue_example_is_valid():
    s = parse_spec(ISSUE_EXAMPLE)
    assert s.n_tasks == 2 * 2 * 3 * 4
    assert [v.name for v in s.variants] == ["default", "loose"]
    assert s.variants[1].protocol_dict == {"window": 0.1, "force_tolerance": 1e-3}
    assert s.observables == DEFAULT_OBSERVABLES and s.output == "results/quickstart.h5"


def test_quickstart():
    s = load_spec(ROOT / "campaigns" / "quickstart.yaml")
    assert s.N == (64, 128, 256, 512) and s.E == tuple(float(f"1e-{k}") for k in range(12, 3, -1))
    assert s.n_tasks == 2 * 4 * 9 * 4
    assert [v.name for v in s.variants] == ["default", "loose"]


def test_quickstart_is_the_packaged_spec():
    link = ROOT / "campaigns" / "quickstart.yaml"
    assert link.is_symlink() and not Path(link.readlink()).is_absolute()
    assert link.read_text() == packaged_spec_text("quickstart")
    assert load_spec(None) == load_spec(link)


@pytest.mark.parametrize("name", ["ci", "quickstart", "paper"])
def test_shipped_specs_validate(name, capsys):
    assert cli.main(["validate", str(ROOT / "campaigns" / f"{name}.yaml")]) == 0
    out = capsys.readouterr().out
    assert "tasks" in out and "core-hours" in out


def test_paper_spec_covers_the_study():
    s = load_spec(ROOT / "campaigns" / "paper.yaml")
    assert s.N == (128, 256, 512, 1024, 2048, 4096, 8192)
    assert s.E == tuple(float(f"1e-{k}") for k in range(15, 2, -1))


def test_log_range_gives_exact_decades():
    s = parse_spec(MINIMAL.replace("E_G: [1.0e-3, 1.0e-6]", "E_G: {log_range: [1.0e-6, 1.0e-3], per_decade: 2}"))
    assert s.E[0] == 1e-6 and s.E[2] == 1e-5 and s.E[-1] == 1e-3 and len(s.E) == 7
    assert all(b / a == pytest.approx(10 ** 0.5, rel=1e-11) for a, b in zip(s.E, s.E[1:]))


def test_seed_range_and_scalars():
    s = parse_spec(MINIMAL.replace("seeds: 3", "seeds: {start: 100, count: 4}").replace("N_G: [16, 32]", "N_G: 64"))
    assert s.seeds == (100, 101, 102, 103) and s.N == (64,)


def test_spec_hash_ignores_formatting_and_execution_settings():
    a = parse_spec(MINIMAL)
    b = parse_spec("# a comment\nseed: 7\nname: t\ngrid:\n  seeds: 3\n  E_G: [1.0e-6, 0.001]\n  N_G: [32, 16]\n"
                   "run: {retries: 5}\noutput: elsewhere.h5\n")
    assert a.hash == b.hash
    assert parse_spec(MINIMAL.replace("seed: 7", "seed: 8")).hash != a.hash
    assert parse_spec(MINIMAL + "observables: [scalars]\n").hash != a.hash


def test_bins_forms():
    s = parse_spec(MINIMAL + "bins: {z_g: [-0.5, 0.5, 1.5, 2.5], alpha_v: {range: [0, 1], count: 4}}\n")
    assert dict(s.bins) == {"z_g": (-0.5, 0.5, 1.5, 2.5), "alpha_v": (0.0, 0.25, 0.5, 0.75, 1.0)}
    with pytest.raises(UserError, match=r"bins\.z_g: expected at least two strictly increasing"):
        parse_spec(MINIMAL + "bins: {z_g: [1, 1, 2]}\n")


def test_missing_file_is_a_user_error(tmp_path, capsys):
    assert cli.main(["validate", str(tmp_path / "nope.yaml")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_empty_file(tmp_path, capsys):
    p = tmp_path / "e.yaml"
    p.write_text("# nothing\n")
    assert cli.main(["validate", str(p)]) == 2
    assert "empty" in capsys.readouterr().err


def test_energies_below_the_float64_floor_are_refused_before_running(tmp_path, capsys):
    from kernels.jamming import energy_floor, initial_state

    _, radii, _ = initial_state(8192, 0, (1.0, 1.0), ((0.5, 1.4), (0.5, 1.0)), 0.86)
    floor = energy_floor(radii, (1.0, 1.0), 2.0, 1e-6)
    assert 1e-17 < floor < 1e-14  # the regime where the check matters
    p = tmp_path / "low.yaml"
    p.write_text(f"name: low\nseed: 1\ngrid: {{N_G: [64, 8192], E_G: [{float(floor) / 2!r}, 1.0e-6], seeds: 1}}\n")
    assert cli.main(["validate", str(p)]) == 2
    err = capsys.readouterr().err
    assert "N_G = 8192" in err and "N_G = 64" not in err and "grid.E_G" in err
    assert cli.main(["run", str(p), "--out", str(tmp_path / "o.h5")]) == 2
    assert not (tmp_path / "o.h5").exists()
    # a looser tolerance lowers the floor: accepted
    p.write_text(p.read_text() + "protocol: {force_tolerance: 1.0e-4}\n")
    assert cli.main(["validate", str(p)]) == 0


def test_protocol_keys_of_the_kernels():
    s = parse_spec(MINIMAL + "protocol: {search: halving, delta: 0.005, search_tolerance: 1.0e-3}\n")
    assert s.variants[0].protocol_dict["search"] == "halving"
    with pytest.raises(UserError, match=r"protocol\.search: unknown search rule 'bisect'"):
        parse_spec(MINIMAL + "protocol: {search: bisect}\n")


def test_billion_laughs_is_refused_at_once(tmp_path):
    """Eight levels of nine aliases each: 9^8 = 43 million nodes from 600 bytes if expanded."""
    import time

    path = ROOT / "tests" / "bad_specs" / "billion_laughs.yaml"
    t0 = time.monotonic()
    with pytest.raises(UserError, match="anchors and aliases are not accepted"):
        parse_spec(path.read_text(), str(path))
    assert time.monotonic() - t0 < 1.0


def test_a_spec_file_larger_than_the_limit_is_refused(tmp_path, capsys):
    from campaign.plan.spec import MAX_SPEC_BYTES

    p = tmp_path / "big.yaml"
    p.write_text(MINIMAL + "#" * MAX_SPEC_BYTES + "\n")
    assert cli.main(["validate", str(p)]) == 2
    err = capsys.readouterr().err
    assert "larger than 256 KiB" in err and "Traceback" not in err
    p.write_text(MINIMAL + "#" * (MAX_SPEC_BYTES - len(MINIMAL) - 2) + "\n")
    assert cli.main(["validate", str(p)]) == 0


def test_an_integer_of_too_many_digits_is_a_user_error(capsys, tmp_path):
    p = tmp_path / "digits.yaml"
    p.write_text(MINIMAL.replace("seed: 7", "seed: " + "9" * 5000))
    assert cli.main(["validate", str(p)]) == 2
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("path", sorted((ROOT / "campaigns").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_shipped_campaign_validates(path):
    """The specs in campaigns/ parse and keep every (variant, N_G) above its float64 floor."""
    from campaign.plan.tasks import energy_floor_problems, expand

    spec = load_spec(path)
    assert energy_floor_problems(spec) == []
    assert len(expand(spec)) == spec.n_tasks > 0


def test_endgame_none_keeps_the_ids_and_newton_is_part_of_the_identity():
    plain = parse_spec(MINIMAL)
    none = parse_spec(MINIMAL + "protocol: {endgame: none}\n")
    newton = parse_spec(MINIMAL + "protocol: {endgame: newton}\n")
    assert none.variants[0].protocol_dict == plain.variants[0].protocol_dict
    assert newton.variants[0].protocol_dict == dict(plain.variants[0].protocol_dict, endgame="newton")
    ids = lambda s: [t.id for t in tasks.expand(s)]  # noqa: E731
    assert ids(none) == ids(plain) and not set(ids(newton)) & set(ids(plain))
