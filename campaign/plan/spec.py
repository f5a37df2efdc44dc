"""What a campaign spec is: the frozen, validated ``Spec`` (its ``System`` of species or sizes,
potential and box; its ``Variant`` sub-campaigns with their protocols and energies; the grid, the
observables and the store's settings), the protocol keys and choices a spec may name, the rule of
``endgame: auto``, and the histogram edges a spec implies. ``campaign.plan.parse`` makes a
``Spec`` from YAML text, checking every key and value.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from campaign.errors import UserError
from campaign.plan import targets
from kernels.names import CELL_NAMES, MINIMIZER_NAMES, OBSERVABLES, STOP_RULES

#: protocol keys a spec may set (forwarded to ``kernels.jam`` as keyword arguments)
PROTOCOL_DEFAULTS = {"window": 0.1, "force_tolerance": 1e-6}
PROTOCOL_KEYS = ("window", "force_tolerance", "search_tolerance", "phi_start", "max_search", "max_steps",
                 "minimizer", "search", "delta", "skin", "start", "stop", "energy_tolerance", "route",
                 "endgame", "cell", "device", "gpu_threads")
MINIMIZERS = MINIMIZER_NAMES
#: how each minimisation of the O'Hern search ends (``kernels.protocol.ENDGAME_NAMES``): FIRE
#: alone ("none", the default) or FIRE handing over to sparse Newton steps (``kernels.newton``)
ENDGAMES = ("none", "newton", "auto")
SEARCH_RULES = ("secant", "halving", "paper")
#: what ends a minimisation: the force residual, or (cg only) the paper's energy-change rule
STOPS = STOP_RULES
#: where each packing's search starts: "random" (independent packings, the paper's protocol) or
#: "ladder" (the same seed's packing at the next higher energy of the grid, decompressed)
STARTS = ("random", "ladder")
#: the periodic cell (``kernels.names.CELL_NAMES``): "fixed" (default, the spec's box) or "shear" (its
#: tilt and aspect ratio relaxed with the disks at fixed area: the shear-stabilised ensemble)
CELLS = CELL_NAMES
#: what runs a packing's search: "cpu" (default, ``kernels.jam``) or "gpu" (one thread block per
#: packing, ``kernels.gpu``): another trajectory from the same seed, so another task id
DEVICES = ("cpu", "gpu")
#: threads per block of a GPU packing (``gpu_threads``): a power of two; it fixes the order of the
#: block's sums, so it is part of the packing's identity (the default, 256, is left out of it)
GPU_THREADS_DEFAULT = 256
#: the GPU block's trajectories, part of a GPU packing's identity (protocol key ``gpu_block``, set
#: with ``device: gpu``, never written in a spec): 2 since 0.3.0, whose block sums FIRE's |v|^2
#: after the kick from the step's sums and the energy over both sides of each pair (version 1: the
#: first block, before 0.3.0, whose stores record 0.2.7: data/gpu-equivalence*.h5)
GPU_BLOCK = 2

TOP_KEYS = ("name", "seed", "system", "grid", "protocol", "variants", "observables", "bins",
            "store", "run", "output", "precision")
REQUIRED_TOP = ("name", "seed", "grid")
MAX_TASKS = 10_000_000
#: A spec is a few kilobytes; anything much larger is a mistake (or an attack on the parser).
MAX_SPEC_BYTES = 256 * 1024
#: Deepest nesting of mappings and lists a spec may have (the schema needs five levels).
MAX_DEPTH = 16
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


@dataclass(frozen=True)
class Species:
    name: str
    fraction: float
    radius: float


@dataclass(frozen=True)
class System:
    box: tuple[float, float] = (1.0, 1.0)
    species: tuple[Species, ...] = (Species("A", 0.5, 1.4), Species("B", 0.5, 1.0))
    exponent: float = 2.0
    #: a continuous size distribution ``(name, polydispersity)`` instead of ``species``
    sizes: tuple[str, float] | None = None

    def canonical(self) -> dict:
        out = {"box": list(self.box), "potential": {"exponent": self.exponent}}
        if self.sizes is None:
            out["species"] = [[s.name, s.fraction, s.radius] for s in self.species]
        else:
            out["sizes"] = {"distribution": self.sizes[0], "polydispersity": self.sizes[1]}
        return out

    def sizes_label(self) -> str:
        """``bidisperse 1.4:1`` (radii over the smallest; fractions when unequal), ``monodisperse``
        or ``lognormal 20%``."""
        if self.sizes is not None:
            return f"{self.sizes[0]} {100 * self.sizes[1]:.3g}%"
        sp = sorted(self.species, key=lambda s: -s.radius)
        radii = [s.radius for s in sp]
        if max(radii) == min(radii):
            return "monodisperse"
        kind = {2: "bidisperse", 3: "tridisperse"}.get(len(sp), f"{len(sp)} species")
        label = f"{kind} " + ":".join(f"{r / radii[-1]:.3g}" for r in radii)
        if max(s.fraction for s in sp) - min(s.fraction for s in sp) > 1e-9:
            label += ", " + ":".join(f"{100 * s.fraction:.3g}" for s in sp)
        return label

    def label(self) -> str:
        """Short description: ``alpha=2.5, bidisperse 1.4:1`` or ``alpha=2, lognormal 20%``."""
        return f"alpha={self.exponent:g}, {self.sizes_label()}"


@dataclass(frozen=True)
class Variant:
    name: str
    protocol: tuple[tuple[str, Any], ...]  # the effective protocol, sorted by key
    system: System = System()               # the effective system (the spec's, or overridden)
    E: tuple[float, ...] = ()               # the variant's energies (the grid's, or its own E_G)

    @property
    def protocol_dict(self) -> dict:
        """The protocol as ``kernels.jam`` keywords. ``endgame: auto`` reads as ``newton``, the
        endgame it may resolve to (what a warm-up must compile); a task's own protocol is
        ``task_protocol(N, E)``."""
        out = dict(self.protocol)
        if out.get("endgame") == "auto":
            out["endgame"] = "newton"
        return out

    def task_protocol(self, N: int, E: float) -> tuple[tuple[str, Any], ...]:
        """The protocol of this variant's packing of N disks at E: ``endgame: auto`` resolved
        (``resolve_protocol``), every other protocol as it is."""
        return resolve_protocol(self.protocol, N, E, self.system.exponent)

    def parent_E(self, E: float) -> float | None:
        """The energy a ``start: ladder`` step at E starts from: the variant's next higher energy
        (its energies are sorted and distinct); None at the top, or without the ladder."""
        if dict(self.protocol).get("start") != "ladder":
            return None
        higher = [e for e in self.E if e > E]
        return min(higher) if higher else None


@dataclass(frozen=True)
class Spec:
    name: str
    seed: int
    system: System
    N: tuple[int, ...]
    E: tuple[float, ...]
    seeds: tuple[int, ...]
    variants: tuple[Variant, ...]  # "default" first, then the spec's variants in order
    observables: tuple[str, ...]
    bins: tuple[tuple[str, tuple[float, ...]], ...] = ()
    configurations: bool = False
    retries: int = 2
    output: str = ""
    #: precision targets (``campaign.plan.targets``): seeds 0..max_seeds-1 in every cell, given out in
    #: rounds; None for a fixed grid
    precision: "targets.Precision | None" = None
    text: str = field(default="", compare=False)
    source: str = field(default="<spec>", compare=False)
    #: the spec's identity (what decides its tasks and what is stored: ``canonical``), once
    hash: str = field(default="", init=False, compare=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "hash", hashlib.blake2b(canonical_json(self.canonical()).encode(),
                                                         digest_size=16).hexdigest())

    @property
    def histograms(self) -> tuple[str, ...]:
        return tuple(h for o in self.observables for h in OBSERVABLES[o])

    @property
    def n_tasks(self) -> int:
        return sum(len(v.E) for v in self.variants) * len(self.N) * len(self.seeds)

    def canonical(self) -> dict:
        """Everything that decides which tasks exist and what is stored (not output, not run)."""
        return {"name": self.name, "seed": self.seed, "system": self.system.canonical(),
                "grid": {"N_G": list(self.N), "E_G": list(self.E), "seeds": list(self.seeds)},
                # a variant's system only when it overrides the spec's (older specs keep their hash)
                "variants": [[v.name, dict(v.protocol)]
                             + ([v.system.canonical()] if v.system != self.system else [])
                             + ([{"E_G": list(v.E)}] if v.E != self.E else []) for v in self.variants],
                "observables": list(self.observables),
                "bins": {k: list(v) for k, v in self.bins},
                "store": {"configurations": self.configurations},
                # only with precision targets (fixed grids keep their hash): the pilot and the seed range
                **({"precision": self.precision.canonical()} if self.precision is not None else {})}

    def worker_context(self) -> dict:
        """What a worker needs of the spec to run and analyse its tasks (``campaign run``'s
        context, docs/CONTRACTS.md): the systems, the observables, histograms and bins, whether
        configurations are kept."""
        return {"system": self.system.canonical(), "systems": {v.name: v.system.canonical() for v in self.variants},
                "observables": list(self.observables), "histograms": list(self.histograms),
                "bins": {h: list(e) for h, e in self.bins}, "configurations": self.configurations}


# --------------------------------------------------------------------------- endgame: auto

#: ``endgame: auto``: the Newton endgame at (N, E_G) where the measured map says it saves time,
#: FIRE alone elsewhere. Pairs (smallest N, largest harmonic-equivalent energy): a packing of N
#: disks at E_G takes the endgame when, for one pair, N >= n_min and harmonic_energy(E_G) <= e_max:
#: N_G >= 1024 at E2 <= 1e-13, N_G >= 4096 at E2 <= 1e-12. There the endgame's mean time is 0.2-0.8
#: of FIRE's (measured: 0.77 at N = 1024 and 1e-13, 0.54-0.56 at 1e-15..1e-16, 0.62 at 2048 and
#: 1e-13, 0.80 at 4096 and 1e-12, 0.25-0.39 at 4096 and 1e-13..1e-15); above those energies it
#: costs 1.0-1.5 times FIRE's, and below N = 1024 it saves little (0.9 at N = 256, 1e-16):
#: docs/NEWTON.md, campaign/plan/calibration.py. A fixed rule, part of what a spec means: changing
#: it changes the ids of `auto` campaigns (a new minor version).
AUTO_NEWTON = ((1024, 1e-13), (4096, 1e-12))


def harmonic_energy(E: float, exponent: float = 2.0) -> float:
    """The energy per grain of a harmonic (alpha = 2) packing with the typical overlap of a packing
    at E_G of potential exponent alpha: the overlap is ``(alpha E_G / 2)^(1/alpha)``, so
    ``(alpha E_G / 2)^(2/alpha)``; E_G itself for alpha = 2. Closeness to jamming, which sets the
    cost of a packing and where the endgame pays, is a matter of overlaps, not of energies."""
    return (exponent * E / 2.0) ** (2.0 / exponent)


def auto_endgame(N: int, E: float, exponent: float = 2.0) -> str:
    """What ``endgame: auto`` resolves to for a packing of N disks at E_G: ``"newton"`` or ``"none"``
    (``AUTO_NEWTON``)."""
    e2 = harmonic_energy(E, exponent)
    for n_min, e_max in AUTO_NEWTON:
        if N >= n_min and e2 <= e_max * (1.0 + 1e-9):
            return "newton"
    return "none"


def resolve_protocol(protocol, N: int, E: float, exponent: float = 2.0) -> tuple[tuple[str, Any], ...]:
    """A protocol (sorted key-value pairs) with ``endgame: auto`` made concrete for (N, E):
    ``endgame: newton``, or no endgame key (FIRE alone, the default). The task is then the explicit
    one: the same id and the same packing."""
    proto = dict(protocol)
    if proto.get("endgame") != "auto":
        return tuple(sorted(proto.items()))
    if auto_endgame(N, E, exponent) == "newton":
        proto["endgame"] = "newton"
    else:
        del proto["endgame"]
    return tuple(sorted(proto.items()))


def canonical_json(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def histogram_edges(histograms, bins=None) -> dict:
    """The bin edges of each named histogram: the spec's ``bins`` where it gives them, else the
    kernels' defaults (``kernels.analysis.DEFAULT_BINS``), as float64 arrays."""
    try:
        from kernels.analysis import DEFAULT_BINS
    except ImportError as exc:
        raise UserError(f"the analysis kernels are not available in this installation ({exc})") from None
    bins = bins or {}
    out = {}
    for h in histograms:
        edges = bins.get(h, DEFAULT_BINS.get(h))
        if edges is None:
            raise RuntimeError(f"kernels.analysis.DEFAULT_BINS has no entry for histogram {h!r}")
        out[h] = np.asarray(edges, dtype=np.float64)
    return out
