"""Campaign specs read: YAML text -> a frozen, completely validated ``Spec`` (``campaign.plan.spec``).

``load_spec(path)`` (or ``parse_spec(text, source)``) reads the YAML with
``yaml.safe_load``, checks every key and value, and raises ``UserError`` listing
*all* the problems found, each with its key path and YAML line::

    ci.yaml:7: grid.E_G[1]: expected a number > 0, got 'small'

A variant overrides protocol keys and, optionally, the ``system`` (key by key over the
spec's: ``box``, ``species`` or ``sizes``, ``potential``) and the energies ``E_G``; each
variant is its own sub-campaign (``Variant.protocol``, ``.system``, ``.E``).

Nothing is defaulted silently except what is documented here: ``system``
defaults to the paper's bidisperse mixture in a unit box, ``protocol`` to
``{window: 0.1, force_tolerance: 1e-6}``, ``observables`` to all of them,
``store`` to no configurations, ``run`` to 2 retries and ``output`` to
``results/<name>.h5``.
"""

from __future__ import annotations

import difflib
import math
import re
from importlib import resources
from pathlib import Path

import yaml

from campaign.errors import UserError
from campaign.plan import targets
from campaign.plan.spec import (CELLS, DEVICES, ENDGAMES, GPU_BLOCK, GPU_THREADS_DEFAULT, MAX_DEPTH, MAX_SPEC_BYTES,
                                MAX_TASKS, MINIMIZERS, NAME_PATTERN, PROTOCOL_DEFAULTS, PROTOCOL_KEYS, REQUIRED_TOP,
                                SEARCH_RULES, STARTS, STOPS, TOP_KEYS, Spec, Species, System, Variant, auto_endgame)
from kernels.names import (DEFAULT_OBSERVABLES, HISTOGRAMS, MAX_POLYDISPERSITY, OBSERVABLES, ROUTES,
                           SIZE_DISTRIBUTIONS, protocol_problem)


# --------------------------------------------------------------------------- loading

def packaged_spec_text(name: str = "quickstart") -> str:
    """The text of a spec shipped inside the package (``campaign/specs/<name>.yaml``)."""
    try:
        return resources.files("campaign").joinpath("specs", f"{name}.yaml").read_text()
    except FileNotFoundError:
        raise UserError(f"no packaged spec named {name!r}") from None


