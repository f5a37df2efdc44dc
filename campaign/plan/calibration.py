"""What a packing costs on one core: the calibrated model, its constants and their file.

**The form.** The mean seconds of one packing of N disks at E_G, made from random positions by
FIRE alone (the O'Hern search, then its analysis), on one core:

    ln t_FIRE = c0 + a x + a2 x^2 + (g0 + g1 x) l,
    x = ln(N / 1024),   l = ln(1 + L / L0),   L = max(0, log10(E_ref / E2)),   E_ref = 1e-3,

where E2 = ``harmonic_energy(E_G, alpha)`` = (alpha E_G / 2)^(2/alpha) is the harmonic energy of
the same typical overlap (E_G itself for alpha = 2): L counts the decades below 1e-3 of how
close to jamming a packing is, whatever its potential. N^(a + a2 x): the exponent in N grows
with N (FIRE needs more steps as N grows, each costs O(N)); (1 + L/L0)^(g0 + g1 x): every decade
closer to jamming costs more, and more so at large N (the energy exponent grows with N). A
fixed L0 (chosen by the calibration, a profile over a grid) keeps the form linear in the other
constants. Chosen on 1924 FIRE packings (N_G 64..4096, E_G 1e-3..1e-15): residuals of the cell
means 0.12 in ln t, against 0.23-0.41 for the same law without the x^2 term, with an energy
exponent independent of N, or in (1 + L).

Other protocols multiply it by measured factors, each log-linear in the same features:

    the Newton endgame      ln F = e0 + e1 x + (e2 + e3 x) max(0, L - 8)  (independent packings)
    a ladder step (FIRE)    ln F = d0 + d1 x + (d2 + d3 x) L              (the child of a ladder: it
    a ladder step (endgame) ln F = h0 + h1 x + (h2 + h3 x) L               starts from its parent's packing)

against t_FIRE at the same (N, E_G). The endgame costs a constant factor (above 1) down to
E2 = 1e-11 (``ENDGAME_HINGE``, 8 decades) and falls by a factor per decade below, faster at large N
(FIRE's slow tail near jamming is what it removes); a ladder step's factor falls with every decade
(chosen on 186 packings of each, N_G 256..4096, E_G 1e-3..1e-15: weighted residuals 0.22, 0.29,
0.31 against 0.27, 0.30, 0.36 with the l of FIRE's law). Ladders one and two decades apart were
measured; no dependence on the spacing was resolved (the chains' scatter is larger). ``endgame: auto`` takes the factor of what it resolves to
(``campaign.plan.spec.auto_endgame``). The force tolerance and the halving search multiply by
fixed factors measured in docs/SPEED_ACCURACY.md (``TOLERANCE_FACTOR``, ``SEARCH_FACTOR``);
other settings (minimizer cg, route pressure, window) are priced as FIRE.

**The uncertainty** of a campaign's total T = sum of its packings' means: the constants'
covariance propagated to T (each block independent), the packings' own scatter (``sigma_task``:
their relative variance within a cell is e^s^2 - 1, so sum n t^2 (e^s^2 - 1) / T^2, a ladder's
chain of one seed counted as one packing: its rungs share their history), and ``sigma_systematic``
(what the held-out validation showed beyond both: another day, another load, kernels changed
since the calibration); the interval is T e^(+-sigma), sigma the three added in quadrature.
It knows this machine: on another, re-run ``campaign calibrate`` (its level moves, its shape
should not).

**The file** (JSON, ``campaign calibrate`` writes it): the packaged default
``campaign/plan/cost_calibration.json``, else the file named by ``CAMPAIGN_COST_CALIBRATION``,
else (for one command) ``--calibration FILE``. A file that is not one is refused (UserError,
exit 2) naming what is wrong.
"""

from __future__ import annotations

import json
import math
import os
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from campaign.errors import UserError
from campaign.plan.spec import auto_endgame, harmonic_energy

