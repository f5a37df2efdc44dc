"""The reducer: a campaign's HDF5 file(s) -> distributions, scaling fits, the finite-size table.

Reading goes through one place, ``load_finished`` (and ``Finished.histogram_blocks``),
which knows the store layout of docs/CONTRACTS.md; everything else works on plain
arrays. Only rows whose status is 1 (done) are used; pending and failed rows are
counted and reported per cell.

The output layout (``/reduced`` group and the tables) is documented in docs/REDUCED.md.
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from campaign.results import fits
from campaign.results.tables import _csv_val, fmt_err, records_csv  # noqa: F401 - also used as reduce.fmt_err
from campaign.errors import UserError

STATUS_PENDING, STATUS_DONE, STATUS_FAILED = 0, 1, 2

#: (quantity, abscissa) pairs fitted per (variant, N), with their table keys.
FITS = (
    ("A_G", "E_G", "A_G_star_E", "beta_E"),
    ("A_G", "delta_Z", "A_G_star_Z", "beta_Z"),
    ("psi_O", "E_G", "psi_O_star", "psi_beta_E"),
    ("psi_O", "delta_Z", "psi_O_star_Z", "psi_beta_Z"),
)
#: Keys of a table row (each also with ``<key>_err``); the first five are the paper's.
TABLE_KEYS = ("A_G_star_E", "beta_E", "A_G_star_Z", "beta_Z", "psi_O_star",
              "psi_O_star_Z", "psi_beta_E", "psi_beta_Z")
#: Histograms whose self-averaging is not tested: radial pair counts are not per-object
#: variables; gaps and forces are counted on log-spaced bins for their small-value tails.
SELF_AVERAGING_SKIP = ("radial_grains", "radial_contacts", "gap", "force", "force_extended")


@dataclass
class Settings:
    min_packings: int = 3       # a cell with fewer finished packings is left out of the fits
    n_boot: int = 1000          # bootstrap resamples (packings within each cell)
    boot_seed: int = 20240917   # fixed: the same file gives the same errors
    area_bins: int = 30         # bins of the per-cell P(A_G) histogram
    sin_bins: int = 100         # bins of P(sin theta) on [0, 1]
    reference: str = "default"  # the variant the others are compared with (campaign.results.tradeoff)
    # The fit range of the scaling laws (docs/REDUCED.md, "The fit range"): the cells whose grid
    # energy lies in fit_energies = [lo, hi] and whose typical relative overlap
    # (alpha E_G / 2)^(1/alpha) is at most fit_overlap (alpha: the variant's exponent). The
    # default, DEFAULT_FIT_OVERLAP, is one distance from jamming for every potential, chosen by
    # experiments/fit_rules.py; fit_overlap = inf with the default fit_energies: every energy.
    fit_energies: tuple = (0.0, float("inf"))
    fit_overlap: float = 0.001
    # a range asked for explicitly (the command line's --fit-all, --fit-energies, --fit-overlap):
    # a (variant, N) whose range holds fewer energies of the grid than a fit needs
    # (fits.MIN_CELLS) is refused (UserError); with the default range it only gets no fits
    strict_range: bool = False


#: The default fit range: typical relative overlaps up to 0.1% (docs/REDUCED.md, "The fit range").
DEFAULT_FIT_OVERLAP = Settings.fit_overlap


def _window(s: Settings) -> list:
    lo, hi = s.fit_energies
    out = [f"E_G in [{lo:g}, {hi:g}]"] if (lo > 0 or math.isfinite(hi)) else []
    if math.isfinite(s.fit_overlap):
        out.append(f"typical overlap <= {s.fit_overlap:g}")
    return out


def is_default_range(s: Settings) -> bool:
    return (s.fit_overlap == DEFAULT_FIT_OVERLAP and tuple(s.fit_energies) == (0.0, math.inf))


def fit_rule_name(s: Settings) -> str:
    """The fit range in a few words, for a CSV column, a figure title or a table's footnote:
    ``typical overlap <= 0.001 (default)``, ``every energy``, ``E_G in [0, 1e-05]``,
    ``typical overlap <= 0.01``, or both of the last two."""
    window = ", ".join(_window(s)) or "every energy"
    return window + (" (default)" if is_default_range(s) else "")


def fit_rule_text(s: Settings) -> str:
    """One sentence saying which cells the scaling fits use."""
    window = " and ".join(_window(s))
    if is_default_range(s):
        return (f"Fits over the cells of typical overlap (alpha E_G / 2)^(1/alpha) <= {s.fit_overlap:g} (the "
                f"default range: one distance from jamming for every potential, E_G <= {s.fit_overlap ** 2:.2g} "
                "at alpha = 2; --fit-all fits every energy)")
    return "Fits over every energy" if not window else f"Fits over the cells with {window}"


# =========================================================================== reading
def _decode(a):
    a = np.asarray(a)
    if a.dtype.kind in ("S", "O"):
        return np.array([x.decode() if isinstance(x, bytes) else str(x) for x in a.ravel()],
                        dtype=object).reshape(a.shape)
    return a


def _columns(f, names):
    """The task table's columns (a group of datasets, or one compound dataset)."""
    t = f["tasks"]
    out = {}
    for n in names:
        if hasattr(t, "keys"):
            if n in t:
                out[n] = t[n][...]
        elif t.dtype.names and n in t.dtype.names:
            out[n] = t[n]
    return out


