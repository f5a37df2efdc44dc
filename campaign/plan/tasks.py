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

A variant with ``endgame: auto`` has each task's protocol resolved for its (N, E) before the id is
computed (``campaign.plan.spec.resolve_protocol``: ``endgame: newton`` or FIRE alone), so that the
task is the explicit one it resolves to: the same id, the same seed, the same packing.

A variant with ``start: ladder`` chains its tasks: the task at each energy but the highest
of the grid has a **parent**, the task of the same variant, N and seed at the next higher
energy, and starts from the parent's packing (``kernels.jam(..., start=...)``). The master
dispatches a task only once its parent is done.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

from campaign.plan import calibration
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
    exponent: float = 2.0   # the variant's potential exponent (what its packings cost depends on it)

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
    protocol, seed, system), which tests/plan/test_tasks.py checks against those functions.
    """
    cseed = int(spec.seed)
    out = []
    n_seeds = len(spec.seeds)
    words = {}
    shared = len(spec.variants) > 1
    for v in spec.variants:
        # each variant's own system (a system variant is another physical system: other ids,
        # other initial states); variants of one system share the seed words
        parents = {E: v.parent_E(E) for E in v.E}
        sys_json = canonical_json(v.system.canonical())
        tail = ',"system":' + sys_json + "}"
        hash_of = _hash_json('{"E":', tail)  # the id and the seed words share the key order
        proto = dict(v.protocol)
        auto = proto.get("endgame") == "auto"
        proto_json = canonical_json(proto)
        protocol = v.protocol
        for N in spec.N:
            for E in v.E:
                parent_E = parents[E]
                upper = parent_E is not None  # its parent is the same seed's packing at parent_E
                if auto:  # resolved per (N, E) before the id: the explicit task it stands for
                    protocol = v.task_protocol(N, E)
                    proto_json = canonical_json(dict(protocol))
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
                                    E=E, seed=s, words=w, campaign_seed=cseed, protocol=protocol,
                                    parent=i + n_seeds if upper else None,
                                    parent_E=parent_E, exponent=v.system.exponent))
    return out


def warm_ups(tasks) -> list:
    """One protocol per distinct choice of compiled kernels among the tasks (minimiser, endgame,
    route, cell): a run's warm-up compiles each once, before any task is timed (variants, and
    ``endgame: auto``, may use several)."""
    out = {}
    for proto in sorted(set(t.protocol for t in tasks), key=repr):
        p = dict(proto)
        out.setdefault(tuple(str(p.get(k)) for k in ("minimizer", "endgame", "route", "cell")), p)
    return list(out.values())


# Cost: the calibrated model of campaign.plan.calibration (its form, constants and their file).
# The master's dispatch order (most expensive first), `campaign validate`'s and `campaign slurm`'s
# estimates and the prior of the learning cost model (campaign.plan.costmodel) rely on it.
E_REF = calibration.E_REF


def cost(N: int, E: float, protocol=None, exponent: float = 2.0, parent_E: float | None = None) -> float:
    """Mean seconds of one packing on one core, by the calibration in force."""
    return calibration.active().seconds(N, E, protocol, exponent, parent_E)


def task_cost(t: Task) -> float:
    # a ladder step starts from its parent's packing (parent_E): the ladder's own factor
    return calibration.active().seconds(t.N, t.E, t.protocol, t.exponent, t.parent_E)


def estimate_seconds(tasks) -> float:
    """Estimated CPU seconds for the given tasks (one core per task)."""
    return math.fsum(task_cost(t) for t in tasks)


def estimate(tasks, cal=None) -> "calibration.Estimate":
    """The tasks' total seconds on one core with its 68% interval (``calibration.Estimate``)."""
    cal = calibration.active() if cal is None else cal
    counts = {}
    for t in tasks:
        key = (t.N, t.E, t.protocol, t.exponent, t.parent_E)
        counts[key] = counts.get(key, 0) + 1
    return cal.estimate((n, *key) for key, n in counts.items())


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
