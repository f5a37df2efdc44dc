"""The reducer's outputs: the finite-size table (markdown, LaTeX, CSV), the per-cell and per-fit
CSVs, the sections' files, ``summary.json`` and the ``/reduced`` HDF5 group (docs/REDUCED.md,
"Output files" and "The ``/reduced`` group"), all from a ``Reduction`` of
``campaign.results.reduce``; what a section writes is its own (``campaign.results.sections``), the
writing is here.
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from pathlib import Path

import h5py
import numpy as np

from campaign.results.reduce import SECTIONS, Reduction, in_order
from campaign.results.scaling import FITS, TABLE_KEYS
from campaign.results.tables import _csv_val, fmt_err, records_csv
from campaign.version import __version__

# =========================================================================== tables
TABLE_HEADER = ("N_G", "A_G*(E_G=0)", "beta_E", "A_G*(Delta Z=0)", "beta_Z", "Psi_O*", "E_G fitted")
TEX_HEADER = (r"$N_G$", r"$A_G^*(E_G=0)$", r"$\beta_E$", r"$A_G^*(\Delta Z=0)$", r"$\beta_Z$",
              r"$\Psi_O^*$", r"$E_G$ fitted")
_SHOWN = ("A_G_star_E", "beta_E", "A_G_star_Z", "beta_Z", "psi_O_star")


def fmt_energy(x) -> str:
    """``1e-15``, ``2.5e-06`` -> ``2.5e-6``: an energy of the grid, short."""
    if x is None or not np.isfinite(x):
        return "--"
    return np.format_float_scientific(float(x), trim="-", exp_digits=1, precision=3)


def fit_range_label(row) -> str:
    """The grid energies a table row's fits used: ``1e-15..1e-5``; ``--`` without a fit."""
    lo, hi = row.get("fit_E_min", np.nan), row.get("fit_E_max", np.nan)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return "--"
    return f"{fmt_energy(lo)}..{fmt_energy(hi)}"


def _table_lines(red: Reduction):
    """(variant, label, cells) per line: the rows, then the extrapolation."""
    out = []
    for v in sorted(red.extrapolated):
        for r in (r for r in red.rows if r["variant"] == v):
            out.append((v, str(r["N_G"]), [_row_cell(r, k) for k in _SHOWN] + [fit_range_label(r)]))
        x = red.extrapolated[v]
        sizes = x.get("beta_E_sizes", "").split()
        label = f"sizes {sizes[0]}..{sizes[-1]}" if sizes else "--"
        out.append((v, "inf", [fmt_err(x[k], x[f"{k}_err"]) for k in _SHOWN] + [label]))
    return out


#: The intercept key of each exponent's fit, whose value is as undetermined as its exponent.
_EXPONENT_OF = {k: b for _, _, k, b in FITS}


def _row_cell(row, key):
    """A per-size entry; ``*`` after an entry whose fit has an undetermined exponent."""
    text = fmt_err(row[key], row[f"{key}_err"])
    bkey = _EXPONENT_OF.get(key, key)
    return text + "*" if row.get(f"{bkey}_undetermined") and text != "--" else text


def table_footnote(red: Reduction) -> str:
    """What the table's marks and its N_G -> inf row mean, in one or two sentences."""
    parts = []
    if any(r.get(f"{b}_undetermined") for r in red.rows for b in ("beta_E", "beta_Z")):
        parts.append("* the exponent of this size's own fit is not determined (at the search bound, or "
                     "its bootstrap cut by one; see the notes)")
    parts.append("N_G -> inf: one fit per law over the sizes named, the exponent shared by the sizes "
                 "and the intercepts extrapolated in 1/N_G (docs/REDUCED.md)")
    return "; ".join(parts) + "."