def usable_mask(scalars, n):
    """``(mask, reasons)``: which of ``n`` finished packings are fit for statistics -- the jam
    converged (``jam_status == 0``) and the analysis identities held (``identities_ok == 1``).
    ``scalars`` maps names to (n,) arrays; ``reasons`` maps each failed condition to its (n,)
    bool mask. Without one of the two columns a packing is taken as passing that condition.
    The one definition of the packings the reducer uses (also ``campaign.results.frames``)."""
    reasons = {}
    if "jam_status" in scalars:
        reasons["jam_status != 0"] = ~(np.asarray(scalars["jam_status"]) == 0)
    if "identities_ok" in scalars:
        reasons["identities_ok != 1"] = ~(np.asarray(scalars["identities_ok"]) == 1)
    bad = np.zeros(n, bool)
    for m in reasons.values():
        bad |= m
    return ~bad, reasons


def first_done(ids, status, seen):
    """Bool mask of the rows that count as finished packings: status 1 (done), and the first
    such row of a task id not in ``seen`` (a set, updated), so that a packing done in several
    rows or files is used once."""
    keep = np.zeros(len(status), bool)
    for r in np.flatnonzero(np.asarray(status) == STATUS_DONE):
        if ids[r] not in seen:
            seen.add(ids[r])
            keep[r] = True
    return keep


@dataclass
class Finished:
    """Finished packings of one or more campaign files (rows with status 1, deduplicated by id)."""

    paths: list
    attrs: dict
    variant: np.ndarray          # (n,) str
    N: np.ndarray                # (n,) int, campaign label (total disks)
    E: np.ndarray                # (n,) float, target E_G
    ids: np.ndarray
    seed: np.ndarray             # (n,) int, seed index (-1 when the file has no seed column)
    scalars: dict                # name -> (n,) float
    edges: dict                  # histogram name -> edges
    tasks: dict                  # every row of every file: variant, N, E, status, error
    _rows: list = field(default_factory=list, repr=False)  # per file: (file rows, positions)

    def __len__(self):
        return len(self.N)

    def usable(self):
        """``(mask, reasons)`` of ``usable_mask`` for these packings."""
        return usable_mask(self.scalars, len(self))

    def subset(self, mask):
        """The finished packings where ``mask`` (n,) is true, in the same order."""
        mask = np.asarray(mask, bool)
        new_pos = np.cumsum(mask) - 1
        rows = []
        for file_rows, pos in self._rows:
            keep = mask[pos]
            rows.append((file_rows[keep], new_pos[pos[keep]]))
        return Finished(paths=self.paths, attrs=self.attrs, variant=self.variant[mask],
                        N=self.N[mask], E=self.E[mask], ids=self.ids[mask], seed=self.seed[mask],
                        scalars={k: v[mask] for k, v in self.scalars.items()}, edges=self.edges,
                        tasks=self.tasks, _rows=rows)

    def histogram_blocks(self, name, block=8192):
        """Yield ``(positions, counts)``: finished-row positions and their int64 counts."""
        import h5py

        for path, (rows, pos) in zip(self.paths, self._rows):
            if len(rows) == 0:
                continue
            with _open(path, h5py) as f:
                try:
                    ds = f[f"histograms/{name}/counts"]
                    lo = int(rows.min())
                    hi = int(rows.max()) + 1
                    for s in range(lo, hi, block):
                        e = min(s + block, hi)
                        m = (rows >= s) & (rows < e)
                        if not m.any():
                            continue
                        data = ds[s:e]
                        yield pos[m], np.asarray(data[rows[m] - s], dtype=np.int64)
                except Exception as exc:  # noqa: BLE001 - read_failure says which failures are the file's
                    from campaign.storage.integrity import read_failure

                    err = read_failure(path, exc, f, [f"histograms/{name}/counts"], what=f"histogram {name!r}")
                    if err is None:
                        raise
                    raise err from None


def _failed_errors(f, status, block=65536):
    """The error column (decoded) with the failed rows' messages, read block by block
    (the column is 512 bytes a row; only failed rows have one)."""
    err = np.full(len(status), "", dtype=object)
    failed = np.flatnonzero(status == STATUS_FAILED)
    if not failed.size or "error" not in _column_names(f):
        return err
    t = f["tasks"]
    for lo in range(0, len(status), block):
        rows = failed[(failed >= lo) & (failed < lo + block)]
        if rows.size:
            data = (t["error"][lo:lo + block] if hasattr(t, "keys") else t[lo:lo + block]["error"])
            err[rows] = _decode(np.asarray(data)[rows - lo])
    return err


def _column_names(f):
    t = f["tasks"]
    return set(t.keys()) if hasattr(t, "keys") else set(t.dtype.names or ())


def _open(path, h5py):
    try:
        return h5py.File(path, "r", locking=False)
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except OSError as exc:
        from campaign.storage.checksums import open_failure

        raise open_failure(path, exc, f"{path}: not a readable HDF5 file ({exc})") from None