def load_spec(path=None) -> Spec:
    """Read and validate a spec file; ``None`` means the packaged quickstart."""
    if path is None:
        return parse_spec(packaged_spec_text("quickstart"), "quickstart.yaml (packaged)")
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            raw = fh.read(MAX_SPEC_BYTES + 1)
        if len(raw) > MAX_SPEC_BYTES:
            raise UserError(f"spec file {str(p)!r} is larger than {MAX_SPEC_BYTES // 1024} KiB; a campaign "
                            "spec is a few kilobytes (is this the right file?)")
        text = raw.decode("utf-8")
    except FileNotFoundError:
        raise UserError(f"spec file {str(p)!r} does not exist") from None
    except (IsADirectoryError, PermissionError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read spec file {str(p)!r}: {exc}") from None
    return parse_spec(text, str(p))


def _line_map(node, path=(), out=None, dups=None):
    """Key path -> 1-based YAML line, from the composed node tree; also finds duplicate keys."""
    out = {} if out is None else out
    dups = [] if dups is None else dups
    out.setdefault(path, node.start_mark.line + 1)
    if isinstance(node, yaml.MappingNode):
        seen = set()
        for key_node, value_node in node.value:
            key = key_node.value
            if key in seen:
                dups.append((path + (key,), key_node.start_mark.line + 1))
            seen.add(key)
            out[path + (key,)] = key_node.start_mark.line + 1
            _line_map(value_node, path + (key,), out, dups)
            out[path + (key,)] = key_node.start_mark.line + 1
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _line_map(item, path + (i,), out, dups)
    return out, dups


def _fmt_path(path) -> str:
    s = ""
    for p in path:
        s += f"[{p}]" if isinstance(p, int) else (f".{p}" if s else str(p))
    return s or "(top level)"


class _Checker:
    def __init__(self, source, lines, first_gpu_block=False):
        self.source, self.lines, self.errors = source, lines, []
        self.first_gpu_block = first_gpu_block  # parse_spec's: a device: gpu variant without gpu_block

    def err(self, path, message):
        line = None
        for k in range(len(path), -1, -1):
            line = self.lines.get(tuple(path[:k]))
            if line is not None:
                break
        where = f"{self.source}:{line}" if line else self.source
        self.errors.append(f"{where}: {_fmt_path(path)}: {message}")

    # -- typed getters: return the value or None after recording an error
    def mapping(self, value, path, allowed, required=()):
        if not isinstance(value, dict):
            self.err(path, f"expected a mapping with keys {', '.join(allowed)}; got {_show(value)}")
            return None
        for k in value:
            if k not in allowed:
                hint = difflib.get_close_matches(str(k), allowed, n=1)
                extra = f" (did you mean {hint[0]!r}?)" if hint else ""
                self.err(path + (k,), f"unknown key {k!r}{extra}; allowed keys: {', '.join(allowed)}")
        for k in required:
            if k not in value:
                self.err(path, f"missing required key {k!r}")
        return value

    def number(self, value, path, lo=None, hi=None, lo_open=False, hi_open=False, integer=False):
        ok_type = isinstance(value, int) if integer else isinstance(value, (int, float))
        if isinstance(value, bool) or not ok_type:
            self.err(path, f"expected {'an integer' if integer else 'a number'}{_range(lo, hi, lo_open, hi_open)}, "
                           f"got {_show(value)}")
            return None
        if not integer and not math.isfinite(value):
            self.err(path, f"expected a finite number, got {value!r}")
            return None
        bad = ((lo is not None and (value <= lo if lo_open else value < lo))
               or (hi is not None and (value >= hi if hi_open else value > hi)))
        if bad:
            self.err(path, f"value {value!r} out of range: expected {'an integer' if integer else 'a number'}"
                           f"{_range(lo, hi, lo_open, hi_open)}")
            return None
        return int(value) if integer else float(value)

    def string(self, value, path, pattern=None, what="a string"):
        if not isinstance(value, str) or not value:
            self.err(path, f"expected {what}, got {_show(value)}")
            return None
        if pattern is not None and not pattern.match(value):
            self.err(path, f"expected {what}, got {value!r}")
            return None
        return value

    def boolean(self, value, path):
        if not isinstance(value, bool):
            self.err(path, f"expected true or false, got {_show(value)}")
            return None
        return value

    def seq(self, value, path, what, allow_scalar=False):
        if allow_scalar and not isinstance(value, (list, dict)):
            return [value], True
        if not isinstance(value, list):
            self.err(path, f"expected a list of {what}, got {_show(value)}")
            return None, False
        return value, False


def _range(lo, hi, lo_open, hi_open):
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {_num(lo)}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {_num(hi)}")
    return (" " + " and ".join(parts)) if parts else ""


def _num(x) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}"


def _show(value) -> str:
    if value is None:
        return "nothing (null)"
    kind = {dict: "a mapping", list: "a list", str: "the string", bool: "the boolean"}.get(type(value))
    if kind in ("a mapping", "a list"):
        return kind
    return f"{kind} {value!r}" if kind else repr(value)


