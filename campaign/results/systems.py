"""Physical systems across the variants of one campaign: which exponents are universal.

A variant may override the spec's ``system`` (the potential exponent ``alpha``, the size
distribution, the box), so one store can hold several systems. Standard jamming scaling gives
``Delta Z ~ E_G^(1/(2 alpha))``; if ``Delta A_G ~ Delta Z^beta_Z`` with a universal ``beta_Z``,
then ``beta_E = beta_Z / (2 alpha)`` (docs/REDUCED.md, "Physical systems"). Per variant,
``compare`` puts the finite-size table's exponents beside that prediction and beside the
reference system's ``beta_Z``:

* ``scaling_tension``: ``(beta_E - beta_Z / (2 alpha)) / sqrt(err_E^2 + err_pred^2)``, the
  two errors in quadrature (their correlation, through the same ``A_G`` data, is ignored, which
  overstates the error when it is positive);
* ``beta_Z_diff``: ``beta_Z`` minus the reference variant's, errors in quadrature, and its
  tension in standard deviations.

Each for the extrapolated values (``N_G -> inf``) and, with the suffix ``_largest``, for the
largest ``N_G``. A section of the reducer (``SECTION``, ``campaign.results.sections``).
"""

from __future__ import annotations

import math

import numpy as np

from campaign.results.scaling import with_fit_rule
from campaign.results.sections import Group, Section
from campaign.results.tables import fmt_err, records_csv

#: finite-size table entries carried into a record (each with ``_err``)
KEYS = ("A_G_star_E", "beta_E", "beta_Z", "psi_O_star")


def _f(x):
    try:
        x = float(x)
    except (TypeError, ValueError):
        return math.nan
    return x


def _ratio(a, b):
    """a / b, NaN when b is 0 or missing or non-finite."""
    a, b = _f(a), _f(b)
    return a / b if np.isfinite(b) and b > 0 and np.isfinite(a) else math.nan


def _system_key(desc):
    return (float(desc.get("exponent", 2.0)), str(desc.get("sizes", "")),
            tuple(desc.get("box", (1.0, 1.0))))


def _box_label(box):
    return "x".join(f"{float(x):g}" for x in box)


def _derived(rec, values, suffix):
    """The prediction beta_Z/(2 alpha) and the tension of beta_E with it."""
    two_alpha = 2.0 * rec["alpha"]
    bz, bz_err = _f(values.get("beta_Z")), _f(values.get("beta_Z_err"))
    be, be_err = _f(values.get("beta_E")), _f(values.get("beta_E_err"))
    pred, pred_err = (bz / two_alpha, bz_err / two_alpha) if two_alpha > 0 else (math.nan, math.nan)
    rec[f"beta_Z_over_2alpha{suffix}"] = pred
    rec[f"beta_Z_over_2alpha{suffix}_err"] = pred_err
    rec[f"scaling_tension{suffix}"] = _ratio(be - pred, math.hypot(be_err, pred_err))