def load_finished(paths) -> Finished:
    """Read the task tables, scalars and histogram edges of the campaign file(s).

    This is the only function that knows the store layout. A packing that appears
    done in several files (same task id) is used once.
    """
    import h5py

    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [str(p) for p in paths]
    seen = set()
    all_rows = {k: [] for k in ("variant", "N", "E", "status", "error", "id")}
    fin = {k: [] for k in ("variant", "N", "E", "id", "seed")}
    scal_parts, per_file, edges, attrs = [], [], None, None
    offset = 0
    for path in paths:
        with _open(path, h5py) as f:
            try:
                if "tasks" not in f:
                    raise UserError(f"{path}: not a campaign file (no /tasks table); "
                                    "expected the layout of docs/CONTRACTS.md")
                if "schema" in f.attrs:
                    from campaign.storage.store import check_format

                    check_format(f.attrs, path)
                # status first: a row's data is complete before its status says done
                cols = _columns(f, ("status", "id", "variant", "N", "E", "seed"))
                for need in ("status", "id", "N", "E"):
                    if need not in cols:
                        raise UserError(f"{path}: /tasks has no column {need!r}")
                status = np.asarray(cols["status"]).astype(np.int64)
                T = len(status)
                variant = _decode(cols.get("variant", np.array(["default"] * T, dtype=object)))
                ids = _decode(cols["id"])
                err = _failed_errors(f, status)
                file_attrs = {k: (v.decode() if isinstance(v, bytes) else v)
                              for k, v in f.attrs.items()}
                names = sorted(f["scalars"].keys()) if "scalars" in f else []
                scal = {n: np.asarray(f[f"scalars/{n}"][...], dtype=float) for n in names}
                hedges = {}
                if "histograms" in f:
                    for n in f["histograms"]:
                        hedges[n] = np.asarray(f[f"histograms/{n}/edges"][...], dtype=float)
            except Exception as exc:  # noqa: BLE001 - read_failure says which failures are the file's
                from campaign.storage.integrity import read_failure

                err = read_failure(path, exc, f, ["tasks", "scalars", "histograms/*/edges"])
                if err is None:
                    raise
                raise err from None
        attrs = attrs or file_attrs
        if edges is None:
            edges = hedges
        else:
            for n in set(edges) & set(hedges):
                if edges[n].shape != hedges[n].shape or not np.allclose(edges[n], hedges[n],
                                                                        rtol=1e-12, atol=0):
                    raise UserError(f"{path}: histogram {n!r} has other bin edges than "
                                    f"{paths[0]}; files with different bins cannot be summed")
            edges = {n: edges[n] for n in set(edges) & set(hedges)}
        rows = np.flatnonzero(first_done(ids, status, seen))
        per_file.append((rows, np.arange(offset, offset + len(rows))))
        offset += len(rows)
        for k, v in (("variant", variant), ("N", cols["N"]), ("E", cols["E"]), ("status", status),
                     ("error", err), ("id", ids)):
            all_rows[k].append(np.asarray(v))
        seeds = cols.get("seed", np.full(T, -1))
        for k, v in (("variant", variant), ("N", cols["N"]), ("E", cols["E"]), ("id", ids), ("seed", seeds)):
            fin[k].append(np.asarray(v)[rows])
        scal_parts.append({n: a[rows] for n, a in scal.items()})
    tasks = {k: np.concatenate(v) for k, v in all_rows.items()}
    # a task done in one file but pending/failed in another counts as done; a task
    # pending or failed in several files counts once
    counted = tasks["status"] == STATUS_DONE
    for i in np.flatnonzero(~counted):
        if tasks["id"][i] not in seen:
            seen.add(tasks["id"][i])
            counted[i] = True
    tasks["counted"] = counted
    names = set.intersection(*(set(p) for p in scal_parts)) if scal_parts else set()
    scalars = {n: np.concatenate([p[n] for p in scal_parts]) for n in sorted(names)}
    return Finished(paths=paths, attrs=attrs or {}, variant=np.concatenate(fin["variant"]),
                    N=np.concatenate(fin["N"]).astype(np.int64),
                    E=np.concatenate(fin["E"]).astype(float), ids=np.concatenate(fin["id"]),
                    seed=np.concatenate(fin["seed"]).astype(np.int64),
                    scalars=scalars, edges=edges or {}, tasks=tasks, _rows=per_file)


def variant_systems(attrs, variants=()) -> dict:
    """The physical system of every variant, from the spec text stored in the file.

    ``{variant: {"exponent": alpha, "sizes": label, "box": (L_x, L_y), "radii": distinct
    discrete radii or () for a continuous distribution}}`` for "default" and each of the
    spec's variants (``campaign.plan.spec``: a variant's ``system`` overrides the spec's).
    ``variants``: names found in the data; those the spec does not list get the base system.
    A spec this version cannot read gives every variant the paper's system (exponent 2, the
    1.4:1 mixture).
    """
    from campaign.plan.spec import System, parse_spec

    try:
        spec = parse_spec(str(attrs.get("spec_yaml", "")), "the stored spec")
        out = {v.name: _describe_system(v.system) for v in spec.variants}
    except UserError:  # an old or foreign spec
        out = {"default": _describe_system(System())}
    for v in variants:
        out.setdefault(str(v), dict(out["default"]))
    return out


def _describe_system(system) -> dict:
    radii = () if system.sizes is not None else tuple(sorted({s.radius for s in system.species}, reverse=True))
    return {"exponent": float(system.exponent), "sizes": system.sizes_label(), "box": tuple(system.box),
            "radii": radii}


def three_disk_peaks(system: dict) -> dict:
    """The exact three-disk peaks of a variant's system (``variant_systems``): of its discrete
    radii; for a continuous size distribution only the equal-disk edge triangle
    (``alpha_e = sqrt(3)/4``, ``theta = pi/3``), the centre of the continuum of peaks a
    polydisperse packing smears out, and no ``alpha_v`` (its scale, the packing's largest
    radius, is itself random)."""
    if system["radii"]:
        alpha_e, theta, alpha_v = fits.three_disk_peaks(system["radii"])
    else:
        alpha_e, theta, alpha_v = np.array([math.sqrt(3) / 4]), np.array([math.pi / 3]), np.array([])
    return {"alpha_e": alpha_e, "theta": theta, "alpha_v": alpha_v}