def _screen(text: str, source: str):
    """Refuse, before anything is built from it, YAML that could make loading expensive:
    anchors and aliases (``&a`` / ``*a``: a few hundred bytes of nested aliases expand to
    billions of nodes), and nesting deeper than ``MAX_DEPTH``. Token by token: linear in
    the text."""
    depth = 0
    opening = (yaml.BlockMappingStartToken, yaml.BlockSequenceStartToken, yaml.FlowMappingStartToken,
               yaml.FlowSequenceStartToken)
    closing = (yaml.BlockEndToken, yaml.FlowMappingEndToken, yaml.FlowSequenceEndToken)
    for tok in yaml.scan(text, Loader=yaml.SafeLoader):
        if isinstance(tok, (yaml.AnchorToken, yaml.AliasToken)):
            kind = "an anchor" if isinstance(tok, yaml.AnchorToken) else "an alias"
            raise UserError(f"{source}:{tok.start_mark.line + 1}: {kind} ({'&' if kind == 'an anchor' else '*'}"
                            f"{tok.value}): YAML anchors and aliases are not accepted in a spec (they can "
                            "make a short file expand to an enormous one); write the values out")
        if isinstance(tok, opening):
            depth += 1
            if depth > MAX_DEPTH:
                raise UserError(f"{source}:{tok.start_mark.line + 1}: mappings and lists nested more than "
                                f"{MAX_DEPTH} deep; a spec needs at most five levels")
        elif isinstance(tok, closing):
            depth -= 1


def parse_spec(text: str, source: str = "<spec>", first_gpu_block: bool = False) -> Spec:
    """Validate the YAML text of a spec completely; raise UserError naming every problem.
    ``first_gpu_block``: a ``device: gpu`` variant's packings are the first GPU block's, which no
    protocol key named (a store written before 0.3.0, ``campaign.storage.layout.stored_spec``);
    else the present block's, ``gpu_block = GPU_BLOCK``."""
    if len(text) > MAX_SPEC_BYTES:
        raise UserError(f"{source}: the spec is larger than {MAX_SPEC_BYTES // 1024} KiB; a campaign spec "
                        "is a few kilobytes")
    try:
        _screen(text, source)
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{source}:{mark.line + 1}" if mark is not None else source
        problem = getattr(exc, "problem", None) or str(exc)
        col = f" (column {mark.column + 1})" if mark is not None else ""
        raise UserError(f"{where}: bad YAML syntax{col}: {problem}") from None
    except ValueError as exc:  # e.g. an integer of more digits than Python converts
        raise UserError(f"{source}: a value cannot be read: {exc}") from None
    except RecursionError:
        raise UserError(f"{source}: nested too deeply") from None
    lines, dups = _line_map(node) if node is not None else ({}, [])
    c = _Checker(source, lines, first_gpu_block)
    for path, line in dups:
        c.errors.append(f"{source}:{line}: {_fmt_path(path)}: duplicate key")
    if data is None:
        raise UserError(f"{source}: the spec is empty; expected a mapping with at least "
                        f"{', '.join(REQUIRED_TOP)}")
    top = c.mapping(data, (), TOP_KEYS, REQUIRED_TOP)
    if top is None:
        raise UserError("\n".join(c.errors))

    name = c.string(top["name"], ("name",), NAME_PATTERN, "a name of letters, digits, '_', '.', '-' "
                    "(at most 64 characters, starting with a letter or digit)") if "name" in top else None
    seed = c.number(top["seed"], ("seed",), lo=0, hi=2**63 - 1, integer=True) if "seed" in top else None
    system = _system(c, top.get("system", {}), ("system",))
    wants_precision = "precision" in top
    N, E, seeds = _grid(c, top.get("grid"), ("grid",), wants_precision) if "grid" in top else ((), (), ())
    base = _protocol(c, top.get("protocol", {}), ("protocol",), allow=PROTOCOL_KEYS)
    variants = _variants(c, top.get("variants", []), ("variants",), base, system, E)
    observables = _observables(c, top.get("observables", list(DEFAULT_OBSERVABLES)), ("observables",))
    if not c.errors:
        _auto_repeats(c, variants, N)
    precision = None
    if wants_precision:
        given = isinstance(top.get("grid"), dict) and "seeds" in top["grid"]
        precision = targets.parse(c, top["precision"], ("precision",), seeds_given=given, N=N,
                                        variants=variants, check_grid=not c.errors)
        if precision is not None:
            seeds = tuple(range(precision.max_seeds))
    bins = _bins(c, top.get("bins", {}), ("bins",), observables)
    configurations = False
    if "store" in top:
        st = c.mapping(top["store"], ("store",), ("configurations",))
        if st is not None and "configurations" in st:
            configurations = c.boolean(st["configurations"], ("store", "configurations"))
    retries = 2
    if "run" in top:
        rn = c.mapping(top["run"], ("run",), ("retries",))
        if rn is not None and "retries" in rn:
            retries = c.number(rn["retries"], ("run", "retries"), lo=0, hi=100, integer=True)
    output = None
    if "output" in top:
        output = c.string(top["output"], ("output",), what="a file path")
    elif name:
        output = f"results/{name}.h5"
    if not c.errors:
        n_tasks = sum(len(v.E) for v in variants) * len(N) * len(seeds)
        if n_tasks > MAX_TASKS:
            c.err(("grid",), f"{n_tasks} tasks is more than the {MAX_TASKS} one store is built for; "
                             "split the campaign into several specs")
    if c.errors:
        raise UserError(f"{len(c.errors)} problem(s) in the spec:\n  " + "\n  ".join(c.errors))
    return Spec(name=name, seed=seed, system=system, N=N, E=E, seeds=seeds, variants=variants,
                observables=observables, bins=bins, configurations=configurations, retries=retries,
                output=output, precision=precision, text=text, source=source)