def table_markdown(red: Reduction) -> str:
    """The finite-size table, after one line naming the fit range or rule."""
    lines = [red.meta.get("fit_rule_text", "") + ".", ""]
    variants = sorted(red.extrapolated)
    for v in variants:
        if len(variants) > 1:
            lines += [f"Variant `{v}`", ""]
        lines.append("| " + " | ".join(TABLE_HEADER) + " |")
        lines.append("|" + "---|" * len(TABLE_HEADER))
        for vv, label, cells in _table_lines(red):
            if vv == v:
                lab = "N_G -> inf" if label == "inf" else label
                lines.append("| " + " | ".join([lab] + cells) + " |")
        lines.append("")
    lines += [table_footnote(red), ""]
    return "\n".join(lines)


def _tex_escape(text):
    return text.replace("\\", "").replace("_", r"\_").replace("^", r"\^{}").replace(">=", r"$\geq$") \
        .replace("<=", r"$\leq$")


def table_latex(red: Reduction) -> str:
    lines = [f"% {red.meta.get('fit_rule_text', '')}"]
    n = len(TEX_HEADER)
    for v in sorted(red.extrapolated):
        lines += [f"% variant {v}", r"\begin{tabular}{| l || l | l || l | l || l || l |}", r"\hline",
                  " & ".join(TEX_HEADER) + r" \\ \hline \hline"]
        for vv, label, cells in _table_lines(red):
            if vv == v:
                lab = r"$\infty$" if label == "inf" else f"${label}$"
                lines.append(" & ".join([lab] + [f"${c}$" for c in cells[:-1]] + [cells[-1].replace("_", r"\_")])
                             + r" \\ \hline")
        lines += [rf"\multicolumn{{{n}}}{{|l|}}{{fits: {_tex_escape(red.meta.get('fit_rule_name', ''))}}} \\ \hline",
                  r"\end{tabular}", ""]
    return "\n".join(lines)


#: per-row columns saying which cells the fits used (table.csv, the JSON rows, /reduced/table)
RANGE_KEYS = ("fit_E_min", "fit_E_max", "fit_p")


def table_csv(red: Reduction) -> str:
    keys = ["variant", "N_G", "n_packings", "n_cells"]
    for k in TABLE_KEYS:
        keys += [k, f"{k}_err"]
    keys += ["fit_rule", *RANGE_KEYS, "beta_E_undetermined", "beta_Z_undetermined"]
    rule = red.meta.get("fit_rule_name", "")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(keys)
    for r in red.rows:
        w.writerow([_csv_val(rule if k == "fit_rule" else r.get(k)) for k in keys])
    for v, x in sorted(red.extrapolated.items()):
        w.writerow([_csv_val(v if k == "variant" else "inf" if k == "N_G" else rule if k == "fit_rule"
                             else x.get(k.replace("_undetermined", "_note"), "")) for k in keys])
    return buf.getvalue()


def cells_records(red: Reduction):
    keys = ["variant", "N", "E", "n_packings", "n_pending", "n_failed"]
    keys += [k for k in red.cells if k.startswith(("mean_", "sem_"))]
    keys += ["A_G_gauss_mean", "A_G_gauss_sigma"]
    recs = []
    for i in range(len(red.cells["N"])):
        r = {k: red.cells[k][i] for k in keys if k in red.cells}
        for name, sa in sorted(red.self_averaging.items()):
            r[f"selfavg_{name}_m1"] = sa["ratio_mean"][i, 0]
            r[f"selfavg_{name}_m1_spread"] = sa["ratio_std"][i, 0]
            r[f"selfavg_{name}_m2"] = sa["ratio_mean"][i, 1]
            r[f"selfavg_{name}_m2_spread"] = sa["ratio_std"][i, 1]
        recs.append(r)
    return recs


# =========================================================================== writing
def _write_columns(group, records_or_columns):
    cols = records_or_columns
    if isinstance(cols, list):
        keys = list(cols[0].keys()) if cols else []
        cols = {k: [r.get(k) for r in records_or_columns] for k in keys}
    for k, v in cols.items():
        a = np.asarray(v)
        if a.dtype.kind in ("U", "O"):
            group.create_dataset(k, data=np.array([str(x) for x in a.ravel()], dtype=object)
                                 .reshape(a.shape), dtype=h5py.string_dtype())
        elif a.dtype.kind == "b":
            group.create_dataset(k, data=a.astype(np.int8))
        else:
            group.create_dataset(k, data=a.astype(float) if a.dtype.kind == "f" else a)