def compare(rows, extrapolated, systems, reference="default") -> list:
    """One record per variant when the variants hold two systems or more, else ``[]``.

    ``rows``: the reducer's table rows (per variant and ``N_G``); ``extrapolated``: variant ->
    the ``N_G -> inf`` entries; ``systems``: variant -> ``{"exponent", "sizes", "box"}``
    (``campaign.results.finished.variant_systems``; a variant it does not list has the "default" one's
    system). ``reference``: the variant ``beta_Z_diff`` is taken against (the first variant
    when it is absent).

    Keys: ``variant``, ``alpha``, ``sizes``, ``box``, ``reference``, ``N_G_largest``; for ``k`` in
    ``A_G_star_E, beta_E, beta_Z, psi_O_star``: ``k``, ``k_err`` (extrapolated) and
    ``k_largest``, ``k_largest_err`` (the largest ``N_G``); ``beta_Z_over_2alpha(_err)``,
    ``scaling_tension``, ``beta_Z_diff``, ``beta_Z_diff_err``, ``beta_Z_diff_tension``, and
    the same five with the suffix ``_largest``.
    """
    variants = sorted(set(extrapolated) | {r["variant"] for r in rows})
    if not variants:
        return []
    base = systems.get("default") or {"exponent": 2.0, "sizes": "", "box": (1.0, 1.0)}
    desc = {v: systems.get(v, base) for v in variants}
    if len({_system_key(d) for d in desc.values()}) < 2:
        return []
    ref = reference if reference in variants else variants[0]
    records = []
    for v in variants:
        d = desc[v]
        rec = {"variant": v, "alpha": float(d.get("exponent", 2.0)), "sizes": str(d.get("sizes", "")),
               "box": _box_label(d.get("box", (1.0, 1.0))), "reference": ref}
        ex = extrapolated.get(v, {})
        mine = [r for r in rows if r["variant"] == v]
        last = max(mine, key=lambda r: r["N_G"]) if mine else {}
        rec["N_G_largest"] = int(last["N_G"]) if last else -1
        for k in KEYS:
            rec[k], rec[f"{k}_err"] = _f(ex.get(k)), _f(ex.get(f"{k}_err"))
        for k in KEYS:
            rec[f"{k}_largest"], rec[f"{k}_largest_err"] = _f(last.get(k)), _f(last.get(f"{k}_err"))
        _derived(rec, ex, "")
        _derived(rec, {k: last.get(k) for k in ("beta_E", "beta_E_err", "beta_Z", "beta_Z_err")},
                 "_largest")
        records.append(rec)
    by = {r["variant"]: r for r in records}
    for rec in records:
        for suffix in ("", "_largest"):
            k = f"beta_Z{suffix}"
            if rec["variant"] == ref:  # the reference against itself: no difference, no tension
                diff, err = 0.0, 0.0
            else:
                diff = rec[k] - by[ref][k]
                err = math.hypot(rec[f"{k}_err"], by[ref][f"{k}_err"])
            rec[f"beta_Z_diff{suffix}"] = diff
            rec[f"beta_Z_diff{suffix}_err"] = err
            rec[f"beta_Z_diff{suffix}_tension"] = _ratio(diff, err)
    # the keys in a fixed order (records_csv and the /reduced group take them from the first)
    order = list(records[0])
    return [{k: r[k] for k in order} for r in records]


def _sigma(t):
    t = _f(t)
    return f"{t:+.1f}" if np.isfinite(t) else "--"


HEADER = ("system", "N_G", "alpha", "sizes", "A_G*", "beta_E", "beta_Z", "beta_Z/(2 alpha)",
          "beta_E - beta_Z/(2 alpha) [sigma]", "beta_Z - beta_Z(ref) [sigma]", "Psi_O*")


def table_markdown(records) -> str:
    """Two lines per system, ``N_G -> inf`` and the largest ``N_G``; ``--`` where no value.

    ``A_G*`` is ``A_G*(E_G = 0)``; the tensions are in standard deviations."""
    if not records:
        return ""
    lines = [f"Fits: {records[0]['fit_rule']}.", ""] if records[0].get("fit_rule") else []
    lines += ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    for r in records:
        for suffix, n in (("", "inf"), ("_largest", str(r["N_G_largest"]))):
            def val(k):
                return fmt_err(r[f"{k}{suffix}"], r[f"{k}{suffix}_err"])

            cells = [r["variant"], n, f"{r['alpha']:g}", r["sizes"], val("A_G_star_E"), val("beta_E"),
                     val("beta_Z"), val("beta_Z_over_2alpha"), _sigma(r[f"scaling_tension{suffix}"]),
                     "ref" if r["variant"] == r["reference"] else _sigma(r[f"beta_Z_diff{suffix}_tension"]),
                     val("psi_O_star")]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def table_csv(records) -> str:
    return records_csv(records)


def compute(table, s, distributions) -> list:
    """The reducer's step: ``compare`` on its table rows, ``N_G -> inf`` row and systems, each record
    with the fit range its exponents come from."""
    return with_fit_rule(compare(table.rows, table.extrapolated, table.systems, reference=s.reference), s)


def console(records) -> str:
    """The systems' table under its title ("" with one system)."""
    title = (f"Systems (beta_E against the prediction beta_Z/(2 alpha); beta_Z against {records[0]['reference']!r}'s; "
             "tensions in standard deviations)") if records else ""
    return f"{title}\n\n{table_markdown(records)}" if title else ""


#: The physical systems compared as a section of the reducer (campaign.results.sections), with two
#: systems or more: systems.csv and systems.md, /reduced/systems, summary.json's "systems", the
#: console's table.
SECTION = Section(
    name="systems", compute=compute,
    files=lambda records: {"systems.csv": table_csv(records), "systems.md": table_markdown(records)} if records else {},
    reduced=lambda records: {"systems": Group(records)} if records else {},
    console=console,
    json=lambda records: {"systems": records})
