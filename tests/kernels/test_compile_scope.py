"""A task compiles only the kernels its settings call (kernels.protocol.OHERN_CORES, one jitted
O'Hern search per minimiser; kernels.analyze by observable), the result does not depend on what
else a process compiled, the numba cache still serves a second process, and
``kernels.compile_report()`` says what was compiled and what loaded.

The real checks run the kernels in subprocesses with a fresh NUMBA_CACHE_DIR (compilation from
a cold cache)."""

import inspect
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

import pytest

ROOT = Path(__file__).resolve().parents[2]

#: One subprocess: the jams named on the command line in that order (then ``analyze`` with
#: scalars only), their arrays into OUT.npz, and what it compiled and loaded into OUT.json.
SCRIPT = r"""
import json, sys
import numpy as np
import kernels

out, names = sys.argv[1], sys.argv[2:]
SETTINGS = {"fire": {}, "cg": {"minimizer": "cg"}, "newton": {"endgame": "newton"}}
arrays = {}
for name in names:
    p = kernels.jam(32, 1e-5, 3, **SETTINGS[name])
    a = kernels.analyze(p.positions, p.radii, p.box, observables=["scalars"])
    arrays[name + ".positions"] = p.positions
    arrays[name + ".radii"] = p.radii
    arrays[name + ".jam"] = np.array([p.energy, p.pressure, p.force_residual, p.iterations,
                                      p.force_evaluations, p.factorizations])
    arrays[name + ".scalars"] = np.array([float(a.scalars[k]) for k in sorted(a.scalars)])
np.savez(out + ".npz", **arrays)
r = kernels.compile_report()
json.dump({"compiled": r.compiled, "loaded": r.loaded, "modules": r.modules,
           "summary": r.summary()}, open(out + ".json", "w"))
"""

#: Kernel modules a FIRE jam and a scalars-only analysis must not compile.
NOT_FOR_FIRE = ("cg", "linesearch", "newton", "sparse", "hessian", "barostat", "triangulate", "cellrelax",
                "observables", "response")


def _run(tmp_path, cache, tag, *names):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONPATH": str(ROOT)}
    out = tmp_path / tag
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(out), *names], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(Path(str(out) + ".json").read_text())
    with np.load(str(out) + ".npz") as z:
        arrays = {k: z[k] for k in z.files}
    return report, arrays


def _cached_modules(cache):
    """Kernel modules with an index file in a numba cache directory (``fire._fire_run-288.py311.nbi``)."""
    return {p.name.split(".")[0] for p in Path(cache).rglob("*.nbi")}


@pytest.mark.slow
def test_a_fire_task_compiles_only_fire_and_gets_the_same_bits(tmp_path):
    # another minimiser first (CG, then FIRE) in one process, from a cold cache (the Newton
    # endgame's compilation, most of a cold cache's minute, is left to tests/kernels/test_newton.py)
    everything, arrays_all = _run(tmp_path, tmp_path / "cache-all", "all", "cg", "fire")
    assert {"cg", "linesearch", "fire"} <= set(everything["modules"])
    assert {"protocol._ohern_cg", "protocol._ohern_fire", "cg._cg_core"} <= set(everything["compiled"])
    assert {"cg", "linesearch"} <= _cached_modules(tmp_path / "cache-all")

    # FIRE alone, from another cold cache: nothing of the other minimisers, the endgame or the
    # histogram and response observables is compiled, nor written to the cache
    cold = tmp_path / "cache-fire"
    fire, arrays_fire = _run(tmp_path, cold, "fire", "fire")
    assert not set(fire["modules"]) & set(NOT_FOR_FIRE), fire["modules"]
    assert {"cells", "fire", "network", "potential", "protocol"} <= set(fire["modules"])
    assert "protocol._ohern_fire" in fire["compiled"] and not fire["loaded"]
    assert fire["summary"].startswith(f"compiled {len(fire['compiled'])} kernels (")
    assert not _cached_modules(cold) & set(NOT_FOR_FIRE), sorted(_cached_modules(cold))

    # the same bits whatever else the process compiled
    for key, value in arrays_fire.items():
        assert np.array_equal(value, arrays_all[key], equal_nan=True), key

    # a second process loads everything from the cache and compiles nothing
    warm, arrays_warm = _run(tmp_path, cold, "warm", "fire")
    assert warm["compiled"] == [] and "protocol._ohern_fire" in warm["loaded"], warm
    for key, value in arrays_fire.items():
        assert np.array_equal(value, arrays_warm[key], equal_nan=True), key


