"""Corrections to scaling in the universality campaign: the exponents of every system fitted
over matched windows of the distance to jamming, and the premise Delta Z ~ E_G^(1/(2 alpha)).

    python experiments/universality.py results/universality.h5 results/universality-1024.h5 \
        [--boot 200] [--json FILE]

Reads the usable packings (converged, identities held) of the store(s), per variant (each a
physical system; its exponent alpha from the stored spec, ``campaign.reduce.variant_systems``)
and N_G, groups them into cells and fits, with the reducer's code (``fit_power_law``, bootstrap
over packings; ``experiments/paper_hypotheses.py``'s ``cells`` and ``fit``):

* ``Delta Z = a + c E_G^x``: the premise of ``beta_E = beta_Z / (2 alpha)`` is ``x = 1/(2 alpha)``;
* ``A_G = A* + c E_G^beta_E`` and ``A_G = A* + c Delta Z^beta_Z`` over the cells whose typical
  relative overlap ``delta = (alpha E_G / 2)^(1/alpha)`` (two contacts per disk carrying the
  energy) lies below ``delta_max`` -- the same distance from jamming for every system, where a
  window in E_G would not be (E_G = 1e-5 is delta = 3e-3 for alpha = 2 but 0.03 for alpha = 3);
  ``delta_max = inf`` is the reducer's default full range;

then extrapolates each exponent linearly in 1/N_G (``fit_inverse_n``), as the reducer does.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_hypotheses import cells, fit, fmt  # noqa: E402

from campaign.fits import fit_inverse_n  # noqa: E402
from campaign.reduce import load_finished, variant_systems  # noqa: E402

WINDOWS = (math.inf, 1e-2, 3e-3)


def overlap(E, alpha):
    """Typical relative overlap of a packing at energy per grain E (two contacts per disk)."""
    return (alpha * np.asarray(E, float) / 2.0) ** (1.0 / alpha)


def extrapolate(per_n, key="beta"):
    ok = [(n, r) for n, r in sorted(per_n.items()) if r is not None and np.isfinite(r[key + "_err"])]
    if len(ok) < 2:
        return None
    res = fit_inverse_n([n for n, _ in ok], [r[key] for _, r in ok], [r[key + "_err"] for _, r in ok])
    return {key: res.value, key + "_err": res.err, "chi2_dof": res.chi2_dof}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store", nargs="+")
    ap.add_argument("--boot", type=int, default=200)
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)

    everything = load_finished(args.store)
    usable, _ = everything.usable()
    systems = variant_systems(everything.attrs, variants=np.unique(everything.variant))
    out = {}
    for v in sorted(systems, key=lambda k: (systems[k]["exponent"], k)):
        var = np.asarray(everything.variant, dtype=str)
        fin = everything.subset(usable & (var == v))
        if len(fin) == 0:
            continue
        alpha = systems[v]["exponent"]
        s = fin.scalars
        E, A, dZ = s["E_G"], s["A_G"], s["delta_Z"]
        rec = {"alpha": alpha, "sizes": systems[v]["sizes"], "premise": 1.0 / (2.0 * alpha), "dZ_vs_E": {},
               "windows": {}}
        for N, groups in cells(fin, dZ, E).items():
            rec["dZ_vs_E"][N] = fit(groups, args.boot)
        rec["dZ_vs_E"]["inf"] = extrapolate(rec["dZ_vs_E"])
        for dmax in WINDOWS:
            emax = 2.0 / alpha * dmax ** alpha if math.isfinite(dmax) else math.inf
            keep = (lambda e, emax=emax: e <= emax * 1.01)
            w = {"E_max": emax, "beta_E": {}, "beta_Z": {}}
            for N, groups in cells(fin, A, E, keep).items():
                w["beta_E"][N] = fit(groups, args.boot)
            for N, groups in cells(fin, A, dZ, lambda e, emax=emax: e <= emax * 1.01).items():
                w["beta_Z"][N] = fit(groups, args.boot)
            w["beta_E"]["inf"] = extrapolate(w["beta_E"])
            w["beta_Z"]["inf"] = extrapolate(w["beta_Z"])
            rec["windows"][str(dmax)] = w
        out[v] = rec

    sizes = sorted({n for r in out.values() for n in r["dZ_vs_E"] if n != "inf"}) + ["inf"]
    head = "| system | alpha | " + " | ".join(f"N_G={n}" for n in sizes) + " | 1/(2 alpha) |"
    print("Delta Z = a + c E_G^x: the exponent x\n")
    print(head)
    print("|" + "---|" * (len(sizes) + 3))
    for v, r in out.items():
        print(f"| {v} | {r['alpha']:g} | " + " | ".join(fmt(r["dZ_vs_E"].get(n)) for n in sizes)
              + f" | {r['premise']:.3f} |")
    for dmax in WINDOWS:
        label = "every energy" if not math.isfinite(dmax) else f"typical overlap <= {dmax:g}"
        print(f"\nbeta_E and beta_Z over {label} (E_G max per system: "
              + ", ".join(f"{v} {r['windows'][str(dmax)]['E_max']:.2g}" for v, r in out.items()) + ")\n")
        print("| system | alpha | " + " | ".join(f"beta_E {n}" for n in sizes) + " | "
              + " | ".join(f"beta_Z {n}" for n in sizes) + " | beta_Z(inf)/(2 alpha) |")
        print("|" + "---|" * (2 * len(sizes) + 3))
        for v, r in out.items():
            w = r["windows"][str(dmax)]
            bz = w["beta_Z"].get("inf")
            pred = f"{bz['beta'] / (2 * r['alpha']):.3f}" if bz else "-"
            print(f"| {v} | {r['alpha']:g} | " + " | ".join(fmt(w["beta_E"].get(n)) for n in sizes) + " | "
                  + " | ".join(fmt(w["beta_Z"].get(n)) for n in sizes) + f" | {pred} |")
    if args.json:
        def clean(x):
            if isinstance(x, dict):
                return {str(k): clean(y) for k, y in x.items()}
            if isinstance(x, (float, np.floating)):
                return float(x) if np.isfinite(x) else None
            if isinstance(x, np.integer):
                return int(x)
            return x
        Path(args.json).write_text(json.dumps(clean(out), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