def _system(c, value, path, base: System | None = None) -> System:
    """The ``system`` mapping over ``base`` (default: the paper's mixture): each key given
    replaces the base's; ``species`` and ``sizes`` replace each other."""
    sysmap = c.mapping(value, path, ("box", "species", "sizes", "potential"))
    base = System() if base is None else base
    if sysmap is None:
        return base
    if "species" in sysmap and "sizes" in sysmap:
        c.err(path + ("sizes",), "give either species (discrete radii) or sizes (a continuous "
                                 "distribution), not both")
    box = base.box
    if "box" in sysmap:
        seq, _ = c.seq(sysmap["box"], path + ("box",), "two box lengths")
        if seq is not None:
            if len(seq) != 2:
                c.err(path + ("box",), f"expected two box lengths [L_x, L_y], got {len(seq)} values")
            else:
                vals = [c.number(v, path + ("box", i), lo=0, lo_open=True) for i, v in enumerate(seq)]
                if None not in vals:
                    box = tuple(vals)
    species, sizes = base.species, base.sizes
    if "species" in sysmap:
        sizes = None
        seq, _ = c.seq(sysmap["species"], path + ("species",), "species")
        if seq is not None:
            if not seq:
                c.err(path + ("species",), "expected at least one species, got an empty list")
            out, names = [], set()
            for i, item in enumerate(seq):
                p = path + ("species", i)
                m = c.mapping(item, p, ("name", "fraction", "radius"), ("name", "fraction", "radius"))
                if m is None or any(k not in m for k in ("name", "fraction", "radius")):
                    continue
                nm = c.string(m["name"], p + ("name",), re.compile(r"^[A-Za-z0-9_]{1,16}$"),
                              "a species name of letters, digits and '_'")
                fr = c.number(m["fraction"], p + ("fraction",), lo=0, hi=1, lo_open=True)
                rd = c.number(m["radius"], p + ("radius",), lo=0, lo_open=True)
                if nm is not None and nm in names:
                    c.err(p + ("name",), f"duplicate species name {nm!r}")
                names.add(nm)
                if None not in (nm, fr, rd):
                    out.append(Species(nm, fr, rd))
            if out and len(out) == len(seq):
                total = math.fsum(s.fraction for s in out)
                if abs(total - 1.0) > 1e-9:
                    c.err(path + ("species",), f"species fractions must add up to 1, they add up to {total!r}")
                else:
                    species = tuple(out)
    elif "sizes" in sysmap:
        p = path + ("sizes",)
        # over a base that has sizes, either key alone overrides it
        given = {} if base.sizes is None else {"distribution": base.sizes[0], "polydispersity": base.sizes[1]}
        m = c.mapping(sysmap["sizes"], p, ("distribution", "polydispersity"),
                      () if given else ("distribution", "polydispersity"))
        if m is not None:
            m = {**given, **m}
        if m is not None and "distribution" in m and "polydispersity" in m:
            name = c.string(m["distribution"], p + ("distribution",),
                            what=f"one of {', '.join(SIZE_DISTRIBUTIONS)}")
            if name is not None and name not in SIZE_DISTRIBUTIONS:
                hint = difflib.get_close_matches(name, SIZE_DISTRIBUTIONS, n=1)
                extra = f" (did you mean {hint[0]!r}?)" if hint else ""
                c.err(p + ("distribution",), f"unknown size distribution {name!r}{extra}; expected one of "
                                             f"{', '.join(SIZE_DISTRIBUTIONS)}")
                name = None
            delta = c.number(m["polydispersity"], p + ("polydispersity",), lo=0, hi=MAX_POLYDISPERSITY,
                             lo_open=True)
            if name is not None and delta is not None:
                sizes = (name, delta)
    exponent = base.exponent
    if "potential" in sysmap:
        pot = c.mapping(sysmap["potential"], path + ("potential",), ("exponent",))
        if pot is not None and "exponent" in pot:
            e = c.number(pot["exponent"], path + ("potential", "exponent"), lo=2.0, hi=3.0)
            exponent = e if e is not None else exponent
    return System(box=box, species=species, exponent=exponent, sizes=sizes)


