"""How much of a store's N_G -> inf errors is the choice between the line and the parabola in 1/N_G
(docs/PRECISION.md, "The rounds on 0.4's estimator").

    python experiments/line_or_average.py STORE [STORE ...] [--boot 1000]

Reduces the stores twice with the reducer's default settings: as ``campaign reduce`` does (the
Akaike average of line and parabola, ``fits.line_in_inverse_n``) and with the line alone (the
average's parabola weight held at zero, everything else the same), and prints each intercept of the
row and ``beta_E`` both ways. Where the average's error is much larger than the line's, more seeds at
the same sizes shrink the intercept's error slowly: its error is mostly the choice between the
models. Beside them, the precision rounds' model of each intercept's error at the store's packings
(``errormodel.LawModel.intercept_variance``: the line's Fisher variance and the choice's part) and the
line's Fisher variance alone, the model before 0.4.
"""

from __future__ import annotations

import argparse
import sys
from unittest import mock

import numpy as np

from campaign.plan.targets import law_of
from campaign.precision import errormodel
from campaign.results import fits
from campaign.results.finished import load_finished
from campaign.results.reduce import Settings, reduce_table

KEYS = ("A_G_star_E", "A_G_star_Z", "psi_O_star", "psi_O_star_Z", "beta_E")


def tables(stores, boot):
    return reduce_table(load_finished(stores), Settings(n_boot=boot), per_size=False)


def model_errors(table) -> dict:
    """(variant, key) -> the rounds' model of the intercept's error at the table's packings, and the
    line's alone."""
    cells = errormodel.table_cells(table)
    n = errormodel.cell_counts(table, cells)
    out = {}
    for v in table.extrapolated:
        for key in KEYS:
            q, x, kind = law_of(key)
            if kind != "intercept":
                continue
            law = errormodel.build_law(table, cells, v, q, x)
            if law.ok:
                st = law.state(n)
                law.anchor(st)
                out[(v, key)] = (np.sqrt(law.intercept_variance(st)), np.sqrt(st[0][0, 0]))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store", nargs="+")
    ap.add_argument("--boot", type=int, default=1000)
    a = ap.parse_args(argv)
    table = tables(a.store, a.boot)
    average, models = table.extrapolated, model_errors(table)
    averaged = fits._averaged
    with mock.patch.object(fits, "_averaged", lambda models: averaged(models[:1])):
        line = tables(a.store, a.boot).extrapolated
    print("| variant | entry | the reducer (average) | the line alone | error ratio | the rounds' model of the "
          "average's error | of the line's |\n|---|---|---|---|---|---|---|")
    for v, row in average.items():
        for k in KEYS:
            x, e, y, f = row.get(k), row.get(f"{k}_err"), line[v].get(k), line[v].get(f"{k}_err")
            if x is None or e is None:
                continue
            m = models.get((v, k))
            mtxt = f"{m[0]:.2g} | {m[1]:.2g}" if m else "- | -"
            print(f"| {v} | {k} | {x:.6f} +- {e:.2g} | {y:.6f} +- {f:.2g} | {e / f:.2f} | {mtxt} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
