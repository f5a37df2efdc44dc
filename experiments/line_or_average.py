"""How much of a store's N_G -> inf errors is the choice between the line and the parabola in 1/N_G
(docs/PRECISION.md, "The rounds on 0.4's estimator").

    python experiments/line_or_average.py STORE [STORE ...] [--boot 1000]

Reduces the stores twice with the reducer's default settings: as ``campaign reduce`` does (the
Akaike average of line and parabola, ``fits.line_in_inverse_n``) and with the line alone (the
average's parabola weight held at zero, everything else the same), and prints each intercept of the
row and ``beta_E`` both ways. Where the average's error is much larger than the line's, more seeds at
the same sizes shrink the intercept's error slowly: its error is mostly the choice between the
models, which the precision rounds' model of the errors (a line in 1/N_G) does not hold.
"""

from __future__ import annotations

import argparse
import sys
from unittest import mock

from campaign.results import fits
from campaign.results.reduce import Settings, reduce_campaign

KEYS = ("A_G_star_E", "A_G_star_Z", "psi_O_star", "psi_O_star_Z", "beta_E")


def rows(stores, boot):
    red = reduce_campaign(stores, Settings(n_boot=boot), distributions=False)
    return red.extrapolated


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store", nargs="+")
    ap.add_argument("--boot", type=int, default=1000)
    a = ap.parse_args(argv)
    average = rows(a.store, a.boot)
    averaged = fits._averaged
    with mock.patch.object(fits, "_averaged", lambda models: averaged(models[:1])):
        line = rows(a.store, a.boot)
    print("| variant | entry | the reducer (average) | the line alone | error ratio |\n|---|---|---|---|---|")
    for v, row in average.items():
        for k in KEYS:
            x, e, y, f = row.get(k), row.get(f"{k}_err"), line[v].get(k), line[v].get(f"{k}_err")
            if x is None or e is None:
                continue
            print(f"| {v} | {k} | {x:.6f} +- {e:.2g} | {y:.6f} +- {f:.2g} | {e / f:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