def _grid(c, value, path, precision=False):
    """``N_G``, ``E_G`` and ``seeds``; with precision targets the seeds are the campaign's to choose
    (``campaign.plan.targets.parse`` refuses them)."""
    g = c.mapping(value, path, ("N_G", "E_G", "seeds"), ("N_G", "E_G") + (() if precision else ("seeds",)))
    if g is None:
        return (), (), ()
    N, E, seeds = (), (), ()
    if "N_G" in g:
        seq, _ = c.seq(g["N_G"], path + ("N_G",), "disk counts", allow_scalar=True)
        if seq is not None:
            vals = [c.number(v, path + ("N_G", i), lo=4, hi=10_000_000, integer=True) for i, v in enumerate(seq)]
            N = _unique_sorted(c, vals, path + ("N_G",))
    if "E_G" in g:
        E = _energies(c, g["E_G"], path + ("E_G",))
    if "seeds" in g:
        raw = g["seeds"]
        if isinstance(raw, dict):
            m = c.mapping(raw, path + ("seeds",), ("start", "count"), ("start", "count"))
            if m is not None and "start" in m and "count" in m:
                s = c.number(m["start"], path + ("seeds", "start"), lo=0, hi=2**40, integer=True)
                n = c.number(m["count"], path + ("seeds", "count"), lo=1, hi=10_000_000, integer=True)
                if s is not None and n is not None:
                    seeds = tuple(range(s, s + n))
        else:
            n = c.number(raw, path + ("seeds",), lo=1, hi=10_000_000, integer=True)
            if n is not None:
                seeds = tuple(range(n))
    return N, E, seeds


def _energies(c, raw, path):
    """``E_G``: a list of energies per grain, or ``{log_range: [lo, hi], per_decade: k}``."""
    if isinstance(raw, dict):
        vals = _log_range(c, raw, path)
        return tuple(vals) if vals else ()
    seq, _ = c.seq(raw, path, "energies per grain", allow_scalar=True)
    if seq is None:
        return ()
    vals = [c.number(v, path + (i,), lo=0, hi=1, lo_open=True, hi_open=True) for i, v in enumerate(seq)]
    return _unique_sorted(c, vals, path)


def _unique_sorted(c, vals, path):
    if not vals:
        c.err(path, "empty: the grid needs at least one value here")
        return ()
    if None in vals:
        return ()
    if len(set(vals)) != len(vals):
        d = sorted({v for v in vals if vals.count(v) > 1})
        c.err(path, f"duplicate values {d}")
        return ()
    return tuple(sorted(vals))