SCHEMA = "jamming-campaign/cost-calibration"
SCHEMA_VERSION = 1
#: the environment variable naming a calibration file that replaces the packaged one
ENV = "CAMPAIGN_COST_CALIBRATION"
PACKAGED = "cost_calibration.json"
E_REF = 1e-3
N_REF = 1024
MAX_FILE_BYTES = 1 << 20

#: each block of constants and what multiplies them (``_features``), in the file's order
BLOCKS = {
    "fire": ("c0", "a", "a2", "g0", "g1"),
    "endgame": ("e0", "e1", "e2", "e3"),
    "ladder": ("d0", "d1", "d2", "d3"),
    "ladder_endgame": ("h0", "h1", "h2", "h3"),
}

#: cost against the force tolerance, relative to 1e-6: force evaluations of docs/SPEED_ACCURACY.md
#: (N_G 64..256, 810 packings per tolerance), interpolated in log10(tolerance), constant beyond
TOLERANCE_FACTOR = ((1e-9, 1.081), (1e-7, 1.025), (1e-6, 1.0), (1e-4, 0.935), (1e-3, 0.760), (1e-2, 0.405))
#: core-seconds per disk per force evaluation of a packing, when a calibration does not give its own
#: (``disk_force_evaluation_seconds``): FIRE packings of this project's 2-core machine, the O'Hern search
#: and the analysis spread over the force evaluations (docs/PRECISION.md, "Costs")
DISK_FE_SECONDS = 5.0e-8
#: cost of a search rule relative to the secant search (docs/SPEED_ACCURACY.md: halving 1.36)
SEARCH_FACTOR = {"halving": 1.36}


def tolerance_factor(tol: float) -> float:
    pts = TOLERANCE_FACTOR
    if tol <= pts[0][0]:
        return pts[0][1]
    for (t0, f0), (t1, f1) in zip(pts, pts[1:]):
        if tol <= t1:
            w = (math.log10(tol) - math.log10(t0)) / (math.log10(t1) - math.log10(t0))
            return f0 + w * (f1 - f0)
    return pts[-1][1]


def decades(E: float, exponent: float = 2.0) -> float:
    """L: decades of the harmonic-equivalent energy below E_ref (0 above it)."""
    return max(0.0, math.log10(E_REF / harmonic_energy(E, exponent)))


#: decades below E_ref (E2 = 1e-11) under which the Newton endgame's factor starts to fall
ENDGAME_HINGE = 8.0


def _features(block: str, x: float, L: float, L0: float) -> np.ndarray:
    if block == "fire":
        l = math.log1p(L / L0)
        return np.array([1.0, x, x * x, l, x * l])
    if block == "endgame":
        h = max(0.0, L - ENDGAME_HINGE)
        return np.array([1.0, x, h, x * h])
    return np.array([1.0, x, L, x * L])  # ladder, ladder_endgame


def _kind(protocol, N, E, exponent, parent_E):
    """Which blocks price this packing: ("fire",) plus the factor of its protocol, if any."""
    proto = dict(protocol or {})
    endgame = proto.get("endgame", "none")
    if endgame == "auto":
        endgame = auto_endgame(N, E, exponent)
    child = parent_E is not None and proto.get("start") == "ladder"
    if child:
        return "ladder_endgame" if endgame == "newton" else "ladder"
    return "endgame" if endgame == "newton" else None


def _fixed_factor(protocol) -> float:
    proto = dict(protocol or {})
    return tolerance_factor(float(proto.get("force_tolerance", 1e-6))) * SEARCH_FACTOR.get(proto.get("search"), 1.0)


@dataclass(frozen=True)
class Estimate:
    """A total of seconds on one core, and its 68% interval."""
    seconds: float
    low: float
    high: float
    sigma: float  # of ln(total)

    def hours(self) -> str:
        """``1.4 core-hours (0.9 - 2.1, 68%)``."""
        return f"{_g(self.seconds / 3600)} core-hours ({_g(self.low / 3600)} - {_g(self.high / 3600)}, 68%)"