# =========================================================================== reduction
@dataclass
class Reduction:
    cells: dict                  # column -> (C,) arrays
    distributions: dict          # name -> {"edges", "counts" (C, nb), "density" (C, nb)};
    #                              sin_theta (derived from contact_angle) has no counts
    self_averaging: dict         # name -> {"ratio_mean" (C, 2), "ratio_std" (C, 2)}
    area_hist: dict              # {"edges" (C, nb+1), "counts" (C, nb)}: a cell uses the
    #                              first ~sqrt(n) bins; unused edges are NaN, counts 0
    fits: list                   # records (dicts), one per (variant, N, quantity, abscissa)
    residuals: np.ndarray        # (F, C) normalised residuals, NaN where a cell was not used
    width_scaling: list          # records per (variant, E)
    rows: list                   # table rows per (variant, N)
    extrapolated: dict           # variant -> {key: value, key_err: ...}
    peaks: dict                  # variant -> {alpha_e, theta, alpha_v} (``three_disk_peaks``)
    notes: list                  # human-readable: what is missing, what was skipped
    meta: dict
    variants: list = field(default_factory=list)  # campaign.results.tradeoff records, one per variant
    systems: list = field(default_factory=list)   # campaign.results.systems records, with two systems or more
    response: dict = field(default_factory=dict)  # campaign.results.response: {"cells", "fits"} records

    def fit_rule(self) -> dict:
        """Which cells the scaling fits use: the range's name and sentence, whether it is the
        default, its window (docs/REDUCED.md, "The fit range")."""
        m = self.meta
        return {"name": m.get("fit_rule_name", ""), "text": m.get("fit_rule_text", ""),
                "default": bool(m.get("fit_default", False)),
                "fit_energies": list(m.get("fit_energies", (0.0, math.inf))),
                "fit_overlap": m.get("fit_overlap", math.inf)}

    def to_json(self):
        def clean(v):
            if isinstance(v, (float, np.floating)):
                return None if not np.isfinite(v) else float(v)
            if isinstance(v, (np.integer,)):
                return int(v)
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [clean(x) for x in v]
            return v

        return clean({"fit_rule": self.fit_rule(), "rows": self.rows, "extrapolated": self.extrapolated,
                      "variants": self.variants, "systems": self.systems,
                      **({"response": self.response} if self.response else {}),
                      "status": {k: self.meta[k] for k in ("done", "pending", "failed", "total")},
                      "notes": self.notes})


def _cell_index(variant, N, E):
    """Unique (variant, N, E) keys sorted by variant, N, then E; and each row's cell."""
    vnames, vcode = np.unique(np.asarray(variant, dtype=str), return_inverse=True)
    order = np.lexsort((E, N, vcode))
    key = np.stack([vcode[order], N[order]], axis=1)
    new = np.ones(len(order), bool)
    new[1:] = (np.any(key[1:] != key[:-1], axis=1)) | (E[order][1:] != E[order][:-1])
    cell_sorted = np.cumsum(new) - 1
    cell = np.empty(len(order), np.int64)
    cell[order] = cell_sorted
    first = order[new]
    return cell, vnames[vcode[first]], N[first], E[first]


def _group_stats(values, cell, C):
    """Count, mean, sample std and standard error per cell, ignoring NaN."""
    ok = np.isfinite(values)
    c = cell[ok]
    v = values[ok]
    n = np.bincount(c, minlength=C).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(c, weights=v, minlength=C) / n
        d = v - mean[c]
        var = np.bincount(c, weights=d * d, minlength=C) / (n - 1)
        std = np.sqrt(var)
        sem = std / np.sqrt(n)
    return n, mean, std, sem


def _min_positive(x):
    x = x[x > 0]
    return float(x.min()) if len(x) else np.nan


@dataclass
class _Grid:
    """The cells of a reduction, (variant, N, E) for every task finished or not, and where
    each usable packing falls (``cell``; ``order``/``bounds``: the packings sorted by cell)."""

    cv: np.ndarray
    cN: np.ndarray
    cE: np.ndarray
    cell: np.ndarray
    n_done: np.ndarray
    n_excluded: np.ndarray
    n_failed: np.ndarray
    n_pending: np.ndarray
    order: np.ndarray
    bounds: np.ndarray

    @property
    def C(self):
        return len(self.cv)

    @property
    def n_tasks(self):
        return self.n_done + self.n_excluded + self.n_failed + self.n_pending

    def packings(self, i):
        """Rows (into the usable packings) of cell ``i``."""
        return self.order[self.bounds[i]:self.bounds[i + 1]]


def _grid(everything, good, tasks) -> _Grid:
    cell_all, cv, cN, cE = _cell_index(tasks["variant"], tasks["N"].astype(np.int64),
                                       tasks["E"].astype(float))
    C = len(cv)
    lookup = {(v, int(n), float(e)): i for i, (v, n, e) in enumerate(zip(cv, cN, cE))}
    cell_everything = np.array([lookup[(v, int(n), float(e))] for v, n, e
                                in zip(everything.variant, everything.N, everything.E)],
                               dtype=np.int64)
    cell = cell_everything[good]
    st = tasks["status"]
    counted = tasks["counted"]
    order = np.argsort(cell, kind="stable")
    return _Grid(cv=cv, cN=cN, cE=cE, cell=cell,
                 n_done=np.bincount(cell, minlength=C),
                 n_excluded=np.bincount(cell_everything[~good], minlength=C),
                 n_failed=np.bincount(cell_all[counted & (st == STATUS_FAILED)], minlength=C),
                 n_pending=np.bincount(cell_all[counted & (st == STATUS_PENDING)], minlength=C),
                 order=order, bounds=np.searchsorted(cell[order], np.arange(C + 1)))


def _cell_table(fin, g: _Grid) -> dict:
    """Counts, and mean, standard deviation and standard error of every scalar, per cell."""
    cells = {"variant": g.cv, "N": g.cN, "E": g.cE, "n_packings": g.n_done, "n_excluded": g.n_excluded,
             "n_pending": g.n_pending, "n_failed": g.n_failed, "n_tasks": g.n_tasks}
    for name, v in fin.scalars.items():
        _, mean, std, sem = _group_stats(v, g.cell, g.C)
        cells[f"mean_{name}"] = mean
        cells[f"std_{name}"] = std
        cells[f"sem_{name}"] = sem
    return cells


