"""What numba compiled in this process, and what it loaded from its cache.

``compile_report()`` looks at the numba dispatchers of the ``kernels`` modules already
imported (it imports nothing itself, not even numba) and returns a ``CompileReport``:

* ``compiled``: the kernels (``"module.function"``, e.g. ``"fire._fire_core"``) numba
  compiled in this process, each as often as it compiled a signature; sorted.
* ``loaded``: those it loaded from its cache (``NUMBA_CACHE_DIR``) instead; sorted.

With a warm cache only the kernels called from Python are loaded (``protocol._ohern_fire``,
``network._rotation_core``, ...): the jitted functions they call are part of their cached
code and are neither compiled nor loaded. With a cold cache every kernel a task reaches is
compiled, callees included. A kernel is compiled when a call needs a signature (argument
types) it has not met, so a campaign compiles only what its minimiser, endgame, route and
observables use (``kernels.protocol.OHERN_CORES``, ``kernels.analyze``). Cheap: a walk over
the dispatchers' counters, no compilation, no I/O.

``campaign run`` calls it after its warm-up to say what the warm-up compiled::

    r = kernels.compile_report()
    r.summary()  # 'compiled 31 kernels (cells, fire, network, potential, protocol, space), 0 loaded from the cache'
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

PACKAGE = "kernels"


@dataclass(frozen=True)
class CompileReport:
    """``compiled`` and ``loaded``: sorted tuples of ``"module.function"`` names (module
    relative to ``kernels``), one entry per signature compiled (or loaded from the cache) in
    this process."""

    compiled: tuple = ()
    loaded: tuple = ()

    @property
    def modules(self) -> tuple:
        """The kernel modules with something compiled, sorted (``("fire", "protocol", ...)``)."""
        return tuple(sorted({name.split(".")[0] for name in self.compiled}))

    def summary(self) -> str:
        """One line: how many kernels were compiled (and in which modules), how many loaded."""
        if self.compiled:
            head = f"compiled {len(self.compiled)} kernels ({', '.join(self.modules)})"
        else:
            head = "compiled nothing"
        return f"{head}, {len(self.loaded)} loaded from the cache"


def _dispatchers():
    """``(name, dispatcher)`` of every numba dispatcher defined in an imported kernels module."""
    seen = set()
    for modname, module in sorted(sys.modules.items()):
        if module is None or not (modname == PACKAGE or modname.startswith(PACKAGE + ".")):
            continue
        short = modname[len(PACKAGE) + 1:] or PACKAGE
        for attr, obj in sorted(vars(module).items()):
            # duck typing: a numba Dispatcher (without importing numba here)
            py_func = getattr(obj, "py_func", None)
            if py_func is None or not hasattr(obj, "overloads") or id(obj) in seen:
                continue
            if getattr(py_func, "__module__", None) != modname:
                continue  # imported from another kernels module: reported there
            seen.add(id(obj))
            yield f"{short}.{attr}", obj


def _count(counter, overloads):
    """Signatures of ``counter`` (numba's per-signature hit or miss counts) that produced an
    overload (a miss is also counted when typing fails)."""
    n = 0
    for sig in counter:
        args = tuple(getattr(sig, "args", sig))
        if args in overloads:
            n += 1
    return n


def compile_report() -> CompileReport:
    """The kernels numba compiled in this process and those it loaded from its cache."""
    compiled = []
    loaded = []
    for name, disp in _dispatchers():
        stats = getattr(disp, "stats", None)
        if stats is None:
            continue
        overloads = disp.overloads
        compiled += [name] * _count(stats.cache_misses, overloads)
        loaded += [name] * _count(stats.cache_hits, overloads)
    return CompileReport(compiled=tuple(sorted(compiled)), loaded=tuple(sorted(loaded)))


__all__ = ["CompileReport", "compile_report"]