def _g(x: float) -> str:
    return f"{x:.2g}" if x < 10 else f"{x:,.0f}"


@dataclass(frozen=True)
class Calibration:
    L0: float
    blocks: dict                 # name -> (values (k,), covariance (k, k)) as numpy arrays
    sigma_task: float            # scatter of ln t between packings of one cell
    sigma_systematic: float      # beyond the constants' errors and the packings' scatter
    source: str = "<calibration>"
    info: dict = field(default_factory=dict)  # free-form: machine, date, data, load
    # GPU workers (campaign calibrate --gpu): {"device", "threads", "batch", "N": [...], "ratio": [...]},
    # a GPU packing's seconds in a full batch over a CPU core's for the same FIRE steps, per N_G
    gpu: dict | None = None
    # core-seconds per disk per force evaluation of a packing (search and analysis spread over its
    # steps): what a precision campaign's rounds price a packing at from its force evaluations
    # (campaign.precision.allocation); None: DISK_FE_SECONDS
    disk_fe_seconds: float | None = None
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def disk_force_evaluation_seconds(self) -> float:
        return DISK_FE_SECONDS if self.disk_fe_seconds is None else self.disk_fe_seconds

    # ------------------------------------------------------------------ the model
    def _terms(self, N, E, protocol=None, exponent=2.0, parent_E=None):
        x = math.log(N / N_REF)
        L = decades(E, exponent)
        out = [("fire", _features("fire", x, L, self.L0))]
        kind = _kind(protocol, N, E, exponent, parent_E)
        if kind is not None:
            out.append((kind, _features(kind, x, L, self.L0)))
        return out

    def log_seconds(self, N, E, protocol=None, exponent=2.0, parent_E=None) -> float:
        s = math.log(_fixed_factor(protocol))
        for block, f in self._terms(N, E, protocol, exponent, parent_E):
            s += float(self.blocks[block][0] @ f)
        return s

    def seconds(self, N, E, protocol=None, exponent=2.0, parent_E=None) -> float:
        """Mean seconds of one packing on one core."""
        key = (int(N), float(E), tuple(sorted(dict(protocol or {}).items())), float(exponent),
               None if parent_E is None else float(parent_E))
        t = self._cache.get(key)
        if t is None:
            t = self._cache[key] = math.exp(self.log_seconds(N, E, protocol, exponent, parent_E))
        return t

    def gpu_seconds(self, N, E, protocol=None, exponent=2.0) -> float | None:
        """GPU seconds of one ``device: gpu`` packing run in a full batch (the CPU's seconds for
        the same FIRE steps times the measured ratio at N, interpolated in log N and held at the
        ends), or None without a GPU calibration."""
        if not self.gpu:
            return None
        cpu = {k: v for k, v in dict(protocol or {}).items() if k not in ("device", "gpu_threads", "gpu_block")}
        ratio = float(np.interp(math.log(N), np.log(self.gpu["N"]), self.gpu["ratio"]))
        return self.seconds(N, E, cpu, exponent) * ratio

    def with_gpu(self, gpu: dict) -> "Calibration":
        """This calibration with the GPU ratios ``gpu`` (``campaign calibrate --gpu``)."""
        return Calibration(L0=self.L0, blocks=self.blocks, sigma_task=self.sigma_task,
                           sigma_systematic=self.sigma_systematic, source=self.source,
                           info=self.info, gpu=gpu, disk_fe_seconds=self.disk_fe_seconds)

    def estimate(self, cells) -> Estimate:
        """The total of ``cells``: (count, N, E, protocol, exponent, parent_E) tuples."""
        total, scatter = 0.0, 0.0
        chains = {}  # a ladder's packings of one seed share their history: their times scatter together
        grads = {b: np.zeros(len(BLOCKS[b])) for b in BLOCKS}
        for n, N, E, protocol, exponent, parent_E in cells:
            t = self.seconds(N, E, protocol, exponent, parent_E)
            total += n * t
            if dict(protocol or {}).get("start") == "ladder":
                key = (N, tuple(sorted((k, v) for k, v in dict(protocol).items() if k != "endgame")), exponent, n)
                chains[key] = chains.get(key, 0.0) + t
            else:
                scatter += n * t * t
            for block, f in self._terms(N, E, protocol, exponent, parent_E):
                grads[block] += n * t * f
        if total <= 0:
            return Estimate(0.0, 0.0, 0.0, 0.0)
        scatter += sum(key[-1] * chain * chain for key, chain in chains.items())
        var = sum(float(g @ self.blocks[b][1] @ g) for b, g in grads.items()) / total ** 2
        var += scatter * math.expm1(self.sigma_task ** 2) / total ** 2 + self.sigma_systematic ** 2
        sigma = math.sqrt(max(var, 0.0))
        return Estimate(total, total * math.exp(-sigma), total * math.exp(sigma), sigma)

    # ------------------------------------------------------------------ the file
    def to_dict(self) -> dict:
        return {"schema": SCHEMA, "version": SCHEMA_VERSION, "E_ref": E_REF, "N_ref": N_REF, "L0": self.L0,
                "sigma_task": self.sigma_task, "sigma_systematic": self.sigma_systematic,
                **{b: {"names": list(BLOCKS[b]), "values": [float(v) for v in self.blocks[b][0]],
                       "covariance": [[float(v) for v in row] for row in self.blocks[b][1]]} for b in BLOCKS},
                "info": self.info, **({"gpu": self.gpu} if self.gpu else {}),
                **({"disk_force_evaluation_seconds": self.disk_fe_seconds} if self.disk_fe_seconds else {})}

    def save(self, path) -> None:
        text = json.dumps(self.to_dict(), indent=1, allow_nan=False)
        Path(path).write_text(text + "\n")


