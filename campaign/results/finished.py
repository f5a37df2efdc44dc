"""What the reducer reads from campaign store(s): the finished packings and the physical systems.

Reading goes through one place, ``load_finished`` (and ``Finished.histogram_blocks``), which
knows the store layout of docs/CONTRACTS.md and checks it (a campaign file of a format this
version reads, the task table's columns, the same histogram bins in every file); everything
else works on plain arrays. Only rows whose status is 1 (done) are used, each task id once
(``first_done``), and of those the statistics use the usable ones (``usable_mask``); every
row's status stays in ``Finished.tasks``, for the counts of pending and failed packings per
cell. ``variant_systems``: each variant's physical system, from the spec text stored in the file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from campaign.errors import UserError
from campaign.plan.spec import System
from campaign.storage.checksums import check_identities, read_rounds
from campaign.storage.layout import DONE, FAILED, stored_spec
from campaign.storage.reader import open_store, read_failure


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
    The one definition of the packings the reducer uses (also ``campaign.report.frames``)."""
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
    for r in np.flatnonzero(np.asarray(status) == DONE):
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
        for path, (rows, pos) in zip(self.paths, self._rows):
            if len(rows) == 0:
                continue
            with open_store(path, accept="layout") as f:
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
                    err = read_failure(path, exc, f, [f"histograms/{name}/counts"], what=f"histogram {name!r}")
                    if err is None:
                        raise
                    raise err from None


def _failed_errors(f, status, block=65536):
    """The error column (decoded) with the failed rows' messages, read block by block
    (the column is 512 bytes a row; only failed rows have one)."""
    err = np.full(len(status), "", dtype=object)
    failed = np.flatnonzero(status == FAILED)
    if not failed.size or "error" not in _column_names(f):
        return err
    t = f["tasks"]
    for lo in range(0, len(status), block):
        rows = failed[(failed >= lo) & (failed < lo + block)]
        if rows.size:
            data = (t["error"][lo:lo + block] if hasattr(t, "keys") else t[lo:lo + block]["error"])
            err[rows] = _decode(np.asarray(data)[rows - lo])
    return err


def given_rows(f, T):
    """Which rows of a store are tasks of its campaign: all of them, except in a campaign with precision
    targets, whose rounds give out seeds 0 .. n - 1 of each cell (the last decision's ``early``
    counts; its task table holds every seed up to ``max_seeds``, in cells of equal length)."""
    got, _ = read_rounds(f)
    if not got:
        return np.ones(T, bool)
    counts = np.asarray(got[max(got)]["early"], np.int64)
    C = len(counts)
    if C == 0 or T % C:
        return np.ones(T, bool)
    S = T // C
    return (np.arange(T) % S) < np.repeat(counts, S)


def _column_names(f):
    t = f["tasks"]
    return set(t.keys()) if hasattr(t, "keys") else set(t.dtype.names or ())


