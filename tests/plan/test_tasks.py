"""Task identity, seeds, order and cost."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from campaign.plan.parse import parse_spec
from campaign.plan.tasks import cost, dispatch_order, expand, task_cost

BASE = """\
name: t
seed: 11
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 3}
variants: [{name: loose, force_tolerance: 1.0e-3}]
"""


def test_ids_are_unique_hex_and_order_is_canonical():
    tasks = expand(parse_spec(BASE))
    assert len(tasks) == 24 and [t.index for t in tasks] == list(range(24))
    assert all(len(t.id) == 32 and int(t.id, 16) >= 0 for t in tasks)
    assert len({t.id for t in tasks}) == 24
    keys = [(0 if t.variant == "default" else 1, t.N, t.E, t.seed) for t in tasks]
    assert keys == sorted(keys)


def test_ids_are_content_addressed():
    a = {(t.variant, t.N, t.E, t.seed): t.id for t in expand(parse_spec(BASE))}
    # more grid points, other observables, another output: existing packings keep their ids
    bigger = BASE.replace("N_G: [16, 32]", "N_G: [16, 32, 64]").replace("seeds: 3", "seeds: 5")
    b = {(t.variant, t.N, t.E, t.seed): t.id for t in expand(parse_spec(bigger + "observables: [scalars]\n"))}
    assert all(b[k] == v for k, v in a.items())
    # a renamed variant is the same packings
    c = {(t.N, t.E, t.seed): t.id for t in expand(parse_spec(BASE.replace("loose", "renamed"))) if t.variant != "default"}
    assert all(a[("loose",) + k] == v for k, v in c.items())
    # the protocol, the system and the seed index are part of the identity
    d = expand(parse_spec(BASE.replace("1.0e-3}", "1.0e-4}")))
    assert {t.id for t in d if t.variant == "loose"}.isdisjoint(a.values())
    e = expand(parse_spec(BASE + "system: {potential: {exponent: 2.5}}\n"))
    assert {t.id for t in e}.isdisjoint(a.values())
    # so is the campaign seed: it changes every packing
    f = expand(parse_spec(BASE.replace("seed: 11", "seed: 12")))
    assert {t.id for t in f}.isdisjoint(a.values())


def test_seeds_shared_by_variants_and_distinct_otherwise():
    tasks = expand(parse_spec(BASE))
    by = {}
    for t in tasks:
        by.setdefault((t.N, t.E, t.seed), set()).add(t.entropy)
    assert all(len(v) == 1 for v in by.values())  # every variant starts from the same state
    entropies = [next(iter(v)) for v in by.values()]
    assert len(set(entropies)) == len(entropies)
    assert all(e[0] == 11 for e in entropies)
    other = expand(parse_spec(BASE.replace("seed: 11", "seed: 12")))
    assert {t.entropy for t in other}.isdisjoint(set(entropies))
    # the streams differ in practice, not only the keys
    draws = {tuple(np.random.default_rng(np.random.SeedSequence(list(e))).integers(0, 2**62, 2)) for e in entropies}
    assert len(draws) == len(entropies)


def test_cost_model_orders_bigger_and_colder_first():
    assert cost(128, 1e-6) > cost(64, 1e-6) > 0
    assert cost(64, 1e-12) > cost(64, 1e-6) > cost(64, 1e-3)
    order = dispatch_order(expand(parse_spec(BASE)))
    costs = [task_cost(t) for t in order]
    assert costs == sorted(costs, reverse=True)
    assert order[0].N == 32 and order[0].E == 1e-6


@settings(max_examples=30, deadline=None)
@given(ns=st.sets(st.integers(4, 5000), min_size=1, max_size=4),
       es=st.sets(st.integers(1, 15), min_size=1, max_size=4), seeds=st.integers(1, 5),
       nvar=st.integers(0, 2))
def test_task_count_is_the_product(ns, es, seeds, nvar):
    variants = "".join(f"  - {{name: v{i}, force_tolerance: 1.0e-{i + 2}}}\n" for i in range(nvar))
    text = (f"name: h\nseed: 1\ngrid:\n  N_G: {sorted(ns)}\n  E_G: [{', '.join(f'1.0e-{k}' for k in sorted(es))}]\n"
            f"  seeds: {seeds}\n" + (f"variants:\n{variants}" if nvar else ""))
    spec = parse_spec(text)
    tasks = expand(spec)
    assert len(tasks) == (1 + nvar) * len(ns) * len(es) * seeds == spec.n_tasks
    assert len({t.id for t in tasks}) == len(tasks)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2 ** 63 - 1), n=st.lists(st.integers(4, 10 ** 6), min_size=1, max_size=3, unique=True),
       e=st.lists(st.floats(1e-300, 0.99), min_size=1, max_size=3, unique=True),
       seeds=st.integers(1, 4), tol=st.floats(1e-14, 1e-2), ladder=st.booleans())
def test_expand_ids_and_seeds_equal_the_reference_hashes(seed, n, e, seeds, tol, ladder):
    """expand assembles the canonical JSON from its parts; it must hash exactly what task_id
    and seed_entropy hash."""
    from campaign.plan.tasks import seed_entropy, task_id

    start = ", start: ladder" if ladder else ""
    energies = ", ".join(f"{x:.17e}" for x in e)  # YAML 1.1 reads a float only with its dot
    spec = parse_spec(f"name: t\nseed: {seed}\ngrid: {{N_G: {n}, E_G: [{energies}], seeds: {seeds}}}\n"
                      f"variants: [{{name: v, force_tolerance: {tol:.17e}{start}}}]\n")
    system = spec.system.canonical()
    for t in expand(spec):
        assert t.id == task_id(system, dict(t.protocol), t.N, t.E, t.seed, spec.seed)
        assert t.entropy == seed_entropy(spec.seed, system, t.N, t.E, t.seed)
