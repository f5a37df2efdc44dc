"""Numba kernels for jammed disk packings: pure functions of arrays.

Public API (each a checked Python wrapper around private jitted cores):

* ``jam(n, energy, seed, **settings) -> Packing``: O'Hern protocol (kernels.jamming)
* ``analyze(positions, radii, box, observables=None, bins=None, ...) -> Analysis``:
  contact-network analysis (kernels.analysis)
* ``compile_report() -> CompileReport``: the kernels numba compiled in this process and
  those it loaded from its cache (kernels.compiled)

No I/O, no logging, no configuration files and no MPI in this package.
"""

_LAZY = {
    "jam": "kernels.jamming",
    "Packing": "kernels.jamming",
    "analyze": "kernels.analysis",
    "Analysis": "kernels.analysis",
    "compile_report": "kernels.compiled",
    "CompileReport": "kernels.compiled",
}


def __getattr__(name):  # import on first use: keeps `import kernels` cheap
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'kernels' has no attribute {name!r}")


__all__ = sorted(_LAZY)
