"""Rules for the N_G -> inf line compared on the same intercepts (docs/REDUCED.md, "Sizes off the
1/N_G line"): the coverage harness's campaigns (``experiments/error_bars.py``) are reduced once by
the reducer, each 1/N_G extrapolation's inputs kept (the sizes, their intercepts and the intercepts'
bootstrap replicas, one file per campaign), and every rule is then applied to those inputs in
seconds: the line alone, the Akaike average of line and parabola with a penalty per parameter
of 2 (Akaike's), 4, 6 and 10, the reducer's rule (penalty 2, the smallest sizes left out while
both models fail their chi^2 test), and penalty 2 with the replicas centred on the data's averaged
model.

    python experiments/line_rules.py dump lines/ --reps 200 base:uniform-12 base:uniform-40 \\
        base:unequal base:ladder 1/N^2:uniform-12 1/N^2:uniform-40     # ~2 s a campaign; resumes
    python experiments/line_rules.py table lines/

Per rule and entry: the root-mean-square of value - truth, the spread of (value - truth) / error
(``error_bars._trimmed_sd``), 1- and 2-sigma coverage.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import error_bars as H  # noqa: E402

from campaign.results import fits  # noqa: E402
from campaign.results.reduce import Settings  # noqa: E402

#: the four intercepts in the order the reducer extrapolates them (campaign.plan.targets.FITS)
KEYS = ("A_G_star_E", "A_G_star_Z", "psi_O_star", "psi_O_star_Z")
PENALTIES = (None, 2.0, 4.0, 6.0, 10.0)   # None: the line alone


def _file_name(truth, form, rep):
    return f"{truth.replace('/', '').replace('^', '')}_{form}_{rep}.npz"


def dump(out: Path, jobs, reps: int, boot: int):
    """Reduce each (truth, form) campaign ``0 .. reps - 1`` and keep its extrapolations' inputs."""
    calls = []
    original = fits.line_in_inverse_n

    def spy(sizes, values, replicas, *a, **k):
        calls.append((np.array(sizes), np.array(values, float), np.array(replicas, float)))
        return original(sizes, values, replicas, *a, **k)

    fits.line_in_inverse_n = spy
    out.mkdir(parents=True, exist_ok=True)
    try:
        for rep in range(reps):
            for truth, form in jobs:
                name = out / _file_name(truth, form, rep)
                if name.exists():
                    continue
                calls.clear()
                e = H.entries(H.campaign(H.TRUTHS[truth], form, rep), Settings(n_boot=boot))
                arr = {"truth": np.array(truth), "form": np.array(form),
                       "entries": np.array(json.dumps({k: [float(x[0]), float(x[1])] for k, x in e.items()}))}
                for j, (s, v, R) in enumerate(calls):  # the four intercepts, then phi_J and the rest
                    arr[f"s{j}"], arr[f"v{j}"], arr[f"R{j}"] = s, v, R
                arr["calls"] = np.array(len(calls))
                tmp = name.with_suffix(".tmp.npz")
                np.savez(tmp, **arr)
                os.replace(tmp, name)
            print(f"  campaign {rep + 1} of {reps} of each", file=sys.stderr)
    finally:
        fits.line_in_inverse_n = original


def _models(N, Y, Winv, penalty):
    """Per row of ``Y``: the line's intercept, or (``penalty`` given, four sizes or more) the Akaike
    average of line and parabola, and the averaged model's values at the sizes."""
    out = []
    for deg in (1, 2):
        X = np.column_stack([N ** -k for k in range(deg + 1)])
        M = np.linalg.pinv(X.T @ Winv @ X) @ X.T @ Winv
        C = Y @ M.T
        F = C @ X.T
        r = Y - F
        out.append((C[:, 0], F, np.einsum("bi,ij,bj->b", r, Winv, r) + (penalty or 0.0) * (deg + 1)))
    (v1, F1, a1), (v2, F2, a2) = out
    if penalty is None or len(N) < 4:
        return v1, F1
    w2 = 1.0 / (1.0 + np.exp(np.clip((a2 - a1) / 2, -700, 700)))
    return (1 - w2) * v1 + w2 * v2, (1 - w2)[:, None] * F1 + w2[:, None] * F2


def averaged(sizes, values, replicas, penalty, centred=False):
    """The value and error of the line alone (``penalty`` None) or of the Akaike-weighted average of
    line and parabola with ``penalty`` per parameter, every replica averaged with its own weights.
    ``centred``: the replicas' deviations from their mean put about the data's averaged model before
    they are fitted, so that a replica's chi^2 holds its own noise and not the data's distance from
    the line a second time."""
    N = np.asarray(sizes, float)
    y = np.asarray(values, float)[None]
    R = np.asarray(replicas, float)
    Winv = np.linalg.pinv(np.cov(R.T))
    v, F = _models(N, y, Winv, penalty)
    if centred:
        R = F + (R - R.mean(0))
    return float(v[0]), fits.spread(_models(N, R, Winv, penalty)[0])