# ---------------------------------------------------------------------- reading and checking

def machine() -> str:
    """This machine as a calibration records it: the CPU model and the core count (the host name
    left out: the nodes of a cluster are one machine for the cost model)."""
    import os
    import platform

    model = ""
    try:
        with open("/proc/cpuinfo") as fh:
            model = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), "")
    except OSError:
        pass
    return f"{model or platform.processor() or platform.machine()}, {os.cpu_count()} cores"


def calibrated_on(cal) -> str | None:
    """The machine a calibration was made on (its ``info``: ``machine``, or the part of ``host`` in
    parentheses, as older calibrations wrote it), or None where it does not say."""
    info = cal.info or {}
    if info.get("machine"):
        return str(info["machine"])
    host = str(info.get("host", ""))
    if "(" in host and host.endswith(")"):
        return host[host.index("(") + 1:-1]
    return None


def _refuse(source, problem):
    raise UserError(f"{source}: not a usable cost calibration: {problem}. `campaign calibrate` writes one; "
                    f"without --calibration and {ENV} the packaged one is used")


def _number(source, d, key, *, positive=False, nonnegative=False, lo=None, hi=None):
    if key not in d:
        _refuse(source, f"missing key {key!r}")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        _refuse(source, f"{key!r} must be a number, got {type(v).__name__} {v!r}"[:300])
    v = float(v)
    if not math.isfinite(v):
        _refuse(source, f"{key!r} must be finite, got {v!r}")
    if positive and v <= 0:
        _refuse(source, f"{key!r} must be positive, got {v!r}")
    if nonnegative and v < 0:
        _refuse(source, f"{key!r} must not be negative, got {v!r}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        _refuse(source, f"{key!r} must be between {lo:g} and {hi:g}, got {v!r}")
    return v


def _block(source, d, name):
    if name not in d:
        _refuse(source, f"missing key {name!r}")
    b = d[name]
    if not isinstance(b, dict):
        _refuse(source, f"{name!r} must be a mapping with names, values, covariance")
    want = list(BLOCKS[name])
    k = len(want)
    for key in ("names", "values", "covariance"):
        if key not in b:
            _refuse(source, f"missing key {name}.{key}")
    if b["names"] != want:
        _refuse(source, f"{name}.names must be {want}, got {b['names']!r}"[:300])
    values = b["values"]
    if not isinstance(values, list) or len(values) != k:
        _refuse(source, f"{name}.values must be a list of {k} numbers")
    cov = b["covariance"]
    if not isinstance(cov, list) or len(cov) != k or any(not isinstance(r, list) or len(r) != k for r in cov):
        _refuse(source, f"{name}.covariance must be a {k} x {k} list of lists of numbers")
    flat = values + [v for r in cov for v in r]
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in flat):
        _refuse(source, f"{name}: values and covariance must be numbers")
    if not all(math.isfinite(float(v)) for v in flat):
        _refuse(source, f"{name}: values and covariance must be finite")
    vals = np.array(values, dtype=float)
    C = np.array(cov, dtype=float)
    if np.any(np.diag(C) < 0):
        _refuse(source, f"{name}.covariance has a negative variance")
    if not np.allclose(C, C.T, rtol=1e-6, atol=1e-12 * max(1.0, float(np.abs(C).max()))):
        _refuse(source, f"{name}.covariance is not symmetric")
    return vals, C


