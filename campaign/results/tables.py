"""Plain-text tables: a value with its error, records as CSV (shared by the reducer and the
comparisons built on it)."""

from __future__ import annotations

import csv
import io
import math

import numpy as np


def fmt_err(value, err):
    """``0.4416(2)``: the value rounded at the error's first significant digit."""
    if value is None or not np.isfinite(value):
        return "--"
    if err is None or not np.isfinite(err) or err <= 0:
        return f"{value:.4g}"
    digits = max(0, -int(math.floor(math.log10(err))))
    e = round(err * 10**digits)
    if e >= 10:  # 0.096 -> 0.1
        digits = max(0, digits - 1)
        e = round(err * 10**digits)
    if digits == 0:
        return f"{value:.0f}({e})"
    return f"{value:.{digits}f}({e})"


def _csv_val(v):
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else repr(float(v))
    return "" if v is None else v


def records_csv(records) -> str:
    if not records:
        return ""
    keys = list(records[0].keys())
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(keys)
    for r in records:
        w.writerow([_csv_val(r.get(k)) for k in keys])
    return buf.getvalue()
