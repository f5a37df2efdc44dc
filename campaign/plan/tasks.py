"""Tasks: identity, seeds, canonical order and cost.

A task is one packing: (variant, N, E, seed index). Its **id** is the blake2b
hash (16 bytes, 32 hex characters) of the canonical JSON of
``{campaign seed, system, effective protocol, N, E, seed}`` (the variant's system: a
variant may override the spec's potential, sizes or box): the description of the packing,
not of its place in a spec. The variant's *name* is not part of it (renaming a
variant keeps its packings); observables, bins and storage options are not
either (they change what is kept of a packing, not the packing; the store's
spec hash already refuses a different spec on an existing file).

Its **seed entropy** is ``[campaign seed, w0, w1, w2, w3]`` where the ``w`` are
32-bit words of the blake2b hash of ``{system, N, E, seed}``; ``kernels.jam``
feeds it to ``numpy.random.SeedSequence``. The protocol is left out on purpose:
every variant of one (N, E, seed) starts from the same initial positions, so
variants are compared packing by packing.

A variant with ``start: ladder`` chains its tasks: the task at each energy but the highest
of the grid has a **parent**, the task of the same variant, N and seed at the next higher
energy, and starts from the parent's packing (``kernels.jam(..., start=...)``). The master
dispatches a task only once its parent is done.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

from campaign.plan.spec import Spec, canonical_json


@dataclass(frozen=True, slots=True)
class Task:
    index: int              # row in the store (canonical order)
    id: str                 # 32 hex characters
    variant: str
    N: int
    E: float
    seed: int               # seed index
    words: int              # the 128-bit seed hash (``entropy`` = campaign seed, then its 32-bit words)
    campaign_seed: int
    protocol: tuple[tuple[str, object], ...]
    parent: int | None = None  # index of the task whose packing this one starts from (ladder)
    parent_E: float | None = None

    @property
    def entropy(self) -> tuple[int, ...]:
        return (self.campaign_seed, *((self.words >> (32 * k)) & 0xFFFFFFFF for k in range(4)))

    def payload(self) -> dict:
        """What a worker needs (small and picklable)."""
        return {"index": self.index, "id": self.id, "variant": self.variant, "N": self.N, "E": self.E,
                "seed": self.seed, "entropy": list(self.entropy), "protocol": dict(self.protocol)}


def task_id(system: dict, protocol: dict, N: int, E: float, seed: int, campaign_seed: int) -> str:
    # The campaign seed is part of the packing's identity: another campaign seed is another packing.
    text = canonical_json({"campaign_seed": int(campaign_seed), "system": system, "protocol": protocol,
                           "N": N, "E": E, "seed": seed})
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def seed_entropy(campaign_seed: int, system: dict, N: int, E: float, seed: int) -> tuple[int, ...]:
    text = canonical_json({"system": system, "N": N, "E": E, "seed": seed})
    digest = hashlib.blake2b(text.encode(), digest_size=16).digest()
    words = [int.from_bytes(digest[i:i + 4], "little") for i in range(0, 16, 4)]
    return (int(campaign_seed), *words)


def _hash_json(prefix: str, suffix: str):
    """blake2b of ``prefix + middle + suffix`` for many middles, the constant parts hashed once."""
    base = hashlib.blake2b(prefix.encode(), digest_size=16)
    tail = suffix.encode()

    def digest(middle: str) -> bytes:
        h = base.copy()
        h.update(middle.encode())
        h.update(tail)
        return h.digest()
    return digest


def expand(spec: Spec) -> list[Task]:
    """Every task of the spec in canonical order: variant (default first), N, E, seed index.

    Ids and seed words are the hashes of ``task_id`` and ``seed_entropy``; the canonical JSON
    is assembled from its constant and varying parts (sorted keys: E, N, campaign_seed,
    protocol, seed, system), which tests/test_tasks.py checks against those functions.
    """
    cseed = int(spec.seed)
    out = []
    n_seeds = len(spec.seeds)
    words = {}
    shared = len(spec.variants) > 1
    for v in spec.variants:
        # each variant's own system (a system variant is another physical system: other ids,
        # other initial states); variants of one system share the seed words
        sys_json = canonical_json(v.system.canonical())
        tail = ',"system":' + sys_json + "}"
        hash_of = _hash_json('{"E":', tail)  # the id and the seed words share the key order
        proto = dict(v.protocol)
        ladder = proto.get("start") == "ladder"
        proto_json = canonical_json(proto)
        for N in spec.N:
            for k, E in enumerate(v.E):
                upper = k + 1 < len(v.E) and ladder
                head = f'{canonical_json(E)},"N":{canonical_json(N)},'
                id_head = f'{head}"campaign_seed":{cseed},"protocol":{proto_json},"seed":'
                for s in spec.seeds:
                    i = len(out)
                    w = words.get((sys_json, N, E, s))
                    if w is None:
                        w = int.from_bytes(hash_of(f'{head}"seed":{canonical_json(s)}'), "little")
                        if shared:
                            words[(sys_json, N, E, s)] = w
                    out.append(Task(index=i, id=hash_of(id_head + canonical_json(s)).hex(), variant=v.name, N=N,
                                    E=E, seed=s, words=w, campaign_seed=cseed, protocol=v.protocol,
                                    parent=i + n_seeds if upper else None,
                                    parent_E=v.E[k + 1] if upper else None))
    return out


# Cost model: seconds of one packing ~ C * N^2 * (1 + decades of E below E_REF) * (1e-6 / tol)^0.1.
# N^2: FIRE needs more steps as N grows, each step costs O(N); every decade of lower energy
# adds grow/shrink steps to the O'Hern search and slower convergence near jamming. C was
# fitted to packings of N = 64..512, E = 1e-4..1e-12 on one core of a 2020s laptop. Only the
# dispatch order (most expensive first) and `campaign validate`'s estimate rely on it.
COST_C = 4.4e-7
E_REF = 1e-3


def cost(N: int, E: float, protocol=None) -> float:
    tol = dict(protocol or {}).get("force_tolerance", 1e-6)
    return COST_C * N ** 2 * (1.0 + max(0.0, math.log10(E_REF / E))) * (1e-6 / tol) ** 0.1


def task_cost(t: Task) -> float:
    if t.parent_E is not None:
        # a ladder step: the decades between the parent's energy and this one
        return max(0.0, cost(t.N, t.E, t.protocol) - cost(t.N, t.parent_E, t.protocol)) + 0.1 * cost(
            t.N, E_REF, t.protocol)
    return cost(t.N, t.E, t.protocol)


def estimate_seconds(tasks) -> float:
    """Estimated CPU seconds for the given tasks (one core per task)."""
    return math.fsum(task_cost(t) for t in tasks)


def dispatch_order(tasks) -> list[Task]:
    """Most expensive first; ties in canonical order (deterministic)."""
    return sorted(tasks, key=lambda t: (-task_cost(t), t.index))


def energy_floor_problems(spec) -> list[str]:
    """Grid energies below what float64 can resolve (``kernels.jamming.energy_floor``).

    ``kernels.jam`` refuses them task by task; checking here turns them into one clear
    refusal before anything runs. Empty when the kernels are not installed.
    """
    try:
        from kernels.jamming import DEFAULTS, energy_floor, initial_state
    except Exception:  # noqa: BLE001 - no kernels, nothing to check against
        return []
    problems = []
    for v in spec.variants:
        system = v.system
        species = tuple((s.fraction, s.radius) for s in system.species)
        proto = dict(v.protocol)
        tol = proto.get("force_tolerance", DEFAULTS["force_tolerance"])
        phi = proto.get("phi_start", DEFAULTS["phi_start"])
        for N in spec.N:
            # a continuous distribution's smallest radius varies from seed to seed: seed 0 stands in
            _, radii, _ = initial_state(N, 0, system.box, species, phi, system.sizes)
            floor = energy_floor(radii, system.box, system.exponent, tol)
            low = [E for E in v.E if E < floor]
            if low:
                where = "grid.E_G" if v.E == spec.E else f"variants[{spec.variants.index(v) - 1}].E_G"
                problems.append(f"{spec.source}: {where}: {', '.join(f'{e:g}' for e in low)} below the lowest "
                                f"energy float64 resolves for N_G = {N} with force_tolerance {tol:g} (variant "
                                f"{v.name!r}): {floor:.3g}; raise E_G, loosen force_tolerance or lower N_G")
    return problems