def _count_notes(fin, g: _Grid, reasons) -> list:
    """What the reduction leaves out: unknown layout, unusable, pending and failed packings."""
    notes = []
    cv, cN, cE = g.cv, g.cN, g.cE
    schema = str(fin.attrs.get("schema", ""))
    if not schema.startswith("jamming-campaign/"):
        notes.append(f"{fin.paths[0]}: unknown store schema {schema!r} (expected "
                     "jamming-campaign/1); reading it as that layout")
    if len(fin) == 0:
        notes.append("no finished packings yet: nothing to fit")
    if g.n_excluded.sum():
        why = ", ".join(f"{int(m.sum())} with {r}" for r, m in reasons.items() if m.any())
        notes.append(f"{int(g.n_excluded.sum())} finished packing(s) left out of the statistics ({why}); "
                     "the cells' n_excluded counts them")
        for i in np.flatnonzero(g.n_excluded > 0):
            notes.append(f"  {cv[i]} N={cN[i]} E={cE[i]:.3g}: {g.n_excluded[i]} of "
                         f"{g.n_done[i] + g.n_excluded[i]} finished left out")
    pend_total, fail_total = int(g.n_pending.sum()), int(g.n_failed.sum())
    if pend_total or fail_total:
        notes.append(f"{len(fin)} packings done, {pend_total} pending, {fail_total} failed: "
                     "the reduction uses the finished ones only")
        for i in np.flatnonzero((g.n_pending + g.n_failed) > 0):
            notes.append(f"  {cv[i]} N={cN[i]} E={cE[i]:.3g}: {g.n_done[i]} done, "
                         f"{g.n_pending[i]} pending, {g.n_failed[i]} failed")
        errs = fin.tasks["error"][(fin.tasks["status"] == STATUS_FAILED)]
        if len(errs):
            first = next((e for e in errs if e), "")
            if first:
                notes.append(f"  first failure: {first.splitlines()[-1] if first else ''}")
    return notes


def _area_distributions(fin, g: _Grid, s: Settings, cells):
    """P(A_G) per cell: its best Gaussian (added to ``cells``) and a histogram of about
    sqrt(n) bins; and the width scaling sigma(A_G) ~ N^-gamma per (variant, E)."""
    C = g.C
    A = fin.scalars.get("A_G", np.full(len(fin), np.nan))
    gm = np.full((C, 4), np.nan)
    a_edges = np.full((C, s.area_bins + 1), np.nan)
    a_counts = np.zeros((C, s.area_bins), np.int64)
    for i in range(C):
        v = A[g.packings(i)]
        v = v[np.isfinite(v)]
        if v.size >= 2:
            gm[i] = fits.gaussian_mle(v)
            lo, hi = v.min(), v.max()
            if hi <= lo:
                hi = lo + abs(lo) * 1e-9 + 1e-300
            nb = int(min(s.area_bins, max(4, round(np.sqrt(v.size)))))  # ~sqrt(n) bins
            a_edges[i, :nb + 1] = np.linspace(lo, hi, nb + 1)
            a_counts[i, :nb] = np.histogram(v, a_edges[i, :nb + 1])[0]
    cells.update(A_G_gauss_mean=gm[:, 0], A_G_gauss_sigma=gm[:, 1], A_G_gauss_mean_err=gm[:, 2],
                 A_G_gauss_sigma_err=gm[:, 3])
    width = []
    cv, cN, cE = g.cv, g.cN, g.cE
    for v in np.unique(cv):
        for e in np.unique(cE[cv == v]):
            sel = np.flatnonzero((cv == v) & (cE == e) & (g.n_done >= s.min_packings))
            r = fits.fit_width_scaling(cN[sel], gm[sel, 1], gm[sel, 3])
            width.append({"variant": v, "E": float(e), "gamma": r.value, "gamma_err": r.err,
                          "log_prefactor": r.slope, "chi2_dof": r.chi2_dof,
                          "n_sizes": r.n_points, "message": r.message})
    return {"edges": a_edges, "counts": a_counts}, width


def typical_overlap(E, alpha):
    """The typical relative overlap ``(alpha E_G / 2)^(1/alpha)`` of a packing at energy per
    grain ``E_G`` (two contacts per disk carrying it): the distance from jamming that is
    comparable across exponents, where ``E_G`` is not."""
    return (alpha * np.asarray(E, float) / 2.0) ** (1.0 / alpha)


