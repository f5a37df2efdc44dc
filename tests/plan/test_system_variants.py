"""Variants that override the system (potential exponent, size distribution, box) or the
energies: each is its own sub-campaign, with the ids of the packings it describes."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from campaign import cli
from campaign.plan.spec import System
from campaign.plan.parse import parse_spec
from campaign.plan.tasks import expand, seed_entropy, task_id

BASE = """\
name: t
seed: 11
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 3}
"""


def _ids(spec, variant=None):
    return {(t.N, t.E, t.seed): t.id for t in expand(spec) if variant is None or t.variant == variant}


def test_system_variant_has_the_ids_of_a_spec_with_that_system():
    spec = parse_spec(BASE + "variants:\n  - {name: hertz, system: {potential: {exponent: 2.5}}}\n"
                             "  - {name: poly, system: {sizes: {distribution: lognormal, polydispersity: 0.2}}}\n")
    hertz = parse_spec(BASE + "system: {potential: {exponent: 2.5}}\n")
    poly = parse_spec(BASE + "system: {sizes: {distribution: lognormal, polydispersity: 0.2}}\n")
    plain = parse_spec(BASE)
    assert _ids(spec, "default") == _ids(plain)          # adding system variants keeps the base's ids
    assert _ids(spec, "hertz") == _ids(hertz)            # the id describes the packing, not the spec
    assert _ids(spec, "poly") == _ids(poly)
    assert set(_ids(spec, "hertz").values()).isdisjoint(_ids(plain).values())  # the exponent changes it
    assert set(_ids(spec, "poly").values()).isdisjoint(_ids(plain).values())
    # and so do the initial states: a system variant does not share the base's seed words
    ent = {(t.variant, t.N, t.E, t.seed): t.entropy for t in expand(spec)}
    assert all(ent[("hertz",) + k] != ent[("default",) + k] for k in _ids(plain))
    assert [t.entropy for t in expand(spec) if t.variant == "hertz"] == [t.entropy for t in expand(hertz)]


def test_unchanged_system_override_keeps_the_ids():
    proto = parse_spec(BASE + "variants: [{name: loose, force_tolerance: 1.0e-4}]\n")
    same = parse_spec(BASE + "variants: [{name: loose, force_tolerance: 1.0e-4, "
                             "system: {potential: {exponent: 2.0}, box: [1.0, 1.0]}}]\n")
    assert _ids(same, "loose") == _ids(proto, "loose")
    assert same.hash == proto.hash                       # nothing changed: the same campaign
    assert same.variants[1].system == same.system
    # protocol variants of one system share their initial states
    ent = {(t.variant, t.N, t.E, t.seed): t.entropy for t in expand(same)}
    assert all(ent[("loose",) + k] == ent[("default",) + k] for k in _ids(same, "default"))


def test_overrides_merge_key_by_key_over_the_base_system():
    spec = parse_spec(BASE + "system: {box: [2.0, 1.0], potential: {exponent: 2.5},\n"
                             "         species: [{name: A, fraction: 0.3, radius: 1.2}, {name: B, fraction: 0.7, radius: 1.0}]}\n"
                             "variants:\n"
                             "  - {name: harm, system: {potential: {exponent: 2.0}}}\n"
                             "  - {name: poly, system: {sizes: {distribution: uniform, polydispersity: 0.1}}}\n"
                             "  - {name: mono, system: {species: [{name: A, fraction: 1.0, radius: 1.0}]}}\n")
    base, harm, poly, mono = (v.system for v in spec.variants)
    assert harm == System(box=(2.0, 1.0), species=base.species, exponent=2.0)
    assert poly.sizes == ("uniform", 0.1) and poly.exponent == 2.5 and poly.box == (2.0, 1.0)
    assert "species" not in poly.canonical() and poly.canonical()["sizes"]["polydispersity"] == 0.1
    assert mono.sizes is None and [s.name for s in mono.species] == ["A"] and mono.exponent == 2.5
    # a variant's species replace a base's continuous sizes, and the other way round
    back = parse_spec(BASE + "system: {sizes: {distribution: uniform, polydispersity: 0.1}}\n"
                             "variants: [{name: bi, system: {species: [{name: A, fraction: 0.5, radius: 1.4}, "
                             "{name: B, fraction: 0.5, radius: 1.0}]}}]\n")
    assert back.variants[1].system == System()


def test_variant_energies_expand_and_chain_within_the_variant():
    spec = parse_spec(BASE + "variants:\n  - {name: a3, system: {potential: {exponent: 3.0}}, "
                             "E_G: {log_range: [1.0e-9, 1.0e-3], per_decade: 1}, start: ladder}\n")
    tasks = expand(spec)
    assert spec.n_tasks == len(tasks) == 2 * 2 * 3 + 7 * 2 * 3
    a3 = [t for t in tasks if t.variant == "a3"]
    assert sorted({t.E for t in a3}) == [10.0 ** -k for k in range(9, 2, -1)]
    assert sorted({t.E for t in tasks if t.variant == "default"}) == [1e-6, 1e-3]
    for t in a3:  # the ladder's parent: same variant, N and seed, the next energy up
        if t.E == 1e-3:
            assert t.parent is None
        else:
            p = tasks[t.parent]
            assert (p.variant, p.N, p.seed) == ("a3", t.N, t.seed) and np.isclose(p.E, t.E * 10)
    # ids of the common energies equal those of a spec with that grid
    alone = parse_spec(BASE.replace("[1.0e-3, 1.0e-6]", "{log_range: [1.0e-9, 1.0e-3], per_decade: 1}")
                       + "system: {potential: {exponent: 3.0}}\nprotocol: {start: ladder}\n")
    assert _ids(spec, "a3") == _ids(alone)
    # the default's energies in the spec hash are untouched; the variant's are recorded
    assert spec.canonical()["variants"][1][-1] == {"E_G": list(spec.variants[1].E)}


@settings(max_examples=25, deadline=None, derandomize=True)
@given(exponent=st.floats(2.0, 3.0, exclude_min=True), dist=st.sampled_from(["uniform", "lognormal"]),
       delta=st.floats(1e-3, 0.5), box=st.floats(0.5, 4.0))
def test_expand_hashes_each_variants_own_system(exponent, dist, delta, box):
    """Every task's id and seed words are the reference hashes of its variant's system."""
    spec = parse_spec(BASE + f"variants:\n  - {{name: a, system: {{potential: {{exponent: {exponent!r}}}}}}}\n"
                             f"  - {{name: b, system: {{sizes: {{distribution: {dist}, polydispersity: {delta!r}}},"
                             f" box: [{box!r}, 1.0]}}}}\n")
    systems = {v.name: v.system.canonical() for v in spec.variants}
    assert systems["b"]["sizes"] == {"distribution": dist, "polydispersity": delta}
    for t in expand(spec):
        s = systems[t.variant]
        assert t.id == task_id(s, dict(t.protocol), t.N, t.E, t.seed, spec.seed)
        assert t.entropy == seed_entropy(spec.seed, s, t.N, t.E, t.seed)


@pytest.mark.parametrize("variant, path, fragment", [
    ("{name: h, system: {potential: {exponent: 1.5}}}", "variants[0].system.potential.exponent", "out of range"),
    ("{name: p, system: {sizes: {distribution: gamma, polydispersity: 0.2}}}",
     "variants[0].system.sizes.distribution", "unknown size distribution 'gamma'"),
    ("{name: p, system: {sizes: {distribution: uniform, polydispersity: 0}}}",
     "variants[0].system.sizes.polydispersity", "out of range"),
    ("{name: p, system: {sizes: {distribution: uniform}}}", "variants[0].system.sizes",
     "missing required key 'polydispersity'"),
    ("{name: p, system: {sizes: [uniform, 0.2]}}", "variants[0].system.sizes", "expected a mapping"),
    ("{name: p, system: {box: [1.0]}}", "variants[0].system.box", "expected two box lengths"),
    ("{name: p, sytem: {box: [1.0, 1.0]}}", "variants[0].sytem", "did you mean 'system'?"),
    ("{name: p, E_G: {log_range: [1.0e-3, 1.0e-9], per_decade: 1}}", "variants[0].E_G.log_range",
     "expected low < high"),
    ("{name: default2, system: {potential: {exponent: 2.0}}}", "variants[0]", "same effective protocol and system"),
])
def test_bad_system_variant_exits_2_naming_the_key_path(tmp_path, capsys, variant, path, fragment):
    p = tmp_path / "s.yaml"
    p.write_text(BASE + f"variants:\n  - {variant}\n")
    assert cli.main(["validate", str(p)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert f"{p}:5: {path}: " in err and fragment in err, err


def test_validate_prints_each_system(tmp_path, capsys):
    p = tmp_path / "s.yaml"
    p.write_text(BASE + "variants:\n  - {name: hertz, system: {potential: {exponent: 2.5}}}\n"
                        "  - {name: poly, system: {sizes: {distribution: lognormal, polydispersity: 0.2}},"
                        " E_G: [1.0e-4]}\n")
    assert cli.main(["validate", str(p)]) == 0
    out = capsys.readouterr().out
    assert "alpha=2, bidisperse 1.4:1" in out and "alpha=2.5, bidisperse 1.4:1" in out
    assert "alpha=2, lognormal 20%" in out and "E_G of poly: 0.0001" in out
    assert "tasks       30 = 5 (variant, E_G) x 2 N_G x 3 seed(s)" in out
