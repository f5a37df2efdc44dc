"""The prior `campaign validate` prices a precision campaign with before its pilot has run: per cell
(N_G, E_G) of a finished store, the packings' means and covariances of E_G, Delta Z, A_G and psi_O.

    python experiments/precision_prior.py results/paper-small.h5 --out campaign/plan/precision_prior.json

The shipped one (campaign/plan/precision_prior.json) comes from `campaign run campaigns/paper-small.yaml`
(the paper's mixture, alpha = 2, a fixed unit box, FIRE on the O'Hern route; N_G 64..1024, E_G 1e-15..1e-3,
20 seeds per cell). `campaign.precision.allocation.plan_from_prior` reads it; docs/PRECISION.md says how
it stands in for sizes it does not hold.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from campaign.plan.parse import parse_spec
from campaign.results.finished import load_finished, usable_mask

NAMES = ("E_G", "delta_Z", "A_G", "psi_O")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("store")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    fin = load_finished(a.store)
    good, _ = usable_mask(fin.scalars, len(fin))
    spec = parse_spec(str(fin.attrs["spec_yaml"]), "the store's spec")
    if len(spec.variants) != 1:
        raise SystemExit("a prior comes from a store of one variant")
    cells = []
    for N in sorted(set(fin.N.tolist())):
        for E in sorted(set(fin.E.tolist())):
            m = good & (fin.N == N) & (fin.E == E) & (np.asarray(fin.variant) == "default")
            X = np.column_stack([fin.scalars[k][m] for k in NAMES])
            X = X[np.all(np.isfinite(X), axis=1)]
            if len(X) < 3:
                continue
            cells.append({"N": int(N), "E": float(E), "n": int(len(X)),
                          "mean": [float(v) for v in X.mean(axis=0)],
                          "cov": [[float(v) for v in row] for row in np.cov(X.T, ddof=1)]})
    out = {"schema": "jamming-campaign/precision-prior", "version": 1, "names": list(NAMES),
           "system": spec.system.canonical(), "protocol": dict(spec.variants[0].protocol),
           "source": f"{fin.attrs.get('name', '?')} ({a.store}), {len(good)} packings, package "
                     f"{fin.attrs.get('package_version', '?')}", "cells": cells}
    with open(a.out, "w") as fh:
        json.dump(out, fh, indent=1)
        fh.write("\n")
    print(f"wrote {a.out}: {len(cells)} cells", file=sys.stderr)


if __name__ == "__main__":
    main()