def _scaling_fits(fin, g: _Grid, s: Settings, cells, notes, exponents=None):
    """The power-law fits of A_G and Psi_O against E_G and Delta Z per (variant, N), with
    bootstrap errors; returns (fit records, normalised residuals per cell, table rows, the
    inputs of the shared-exponent fits: (variant, quantity, abscissa) -> per N the cell means,
    their errors and bootstrap replicas). ``exponents``: variant -> alpha, for ``s.fit_overlap``."""
    C, cv, cN, cE, n_done = g.C, g.cv, g.cN, g.cE, g.n_done
    fit_records, residuals, rows, shared_in = [], [], [], {}
    cols = ["E_G", "delta_Z", "A_G", "psi_O"]
    have = all(c in fin.scalars for c in cols)
    if not have:
        notes.append("the file lacks one of the scalars " + ", ".join(cols) + ": no scaling fits")
    groups = sorted({(v, int(n)) for v, n in zip(cv, cN)})
    for gi, (v, n) in enumerate(groups):
        in_group = np.flatnonzero((cv == v) & (cN == n))
        row = {"variant": v, "N_G": n, "n_packings": int(n_done[in_group].sum()),
               "n_cells": 0}
        lo, hi = s.fit_energies
        in_range = (cE[in_group] >= lo * (1 - 1e-9)) & (cE[in_group] <= hi * (1 + 1e-9))
        if not in_range.all() and gi == 0:
            notes.append(f"scaling fits use the cells with E_G in [{lo:g}, {hi:g}] only")
        if math.isfinite(s.fit_overlap):
            alpha = (exponents or {}).get(v, 2.0)
            in_range &= typical_overlap(cE[in_group], alpha) <= s.fit_overlap * (1 + 1e-9)
            if n == min(int(x) for x in cN[cv == v]):
                e_max = 2.0 / alpha * s.fit_overlap ** alpha
                notes.append(f"{v}: scaling fits use the cells with typical overlap <= {s.fit_overlap:g} "
                             f"(E_G <= {e_max:.3g} at alpha = {alpha:g})")
        in_group = in_group[in_range]
        short = len(in_group) < fits.MIN_CELLS
        why = (f"the fit range ({fit_rule_name(s)}) holds {len(in_group)} energies of the grid, fewer than "
               f"the {fits.MIN_CELLS} a power law with an intercept needs (three parameters and one "
               "degree of freedom)")
        if short and s.strict_range:
            raise UserError(f"{v} N={n}: {why}; widen the range")
        if short and have:
            notes.append(f"{v} N={n}: no fits: {why}; --fit-all or --fit-energies fit a wider range")
        small = in_group[n_done[in_group] < s.min_packings]
        usable = in_group[n_done[in_group] >= s.min_packings]
        if len(small) and have:
            notes.append(f"{v} N={n}: {len(small)} cell(s) with fewer than {s.min_packings} "
                         "finished packings left out of the fits (E = "
                         + ", ".join(f"{cE[i]:.3g} ({n_done[i]})" for i in small) + ")")
        row["n_cells"] = int(len(usable))
        row["fit_E_min"] = float(cE[usable].min()) if len(usable) else np.nan
        row["fit_E_max"] = float(cE[usable].max()) if len(usable) else np.nan
        boot = None
        if have and len(usable) >= 3 and s.n_boot > 1:
            data = [np.column_stack([fin.scalars[c][g.packings(i)] for c in cols]) for i in usable]
            data = [d[np.all(np.isfinite(d), axis=1)] for d in data]
            if all(len(d) >= 2 for d in data):
                boot = fits.bootstrap_cell_means(data, s.n_boot, seed=[s.boot_seed, gi])
        not_determined = []
        for quantity, absc, key, bkey in FITS:
            res = np.full(C, np.nan)
            rec = {"variant": v, "N_G": n, "quantity": quantity, "abscissa": absc}
            if have and len(usable):
                x = cells[f"mean_{absc}"][usable]
                y = cells[f"mean_{quantity}"][usable]
                ye = cells[f"sem_{quantity}"][usable]
                # x = 0 is a legitimate abscissa (an isostatic cell: Delta Z = 0 exactly)
                ok = np.isfinite(x) & (x >= 0) & np.isfinite(y) & np.isfinite(ye) & (ye > 0)
                n_pos = int(np.count_nonzero(x[ok] > 0))
                bx = by = None
                if boot is not None:
                    bx = boot[:, ok, cols.index(absc)]
                    by = boot[:, ok, cols.index(quantity)]
                if n_pos < 3:  # the size's cells, or why it cannot enter the shared fit
                    entry = f"{n_pos} cell(s) with a positive mean {absc} in the fit range (3 needed)"
                elif bx is None and s.n_boot > 1:
                    entry = "a cell with fewer than 2 usable packings (no bootstrap)"
                else:
                    entry = (x[ok], y[ok], ye[ok], bx, by)
                shared_in.setdefault((v, quantity, absc), {})[n] = entry
            if not have:
                f = fits.PowerLawFit(message="scalars missing")
                ok_cells = np.zeros(0, int)
            elif short:
                f = fits.PowerLawFit(n_points=len(usable), message=why)
                ok_cells = np.zeros(0, int)
            else:
                ok_cells = usable[ok]
                if n_pos < 3:  # the exponent needs three positive abscissae
                    f = fits.PowerLawFit(n_points=int(ok.sum()), message=(
                        f"needs at least 3 cells with a positive mean {absc}, has {n_pos}"))
                else:
                    f = fits.fit_power_law(x[ok], y[ok], ye[ok], boot_x=bx, boot_y=by)
                if (~ok).any():
                    f.message = (f.message + "; " if f.message else "") + (
                        f"{int((~ok).sum())} cell(s) with a negative mean {absc} or without "
                        f"a spread of {quantity} left out")
                if f.residuals.size == len(ok_cells):
                    res[ok_cells] = f.residuals
            undetermined = f.undetermined if (f.ok and not short) else ""
            if not f.ok and not short:
                notes.append(f"{v} N={n}: no fit of {quantity} against {absc}: {f.message}")
            elif undetermined:
                not_determined.append(f"{quantity} against {absc} ({undetermined})")
            rec.update(intercept=f.intercept, intercept_err=f.intercept_err, coeff=f.coeff,
                       coeff_err=f.coeff_err, exponent=f.exponent, exponent_err=f.exponent_err,
                       chi2=f.chi2, dof=f.dof, chi2_dof=f.chi2_dof, n_points=f.n_points,
                       n_boot=f.n_boot, ok=f.ok, message=f.message, undetermined=undetermined,
                       boot_at_bound=f.boot_at_bound,
                       p_value=fits.chi2_p_value(f.chi2, f.dof),
                       E_min=float(cE[ok_cells].min()) if len(ok_cells) else np.nan,
                       E_max=float(cE[ok_cells].max()) if len(ok_cells) else np.nan,
                       x_min=_min_positive(xs := cells.get(f"mean_{absc}", np.zeros(C))[ok_cells]),
                       x_max=float(xs.max()) if len(xs) else np.nan)
            fit_records.append(rec)
            residuals.append(res)
            row[key], row[f"{key}_err"] = f.intercept, f.intercept_err
            row[bkey], row[f"{bkey}_err"] = f.exponent, f.exponent_err
            row[f"{bkey}_undetermined"] = undetermined
            row[f"chi2_dof_{quantity}_{absc}"] = f.chi2_dof
        if not_determined:
            notes.append(f"{v} N={n}: exponents not determined, marked * in the table: "
                         + "; ".join(not_determined))
        row["fit_p"] = next(r["p_value"] for r in fit_records[-len(FITS):]
                            if r["quantity"] == "A_G" and r["abscissa"] == "E_G")
        rows.append(row)
    return fit_records, np.array(residuals).reshape(len(fit_records), C), rows, shared_in


