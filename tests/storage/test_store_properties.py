"""Any store a user can hold: stores of random shape and values, written by the store's own
writer (``campaign.storage.store.Store.record``, as ``campaign run``'s master writes them), read by
every reader a user runs on them: ``reduce``, ``export``, ``plot``, ``status`` and ``verify``.

A store is built shape first, then its values perturbed. The shape: one to three sizes, one or two
systems (the second at alpha = 2.5), four or five seeds, four or five energies inside the fit
range of both systems (typical overlap ``(alpha E_G / 2)^(1/alpha) <= 0.001``: ``E_G <= 1e-6`` at
alpha = 2, ``<= 2.5e-8`` at alpha = 2.5) and up to two outside it, every task done; so that every
size of either system has its four fits and two sizes or more give the N_G -> inf row. Then one
size may be spoilt (no packing finished, every one failed, one seed, some, a mix of done, failed
and pending), one of the fitted scalars (``A_G``, ``psi_O``, ``delta_Z``, ``E_G``) perturbed (NaN,
infinities, zero, a denormal in some packings; negative; without a spread; the same everywhere;
NaN everywhere; never reported), any other scalar anything (NaN, infinities, 1e300, a denormal,
...), packings marked as not converged or breaking an identity, histograms all zero.

What every reader must give a sound store (docs/REDUCED.md), computed here with numpy from what
was written, never from the reducer: exit 0; per cell the counts, every scalar's mean where a
usable packing (done, ``jam_status == 0``, ``identities_ok == 1``) has a finite value and its
standard error where two have, the Gaussian of P(A_G), the histograms' self-averaging ratios, and
nothing where the cell has none; per (variant, N_G) each fit where the fit range holds four
energies of the grid and four cells of three usable packings or more with a non-negative mean
abscissa and a spread of the quantity, three of them with distinct positive mean abscissae, its
bootstrap errors where every such cell has two packings with the four quantities finite, and no
fit elsewhere (cells whose abscissae are all one number determine no exponent: no fit, or one
marked undetermined); per variant and law the N_G -> inf row from exactly the sizes with three
such cells of distinct positive abscissae and a bootstrap, a value where two sizes enter and the
values were not perturbed, none where fewer do. A store whose fitted scalars follow the law unperturbed gives back the law's exponents
and intercepts. ``export`` writes every usable packing with its values as written, ``status``
counts every row. The only exit 2 is the one a store is built for (``refused``): a fit range on
the command line that holds one energy of the grid, and an export of configurations the store
does not keep, each refused in one paragraph naming why.

Seeded (hypothesis' ``derandomize``, no example database): the same examples at every run with a
given hypothesis. The shape is drawn so that another hypothesis's examples reach the fits too:
with hypothesis 6.170, 21 of the 25 stores have fits, 18 of the second system, 18 an N_G -> inf
row (22 distinct stores; of 150 unseeded examples 113, 77 and 77). 25 stores for every reader but
``plot`` (about 25 s here), which draws each figure (about half a second each): two stores of one
system and one of two, about 45 s of CPU together.
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
from campaign.plan.parse import parse_spec
from campaign.plan.tasks import expand
from campaign.run.worker import SyntheticTask
from campaign.storage.store import Store

SIZES = (16, 24, 32)
#: energies inside the fit range of both systems, and outside it (1e-7: inside at alpha = 2 only)
INSIDE = (1e-8, 1e-9, 1e-10, 1e-11, 1e-12, 1e-13)
OUTSIDE = (1e-7, 1e-5, 1e-3)
ALPHA = {"default": 2.0, "hertz": 2.5}
SPECIAL = (math.nan, math.inf, -math.inf, 0.0, -1.0, 1e300, -1e300, 5e-324)
#: the fitted scalars' perturbations: NaN, infinities, zero, -1 or a denormal in some packings
ODD = (math.nan, math.inf, -math.inf, 0.0, -1.0, 5e-324)
FITTED = ("A_G", "psi_O", "delta_Z", "E_G")
OTHER = ("phi", "N_G", "z_g_mean", "force_evaluations", "jam_seconds")
LAWS = FITTED + OTHER
FLAGS = ("jam_status", "identities_ok")
KINDS = ("law", "flat", "constant", "special", "negative", "all_nan", "absent")
#: how a spoilt size ends: no packing finished, every one failed, seed 0 only, about half, a mix
FATES = ("none", "failed", "one", "some", "mixed")
MIN_PACKINGS = 3
MIN_CELLS = 4  # three parameters and one degree of freedom (docs/REDUCED.md, "The power-law fits")
FIT_OVERLAP = 1e-3  # the reducer's default range (docs/REDUCED.md, "The fit range")
FITS = (("A_G", "E_G", "A_G_star_E", "beta_E"), ("A_G", "delta_Z", "A_G_star_Z", "beta_Z"),
        ("psi_O", "E_G", "psi_O_star", "psi_beta_E"), ("psi_O", "delta_Z", "psi_O_star_Z", "psi_beta_Z"))
#: the law the fitted scalars are written with: A_G = A(N) + 0.5 E^0.28, psi_O = 0.369 + 0.6 E^0.27,
#: Delta Z = 3 E^0.25, each with 2% noise; so the exponents against E_G and Delta Z, and the
#: intercepts (A(N) = 0.446 - 0.6 / N, 0.446 as N -> inf)
A_STAR, A_SLOPE, PSI_STAR = 0.446, 0.6, 0.369
EXPONENTS = {"beta_E": 0.28, "beta_Z": 0.28 / 0.25, "psi_beta_E": 0.27, "psi_beta_Z": 0.27 / 0.25}


def _intercept(key, n):
    """The law's intercept of table key ``key`` at N_G ``n`` (``math.inf``: the N_G -> inf row)."""
    return PSI_STAR if key.startswith("psi") else A_STAR - (0.0 if n == math.inf else A_SLOPE / n)