def from_dict(d, source="<calibration>") -> Calibration:
    """A checked ``Calibration`` from the file's JSON object; UserError naming the first problem."""
    if not isinstance(d, dict):
        _refuse(source, "expected a JSON object")
    if d.get("schema") != SCHEMA:
        _refuse(source, f"'schema' must be {SCHEMA!r}, got {d.get('schema')!r}"[:300])
    version = d.get("version")
    if isinstance(version, bool) or not isinstance(version, int):
        _refuse(source, f"'version' must be an integer, got {version!r}"[:300])
    if version != SCHEMA_VERSION:
        _refuse(source, f"schema version {version} is not known to this program (it reads version "
                        f"{SCHEMA_VERSION}); re-run `campaign calibrate` with this version")
    if _number(source, d, "E_ref", positive=True) != E_REF or _number(source, d, "N_ref", positive=True) != N_REF:
        _refuse(source, f"E_ref and N_ref must be {E_REF:g} and {N_REF}")
    L0 = _number(source, d, "L0", positive=True)
    sigma_task = _number(source, d, "sigma_task", nonnegative=True, hi=5.0)
    sigma_sys = _number(source, d, "sigma_systematic", nonnegative=True, hi=5.0)
    blocks = {b: _block(source, d, b) for b in BLOCKS}
    info = d.get("info", {})
    if not isinstance(info, dict):
        _refuse(source, "'info' must be a mapping")
    disk = (_number(source, d, "disk_force_evaluation_seconds", positive=True)
            if "disk_force_evaluation_seconds" in d else None)
    return Calibration(L0=L0, blocks=blocks, sigma_task=sigma_task, sigma_systematic=sigma_sys,
                       source=source, info=info, gpu=_gpu_block(source, d.get("gpu")), disk_fe_seconds=disk)


def _gpu_block(source, g):
    """The optional GPU ratios, checked: a device name, sizes ascending, positive finite ratios."""
    if g is None:
        return None
    if not isinstance(g, dict) or not isinstance(g.get("device"), str):
        _refuse(source, "'gpu' must be a mapping with a 'device' name, 'N' and 'ratio'")
    N, ratio = g.get("N"), g.get("ratio")
    ok = (isinstance(N, list) and isinstance(ratio, list) and len(N) == len(ratio) >= 1
          and all(isinstance(n, int) and not isinstance(n, bool) and n >= 2 for n in N)
          and all(isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r) and r > 0
                  for r in ratio) and N == sorted(set(N)))
    if not ok:
        _refuse(source, "'gpu' must give 'N' (ascending sizes) and 'ratio' (positive numbers) of equal length")
    return dict(g)