def load_finished(paths) -> Finished:
    """Read the task tables, scalars and histogram edges of the campaign file(s).

    This is the only function that knows the store layout. A packing that appears
    done in several files (same task id) is used once.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [str(p) for p in paths]
    seen = set()
    all_rows = {k: [] for k in ("variant", "N", "E", "status", "error", "id", "given")}
    fin = {k: [] for k in ("variant", "N", "E", "id", "seed")}
    scal_parts, per_file, edges, attrs = [], [], None, None
    offset = 0
    for path in paths:
        with open_store(path, accept="layout") as f:  # a file of the layout without a schema is read too
            try:
                if "tasks" not in f:
                    raise UserError(f"{path}: not a campaign file (no /tasks table); "
                                    "expected the layout of docs/CONTRACTS.md")
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
                given = given_rows(f, T)  # a precision campaign: the rows its rounds gave out
                names = sorted(f["scalars"].keys()) if "scalars" in f else []
                scal = {n: np.asarray(f[f"scalars/{n}"][...], dtype=float) for n in names}
                hedges = {}
                if "histograms" in f:
                    for n in f["histograms"]:
                        hedges[n] = np.asarray(f[f"histograms/{n}/edges"][...], dtype=float)
            except Exception as exc:  # noqa: BLE001 - read_failure says which failures are the file's
                err = read_failure(path, exc, f, ["tasks", "scalars", "histograms/*/edges"])
                if err is None:
                    raise
                raise err from None
        check_identities(path, stored_spec(file_attrs, verified=True), variant, cols["N"], cols["E"])
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
                     ("error", err), ("id", ids), ("given", given)):
            all_rows[k].append(np.asarray(v))
        seeds = cols.get("seed", np.full(T, -1))
        for k, v in (("variant", variant), ("N", cols["N"]), ("E", cols["E"]), ("id", ids), ("seed", seeds)):
            fin[k].append(np.asarray(v)[rows])
        scal_parts.append({n: a[rows] for n, a in scal.items()})
    tasks = {k: np.concatenate(v) for k, v in all_rows.items()}
    # a task done in one file but pending/failed in another counts as done; a task
    # pending or failed in several files counts once
    counted = tasks["status"] == DONE
    # a seed a precision campaign's rounds did not give out is no task of the campaign (yet)
    for i in np.flatnonzero(~counted & tasks.pop("given")):
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


def finished_from_arrays(*, attrs, variant, N, E, ids, seed, status, scalars, error=None) -> Finished:
    """``Finished`` packings from a task table held in memory (the campaign master's, whose rounds
    of a precision campaign are reduced while it runs): one row per task, ``status`` 1 for done;
    ``scalars`` (name -> one value per row) are read at the done rows. No histograms. Every row
    counts (a task table has each id once)."""
    status = np.asarray(status).astype(np.int64)
    T = len(status)
    done = np.flatnonzero(status == DONE)
    variant = np.asarray(variant, dtype=object)
    N, E, ids, seed = (np.asarray(a) for a in (N, E, ids, seed))
    err = np.full(T, "", dtype=object) if error is None else np.asarray(error, dtype=object)
    tasks = {"variant": variant, "N": N, "E": E, "status": status, "error": err, "id": ids,
             "counted": np.ones(T, bool)}
    return Finished(paths=[], attrs=dict(attrs), variant=variant[done], N=N[done].astype(np.int64),
                    E=E[done].astype(float), ids=ids[done], seed=seed[done].astype(np.int64),
                    scalars={k: np.asarray(v, float)[done] for k, v in sorted(scalars.items())}, edges={},
                    tasks=tasks, _rows=[])


def variant_systems(attrs, variants=()) -> dict:
    """The physical system of every variant, from the spec text stored in the file.

    ``{variant: {"exponent": alpha, "sizes": label, "box": (L_x, L_y), "radii": distinct
    discrete radii or () for a continuous distribution}}`` for "default" and each of the
    spec's variants (``campaign.plan.spec``: a variant's ``system`` overrides the spec's).
    ``variants``: names found in the data; those the spec does not list get the base system.
    A spec this version cannot read gives every variant the paper's system (exponent 2, the
    1.4:1 mixture).
    """
    spec = stored_spec(attrs)
    if spec is not None:
        out = {v.name: _describe_system(v.system) for v in spec.variants}
    else:  # an old or foreign spec
        out = {"default": _describe_system(System())}
    for v in variants:
        out.setdefault(str(v), dict(out["default"]))
    return out


def ladder_variants(attrs) -> set:
    """The variants of the stored spec whose packings of one seed share a history (``start:
    ladder``: each energy from the seed's packing one energy up); empty for a spec this version
    cannot read."""
    spec = stored_spec(attrs)
    if spec is None:
        return set()
    return {v.name for v in spec.variants if dict(v.protocol).get("start") == "ladder"}


def _describe_system(system) -> dict:
    radii = () if system.sizes is not None else tuple(sorted({s.radius for s in system.species}, reverse=True))
    return {"exponent": float(system.exponent), "sizes": system.sizes_label(), "box": tuple(system.box),
            "radii": radii}