def write_reduced(red: Reduction, h5path, *, mode="w"):
    """Write the ``/reduced`` group (replacing an older one) into ``h5path``."""
    with h5py.File(h5path, mode) as f:
        if "reduced" in f:
            del f["reduced"]
        g = f.create_group("reduced")
        g.attrs.update(
            schema="jamming-campaign-reduced/1", package_version=__version__,
            generated=time.strftime("%Y-%m-%dT%H:%M:%S%z"), sources=json.dumps(red.meta["sources"]),
            spec_hash=str(red.meta["spec_hash"]), n_done=red.meta["done"],
            n_excluded=red.meta["excluded"], n_pending=red.meta["pending"], n_failed=red.meta["failed"],
            n_boot=red.meta["n_boot"], boot_seed=red.meta["boot_seed"],
            min_packings=red.meta["min_packings"], notes=json.dumps(red.notes),
            fit_rule_name=str(red.meta.get("fit_rule_name", "")),
            fit_rule_text=str(red.meta.get("fit_rule_text", "")),
            fit_default=int(bool(red.meta.get("fit_default", False))),
            fit_energies=np.asarray(red.meta.get("fit_energies", (0.0, math.inf)), float),
            fit_overlap=float(red.meta.get("fit_overlap", math.inf)))
        _write_columns(g.create_group("cells"), red.cells)
        sa = g.create_group("self_averaging")
        for name, d in red.self_averaging.items():
            _write_columns(sa.create_group(name), d)
        dg = g.create_group("distributions")
        for name, d in red.distributions.items():
            _write_columns(dg.create_group(name), d)
        _write_columns(dg.create_group("A_G"), red.area_hist)
        fg = g.create_group("fits")
        if red.fits:
            _write_columns(fg, red.fits)
        fg.create_dataset("residuals", data=red.residuals)
        if red.width_scaling:
            _write_columns(g.create_group("width_scaling"), red.width_scaling)
        if red.rows:
            _write_columns(g.create_group("table"), red.rows)
        ex = [{"variant": v, **x} for v, x in sorted(red.extrapolated.items())]
        if ex:
            _write_columns(g.create_group("extrapolated"), ex)
        pk = g.create_group("peaks")
        for v, d in red.peaks.items():
            _write_columns(pk.create_group(str(v)), d)
        for sec in in_order("reduced"):
            for path, group in sec.reduced(red.sections[sec.name]).items():
                sg = g.create_group(path)
                sg.attrs.update(group.attrs)
                if group.columns is not None:
                    _write_columns(sg, group.columns)


def write_outputs(red: Reduction, out_dir, *, write_h5=True):
    """Tables (md, csv, tex), per-cell and per-fit CSVs, the sections' files, ``summary.json`` and
    the reduced HDF5 file."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "table.md": table_markdown(red), "table.csv": table_csv(red), "table.tex": table_latex(red),
        "cells.csv": records_csv(cells_records(red)), "fits.csv": records_csv(red.fits),
        "width_scaling.csv": records_csv(red.width_scaling),
    }
    for sec in SECTIONS:
        files.update(sec.tables(red.sections[sec.name]))
    files["summary.json"] = json.dumps(red.to_json(), indent=1) + "\n"
    for sec in in_order("files"):
        files.update(sec.files(red.sections[sec.name]))
    for name, text in files.items():
        (out / name).write_text(text)
    written = [out / n for n in files]
    if write_h5:
        write_reduced(red, out / "reduced.h5")
        written.append(out / "reduced.h5")
    return written


def default_out_dir(path) -> Path:
    p = Path(path)
    return p.with_name(p.stem + "_reduced")