def _log_range(c, raw, path):
    m = c.mapping(raw, path, ("log_range", "per_decade"), ("log_range", "per_decade"))
    if m is None or "log_range" not in m or "per_decade" not in m:
        return None
    seq, _ = c.seq(m["log_range"], path + ("log_range",), "two energies [low, high]")
    k = c.number(m["per_decade"], path + ("per_decade",), lo=1, hi=100, integer=True)
    if seq is None or k is None:
        return None
    if len(seq) != 2:
        c.err(path + ("log_range",), f"expected two energies [low, high], got {len(seq)} values")
        return None
    lo = c.number(seq[0], path + ("log_range", 0), lo=0, hi=1, lo_open=True, hi_open=True)
    hi = c.number(seq[1], path + ("log_range", 1), lo=0, hi=1, lo_open=True, hi_open=True)
    if lo is None or hi is None:
        return None
    if not lo < hi:
        c.err(path + ("log_range",), f"expected low < high, got [{lo!r}, {hi!r}]")
        return None
    steps = math.log10(hi / lo) * k
    if abs(steps - round(steps)) > 1e-6:
        c.err(path, f"log_range [{lo!r}, {hi!r}] does not span a whole number of steps at {k} per decade")
        return None
    a = math.log10(lo)
    out = []
    for i in range(int(round(steps)) + 1):
        x = a + i / k
        out.append(float(f"{10.0 ** x:.12g}"))
    return out


def _protocol(c, value, path, allow, base=None):
    m = c.mapping(value, path, allow)
    out = dict(PROTOCOL_DEFAULTS) if base is None else dict(base)
    if m is None:
        return out
    checks = {
        "window": dict(lo=0, hi=10, lo_open=True),
        "force_tolerance": dict(lo=0, hi=1, lo_open=True, hi_open=True),
        "search_tolerance": dict(lo=0, hi=1, lo_open=True, hi_open=True),
        "delta": dict(lo=0, hi=1, lo_open=True, hi_open=True),
        "phi_start": dict(lo=0, hi=1, lo_open=True, hi_open=True),
        "skin": dict(lo=0, hi=10, lo_open=True),
        "max_search": dict(lo=1, hi=10**9, integer=True),
        "max_steps": dict(lo=1, hi=10**12, integer=True),
        "energy_tolerance": dict(lo=0, hi=1, lo_open=True),
        "gpu_threads": dict(lo=1, hi=1024, integer=True),
    }
    choices = {"search": ("search rule", SEARCH_RULES), "start": ("start", STARTS),
               "minimizer": ("minimizer", MINIMIZERS), "stop": ("stop rule", STOPS),
               "route": ("route", ROUTES), "endgame": ("endgame", ENDGAMES), "cell": ("cell", CELLS),
               "device": ("device", DEVICES)}
    for k, v in m.items():
        if k in checks:
            x = c.number(v, path + (k,), **checks[k])
            if x is not None:
                out[k] = x
        elif k in choices:
            what, allowed = choices[k]
            x = c.string(v, path + (k,), what=f"one of {', '.join(allowed)}")
            if x is not None and x not in allowed:
                c.err(path + (k,), f"unknown {what} {x!r}; expected one of {', '.join(allowed)}")
            elif x is not None:
                out[k] = x
    if out.get("start") == "random":
        del out["start"]  # the default: independent packings keep their ids
    if out.get("stop") == "force":
        del out["stop"]  # the default: packings keep their ids
    if out.get("stop") != "energy" and "energy_tolerance" in out:
        if "energy_tolerance" in m:
            c.err(path + ("energy_tolerance",), "energy_tolerance is only used with stop 'energy'; "
                                                f"got stop {out.get('stop', 'force')!r}")
        del out["energy_tolerance"]  # inherited by a variant that stops on forces: unused
    if out.get("route") == "ohern":
        del out["route"]  # the default route: its packings keep their ids
    if out.get("endgame") == "none":
        del out["endgame"]  # the default: packings keep their ids
    if out.get("cell") == "fixed":
        del out["cell"]  # the default: packings keep their ids
    auto = out.get("endgame") == "auto"  # the Newton endgame where it pays: it runs as "newton"
    problem = protocol_problem(dict(out, endgame="newton") if auto else out, {"endgame": "auto"} if auto else None)
    if problem is not None:
        c.err(path + (problem[0],), problem[1])
    if out.get("device") == "cpu":
        del out["device"]  # the default: packings keep their ids
    if "gpu_threads" in out:
        t = int(out["gpu_threads"])
        if out.get("device") != "gpu":
            c.err(path + ("gpu_threads",), "gpu_threads sets the thread block of device 'gpu'; got device "
                                           f"{out.get('device', 'cpu')!r}")
        elif t & (t - 1):
            c.err(path + ("gpu_threads",), f"gpu_threads must be a power of two (1 ... 1024), got {t}")
        out["gpu_threads"] = t
        if t == GPU_THREADS_DEFAULT:
            del out["gpu_threads"]  # the default block: its packings keep their ids
    if out.get("device") == "gpu":
        if not c.first_gpu_block:
            out["gpu_block"] = GPU_BLOCK
    if out.get("device") == "gpu" and any(k in out for k in ("stop", "route", "endgame", "cell", "start")) \
            or out.get("device") == "gpu" and out.get("minimizer", "fire") != "fire":
        c.err(path + ("device",), "device 'gpu' runs FIRE on the O'Hern route in a fixed cell from random "
                                  "starts: it needs minimizer 'fire', stop 'force', route 'ohern', endgame "
                                  "'none', cell 'fixed' and start 'random', got minimizer "
                                  f"{out.get('minimizer', 'fire')!r}, stop {out.get('stop', 'force')!r}, route "
                                  f"{out.get('route', 'ohern')!r}, endgame {out.get('endgame', 'none')!r}, cell "
                                  f"{out.get('cell', 'fixed')!r}, start {out.get('start', 'random')!r}")
    return out


