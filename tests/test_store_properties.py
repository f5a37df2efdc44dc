"""Any store a user can hold: stores of random shape and values, written by the store's own
writer (``campaign.storage.store.Store.record``, as ``campaign run``'s master writes them), read by
every reader a user runs on them: ``reduce``, ``export``, ``plot``, ``status`` and ``verify``.

The shapes and values are those a campaign can reach: sizes whose cells have no finished packing,
one packing a cell, every packing failed, NaN and infinities in any scalar, a scalar without a
spread, a negative Delta Z, one seed, every packing at the same E_G, histograms all zero, a scalar
the task never reported. Each reader must end with exit 0 (and a note where it left something out)
or 2 with one paragraph, never a traceback; and no table may hold a finite number from a cell that
had none: the expectations below are computed here from what was written, by the rules of
docs/REDUCED.md (the usable packings: done, ``jam_status == 0``, ``identities_ok == 1``; the fit
range: typical overlap ``(alpha E_G / 2)^(1/alpha) <= 0.001``; a fit needs three cells of at
least three packings with a positive mean abscissa and a spread of the quantity).

Seeded (hypothesis' ``derandomize``): the same examples at every run. 25 stores for every reader but
`plot`, which draws each figure (about half a second each): two stores of one system and one of two,
about 45 s of CPU together.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from campaign import cli
from campaign.plan.spec import parse_spec
from campaign.plan.tasks import expand
from campaign.run.worker import SyntheticTask
from campaign.storage.store import Store

SIZES = (16, 24, 32)
ENERGIES = (1e-3, 1e-5, 1e-7, 1e-8, 1e-9, 1e-10, 1e-12)
SPECIAL = (math.nan, math.inf, -math.inf, 0.0, -1.0, 1e300, -1e300, 5e-324)
#: the scalars a task reports here (the reducer's and the comparison's), and how each is made
LAWS = ("A_G", "psi_O", "delta_Z", "E_G", "phi", "N_G", "z_g_mean", "force_evaluations", "jam_seconds")
FLAGS = ("jam_status", "identities_ok")
KINDS = ("law", "law", "law", "flat", "constant", "special", "negative", "all_nan", "absent")
FATES = ("full", "full", "none", "failed", "one", "some", "mixed")
MIN_PACKINGS = 3
FIT_OVERLAP = 1e-3  # the reducer's default range (docs/REDUCED.md, "The fit range")
FITS = (("A_G", "E_G", "A_G_star_E", "beta_E"), ("A_G", "delta_Z", "A_G_star_Z", "beta_Z"),
        ("psi_O", "E_G", "psi_O_star", "psi_beta_E"), ("psi_O", "delta_Z", "psi_O_star_Z", "psi_beta_Z"))


@st.composite
def campaigns(draw, variant=st.booleans()):
    """What a store holds: its grid, each size's fate, each scalar's kind, the flags, the histograms;
    ``variant``: whether a second system (alpha = 2.5) runs beside the default."""
    sizes = sorted(draw(st.sets(st.sampled_from(SIZES), min_size=1, max_size=3)))
    return {
        "sizes": sizes,
        "energies": sorted(draw(st.sets(st.sampled_from(ENERGIES), min_size=1, max_size=5)), reverse=True),
        "seeds": draw(st.integers(1, 4)),
        "variant": draw(variant),
        "fate": {n: draw(st.sampled_from(FATES)) for n in sizes},
        "kind": {k: draw(st.sampled_from(KINDS)) for k in LAWS},
        "flags": draw(st.sampled_from(("good", "good", "some_bad", "special"))),
        "histograms": draw(st.sampled_from(("counts", "zero"))),
        "seed": draw(st.integers(0, 2**31 - 1)),
    }


def spec_text(c) -> str:
    energies = ", ".join(f"{e:.1e}" for e in c["energies"])  # YAML reads 1e-05 as a string
    text = (f"name: prop\nseed: 7\ngrid: {{N_G: {c['sizes']}, E_G: [{energies}], seeds: {c['seeds']}}}\n"
            "observables: [scalars, connectivity, contact_angles]\n"
            "bins: {z_g: {range: [-0.5, 8.5], count: 9}, z_v: {range: [2.5, 8.5], count: 6}, "
            "contact_angle: {range: [0.0, 3.2], count: 16}}\n")
    if c["variant"]:
        text += "variants: [{name: hertz, system: {potential: {exponent: 2.5}}}]\n"
    return text


def _law(name, n, E, rng):
    """A plausible value of a scalar of a packing of n disks at E (jamming scaling, noise)."""
    u = rng.normal()
    return {"A_G": 0.446 - 0.6 / n + 0.5 * E**0.28 + 0.03 * u / math.sqrt(n),
            "psi_O": 0.369 + 0.6 * E**0.27 + 0.05 * u / math.sqrt(n),
            "delta_Z": 3.0 * E**0.25 * (1 + 0.05 * u), "E_G": E * (1 + 0.1 * rng.random()),
            "phi": 0.84 + 0.5 * math.sqrt(E), "N_G": float(n - rng.integers(0, 3)),
            "z_g_mean": 4.0 + 3.0 * E**0.25, "force_evaluations": float(rng.integers(100, 900)),
            "jam_seconds": 0.01 * rng.random()}[name]


def _value(kind, name, n, E, rng):
    if kind == "constant":  # one value in every cell: no spread, and every E_G the same
        return 0.25
    if kind == "flat":  # the law without noise: no spread within a cell (E_G: the grid's energy)
        return _law(name, n, E, np.random.default_rng(0)) if name != "E_G" else E
    if kind == "all_nan":
        return math.nan
    x = _law(name, n, E, rng)
    if kind == "negative":
        return -abs(x) - 1e-3
    if kind == "special" and rng.random() < 0.4:
        return SPECIAL[rng.integers(len(SPECIAL))]
    return x


def _flag(how, good, rng):
    if how == "good" or rng.random() < 0.6:
        return good
    if how == "some_bad":
        return float(1 - good if good in (0.0, 1.0) else 1)
    return SPECIAL[rng.integers(len(SPECIAL))]


def write(c, path):
    """Write the campaign ``c`` into ``path`` through the master's writer; returns what was written:
    per task row its status (0 pending, 1 done, 2 failed) and its scalars."""
    spec = parse_spec(spec_text(c))
    tasks = expand(spec)
    edges = SyntheticTask().histogram_edges(spec.worker_context())
    rng = np.random.default_rng(c["seed"])
    status, scalars = np.zeros(len(tasks), np.int8), [None] * len(tasks)
    store = Store(path, spec, tasks, edges, log=lambda msg: None)
    try:
        for i, t in enumerate(tasks):
            fate = c["fate"][t.N]
            roll = rng.random()
            done = {"full": True, "none": False, "failed": False, "one": t.seed == 0, "some": roll < 0.5,
                    "mixed": roll < 0.4}[fate]
            failed = fate == "failed" or (fate == "mixed" and roll > 0.7)
            if not (done or failed):
                continue
            summary = {"id": t.id, "ok": done, "scalars": {}, "histograms": {}, "configuration": None,
                       "wall": 0.5, "rank": 1, "host": "prop", "error": None}
            if done:
                sc = {k: _value(c["kind"][k], k, t.N, t.E, rng) for k in LAWS if c["kind"][k] != "absent"}
                sc["jam_status"] = _flag(c["flags"], 0.0, rng)
                sc["identities_ok"] = _flag(c["flags"], 1.0, rng)
                summary["scalars"] = sc
                summary["histograms"] = {h: (rng.poisson(2.0, len(e) - 1) if c["histograms"] == "counts"
                                             else np.zeros(len(e) - 1, np.int64)) for h, e in edges.items()}
                scalars[i] = sc
            else:
                summary["error"] = {"message": "RuntimeError: no packing", "traceback": "Traceback: ..."}
            store.record(i, summary, attempts=1)
            status[i] = 1 if done else 2
    finally:
        store.close()
    return tasks, status, scalars


def run(*argv):
    """``campaign ARGV`` in this process: (exit status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def assert_ended_well(code, err, what):
    """Exit 0, or 2 with one paragraph; never a traceback."""
    assert "Traceback" not in err and "internal error" not in err, f"{what}: {err}"
    assert code in (0, 2), f"{what}: exit {code}: {err}"
    if code == 2:
        message = [line for line in err.splitlines() if line.startswith("campaign ")]
        assert len(message) == 1 and "\n\n" not in err.strip(), f"{what}: {err}"


def _float(text):
    return float(text) if text != "" else math.nan


def _read_csv(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _alpha(variant):
    return 2.5 if variant == "hertz" else 2.0


def expectations(tasks, status, scalars):
    """Per cell (variant, N, E): the counts and, per scalar, the finite values of its usable packings."""
    cells = {}
    for i, t in enumerate(tasks):
        c = cells.setdefault((t.variant, t.N, t.E), {"done": 0, "failed": 0, "pending": 0, "values": {}})
        c[{0: "pending", 1: "done", 2: "failed"}[int(status[i])]] += 1
        sc = scalars[i]
        if sc is None or not (sc["jam_status"] == 0 and sc["identities_ok"] == 1):
            continue
        c["usable"] = c.get("usable", 0) + 1
        for k, x in sc.items():
            c["values"].setdefault(k, [])
            if math.isfinite(x):
                c["values"][k].append(x)
    return cells


def fit_cells(cells, variant, n, quantity, absc):
    """How many cells of (variant, n) a fit of ``quantity`` against ``absc`` can use (docs/REDUCED.md)."""
    count = 0
    for (v, N, E), c in cells.items():
        if v != variant or N != n or c.get("usable", 0) < MIN_PACKINGS:
            continue
        if (_alpha(v) * E / 2.0) ** (1.0 / _alpha(v)) > FIT_OVERLAP * (1 + 1e-9):
            continue
        x, y = c["values"].get(absc, []), c["values"].get(quantity, [])
        if len(x) and len(y) >= 2 and np.mean(x) > 0 and np.std(y) > 0:
            count += 1
    return count


def check_reduce(out, cells, notes=None):
    """The reducer's tables hold no finite number from a cell without the packings behind it; what it
    left out, its notes say."""
    if notes is not None:
        excluded = sum(c["done"] - c.get("usable", 0) for c in cells.values())
        unfinished = sum(c["failed"] + c["pending"] for c in cells.values())
        assert (f"{excluded} finished packing(s) left out of the statistics" in notes) == (excluded > 0), notes
        assert ("pending" in notes and "the reduction uses the finished ones only" in notes) == (unfinished > 0), notes
    rows = _read_csv(out / "cells.csv")
    assert len(rows) == len(cells)
    for r in rows:
        c = cells[(r["variant"], int(r["N"]), float(r["E"]))]
        assert (int(r["n_packings"]), int(r["n_failed"]), int(r["n_pending"])) == (
            c.get("usable", 0), c["failed"], c["pending"])
        for col, text in r.items():
            if text == "" or col in ("variant", "N", "E", "n_packings", "n_failed", "n_pending"):
                continue
            if col.startswith("selfavg_"):  # a histogram's moments over the cell's packings
                assert c.get("usable", 0) >= 1, f"{col} = {text} from a cell without a usable packing"
                continue
            name = col.split("_", 1)[1] if not col.startswith("A_G_gauss_") else "A_G"
            vals = c["values"].get(name, [])
            need = 1 if col.startswith("mean_") else 2
            assert len(vals) >= need, f"{col} = {text} from a cell with {len(vals)} finite value(s)"
            mean = float(np.mean(vals)) if vals else math.nan
            if col.startswith("mean_") and math.isfinite(mean):
                scale = max(abs(x) for x in vals)
                assert math.isclose(float(text), mean, rel_tol=1e-9, abs_tol=1e-12 * scale), (col, text, mean)
    table = _read_csv(out / "table.csv")
    fitted = {}
    for r in table:
        if r["N_G"] == "inf":
            continue
        v, n = r["variant"], int(r["N_G"])
        for quantity, absc, key, bkey in FITS:
            q = fit_cells(cells, v, n, quantity, absc)
            fitted.setdefault((v, quantity, absc), []).append(q >= 3)
            for k in (key, f"{key}_err", bkey, f"{bkey}_err"):
                assert r[k] == "" or q >= 3, f"{v} N={n} {k} = {r[k]} from {q} usable cell(s)"
    for r in table:
        if r["N_G"] == "inf":
            for quantity, absc, key, bkey in FITS:
                sizes = sum(fitted.get((r["variant"], quantity, absc), []))
                assert r[key] == r[bkey] == "" or sizes >= 2, f"{r['variant']} N_G -> inf {key} from {sizes} size(s)"


def check_export(path, tasks, status, scalars):
    """The exported rows are the usable packings, every value as written."""
    rows = _read_csv(path)
    usable = [i for i, sc in enumerate(scalars) if sc is not None and sc["jam_status"] == 0
              and sc["identities_ok"] == 1]
    assert [int(r["row"]) for r in rows] == usable
    for r in rows:
        i = int(r["row"])
        assert r["id"] == tasks[i].id and int(r["status"]) == 1
        for k, x in scalars[i].items():
            got = float(r[k])
            assert got == x or (math.isnan(got) and math.isnan(x)), (k, got, x)


def check_status(text, tasks, status):
    got = json.loads(text)
    assert (got["done"], got["failed"], got["remaining"], got["tasks"]) == (
        int((status == 1).sum()), int((status == 2).sum()), int((status == 0).sum()), len(tasks))


@settings(max_examples=25, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(campaigns())
def test_every_reader_ends_well_on_any_store(c):
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        h5 = tmp / "p.h5"
        tasks, status, scalars = write(c, h5)
        cells = expectations(tasks, status, scalars)
        code, out, err = run("verify", h5, "--quiet")
        assert code == 0, err  # the writer's own store is sound
        code, out, err = run("status", h5, "--json")
        assert_ended_well(code, err, "status")
        assert code == 0
        check_status(out, tasks, status)
        code, out, err = run("reduce", h5, "--boot", 20, "-o", tmp / "red")
        assert_ended_well(code, err, "reduce")
        if code == 0:
            check_reduce(tmp / "red", cells, err)
        code, out, err = run("export", h5, "--out", tmp / "p.csv")
        assert_ended_well(code, err, "export")
        if code == 0:
            check_export(tmp / "p.csv", tasks, status, scalars)


#: a store of two systems, every size's cells odd in another way, and odd values: the system figures too
TWO_SYSTEMS = {"sizes": [16, 24, 32], "energies": [1e-5, 1e-7, 1e-8, 1e-9], "seeds": 3, "variant": True,
               "fate": {16: "full", 24: "one", 32: "mixed"},
               "kind": dict({k: "law" for k in LAWS}, delta_Z="negative", psi_O="special", E_G="flat"),
               "flags": "some_bad", "histograms": "zero", "seed": 5}


@pytest.mark.slow  # every figure of two stores: tests/test_plots.py draws them in the quick suite
@settings(max_examples=2, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(campaigns(variant=st.just(False)))  # every figure is drawn, about half a second each: one system
@example(TWO_SYSTEMS)
def test_plot_ends_well_on_any_store(c):
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        write(c, tmp / "p.h5")
        code, out, err = run("plot", tmp / "p.h5", "--boot", 20, "--out", tmp / "fig", "--dpi", 30)
        assert_ended_well(code, err, "plot")


def test_a_size_without_a_usable_cell_after_one_with_fits(tmp_path):
    """The reducer's former IndexError (scaling.py, a mask of the previous size): N_G = 24 has one
    packing a cell, below the three a fit needs, after N_G = 16, whose cells are fitted."""
    c = {"sizes": [16, 24], "energies": [1e-7, 1e-8, 1e-9, 1e-10, 1e-12], "seeds": 4, "variant": False,
         "fate": {16: "full", 24: "one"}, "kind": {k: "law" for k in LAWS}, "flags": "good",
         "histograms": "counts", "seed": 1}
    tasks, status, scalars = write(c, tmp_path / "p.h5")
    code, out, err = run("reduce", tmp_path / "p.h5", "--boot", 20, "-o", tmp_path / "red")
    assert code == 0, err
    assert "default N=24: 5 cell(s) with fewer than 3 finished packings left out of the fits" in err
    check_reduce(tmp_path / "red", expectations(tasks, status, scalars))
    table = {r["N_G"]: r for r in _read_csv(tmp_path / "red" / "table.csv")}
    assert table["16"]["A_G_star_E"] != "" and table["24"]["A_G_star_E"] == ""