def table(folder: Path, keys=("A_G_star_E", "psi_O_star")):
    by = collections.defaultdict(list)
    for f in sorted(folder.glob("*.npz")):
        d = np.load(f)
        by[(str(d["truth"]), str(d["form"]))].append(d)
    lines = ["| truth, form, entry (campaigns) | " + " | ".join("line" if p is None else f"penalty {p:g}"
                                                              for p in PENALTIES) + " | the reducer | "
             "penalty 2, replicas centred |",
             "|---" * (len(PENALTIES) + 3) + "|"]
    for (truth, form), L in sorted(by.items()):
        want = H.TRUTHS[truth].values(H.SIZES)
        for key in keys:
            j = KEYS.index(key)
            cells = []
            for pen in PENALTIES + ("reducer", "centred"):
                if pen == "reducer":  # penalty 2 and the smallest sizes left out while both fail
                    vr = np.array([(r.value, r.err) for r in (fits.line_in_inverse_n(d[f"s{j}"], d[f"v{j}"],
                                                                                      d[f"R{j}"]) for d in L)])
                elif pen == "centred":
                    vr = np.array([averaged(d[f"s{j}"], d[f"v{j}"], d[f"R{j}"], 2.0, centred=True) for d in L])
                else:
                    vr = np.array([averaged(d[f"s{j}"], d[f"v{j}"], d[f"R{j}"], pen) for d in L])
                dev = vr[:, 0] - want[key]
                z = dev / vr[:, 1]
                cells.append(f"{np.sqrt(np.mean(dev ** 2)) * 1e4:.2f}, {H._trimmed_sd(z):.2f}, "
                             f"{np.mean(np.abs(z) <= 1):.2f} / {np.mean(np.abs(z) <= 2):.2f}")
            lines.append(f"| {truth}, {form}, {key} ({len(L)}) | " + " | ".join(cells) + " |")
    print("\n".join(lines))


def _call_of(d, key):
    """The index of the dumped extrapolation that made entry ``key`` (the four intercepts in order;
    ``phi_J``: the call whose average is the reducer's value)."""
    if key in KEYS:
        return KEYS.index(key)
    want = json.loads(str(d["entries"])).get(key, [np.nan])[0]
    for j in range(len(KEYS), int(d["calls"]) if "calls" in d else 0):
        if np.isclose(averaged(d[f"s{j}"], d[f"v{j}"], d[f"R{j}"], 2.0)[0], want, rtol=0, atol=1e-12):
            return j
    return None


def ratios(folder: Path, before: Path, keys=KEYS + ("phi_J",)):
    """The variance of value - truth of the line alone through the reducer's intercepts and of the
    reducer's own value (the average, with its rule for sizes off the line), each over the reducer
    before 0.4's on the same campaigns (``before``: its error_bars.py results): what the weights
    change, apart from what the line's rule changes."""
    old = collections.defaultdict(dict)
    for r in H.load_results(before):
        old[(r["truth"], r["form"])][r["rep"]] = r["entries"]
    by = collections.defaultdict(list)
    for f in sorted(folder.glob("*.npz")):
        d = np.load(f)
        by[(str(d["truth"]), str(d["form"]))].append((int(f.stem.rsplit("_", 1)[1]), d))
    print("| truth, form (campaigns) | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys))
    for (truth, form), L in sorted(by.items()):
        want = H.TRUTHS[truth].values(H.SIZES)
        cells = []
        for key in keys:
            dev = {"line": [], "reducer": [], "before": []}
            for rep, d in L:
                j = _call_of(d, key)
                o = old[(truth, form)].get(rep, {}).get(key)
                if j is None or o is None or not np.isfinite(o[0]):
                    continue
                dev["line"].append(averaged(d[f"s{j}"], d[f"v{j}"], d[f"R{j}"], None)[0] - want[key])
                dev["reducer"].append(json.loads(str(d["entries"]))[key][0] - want[key])
                dev["before"].append(o[0] - want[key])
            var = {k: np.var(v, ddof=1) if len(v) > 2 else np.nan for k, v in dev.items()}
            cells.append(f"{var['line'] / var['before']:.2f}, {var['reducer'] / var['before']:.2f}")
        print(f"| {truth}, {form} ({len(L)}) | " + " | ".join(cells) + " |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("dump", help="reduce the campaigns, keep each extrapolation's inputs")
    d.add_argument("folder", type=Path)
    d.add_argument("jobs", nargs="+", help="truth:form pairs, e.g. base:uniform-12 '1/N^2:uniform-40'")
    d.add_argument("--reps", type=int, default=200)
    d.add_argument("--boot", type=int, default=Settings().n_boot)
    t = sub.add_parser("table", help="every rule on the kept inputs: a markdown table")
    t.add_argument("folder", type=Path)
    t.add_argument("--keys", nargs="+", default=["A_G_star_E", "psi_O_star"], choices=KEYS)
    r = sub.add_parser("ratios", help="variance ratios against the reducer before 0.4: the line alone, the reducer")
    r.add_argument("folder", type=Path)
    r.add_argument("before", type=Path, help="error_bars.py --results of the reducer before 0.4, the same campaigns")
    args = ap.parse_args(argv)
    if args.cmd == "dump":
        jobs = [tuple(j.split(":", 1)) for j in args.jobs]
        bad = [j for j in jobs if len(j) != 2 or j[0] not in H.TRUTHS or j[1] not in H.FORMS]
        if bad:
            ap.error(f"jobs: expected truth:form with a truth of {list(H.TRUTHS)} and a form of {list(H.FORMS)}, "
                     f"got {bad}")
        dump(args.folder, jobs, args.reps, args.boot)
    elif args.cmd == "ratios":
        ratios(args.folder, args.before)
    else:
        table(args.folder, tuple(args.keys))


if __name__ == "__main__":
    main()