#: variant keys besides the protocol's
VARIANT_KEYS = ("name", "system", "E_G")


def _variants(c, value, path, base, system, E):
    """The base protocol, system and energies as "default", then each variant: protocol keys,
    a ``system`` mapping and ``E_G`` override the base's (``_protocol``, ``_system``, ``_energies``)."""
    out = [Variant("default", tuple(sorted(base.items())), system, E)]
    seq, _ = c.seq(value, path, "variants")
    if seq is None:
        return tuple(out)
    names = {"default": None}
    for i, item in enumerate(seq):
        p = path + (i,)
        m = c.mapping(item, p, VARIANT_KEYS + PROTOCOL_KEYS, ("name",))
        if m is None or "name" not in m:
            continue
        nm = c.string(m["name"], p + ("name",), NAME_PATTERN, "a variant name of letters, digits, '_', '.', '-'")
        if nm is None:
            continue
        if nm in names:
            c.err(p + ("name",), "duplicate variant name 'default' (the base protocol's name)" if nm == "default"
                  else f"duplicate variant name {nm!r} (also variants[{names[nm]}])")
            continue
        names[nm] = i
        overrides = {k: v for k, v in m.items() if k not in VARIANT_KEYS}
        proto = _protocol(c, overrides, p, allow=VARIANT_KEYS + PROTOCOL_KEYS, base=base)
        vsys = _system(c, m["system"], p + ("system",), base=system) if "system" in m else system
        vE = _energies(c, m["E_G"], p + ("E_G",)) if "E_G" in m else E
        key = tuple(sorted(proto.items()))
        same = [v.name for v in out if v.protocol == key and v.system == vsys]
        if same:
            c.err(p, f"variant {nm!r} has the same effective protocol and system as {same[0]!r}; "
                     "it would repeat the same packings")
            continue
        out.append(Variant(nm, key, vsys, vE))
    return tuple(out)