# ------------------------------------------------------------------ cheap checks, in this process

def test_spatial_order_is_the_argsort_of_the_cell_keys():
    """The counting sort of ``_spatial_order`` gives the permutation of the former
    ``np.argsort((cell * n) + index)``, also for coordinates outside the box or on its edges."""
    from kernels.protocol import _spatial_order

    def reference(positions, box, cell):
        n = positions.shape[0]
        nx = max(1, int(box[0] / cell))
        ny = max(1, int(box[1] / cell))
        key = np.empty(n, dtype=np.int64)
        for i in range(n):
            x = positions[i, 0] - box[0] * np.floor(positions[i, 0] / box[0])
            y = positions[i, 1] - box[1] * np.floor(positions[i, 1] / box[1])
            cx = min(int(x / box[0] * nx), nx - 1)
            cy = min(int(y / box[1] * ny), ny - 1)
            if cy % 2 == 1:
                cx = nx - 1 - cx
            key[i] = (cy * nx + cx) * n + i
        return np.argsort(key)

    rng = np.random.default_rng(5)
    for n, box, cell in ((1, (1.0, 1.0), 0.3), (7, (1.0, 2.0), 5.0), (300, (1.0, 1.0), 0.05),
                         (1000, (2.0, 0.7), 0.011)):
        b = np.array(box)
        pos = rng.random((n, 2)) * b * 3.0 - b  # outside the box too
        pos[: n // 4] = np.round(pos[: n // 4] * 4.0) / 4.0  # on cell and box edges
        got = _spatial_order(pos, b, cell)
        assert got.dtype == np.int64
        assert np.array_equal(got, reference(pos, b, cell)), (n, box, cell)


def test_ohern_cores_one_per_minimiser():
    from kernels import protocol

    fixed, shear = protocol.CELL_FIXED, protocol.CELL_SHEAR
    assert set(protocol.OHERN_CORES) == {(protocol.MIN_FIRE, protocol.ENDGAME_NONE, fixed),
                                         (protocol.MIN_CG, protocol.ENDGAME_NONE, fixed),
                                         (protocol.MIN_FIRE, protocol.ENDGAME_NEWTON, fixed),
                                         (protocol.MIN_FIRE, protocol.ENDGAME_NONE, shear)}
    settings = protocol.SearchSettings(*([None] * len(protocol.SearchSettings._fields)))
    with pytest.raises(ValueError, match="endgame"):
        protocol.ohern_search(None, None, None, settings, protocol.MIN_CG, protocol.ENDGAME_NEWTON)
    with pytest.raises(ValueError, match="cell"):
        protocol.ohern_search(None, None, None, settings, protocol.MIN_CG, protocol.ENDGAME_NONE, shear)
    # the record names the jitted searches' arguments, in their order
    for core in protocol.OHERN_CORES.values():
        params = list(inspect.signature(core.py_func).parameters)
        assert params[:3] == ["positions", "radii0", "box"]
        assert tuple(params[3:]) == protocol.SearchSettings._fields, core


def test_jam_and_the_spec_accept_exactly_the_runnable_combinations():
    """kernels.jam and a campaign spec accept a combination of route, minimiser, stop rule,
    endgame and cell exactly when kernels.names.RUNNABLE has it, and refuse the others naming
    the choice at fault."""
    import itertools

    from campaign.errors import UserError
    from campaign.plan.parse import parse_spec
    from kernels.jamming import _prepare
    from kernels.names import CHOICE_DEFAULTS, CHOICES, RUNNABLE

    base = "name: t\nseed: 1\ngrid: {N_G: [32], E_G: [1.0e-4], seeds: 1}\n"
    for combo in itertools.product(*CHOICES.values()):
        choice = dict(zip(CHOICES, combo))
        runs = combo in RUNNABLE
        settings = dict(choice, energy_tolerance=1e-16)
        try:
            _prepare(32, 1e-4, 0, None, settings)
            jam_error = None
        except ValueError as exc:
            jam_error = str(exc)
        assert (jam_error is None) == runs, (combo, jam_error)
        protocol = ", ".join(f"{k}: {v}" for k, v in choice.items() if v != CHOICE_DEFAULTS[k])
        try:
            parse_spec(base + f"protocol: {{{protocol}}}\n", "t.yaml")
            spec_error = None
        except UserError as exc:
            spec_error = str(exc)
        assert (spec_error is None) == runs, (combo, spec_error)
        if not runs:
            key = jam_error.split(":")[0]
            assert choice[key] != CHOICE_DEFAULTS[key] or key == "minimizer", jam_error
            assert f"protocol.{key}: {key} {choice[key]!r}" in spec_error, spec_error


def test_compile_report_names_kernels_and_summarises():
    import kernels
    from kernels.compiled import CompileReport, _dispatchers

    import kernels.protocol  # noqa: F401 - its dispatchers (and those it imports) are listed

    names = {name for name, _ in _dispatchers()}
    assert {"protocol._ohern_fire", "fire._fire_run", "cells._candidate_pairs_core"} <= names
    assert not any(n.startswith("compiled.") for n in names)
    r = kernels.compile_report()
    assert isinstance(r, CompileReport) and list(r.compiled) == sorted(r.compiled)
    assert CompileReport().summary() == "compiled nothing, 0 loaded from the cache"
    r = CompileReport(compiled=("fire._fire_run", "protocol._ohern_fire"), loaded=("network._faces_core",))
    assert r.modules == ("fire", "protocol")
    assert r.summary() == "compiled 2 kernels (fire, protocol), 1 loaded from the cache"


def test_the_warm_up_covers_every_minimiser_the_tasks_use():
    """A spec whose variants (or ``endgame: auto``) use several minimisers warms each once, so no
    task's time includes a compilation; one variant, one warm-up."""
    from campaign.plan.parse import parse_spec
    from campaign.plan.tasks import expand
    from campaign.plan.tasks import warm_ups as _warm_ups

    base = """name: w
seed: 1
system:
  box: [1.0, 1.0]
  species: [{name: A, fraction: 0.5, radius: 1.4}, {name: B, fraction: 0.5, radius: 1.0}]
  potential: {exponent: 2.0}
grid: {N_G: [64, 4096], E_G: [1.0e-3, 1.0e-14], seeds: 2}
protocol: {window: 0.1, force_tolerance: 1.0e-6}
observables: [scalars]
"""
    one = _warm_ups(expand(parse_spec(base)))
    assert len(one) == 1 and one[0].get("endgame", "none") == "none"
    several = base + "variants:\n  - {name: cg, minimizer: cg}\n  - {name: pressure, route: pressure}\n"
    keys = {(p.get("minimizer", "fire"), p.get("endgame", "none"), p.get("route", "ohern"))
            for p in _warm_ups(expand(parse_spec(several)))}
    assert keys == {("fire", "none", "ohern"), ("cg", "none", "ohern"), ("fire", "none", "pressure")}
    auto = base.replace("force_tolerance: 1.0e-6}", "force_tolerance: 1.0e-6, endgame: auto}")
    endgames = sorted(p.get("endgame", "none") for p in _warm_ups(expand(parse_spec(auto))))
    assert endgames == ["newton", "none"]  # N_G 4096 at 1e-14: Newton; N_G 64: FIRE


def test_the_analysis_helper_compiles_what_a_task_analyses():
    """A local run's master on a cold cache has a second process compile the analysis
    (``campaign.run.worker._warm_analysis``) while it compiles the search: it analyses, with the
    tasks' observables and bins, a stand-in of 16 disks that calls the kernels a packing's
    analysis calls (contacts, rattlers, voids, fictitious contacts, every histogram filled); the
    quickstart's spec here. Without the helper, or where it misses a kernel, the master compiles
    it: only the time is at stake."""
    from campaign.plan.parse import load_spec
    from campaign.plan.tasks import expand, warm_ups
    from campaign.run.worker import KernelTask, _warm_analysis

    spec = load_spec(None)
    context = dict(spec.worker_context(), task_function="kernels")
    context["protocol_warmups"] = warm_ups(expand(spec))
    context["edges"] = {h: [float(x) for x in e] for h, e in KernelTask().histogram_edges(context).items()}
    scalars, hists, _ = _warm_analysis(context, quiet=False)
    assert scalars["N_G"] >= 12 and scalars["N_R"] > 0 and scalars["N_V"] > 0 and scalars["N_F"] > 0, scalars
    assert set(hists) == set(context["histograms"]) and all(h.sum() > 0 for h in hists.values()), hists