def _extrapolate(rows, shared_in, notes) -> dict:
    """The N_G -> inf row per variant (docs/REDUCED.md, "The N_G -> inf row"): for each of the
    four laws one fit over every size with the exponent shared (``fits.fit_shared_exponent``: an
    intercept and an amplitude per size); its exponent is the row's exponent and its intercepts,
    extrapolated linearly in 1/N_G, the row's intercept. A size with fewer than three cells in
    the fit range does not enter; an undetermined shared exponent gives no value."""
    extrapolated = {}
    for v in sorted({r["variant"] for r in rows}):
        out = {}
        for quantity, absc, key, bkey in FITS:
            per_n = shared_in.get((v, quantity, absc), {})
            sizes = sorted(n for n, d in per_n.items() if not isinstance(d, str))
            left = {n: d for n, d in per_n.items() if isinstance(d, str)}
            left.update({r["N_G"]: "no cell in the fit range" for r in rows
                         if r["variant"] == v and r["N_G"] not in per_n})
            d = [per_n[n] for n in sizes]
            boot = all(x[3] is not None for x in d) and len(d) > 0
            f = fits.fit_shared_exponent([x[0] for x in d], [x[1] for x in d], [x[2] for x in d],
                                         boot_xs=[x[3] for x in d] if boot else None,
                                         boot_ys=[x[4] for x in d] if boot else None)
            why = f.undetermined
            if not why and len(sizes) < 2:
                why = ("one size with three cells or more in the fit range; an extrapolation in 1/N_G "
                       "needs two")
            out[f"{bkey}_sizes"] = " ".join(str(n) for n in sizes) if not why else ""
            out[f"{bkey}_left_out"] = "; ".join(f"N_G={n}: {w}" for n, w in sorted(left.items()))
            out[f"{bkey}_note"] = why
            if why:
                for k in (key, bkey):
                    out[k] = out[f"{k}_err"] = out[f"{k}_slope"] = out[f"{k}_chi2_dof"] = np.nan
                    out[f"{k}_n_sizes"] = 0
                continue
            r = fits.fit_inverse_n(sizes, f.intercepts, f.intercept_errs)
            out[key], out[f"{key}_err"] = r.value, r.err
            out[f"{key}_slope"], out[f"{key}_chi2_dof"], out[f"{key}_n_sizes"] = r.slope, r.chi2_dof, r.n_points
            out[bkey], out[f"{bkey}_err"] = f.exponent, f.exponent_err
            out[f"{bkey}_slope"], out[f"{bkey}_chi2_dof"], out[f"{bkey}_n_sizes"] = 0.0, f.chi2_dof, len(sizes)
            out[f"{bkey}_p"] = fits.chi2_p_value(f.chi2, f.dof)
        extrapolated[v] = out
        if not np.isfinite(out["beta_E"]):
            notes.append(f"{v}: no N_G -> inf value of A_G against E_G: {out['beta_E_note']}"
                         + (f" ({out['beta_E_left_out']})" if out["beta_E_left_out"] else ""))
        else:
            notes.append(f"{v}: N_G -> inf from the sizes {out['beta_E_sizes'].replace(' ', ', ')} "
                         "(one exponent shared by the sizes, intercepts extrapolated in 1/N_G)"
                         + (f"; left out: {out['beta_E_left_out']}" if out["beta_E_left_out"] else ""))
    return extrapolated


def _histograms(fin, g: _Grid, s: Settings):
    """One pass over every histogram: summed and normalised counts per cell, the
    self-averaging ratios, and P(sin theta)."""
    C, cell = g.C, g.cell
    dists, selfavg = {}, {}
    for name, edges in sorted(fin.edges.items()):
        nb = len(edges) - 1
        centres = 0.5 * (edges[1:] + edges[:-1])
        counts = np.zeros((C, nb), np.int64)
        want_m = name not in SELF_AVERAGING_SKIP
        mom = np.full((len(fin), 2), np.nan) if want_m else None
        for pos, block in fin.histogram_blocks(name):
            cb = cell[pos]
            o = np.argsort(cb, kind="stable")
            cbs = cb[o]
            starts = np.flatnonzero(np.r_[True, cbs[1:] != cbs[:-1]])
            counts[cbs[starts]] += np.add.reduceat(block[o], starts, axis=0)
            if want_m:
                bf = block.astype(float)
                tot = bf.sum(axis=1)
                with np.errstate(invalid="ignore", divide="ignore"):
                    mom[pos, 0] = bf @ centres / tot
                    mom[pos, 1] = bf @ (centres * centres) / tot
        widths = np.diff(edges)
        with np.errstate(invalid="ignore", divide="ignore"):
            density = counts / counts.sum(axis=1, keepdims=True) / widths
        dists[name] = {"edges": edges, "counts": counts, "density": density}
        if want_m:
            tot = counts.sum(axis=1).astype(float)
            with np.errstate(invalid="ignore", divide="ignore"):
                ens = np.stack([counts @ centres / tot, counts @ (centres**2) / tot], axis=1)
                ratio = mom / ens[cell]
            rm = np.full((C, 2), np.nan)
            rs = np.full((C, 2), np.nan)
            for k in range(2):
                _, rm[:, k], rs[:, k], _ = _group_stats(ratio[:, k], cell, C)
            selfavg[name] = {"ratio_mean": rm, "ratio_std": rs, "ensemble_moments": ens}
    if "contact_angle" in dists:
        se = np.linspace(0.0, 1.0, s.sin_bins + 1)
        d = dists["contact_angle"]
        dens = np.full((C, s.sin_bins), np.nan)
        has = d["counts"].sum(axis=1) > 0
        if has.any():
            dens[has] = fits.sin_theta_density(d["counts"][has], d["edges"], se)
        dists["sin_theta"] = {"edges": se, "density": dens}
    return dists, selfavg