def _observables(c, value, path):
    seq, _ = c.seq(value, path, "observable names")
    if seq is None:
        return ("scalars",)
    out = []
    for i, v in enumerate(seq):
        nm = c.string(v, path + (i,), what="an observable name")
        if nm is None:
            continue
        if nm not in OBSERVABLES:
            hint = difflib.get_close_matches(nm, list(OBSERVABLES), n=1)
            extra = f" (did you mean {hint[0]!r}?)" if hint else ""
            c.err(path + (i,), f"unknown observable {nm!r}{extra}; known: {', '.join(OBSERVABLES)}")
        elif nm in out:
            c.err(path + (i,), f"duplicate observable {nm!r}")
        else:
            out.append(nm)
    if "scalars" not in out:
        out.insert(0, "scalars")  # always computed (contract): listed or not
    return tuple(sorted(out, key=list(OBSERVABLES).index))


def _bins(c, value, path, observables):
    m = c.mapping(value, path, HISTOGRAMS)
    if m is None:
        return ()
    wanted = {h for o in observables for h in OBSERVABLES[o]}
    out = []
    for name, spec in m.items():
        p = path + (name,)
        if name not in HISTOGRAMS:
            continue  # already reported as an unknown key
        if name not in wanted:
            owner = next(o for o, hs in OBSERVABLES.items() if name in hs)
            c.err(p, f"bins given for histogram {name!r} but observable {owner!r} is not requested")
            continue
        if isinstance(spec, dict):
            r = c.mapping(spec, p, ("range", "count"), ("range", "count"))
            if r is None or "range" not in r or "count" not in r:
                continue
            seq, _ = c.seq(r["range"], p + ("range",), "two numbers [low, high]")
            n = c.number(r["count"], p + ("count",), lo=1, hi=100_000, integer=True)
            if seq is None or n is None:
                continue
            if len(seq) != 2:
                c.err(p + ("range",), f"expected [low, high], got {len(seq)} values")
                continue
            lo = c.number(seq[0], p + ("range", 0))
            hi = c.number(seq[1], p + ("range", 1))
            if lo is None or hi is None:
                continue
            if not lo < hi:
                c.err(p + ("range",), f"expected low < high, got [{lo!r}, {hi!r}]")
                continue
            edges = tuple(float(lo + (hi - lo) * i / n) for i in range(n + 1))
        else:
            seq, _ = c.seq(spec, p, "increasing bin edges (or {range: [lo, hi], count: n})")
            if seq is None:
                continue
            vals = [c.number(v, p + (i,)) for i, v in enumerate(seq)]
            if None in vals:
                continue
            if len(vals) < 2 or any(b <= a for a, b in zip(vals, vals[1:])):
                c.err(p, "expected at least two strictly increasing bin edges")
                continue
            edges = tuple(vals)
        out.append((name, edges))
    return tuple(sorted(out))


def _auto_repeats(c, variants, N):
    """Variants whose packings coincide at some (N, E) once ``endgame: auto`` is resolved (an auto
    variant beside a FIRE or a Newton one): a store holds each packing once, so they are refused."""
    if not any(dict(v.protocol).get("endgame") == "auto" for v in variants):
        return
    owner = {}
    for i, v in enumerate(variants):
        clash = {}
        for n in N:
            for e in v.E:
                key = (v.system, n, e, v.task_protocol(n, e))
                other = owner.setdefault(key, v.name)
                if other != v.name:
                    clash.setdefault(other, []).append((n, e))
        for other, cells in clash.items():
            n, e = cells[0]
            c.err(("variants", i - 1), f"variant {v.name!r} repeats packings of {other!r} at {len(cells)} "
                                       f"(N_G, E_G), e.g. N_G = {n}, E_G = {e:g}, where endgame 'auto' "
                                       f"resolves to {auto_endgame(n, e, v.system.exponent)!r}; a store "
                                       "holds each packing once: drop one of the two, or compare "
                                       "'newton' with FIRE explicitly")