@st.composite
def campaigns(draw, variant=st.sampled_from((True, True, False))):
    """What a store holds (module docstring): the shape, then what spoils it. ``variant``: whether a
    second system (alpha = 2.5) runs beside the default."""
    sizes = sorted(draw(st.permutations(SIZES))[:draw(st.sampled_from((3, 3, 1, 3, 2, 3)))])
    inside = draw(st.sets(st.sampled_from(INSIDE), min_size=4, max_size=5))
    outside = draw(st.sets(st.sampled_from(OUTSIDE), max_size=2))
    spoilt = draw(st.sampled_from((None, None) + FATES))
    fitted = draw(st.sampled_from((None,) * 7 + (("A_G", "special"), ("psi_O", "special"), ("delta_Z", "negative"),
                                                 ("psi_O", "flat"), ("E_G", "constant"), ("delta_Z", "all_nan"),
                                                 ("A_G", "absent"))))
    kind = {k: "law" for k in FITTED}
    if fitted:
        kind[fitted[0]] = fitted[1]
    kind.update({k: draw(st.sampled_from(KINDS)) for k in OTHER})
    return {
        "sizes": sizes,
        "energies": sorted(inside | outside, reverse=True),
        "seeds": draw(st.integers(4, 5)),
        "variant": draw(variant),
        "fate": {n: spoilt if spoilt and n == sizes[-1] else "full" for n in sizes},
        "kind": kind,
        "flags": draw(st.sampled_from(("good", "good", "some_bad", "special"))),
        "histograms": draw(st.sampled_from(("counts", "zero"))),
        "refused": draw(st.sampled_from((False, False, False, True))),
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
    return {"A_G": A_STAR - A_SLOPE / n + 0.5 * E**0.28 * (1 + 0.02 * u),
            "psi_O": PSI_STAR + 0.6 * E**0.27 * (1 + 0.02 * u), "delta_Z": 3.0 * E**0.25 * (1 + 0.02 * u),
            "E_G": E * (1 + 0.1 * rng.random()), "phi": 0.84 + 0.5 * math.sqrt(E),
            "N_G": float(n - rng.integers(0, 3)), "z_g_mean": 4.0 + 3.0 * E**0.25,
            "force_evaluations": float(rng.integers(100, 900)), "jam_seconds": 0.01 * rng.random()}[name]


def _value(kind, name, n, E, rng):
    if kind == "constant":  # one value in every cell: no spread, and every E_G the same
        return 0.25
    if kind == "flat":  # the law without noise, a dyadic number: no spread within a cell, exactly
        return math.ldexp(round(math.ldexp(_law(name, n, E, np.random.default_rng(0)), 40)), -40)
    if kind == "all_nan":
        return math.nan
    x = _law(name, n, E, rng)
    if kind == "negative":
        return -abs(x) - 1e-3
    if kind == "special" and rng.random() < 0.2:
        odd = ODD if name in FITTED else SPECIAL
        return odd[rng.integers(len(odd))]
    return x


def _flag(how, good, rng):
    if how == "good" or rng.random() < 0.9:
        return good
    if how == "some_bad":
        return float(1 - good if good in (0.0, 1.0) else 1)
    return SPECIAL[rng.integers(len(SPECIAL))]


def write(c, path):
    """Write the campaign ``c`` into ``path`` through the master's writer; returns what was written:
    the tasks, per task row its status (0 pending, 1 done, 2 failed), its scalars and its histograms
    (None where it did not finish), and the bin edges."""
    spec = parse_spec(spec_text(c))
    tasks = expand(spec)
    edges = SyntheticTask().histogram_edges(spec.worker_context())
    rng = np.random.default_rng(c["seed"])
    status, scalars, hists = np.zeros(len(tasks), np.int8), [None] * len(tasks), [None] * len(tasks)
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
                scalars[i], hists[i] = sc, summary["histograms"]
            else:
                summary["error"] = {"message": "RuntimeError: no packing", "traceback": "Traceback: ..."}
            store.record(i, summary, attempts=1)
            status[i] = 1 if done else 2
    finally:
        store.close()
    return tasks, status, scalars, hists, edges


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


def _read_csv(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _finite(vals):
    return np.array([x for x in vals if math.isfinite(x)], float)


def _mean_sem(vals):
    """numpy's mean (one finite value or more) and standard error (two or more) of the finite values."""
    v = _finite(vals)
    with np.errstate(over="ignore", invalid="ignore"):
        mean = float(np.mean(v)) if len(v) else math.nan
        sem = float(np.std(v, ddof=1) / np.sqrt(len(v))) if len(v) >= 2 else math.nan
    return mean, sem


def _agrees(text, want, scale):
    """A CSV cell against numpy's value: blank where that is not finite (the reducer's CSV leaves
    those blank), else equal up to the summation order."""
    if not math.isfinite(want):
        return text == ""
    return text != "" and math.isclose(float(text), want, rel_tol=1e-9, abs_tol=1e-12 * scale)


def expectations(tasks, status, scalars, hists, edges):
    """Per cell (variant, N, E): the counts, per scalar the values of its usable packings, and
    per histogram the usable packings' counts."""
    cells = {}
    for i, t in enumerate(tasks):
        c = cells.setdefault((t.variant, t.N, t.E), {"done": 0, "failed": 0, "pending": 0, "usable": 0,
                                                      "values": {}, "rows": [], "hists": {h: [] for h in edges}})
        c[{0: "pending", 1: "done", 2: "failed"}[int(status[i])]] += 1
        sc = scalars[i]
        if sc is None or not (sc["jam_status"] == 0 and sc["identities_ok"] == 1):
            continue
        c["usable"] += 1
        c["rows"].append(sc)
        for k, x in sc.items():
            c["values"].setdefault(k, []).append(x)
        for h, counts in hists[i].items():
            c["hists"][h].append(np.asarray(counts, np.int64))
    return cells


def in_range(variant, E):
    return (ALPHA[variant] * E / 2.0) ** (1.0 / ALPHA[variant]) <= FIT_OVERLAP * (1 + 1e-9)


def fit_plan(cells, present):
    """What the scaling fits must be, from the rules of docs/REDUCED.md ("The power-law fits", "The
    N_G -> inf row") applied to the written values: per (variant, N, quantity, abscissa) whether
    there is a fit and whether it has bootstrap errors; per (variant, quantity, abscissa) the sizes
    that enter the N_G -> inf fit. ``present``: the scalars the store has a column of."""
    fit, errors, enters, degenerate = {}, {}, {}, {}
    groups = sorted({(v, n) for v, n, _ in cells})
    for v, n in groups:
        grid = [E for (w, m, E) in cells if (w, m) == (v, n)]
        inside = [E for E in grid if in_range(v, E)]
        usable = [cells[(v, n, E)] for E in inside if cells[(v, n, E)]["usable"] >= MIN_PACKINGS]
        # the bootstrap resamples a cell's packings with their four quantities together
        boot = len(usable) >= 3 and all(
            sum(all(math.isfinite(r.get(k, math.nan)) for k in FITTED) for r in c["rows"]) >= 2 for c in usable)
        for quantity, absc, _, _ in FITS:
            if not all(k in present for k in FITTED):
                fit[(v, n, quantity, absc)] = errors[(v, n, quantity, absc)] = False
                degenerate[(v, n, quantity, absc)] = False
                continue
            ok, n_positive, positive = 0, 0, set()
            for c in usable:
                x, _ = _mean_sem(c["values"].get(absc, []))
                y, ye = _mean_sem(c["values"].get(quantity, []))
                if math.isfinite(x) and x >= 0 and math.isfinite(y) and math.isfinite(ye):  # two packings or more
                    ok += 1
                    n_positive += x > 0
                    positive |= {x} if x > 0 else set()
            pos = len(positive)  # an exponent needs three distinct abscissae
            fit[(v, n, quantity, absc)] = len(inside) >= MIN_CELLS and ok >= MIN_CELLS and pos >= 3
            errors[(v, n, quantity, absc)] = fit[(v, n, quantity, absc)] and boot
            # every packing at one E_G: cells enough, but no exponent they could determine
            degenerate[(v, n, quantity, absc)] = (len(inside) >= MIN_CELLS and ok >= MIN_CELLS and pos < 3
                                                  and n_positive >= 3)
            if pos >= 3 and boot:
                enters.setdefault((v, quantity, absc), []).append(n)
    return fit, errors, enters, degenerate


def check_reduce(out, cells, edges, notes, plan, report, clean):
    """The reducer's outputs against numpy's over the written values (``edges``: the histograms'
    bin edges); ``report``: its JSON; ``clean``: the fitted scalars follow the law unperturbed
    (the law's numbers must come back); ``plan``: ``fit_plan``'s."""
    fit, errors, enters, degenerate = plan
    excluded = sum(c["done"] - c["usable"] for c in cells.values())
    unfinished = sum(c["failed"] + c["pending"] for c in cells.values())
    assert (f"{excluded} finished packing(s) left out of the statistics" in notes) == (excluded > 0), notes
    assert ("pending" in notes and "the reduction uses the finished ones only" in notes) == (unfinished > 0), notes
    rows = _read_csv(out / "cells.csv")
    assert len(rows) == len(cells)
    for r in rows:
        c = cells[(r["variant"], int(r["N"]), float(r["E"]))]
        assert (int(r["n_packings"]), int(r["n_failed"]), int(r["n_pending"])) == (
            c["usable"], c["failed"], c["pending"])
        for col, text in r.items():
            if col in ("variant", "N", "E", "n_packings", "n_failed", "n_pending"):
                continue
            if col.startswith("selfavg_"):
                want, scale = _selfaverage(col, c, edges)
            elif col.startswith("A_G_gauss_"):
                vals = _finite(c["values"].get("A_G", []))
                want = math.nan if len(vals) < 2 else float(np.mean(vals) if col.endswith("mean")
                                                                 else np.std(vals, ddof=1))
                scale = float(np.abs(vals).max()) if len(vals) else 1.0
            else:
                stat, name = col.split("_", 1)
                vals = c["values"].get(name, [])
                mean, sem = _mean_sem(vals)
                want = {"mean": mean, "sem": sem}[stat]
                scale = float(np.abs(_finite(vals)).max()) if len(_finite(vals)) else 1.0
            assert _agrees(text, want, scale), (r["variant"], r["N"], r["E"], col, text, want)
    table = _read_csv(out / "table.csv")
    rows = {(r["variant"], r["N_G"]): r for r in report["rows"]}
    sizes = {}
    for r in table:
        if r["N_G"] == "inf":
            continue
        v, n = r["variant"], int(r["N_G"])
        sizes.setdefault(v, []).append(n)
        for quantity, absc, key, bkey in FITS:
            want, err = fit[(v, n, quantity, absc)], errors[(v, n, quantity, absc)]
            if degenerate[(v, n, quantity, absc)]:  # no fit, or one that says its exponent is undetermined
                assert r[key] == "" or rows[(v, n)][f"{bkey}_undetermined"], (v, n, bkey, rows[(v, n)])
                continue
            for k in (key, bkey):
                assert (r[k] != "") == want, f"{v} N={n} {k} = {r[k]!r}: the cells {'do' if want else 'do not'} fit"
                assert (r[f"{k}_err"] != "") == err, f"{v} N={n} {k}_err = {r[f'{k}_err']!r}, bootstrap: {err}"
            if clean and want and err:  # the law the store was written with
                b, b_err = float(r[bkey]), float(r[f"{bkey}_err"])
                a, a_err = float(r[key]), float(r[f"{key}_err"])
                assert abs(b - EXPONENTS[bkey]) <= 5 * b_err + 0.02, (v, n, bkey, b, b_err)
                assert abs(a - _intercept(key, n)) <= 5 * a_err + 1e-4, (v, n, key, a, a_err)
    assert sorted(sizes) == sorted({v for v, _, _ in cells}) and all(
        sorted(ns) == sorted({n for w, n, _ in cells if w == v}) for v, ns in sizes.items())
    inf = {r["variant"]: r for r in table if r["N_G"] == "inf"}
    assert sorted(inf) == sorted(sizes)
    for v, r in inf.items():
        x = report["extrapolated"][v]
        for quantity, absc, key, bkey in FITS:
            entered = sorted(enters.get((v, quantity, absc), []))
            if len(entered) < 2:  # one size or none: no extrapolation, and the notes say why
                assert r[key] == r[bkey] == "" and x[f"{bkey}_note"], (v, bkey, entered, r)
                continue
            if r[bkey] == "" and not clean:  # a perturbed law may leave the shared exponent undetermined
                assert x[f"{bkey}_note"] and r[key] == "", (v, bkey, x)
                continue
            assert r[key] != "" and r[bkey] != "" and x[f"{bkey}_note"] == "", (v, bkey, entered, x[f"{bkey}_note"])
            assert [int(s) for s in x[f"{bkey}_sizes"].split()] == entered, (v, bkey, x[f"{bkey}_sizes"], entered)
            if clean:
                b, b_err = float(r[bkey]), float(r[f"{bkey}_err"])
                a, a_err = float(r[key]), float(r[f"{key}_err"])
                assert abs(b - EXPONENTS[bkey]) <= 5 * b_err + 0.02, (v, "inf", bkey, b, b_err)
                assert abs(a - _intercept(key, math.inf)) <= 5 * a_err + 1e-4, (v, "inf", key, a, a_err)


def _selfaverage(col, c, edges):
    """numpy's self-averaging ratio of a cell: each usable packing's first (m1) or second (m2)
    moment of a histogram over the bin centres, divided by the cell's summed counts' moment; the
    mean of the finite ratios (``_spread``: their std)."""
    name, moment = col[len("selfavg_"):].rsplit("_m", 1)
    spread = moment.endswith("_spread")
    power = int(moment[0])
    e = np.asarray(edges[name], float)
    centres = (0.5 * (e[1:] + e[:-1])) ** power
    counts = c["hists"][name]
    with np.errstate(invalid="ignore", divide="ignore"):
        total = np.sum(counts, axis=0) if counts else np.zeros(len(centres), np.int64)
        ens = float(total @ centres / total.sum())
        ratios = [float(h @ centres / h.sum()) / ens for h in counts]
    v = _finite(ratios)
    if spread:
        want = float(np.std(v, ddof=1)) if len(v) >= 2 else math.nan
    else:
        want = float(np.mean(v)) if len(v) else math.nan
    return want, float(np.abs(v).max()) if len(v) else 1.0


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


def check_refused(c, h5, tmp):
    """The two refusals a store is built for: a fit range holding one energy of the grid (docs/REDUCED.md,
    "The fit range": fewer than four, refused naming the first (variant, N_G)), and configurations
    exported from a store that keeps none."""
    low = min(c["energies"])
    code, out, err = run("reduce", h5, "--boot", 20, "-o", tmp / "narrow", "--fit-energies", low / 2, low * 2)
    assert_ended_well(code, err, "reduce --fit-energies")
    assert code == 2 and f"default N={c['sizes'][0]}: the fit range (E_G in [" in err and "holds 1 energies" in err \
        and "widen the range" in err, err
    code, out, err = run("export", h5, "--out", tmp / "p.xyz")
    assert_ended_well(code, err, "export --out p.xyz")
    assert code == 2 and "the store holds no configurations" in err, err


@settings(max_examples=25, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(campaigns())
def test_every_reader_ends_well_on_any_store(c):
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        h5 = tmp / "p.h5"
        tasks, status, scalars, hists, edges = write(c, h5)
        cells = expectations(tasks, status, scalars, hists, edges)
        present = {k for sc in scalars if sc is not None for k in sc}
        plan = fit_plan(cells, present)
        clean = all(c["kind"][k] == "law" for k in FITTED)
        code, out, err = run("verify", h5, "--quiet")
        assert code == 0, err  # the writer's own store is sound
        code, out, err = run("status", h5, "--json")
        assert_ended_well(code, err, "status")
        assert code == 0
        check_status(out, tasks, status)
        if c["refused"]:
            check_refused(c, h5, tmp)
        code, out, err = run("reduce", h5, "--boot", 20, "-o", tmp / "red", "--json")
        assert_ended_well(code, err, "reduce")
        assert code == 0, err
        check_reduce(tmp / "red", cells, edges, err, plan, json.loads(out), clean)
        code, out, err = run("export", h5, "--out", tmp / "p.csv")
        assert_ended_well(code, err, "export")
        assert code == 0, err
        check_export(tmp / "p.csv", tasks, status, scalars)


#: a store of two systems, every size's cells odd in another way, and odd values: the system figures too
TWO_SYSTEMS = {"sizes": [16, 24, 32], "energies": [1e-5, 1e-7, 1e-8, 1e-9], "seeds": 3, "variant": True,
               "fate": {16: "full", 24: "one", 32: "mixed"},
               "kind": dict({k: "law" for k in LAWS}, delta_Z="negative", psi_O="special", E_G="flat"),
               "flags": "some_bad", "histograms": "zero", "refused": False, "seed": 5}


@pytest.mark.slow  # every figure of two stores: tests/report/test_plots.py draws them in the quick suite
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
        assert code == 0, err


def test_a_size_without_a_usable_cell_after_one_with_fits(tmp_path):
    """The reducer's former IndexError (scaling.py, a mask of the previous size): N_G = 24 has one
    packing a cell, below the three a fit needs, after N_G = 16, whose cells are fitted."""
    c = {"sizes": [16, 24], "energies": [1e-7, 1e-8, 1e-9, 1e-10, 1e-12], "seeds": 4, "variant": False,
         "fate": {16: "full", 24: "one"}, "kind": {k: "law" for k in LAWS}, "flags": "good",
         "histograms": "counts", "refused": False, "seed": 1}
    tasks, status, scalars, hists, edges = write(c, tmp_path / "p.h5")
    code, out, err = run("reduce", tmp_path / "p.h5", "--boot", 20, "-o", tmp_path / "red", "--json")
    assert code == 0, err
    assert "default N=24: 5 cell(s) with fewer than 3 finished packings left out of the fits" in err
    cells = expectations(tasks, status, scalars, hists, edges)
    plan = fit_plan(cells, set(LAWS))
    assert plan[0][("default", 16, "A_G", "E_G")] and not plan[0][("default", 24, "A_G", "E_G")]
    check_reduce(tmp_path / "red", cells, edges, err, plan, json.loads(out), True)
    table = {r["N_G"]: r for r in _read_csv(tmp_path / "red" / "table.csv")}
    assert table["16"]["A_G_star_E"] != "" and table["24"]["A_G_star_E"] == ""