def load(path) -> Calibration:
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            raw = fh.read(MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        raise UserError(f"cost calibration file {str(p)!r} does not exist") from None
    except (IsADirectoryError, PermissionError, OSError) as exc:
        raise UserError(f"cannot read cost calibration file {str(p)!r}: {exc}") from None
    if len(raw) > MAX_FILE_BYTES:
        _refuse(str(p), f"larger than {MAX_FILE_BYTES >> 10} KiB")
    try:
        data = json.loads(raw.decode("utf-8"), parse_constant=lambda c: float("nan"))
    except (UnicodeDecodeError, ValueError) as exc:
        _refuse(str(p), f"not JSON ({exc})")
    return from_dict(data, str(p))


def packaged_text() -> str:
    return resources.files("campaign").joinpath("plan", PACKAGED).read_text()


def packaged() -> Calibration:
    return from_dict(json.loads(packaged_text()), f"{PACKAGED} (packaged)")


_override = threading.local()
_loaded = {}


def _cached(key, make):
    cal = _loaded.get(key)
    if cal is None:
        cal = _loaded[key] = make()
    return cal


def active() -> Calibration:
    """The calibration in force: ``using(path)``'s, else ``$CAMPAIGN_COST_CALIBRATION``'s, else the
    packaged one. A file is read once per process (``using`` reads it again)."""
    path = getattr(_override, "path", None) or os.environ.get(ENV) or None
    if path is None:
        return _cached(("packaged",), packaged)
    return _cached(("file", str(path)), lambda: load(path))


def source_label() -> str:
    """Where the calibration in force comes from, for the command line."""
    cal = active()
    return cal.source


@contextmanager
def using(path):
    """Within the block, ``active()`` is the calibration in ``path`` (None: no change). Refuses a
    bad file at once."""
    if path is None:
        yield active()
        return
    cal = _loaded[("file", str(path))] = load(path)  # read afresh: the file may have been rewritten
    before = getattr(_override, "path", None)
    _override.path = str(path)
    try:
        yield cal
    finally:
        _override.path = before


# ---------------------------------------------------------------------- fitting

#: prior standard deviations of the constants around the base calibration's (a calibration on
#: little data keeps the base's shape and moves its level: another machine is mostly another level)
PRIOR_SD = {"fire": (2.0, 0.25, 0.05, 0.5, 0.25), "endgame": (1.0, 0.3, 0.15, 0.1),
            "ladder": (1.0, 0.3, 0.1, 0.05), "ladder_endgame": (1.0, 0.3, 0.1, 0.05)}
#: the grid of L0 the calibration profiles over
L0_GRID = (1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 10.0, 12.0, 15.0, 20.0)


def neutral() -> Calibration:
    """A rough calibration to start from when there is none (FIRE's law of this machine, factors 1)."""
    fire = np.array([-2.16, 1.6, 0.077, 3.5, 0.56])
    blocks = {"fire": (fire, np.diag(np.square(PRIOR_SD["fire"])))}
    for b in ("endgame", "ladder", "ladder_endgame"):
        blocks[b] = (np.zeros(len(BLOCKS[b])), np.diag(np.square(PRIOR_SD[b])))
    return Calibration(L0=7.0, blocks=blocks, sigma_task=0.4, sigma_systematic=0.15, source="neutral")


@dataclass
class Cell:
    kind: str        # "fire" or a factor block
    group: str       # the store (or run) its packings come from ("" once pooled)
    N: int
    L: float
    D: float         # decades to the ladder parent (1 for others)
    E2: float        # harmonic-equivalent energy
    n: int
    mean: float      # measured mean seconds
    cv2: float       # relative variance of t within the cell (0 for one packing)
    model: float = math.nan  # the fitted model's mean seconds


@dataclass
class Fit:
    calibration: Calibration
    cells: list
    counts: dict     # block -> (cells, packings) it learnt from
    rms: dict        # block -> rms of ln(measured / model) over its cells


def _cells_of(records) -> list:
    """Per (kind, group, N, E2, D) cell: the packings' count, mean seconds and ln-variance."""
    acc = {}
    for N, E, alpha, endgame, parent_E, t, group in zip(records["N"], records["E"], records["exponent"],
                                                          records["endgame"], records["parent_E"],
                                                          records["seconds"], records["group"]):
        if not (t > 0 and math.isfinite(t)):
            continue
        ladder = parent_E == parent_E  # not NaN
        kind = ("ladder_endgame" if endgame == "newton" else "ladder") if ladder else \
            ("endgame" if endgame == "newton" else "fire")
        L = decades(E, alpha)
        D = L - decades(parent_E, alpha) if ladder else 1.0
        key = (kind, str(group), int(N), round(L, 9), round(D, 9))
        a = acc.setdefault(key, [0, 0.0, 0.0, harmonic_energy(E, alpha)])
        a[0] += 1
        a[1] += t
        a[2] += t * t
    cells = []
    for (kind, group, N, L, D), (n, s, s2, e2) in sorted(acc.items()):
        mean = s / n
        cv2 = max(0.0, (s2 - s * mean) / (n - 1)) / mean ** 2 if n > 1 else 0.0
        cells.append(Cell(kind, group, N, L, D, e2, n, mean, cv2))
    return cells


def _bayes(X, y, w, mu0, sd0, s2=None):
    """Weighted least squares with a Gaussian prior (mean mu0, sd sd0): the posterior mean and
    covariance, the residual scale s^2 (per unit weight) estimated from the data when not given."""
    P0 = np.diag(1.0 / np.square(sd0))
    own = s2 is None
    s2 = 0.1 if own else s2
    for _ in range(4 if own else 1):
        A = P0 + (X.T * w) @ X / s2
        beta = np.linalg.solve(A, P0 @ mu0 + (X.T * w) @ y / s2)
        r = y - X @ beta
        if own:
            dof = max(1.0, len(y) - X.shape[1])
            s2 = max(1e-4, float(np.sum(w * r * r) / dof)) if len(y) > X.shape[1] else 0.1
    A = P0 + (X.T * w) @ X / s2
    cov = np.linalg.inv(A)
    return beta, (cov + cov.T) / 2, r


def fit(records, base: Calibration | None = None, *, L0=None, sigma_systematic=None, info=None) -> Fit:
    """Fit the model's constants to finished packings.

    ``records``: a mapping of equal-length sequences: ``N``, ``E`` (target E_G), ``exponent``,
    ``endgame`` (``"none"`` or ``"newton"``, resolved), ``parent_E`` (NaN unless a ladder child),
    ``seconds`` (jam + analysis on one core) and ``group`` (the store or run). Each block is fitted
    to the ln of its cells' means (corrected for the bias of the ln of a mean of few packings),
    weighted by the packings per cell, with a Gaussian prior around ``base``'s constants
    (``PRIOR_SD``); blocks without data keep ``base``'s constants and errors. FIRE's law is fitted
    to every group's FIRE packings pooled per (N, E2); a factor is measured against that law
    (a mean over many seeds: FIRE's rare slow packings, which a campaign pays for, are in it) times
    the level of its own group's FIRE packings (the machine and load its timings saw).
    """
    base = neutral() if base is None else base
    cells = _cells_of(records)
    fire = [c for c in cells if c.kind == "fire"]
    within = [(c.n - 1, c.cv2) for c in fire if c.n > 1]
    dof = sum(k for k, _ in within)
    # the scatter of one packing's time about its cell's mean, as the ln-scatter of a log-normal of
    # the same relative variance (FIRE's slow packings near jamming make it larger than ln t's own)
    sigma_task = (math.sqrt(math.log1p(sum(k * v for k, v in within) / dof)) if dof >= 5
                  else base.sigma_task)
    s2t = sigma_task ** 2

    blocks, counts, rms = dict(base.blocks), {}, {}
    # FIRE: pooled over groups per (N, E2)
    pooled = {}
    for c in fire:
        p = pooled.setdefault((c.N, c.L), [0, 0.0])
        p[0] += c.n
        p[1] += c.n * c.mean
    use_L0 = base.L0 if L0 is None else float(L0)
    if pooled:
        keys = sorted(pooled)
        n = np.array([pooled[k][0] for k in keys], float)
        y = np.log([pooled[k][1] / pooled[k][0] for k in keys]) + np.expm1(s2t) / (2 * n)
        x = np.log(np.array([k[0] for k in keys], float) / N_REF)
        Ls = np.array([k[1] for k in keys])
        mu0, sd0 = base.blocks["fire"][0], np.array(PRIOR_SD["fire"])

        def solve(L0_):
            X = np.stack([_features("fire", xi, Li, L0_) for xi, Li in zip(x, Ls)])
            return _bayes(X, y, n / n.mean(), mu0, sd0)
        if L0 is None and len(set(np.round(Ls, 6))) >= 5 and len(set(x)) >= 3:
            use_L0 = min(L0_GRID, key=lambda L0_: float(np.sum(n * solve(L0_)[2] ** 2)))
        beta, cov, r = solve(use_L0)
        blocks["fire"] = (beta, cov)
        counts["fire"], rms["fire"] = (len(keys), int(n.sum())), float(np.sqrt(np.mean(r * r)))
    cal = Calibration(use_L0, dict(blocks), sigma_task, base.sigma_systematic)
    # the factors: against the fitted FIRE law (a mean over many seeds: FIRE's rare slow packings
    # make the ratio of means, what a campaign pays, smaller than the typical ratio of a few pairs)
    # at the level of FIRE's packings of the same group (the load its timings saw)
    fire_law = cal.blocks["fire"][0]

    def law(c):
        return float(fire_law @ _features("fire", math.log(c.N / N_REF), c.L, use_L0))
    level = {}
    for c in fire:
        m = level.setdefault(c.group, [0.0, 0.0])
        m[0] += c.n * c.mean
        m[1] += c.n * math.exp(law(c))
    level = {g: math.log(a / b) for g, (a, b) in level.items()}
    for block in ("endgame", "ladder", "ladder_endgame"):
        mine = [c for c in cells if c.kind == block]
        if not mine:
            continue
        ys, ws, Xs = [], [], []
        for c in mine:
            ys.append(math.log(c.mean) + math.expm1(s2t) / (2 * c.n) - law(c) - level.get(c.group, 0.0))
            ws.append(float(c.n))
            Xs.append(_features(block, math.log(c.N / N_REF), c.L, use_L0))
        w = np.array(ws)
        beta, cov, r = _bayes(np.array(Xs), np.array(ys), w / w.mean(), base.blocks[block][0],
                              np.array(PRIOR_SD[block]))
        blocks[block] = (beta, cov)
        counts[block], rms[block] = (len(mine), sum(c.n for c in mine)), float(np.sqrt(np.mean(r * r)))
    cal = Calibration(use_L0, blocks, sigma_task,
                      base.sigma_systematic if sigma_systematic is None else float(sigma_systematic),
                      source="fitted", info=dict(info or {}))
    for c in cells:
        proto = {"endgame": "newton"} if c.kind in ("endgame", "ladder_endgame") else {}
        parent = None
        if c.kind.startswith("ladder"):
            proto["start"] = "ladder"
            parent = E_REF / 10 ** (c.L - c.D)
        c.model = cal.seconds(c.N, c.E2, proto, 2.0, parent)
    return Fit(cal, cells, counts, rms)
