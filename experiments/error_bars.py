"""Do the finite-size table's error bars hold? Synthetic campaigns of known truth, reduced by the
reducer itself (``campaign.results.reduce.reduce_table`` and the jamming point, default settings),
many times over (docs/REDUCED.md, "Error bars that hold").

    python experiments/error_bars.py --reps 400 --json coverage.json            # every form, the base truth
    python experiments/error_bars.py --forms uniform-12 --truths all --reps 400  # every truth, one form
    python experiments/error_bars.py --reps 40 --forms unequal --truths base    # a quick look

A campaign is the paper-small grid (N_G 64..1024, E_G 1e-15..1e-3, one energy per decade) whose
packings are drawn from a truth (``TRUTHS``), with a number of packings per cell set by a form
(``FORMS``). Per packing, at energy ``E_G`` in ``[E, 1.1 E]`` with typical overlap
``delta = (alpha E_G / 2)^(1/alpha)`` and typical excess contact number ``z_t = Z0 delta^(1/2)``:

* ``Delta Z = (2 / N_G) Binomial(t, m / t)`` with ``m = N_G z_t / 2`` excess contacts (whole
  numbers, as packings have; ``t = ceil(m / 0.55)``), so the cell mean of ``Delta Z`` is ``z_t``;
* ``A_G = A*(N) + B z_t^beta_Z (1 + k z_t^omega) + rho B beta_Z z_t^(beta_Z - 1) (Delta Z - z_t)
  + s_A(E) / sqrt(N_G) xi``: the cell means follow ``A*(N) + c x^beta`` exactly in both abscissae
  (``beta_E = beta_Z / (2 alpha)``), packing by packing ``A_G`` follows the packing's own excess
  contacts with a share ``rho`` of the law's slope, and ``A*(N) = A* + a_1 / N + a_2 / N^2``;
* ``Psi_O`` alike (``P*``, ``B_P``, ``psi_beta_Z``, ``s_P``); ``phi = phi_J(N) + c_phi delta + s_phi
  / sqrt(N) xi``;
* ``xi`` Gaussian or Student's t with 3 degrees of freedom scaled to unit variance (heavy tails);
  ``s(E)`` constant or growing across the fit range (``trend``: the spread at the fit range's top
  energy over its bottom one).

An energy ladder (form ``ladder``) draws one seed's packings at all its energies with a shared part of
``xi`` (correlation ``LADDER_RHO``), as chains from one start are; its spec says ``start: ladder``, so
the reducer resamples whole seeds.

Per entry (the eight of the N_G -> inf row, each size's intercept and exponent of the four laws, and
``phi_J``): ``z = (value - truth) / error`` over the campaigns; its median, its spread (the standard
deviation of ``z`` with the 1% most extreme on each side left out: a few campaigns with a tiny error
would otherwise decide it), the share of 1- and 2-sigma intervals holding the truth (nominal 0.683 and
0.954), the standard deviation of ``value - truth`` (what the estimator's precision is), the
campaigns without a value, and those whose size's fit the reducer marks undetermined (``*`` in the
table: an exponent at a search bound, or too many of its bootstrap refits there; its value and error
are reported as not a measurement, so they are counted apart and not in ``z``). The same campaigns' packings are reproducible (``numpy`` generators
keyed by truth, form and repetition), so two versions of the reducer are compared on the same data
(``--json`` then ``--compare OLD.json``: variance ratios per entry).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from campaign.results.finished import finished_from_arrays
from campaign.results.reduce import Settings, reduce_table

SIZES = (64, 128, 256, 512, 1024)
ENERGIES = tuple(10.0 ** np.arange(-15, -2))
Z0 = 5.0          # Delta Z = 0.28 at E_G = 1e-5 (paper-small, N_G 1024)
Z_P = 0.55
LADDER_RHO = 0.7  # correlation of one seed's packings along a ladder's energies
ROW = ("A_G_star_E", "beta_E", "A_G_star_Z", "beta_Z", "psi_O_star", "psi_beta_E", "psi_O_star_Z", "psi_beta_Z")
LAWS = (("A_G", "E_G", "A_G_star_E", "beta_E"), ("A_G", "delta_Z", "A_G_star_Z", "beta_Z"),
        ("psi_O", "E_G", "psi_O_star", "psi_beta_E"), ("psi_O", "delta_Z", "psi_O_star_Z", "psi_beta_Z"))


@dataclass(frozen=True)
class Truth:
    alpha: float = 2.0
    A_star: float = 0.446
    a_1: float = -0.6       # A*(N) = A* + a_1 / N + a_2 / N^2
    a_2: float = 0.0
    B: float = 0.22         # Delta A_G = 0.054 at Delta Z = 0.28 (paper-small, N_G 1024, 1e-5)
    beta_Z: float = 1.05
    P_star: float = 0.369
    p_1: float = -0.4
    p_2: float = 0.0
    B_P: float = 0.30
    psi_beta_Z: float = 0.98
    k: float = 0.0          # correction to scaling: (1 + k z_t^omega)
    omega: float = 1.0
    rho: float = 0.5        # share of the law's slope a packing's own excess contacts carry
    s_A: float = 0.10       # spread between packings times sqrt(N_G) (paper-small: 0.10)
    s_P: float = 0.33       # (the prior's fit-range cells: 0.33)
    trend: float = 1.0      # spread at the fit range's top energy over its bottom one
    tails: str = "gauss"    # or "t3"
    phi_J: float = 0.8420
    phi_1: float = -0.15
    c_phi: float = 1.7
    s_phi: float = 0.056

    def values(self, sizes=SIZES) -> dict:
        """The true N_G -> inf row, and per size its intercepts; exponents are the same at every size."""
        bE, pE = self.beta_Z / (2 * self.alpha), self.psi_beta_Z / (2 * self.alpha)
        row = {"A_G_star_E": self.A_star, "beta_E": bE, "A_G_star_Z": self.A_star, "beta_Z": self.beta_Z,
               "psi_O_star": self.P_star, "psi_beta_E": pE, "psi_O_star_Z": self.P_star,
               "psi_beta_Z": self.psi_beta_Z, "phi_J": self.phi_J}
        for n in sizes:
            a = self.A_star + self.a_1 / n + self.a_2 / n ** 2
            p = self.P_star + self.p_1 / n + self.p_2 / n ** 2
            row.update({f"{n}:A_G_star_E": a, f"{n}:A_G_star_Z": a, f"{n}:psi_O_star": p, f"{n}:psi_O_star_Z": p,
                        f"{n}:beta_E": bE, f"{n}:beta_Z": self.beta_Z, f"{n}:psi_beta_E": pE,
                        f"{n}:psi_beta_Z": self.psi_beta_Z, f"{n}:phi_J": self.phi_J + self.phi_1 / n})
        return row


TRUTHS = {
    "base": Truth(),
    "no 1/N": Truth(a_1=0.0, p_1=0.0),
    "heavy tails": Truth(tails="t3"),
    "spread grows 1.5x": Truth(trend=1.5),
    "correction to scaling": Truth(k=-0.2),            # experiments/fit_rules.py's "like paper-small"
    "alpha 2.5": Truth(alpha=2.5, beta_Z=1.05),
    "1/N^2": Truth(a_2=-40.0, p_2=-60.0),             # beyond 1/N_G: 1e-2 at N_G 64, 6e-4 at 256
}


def _counts_uniform(k):
    return lambda rng, C: np.full(C, k)


def _counts_unequal(rng, C):
    return rng.integers(3, 25, C)


def _counts_small(rng, C):
    return rng.integers(3, 13, C)


def _counts_few_full(rng, C):
    c = np.full(C, 5)
    c[rng.choice(C, max(1, C // 10), replace=False)] = 40
    return c


def _counts_precision(rng, C):
    """Like a precision campaign's allocation: the pilot everywhere, more seeds at large N_G and low
    energy (where the row's leverage is), scattered by the rounds."""
    n = np.repeat(np.arange(len(SIZES)), len(ENERGIES))
    e = np.tile(np.arange(len(ENERGIES)), len(SIZES))
    want = 4 + 20 * (n / (len(SIZES) - 1)) * (1 - e / (len(ENERGIES) - 1)) ** 2
    return np.maximum(4, np.round(want * np.exp(0.4 * rng.normal(size=C)))).astype(int)


#: name -> (packings per cell, share of tasks that fail, ladder)
FORMS = {
    "uniform-5": (_counts_uniform(5), 0.0, False),
    "uniform-12": (_counts_uniform(12), 0.0, False),
    "uniform-40": (_counts_uniform(40), 0.0, False),
    "unequal": (_counts_unequal, 0.0, False),
    "few full": (_counts_few_full, 0.0, False),
    "precision": (_counts_precision, 0.0, False),
    "ladder": (_counts_uniform(12), 0.0, True),
    "failures": (_counts_uniform(12), 0.15, False),
    "small": (_counts_small, 0.0, False),     # the quick suite's (tests/results/test_error_bars.py)
}


def _spec(truth: Truth, ladder: bool, sizes=SIZES) -> str:
    variant = "protocol: {start: ladder}\n" if ladder else ""
    return ("name: coverage\nseed: 1\n"
            f"system: {{potential: {{exponent: {truth.alpha}}}}}\n"
            f"grid: {{N_G: {list(sizes)}, E_G: {{log_range: [1.0e-15, 1.0e-3], per_decade: 1}}, seeds: 1}}\n"
            + variant)


def _noise(rng, shape, tails):
    if tails == "gauss":
        return rng.normal(size=shape)
    return rng.standard_t(3, size=shape) / math.sqrt(3.0)


def campaign(truth: Truth, form: str, rep: int, sizes=SIZES, energies=ENERGIES):
    """The packings of one synthetic campaign: ``finished_from_arrays`` of its task table (the grid
    ``sizes`` x ``energies``, by default paper-small's)."""
    counts_of, fail, ladder = FORMS[form]
    key = [20261128, rep, list(TRUTHS.values()).index(truth) if truth in TRUTHS.values() else 99,
           list(FORMS).index(form)]
    rng = np.random.default_rng(key)
    C = len(sizes) * len(energies)
    counts = counts_of(rng, C)
    # the fit range's energies (typical overlap <= 1e-3) span log10 E in [lo, hi]: the spread's trend
    logE = np.log10(energies)
    fit = (truth.alpha * np.asarray(energies) / 2) ** (1 / truth.alpha) <= 1e-3 * (1 + 1e-9)
    lo, hi = logE[fit].min(), logE[fit].max()
    cols = {k: [] for k in ("variant", "N", "E", "seed", "status")}
    sc = {k: [] for k in ("E_G", "delta_Z", "A_G", "psi_O", "phi", "N", "N_R", "jam_status", "identities_ok")}
    for i, n in enumerate(sizes):
        S = int(counts[i * len(energies):(i + 1) * len(energies)].max())
        shared = _noise(rng, (S, 3), truth.tails)  # a ladder seed's shared part of xi (A_G, Psi_O, phi)
        for j, E in enumerate(energies):
            m_c = int(counts[i * len(energies) + j])
            E_G = E * (1 + 0.1 * rng.random(m_c))
            delta = (truth.alpha * E_G / 2) ** (1 / truth.alpha)
            zt = Z0 * delta ** 0.5
            m = n * zt / 2
            t = np.maximum(np.ceil(m / Z_P), 1).astype(np.int64)
            dz = 2.0 / n * rng.binomial(t, m / t)
            xi = _noise(rng, (m_c, 3), truth.tails)
            if ladder:
                xi = math.sqrt(LADDER_RHO) * shared[:m_c] + math.sqrt(1 - LADDER_RHO) * xi
            grow = truth.trend ** np.clip((np.log10(E) - lo) / (hi - lo), 0, 1)
            corr = 1 + truth.k * zt ** truth.omega
            A = (truth.A_star + truth.a_1 / n + truth.a_2 / n ** 2 + truth.B * zt ** truth.beta_Z * corr
                 + truth.rho * truth.B * truth.beta_Z * zt ** (truth.beta_Z - 1) * (dz - zt)
                 + truth.s_A * grow / math.sqrt(n) * xi[:, 0])
            P = (truth.P_star + truth.p_1 / n + truth.p_2 / n ** 2 + truth.B_P * zt ** truth.psi_beta_Z * corr
                 + truth.rho * truth.B_P * truth.psi_beta_Z * zt ** (truth.psi_beta_Z - 1) * (dz - zt)
                 + truth.s_P * grow / math.sqrt(n) * xi[:, 1])
            phi = truth.phi_J + truth.phi_1 / n + truth.c_phi * delta + truth.s_phi / math.sqrt(n) * xi[:, 2]
            status = np.where(rng.random(m_c) < fail, 2, 1)
            cols["variant"] += ["default"] * m_c
            cols["N"] += [n] * m_c
            cols["E"] += [E] * m_c
            cols["seed"] += list(range(m_c))
            cols["status"] += list(status)
            for k, v in (("E_G", E_G), ("delta_Z", dz), ("A_G", A), ("psi_O", P), ("phi", phi)):
                sc[k] += list(v)
            sc["N"] += [n] * m_c
            sc["N_R"] += list(rng.binomial(n, 0.04, m_c))
            sc["jam_status"] += [0] * m_c
            sc["identities_ok"] += [1] * m_c
    T = len(cols["N"])
    return finished_from_arrays(attrs={"schema": "jamming-campaign/1", "spec_yaml": _spec(truth, ladder, sizes)},
                                variant=cols["variant"], N=np.array(cols["N"]), E=np.array(cols["E"]),
                                ids=[str(k) for k in range(T)], seed=np.array(cols["seed"]),
                                status=np.array(cols["status"]), scalars={k: np.array(v, float) for k, v in sc.items()})


def entries(fin, settings: Settings) -> dict:
    """The reducer's values and errors of every entry the harness judges: key -> (value, error)."""
    from campaign.results.protocols import jamming_point

    tab = reduce_table(fin, settings)
    out = {}
    x = tab.extrapolated.get("default", {})
    for k in ROW:
        out[k] = (x.get(k, np.nan), x.get(f"{k}_err", np.nan), 0.0)
    for r in tab.rows:
        for _, _, key, bkey in LAWS:
            undetermined = float(bool(r.get(f"{bkey}_undetermined")))   # marked * in the table
            for k in (key, bkey):
                out[f"{r['N_G']}:{k}"] = (r.get(k, np.nan), r.get(f"{k}_err", np.nan), undetermined)
    try:
        jam_rows, jam, _ = jamming_point(tab, settings)
    except TypeError:  # the reducer before 0.4 (jamming_point(fin, grid, settings, exponents)): --compare's
        jam_rows, jam = jamming_point(tab.fin, tab.grid, settings,
                                      {v: d["exponent"] for v, d in tab.systems.items()})
    j = jam.get("default", {})
    out["phi_J"] = (j.get("phi_J", np.nan), j.get("phi_J_err", np.nan), 0.0)
    for r in jam_rows:
        out[f"{r['N_G']}:phi_J"] = (r.get("phi_J", np.nan), r.get("phi_J_err", np.nan), 0.0)
    return out


def one(job):
    truth_name, form, rep, boot = job
    fin = campaign(TRUTHS[truth_name], form, rep)
    t0 = time.perf_counter()
    e = entries(fin, Settings(n_boot=boot))
    return {"truth": truth_name, "form": form, "rep": rep, "boot": boot, "seconds": time.perf_counter() - t0,
            "entries": {k: [float(x) for x in v] for k, v in e.items()}}


def summarise(results, truth: Truth, keys=None, sizes=SIZES) -> list:
    """Per entry: the statistics of ``z = (value - truth) / error`` over the campaigns."""
    values = truth.values(sizes)
    keys = keys or sorted({k for r in results for k in r["entries"]}, key=_order)
    out = []
    for k in keys:
        ve = np.array([(r["entries"].get(k, [np.nan, np.nan]) + [0.0])[:3] for r in results], float)
        marked = ve[:, 2] > 0
        ok = np.all(np.isfinite(ve[:, :2]), axis=1) & (ve[:, 1] > 0) & ~marked
        v, e = ve[ok, 0], ve[ok, 1]
        d = v - values[k.partition("~")[0]]
        z = d / e
        out.append({"key": k, "n": int(ok.sum()), "missing": int((~ok & ~marked).sum()), "undetermined": int(marked.sum()),
                    "median_z": float(np.median(z)) if len(z) else np.nan, "spread_z": _trimmed_sd(z),
                    "cover_1": float(np.mean(np.abs(z) <= 1)) if len(z) else np.nan,
                    "cover_2": float(np.mean(np.abs(z) <= 2)) if len(z) else np.nan,
                    "sd": float(np.std(d, ddof=1)) if len(d) > 1 else np.nan,
                    "median_error": float(np.median(e)) if len(e) else np.nan})
    return out


def _trimmed_sd(z):
    if len(z) < 3:
        return np.nan
    lo, hi = np.quantile(z, [0.01, 0.99])
    zz = z[(z >= lo) & (z <= hi)]
    # the standard deviation of a unit normal cut at its 1% tails is 0.9427: undo that cut
    return float(np.std(zz, ddof=1) / 0.9427)


def _order(k):
    size, _, name = k.partition("~")[0].rpartition(":")
    keys = ROW + ("phi_J",)
    return (int(size) if size else 10 ** 9, keys.index(name) if name in keys else 99, name)


#: what the docs' table asks of every entry and form
BOUNDS = {"cover_1": (0.63, 0.73), "cover_2": (0.92, 0.98), "median_z": (-0.2, 0.2), "spread_z": (0.9, 1.1)}


def failing(summary) -> list:
    """The (key, statistic, value) outside ``BOUNDS``."""
    return [(s["key"], name, s[name]) for s in summary for name, (lo, hi) in BOUNDS.items()
            if not (lo <= s[name] <= hi)]


def _cell(s) -> str:
    return f"{s['cover_1']:.2f} / {s['cover_2']:.2f}, {s['median_z']:+.2f}, {s['spread_z']:.2f}"


def doc_tables(summaries, old=None) -> str:
    """The docs' compact tables from ``summaries`` (``main``'s, ``--entries all``): per truth and
    form, each entry of the N_G -> inf row and ``phi_J`` as "1-sigma / 2-sigma, median z, spread
    z"; the same for ``old`` (the other reducer's summaries per (truth, form), entry -> summary) and the variance
    ratios of value - truth, this / that; then every size's entries outside ``BOUNDS``, split by the
    share of campaigns whose fit at that size is marked undetermined (a tenth or more: the
    determined ones are a selected sample)."""
    keys = ROW + ("phi_J",)
    head = "| truth, form (campaigns) | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys) + "\n"
    lines = []

    def table(title, cell, rows):
        lines.append(f"{title}\n\n" + head + "".join(
            f"| {t}, {f} ({reps}) | " + " | ".join(cell(by.get(k), t, f, k) for k in keys) + " |\n"
            for t, f, reps, by in rows))

    rows = [(s["truth"], s["form"], s["reps"], {e["key"]: e for e in s["entries"]}) for s in summaries]
    table("This reducer: 1-sigma / 2-sigma coverage, median z, spread of z", lambda e, *_: _cell(e) if e else "", rows)
    if old:
        table("The reducer before 0.4, the same campaigns", lambda e, t, f, k: _cell(old[(t, f)][k])
              if k in old.get((t, f), {}) else "", rows)
        table("Variance of value - truth, this reducer / before 0.4",
              lambda e, t, f, k: f"{(e['sd'] / old[(t, f)][k]['sd']) ** 2:.2f}"
              if e and k in old.get((t, f), {}) else "", rows)
    per_size = ("Every size's entries (intercept and exponent of the four laws, phi_J) outside the bounds\n\n"
                "| truth, form | outside, fit determined in 90% of campaigns or more | outside, "
                "undetermined in a tenth or more |\n|---|---|---|\n")
    for t, f, reps, by in rows:
        per = [e for k, e in by.items() if ":" in k]
        bad = failing(per)
        names = sorted({k for k, *_ in bad}, key=_order)
        sel = [k for k in names if by[k]["undetermined"] >= 0.1 * reps]
        rest = [k for k in names if k not in sel]
        per_size += (f"| {t}, {f} | {len(rest)} of {len(per)}" + (f": {', '.join(rest)}" if rest else "")
                     + f" | {len(sel)}" + (f": {', '.join(sel)}" if sel else "") + " |\n")
    return "\n".join(lines + [per_size])


def load_results(path) -> list:
    """Campaigns' records from a --json file or a --results file (a torn last line left out)."""
    text = Path(path).read_text() if Path(path).exists() else ""
    if text.lstrip().startswith("{") and '"results"' in text[:2000] and "\n{" not in text.strip():
        return json.loads(text)["results"]
    out = []
    for line in text.splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            pass
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=400)
    ap.add_argument("--boot", type=int, default=Settings().n_boot,
                    help="the reducer's bootstrap resamples (default: the reducer's own; fewer make the 1/N_G "
                         "line's weights noisy and its errors a few per cent short, docs/REDUCED.md)")
    ap.add_argument("--forms", nargs="+", default=list(FORMS), help=f"of {list(FORMS)}")
    ap.add_argument("--truths", nargs="+", default=["base"], help=f"of {list(TRUTHS)}, or 'all'")
    ap.add_argument("--entries", choices=("row", "all"), default="row",
                    help="print the N_G -> inf row and phi_J (row), or every size's entries too (all)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", help="write every campaign's values and the summaries here")
    ap.add_argument("--results", help="a JSON-lines file every campaign's values are appended to as it is reduced; "
                                      "run again with the same file, only the campaigns it lacks are reduced "
                                      "(a long run in parts, or one cut short)")
    ap.add_argument("--doc", help="write the docs' compact tables (doc_tables) to this file")
    ap.add_argument("--compare", help="a --json or --results file of another version of the reducer on the same "
                                      "campaigns: the variance ratio (this / that) of value - truth per entry")
    a = ap.parse_args(argv)
    truths = list(TRUTHS) if a.truths == ["all"] else a.truths
    for name in truths + a.forms:
        if name not in TRUTHS and name not in FORMS:
            ap.error(f"unknown truth or form {name!r}")
    jobs = [(t, f, rep, a.boot) for t in truths for f in a.forms for rep in range(a.reps)]
    t0 = time.time()
    done = {(r["truth"], r["form"], r["rep"]): r for r in (load_results(a.results) if a.results else [])
            if r.get("boot") == a.boot}
    todo = [j for j in jobs if j[:3] not in done]
    if done:
        print(f"{len(jobs) - len(todo)} of {len(jobs)} campaigns already in {a.results}", file=sys.stderr)
    sink = open(a.results, "a") if a.results else None
    try:
        with ProcessPoolExecutor(a.workers) as ex:
            for k, r in enumerate(ex.map(one, todo, chunksize=4), 1):
                done[(r["truth"], r["form"], r["rep"])] = r
                if sink:
                    sink.write(json.dumps(r) + "\n")
                    sink.flush()
                if k % 50 == 0 or k == len(todo):
                    print(f"  {k} of {len(todo)} campaigns, {time.time() - t0:.0f} s", file=sys.stderr)
    finally:
        if sink:
            sink.close()
    results = [done[j[:3]] for j in jobs]
    other = {"results": load_results(a.compare)} if a.compare else None
    summaries, olds = [], {}
    print(f"{a.reps} campaigns per form and truth, bootstrap {a.boot}; {time.time() - t0:.0f} s")
    print("| truth | form | entry | median z | spread z | 1 sigma | 2 sigma | sd(value - truth) | no value | marked * |"
          + (" variance ratio |" if other else ""))
    print("|---|---|---|---|---|---|---|---|---|---|" + ("---|" if other else ""))
    for t in truths:
        for f in a.forms:
            res = [r for r in results if r["truth"] == t and r["form"] == f]
            keys = None if a.entries == "all" else [k for k in sorted({k for r in res for k in r["entries"]}, key=_order)
                                                    if ":" not in k]
            summ = summarise(res, TRUTHS[t], keys)
            summaries.append({"truth": t, "form": f, "reps": len(res), "entries": summ})
            old = {}
            if other:
                old_res = [r for r in other["results"] if r["truth"] == t and r["form"] == f]
                old = olds[(t, f)] = {s["key"]: s for s in summarise(old_res, TRUTHS[t], keys)}
            for s in summ:
                ratio = (s["sd"] / old[s["key"]]["sd"]) ** 2 if s["key"] in old else np.nan
                print(f"| {t} | {f} | {s['key']} | {s['median_z']:+.2f} | {s['spread_z']:.2f} | {s['cover_1']:.2f} | "
                      f"{s['cover_2']:.2f} | {s['sd']:.2g} | {s['missing']} | {s['undetermined']} |" + (f" {ratio:.2f} |" if other else ""))
    bad = [(s["truth"], s["form"], *x) for s in summaries for x in failing(s["entries"])]
    print(f"{len(bad)} (truth, form, entry, statistic) outside the bounds {BOUNDS}")
    for b in bad:
        print("   ", b)
    if a.doc:
        Path(a.doc).write_text(doc_tables(summaries, olds))
    if a.json:
        Path(a.json).write_text(json.dumps({"reps": a.reps, "boot": a.boot, "truths": {t: asdict(TRUTHS[t]) for t in truths},
                                            "summaries": summaries, "results": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