def reduce_campaign(paths, settings: Settings | None = None, *, distributions=True) -> Reduction:
    """Reduce campaign file(s) (see the module docstring). ``distributions=False`` skips the
    histogram pass (scalars, fits and the table only)."""
    s = settings or Settings()
    t0 = time.perf_counter()
    everything = load_finished(paths)
    t_load = time.perf_counter() - t0
    # statistics use the converged packings whose identities hold; the others are
    # counted per cell (n_excluded) and named in the notes
    good, reasons = everything.usable()
    fin = everything.subset(good)
    if len(fin.tasks["status"]) == 0:
        raise UserError(f"{fin.paths[0]}: the task table is empty")
    g = _grid(everything, good, fin.tasks)  # cells are defined by every task, finished or not
    cells = _cell_table(fin, g)
    notes = _count_notes(fin, g, reasons)
    area_hist, width = _area_distributions(fin, g, s, cells)
    vsys = variant_systems(fin.attrs, variants=g.cv)
    fit_records, residuals, rows, shared_in = _scaling_fits(fin, g, s, cells, notes,
                                                            {v: d["exponent"] for v, d in vsys.items()})
    extrapolated = _extrapolate(rows, shared_in, notes)
    t1 = time.perf_counter()
    dists, selfavg = _histograms(fin, g, s) if distributions else ({}, {})
    t_hist = time.perf_counter() - t1

    from campaign.results import systems as sysmod
    from campaign.results import tradeoff

    # speed against accuracy compares packings of one physical system: the reference's
    ref_sys = vsys.get(s.reference)
    same = np.isin(np.asarray(everything.variant, dtype=str), [v for v, d in vsys.items() if d == ref_sys])
    if not same.all() and ref_sys is not None:
        others = sorted({str(v) for v in everything.variant[~same]})
        notes.append(f"variants {', '.join(others)} are other systems than {s.reference!r}: compared in "
                     "systems.md, not packing by packing")
    pick = same if ref_sys is not None else np.ones(len(everything), bool)
    variants, vnotes = tradeoff.compare(everything.subset(pick), extrapolated, s.reference, n_boot=s.n_boot,
                                        seed=s.boot_seed, usable=good[pick])
    notes += vnotes
    systems = sysmod.compare(rows, extrapolated, vsys, reference=s.reference)
    from campaign.results import response as respmod

    resp = (respmod.reduce_response(fin, g, s, dists, {v: d["exponent"] for v, d in vsys.items()}, notes)
            if respmod.present(fin) else {})
    for rec in variants + systems:  # their exponents and A_G* come from the scaling fits
        rec["fit_rule"] = fit_rule_name(s)
    meta = {"sources": fin.paths, "done": int(len(fin)), "excluded": int(g.n_excluded.sum()),
            "pending": int(g.n_pending.sum()), "failed": int(g.n_failed.sum()),
            "total": int(g.n_tasks.sum()), "n_boot": s.n_boot,
            "boot_seed": s.boot_seed, "min_packings": s.min_packings,
            "fit_energies": [float(x) for x in s.fit_energies], "fit_overlap": float(s.fit_overlap),
            "fit_default": is_default_range(s), "fit_rule_name": fit_rule_name(s),
            "fit_rule_text": fit_rule_text(s),
            "spec_hash": fin.attrs.get("spec_hash", ""), "name": fin.attrs.get("name", ""),
            "seconds": {"load": t_load, "histograms": t_hist,
                        "total": time.perf_counter() - t0}}
    return Reduction(cells=cells, distributions=dists, self_averaging=selfavg,
                     area_hist=area_hist, fits=fit_records, residuals=residuals,
                     width_scaling=width, rows=rows, extrapolated=extrapolated,
                     peaks={v: three_disk_peaks(vsys[v]) for v in sorted(set(g.cv))},
                     notes=notes, meta=meta, variants=variants, systems=systems, response=resp)


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
    import h5py

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
    import h5py

    from campaign.version import __version__

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
        if red.variants:
            _write_columns(g.create_group("variants"), red.variants)
        if red.systems:
            _write_columns(g.create_group("systems"), red.systems)
        if red.response:
            rg = g.create_group("response")
            for key in ("cells", "fits", "exponents"):
                if red.response.get(key):
                    _write_columns(rg.create_group(key), red.response[key])


def write_outputs(red: Reduction, out_dir, *, write_h5=True):
    """Tables (md, csv, tex), per-cell and per-fit CSVs, and the reduced HDF5 file."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "table.md": table_markdown(red), "table.csv": table_csv(red), "table.tex": table_latex(red),
        "cells.csv": records_csv(cells_records(red)), "fits.csv": records_csv(red.fits),
        "width_scaling.csv": records_csv(red.width_scaling),
        "variants.csv": records_csv(red.variants),
        "summary.json": json.dumps(red.to_json(), indent=1) + "\n",
    }
    if red.response:
        files["response_cells.csv"] = records_csv(red.response.get("cells", []))
        files["response_fits.csv"] = records_csv(red.response.get("fits", []))
        files["response_exponents.csv"] = records_csv(red.response.get("exponents", []))
    if red.systems:
        from campaign.results import systems

        files["systems.csv"] = systems.table_csv(red.systems)
        files["systems.md"] = systems.table_markdown(red.systems)
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
