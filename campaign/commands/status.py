"""campaign status FILE: progress of a campaign store, per (variant, N, E), and its failures.

Works while a run is writing the file (it opens it read-only, without locking). Whether a
run is writing it comes from the run's progress file (``campaign.storage.progress.writer_state``):
on the same host its process must still exist; from another host the file must have been
updated within the last ``STALE_SECONDS``.

With GPU packings it also says how busy each GPU kept its device (``GpuBusy``) and which packings
wait suspended in the store for the next run (stop and go, docs/GPU.md).
"""

from __future__ import annotations

import datetime
import json
import math

import numpy as np

from campaign.errors import StoreDamaged
from campaign.plan.costmodel import CostModel
from campaign.run.rounds import STOPS
from campaign.run.slurm import has_gpu_tasks
from campaign.storage.checksums import check_identities, damaged_message, failure_problem, has_sums, read_rounds
from campaign.storage.journal import task_indices
from campaign.storage.layout import DONE, FAILED, PENDING, stored_spec
from campaign.storage.progress import progress_text, read_sidecar, writer_state

HELP = "show the progress and failures recorded in a campaign store (also while it runs)"


def configure(parser):
    parser.add_argument("file", help="campaign store (HDF5) written by 'campaign run'")
    parser.add_argument("--tracebacks", action="store_true", help="print each failure's full traceback")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")


def main(args) -> int:
    s = _scan(args.file)
    groups = [[key, c[0], c[1], c[2]] for key, c in s["cells"].items()]
    totals = s["totals"]
    live = read_sidecar(args.file)
    writer = writer_state(live)
    active = writer["state"] == "running"
    running = int(live.get("running", 0)) if active else 0
    state = {"done": totals["done"], "failed": totals["failed"], "running": running,
             "remaining": totals["pending"] - running,
             "per_hour": live.get("per_hour") if active else None,
             "eta_seconds": live.get("eta_seconds") if active else None}
    attrs = s["attrs"]
    if not active:  # the last run's average rate, if it recorded one
        try:
            last = json.loads(attrs.get("runs", "[]"))[-1]
            if last.get("seconds"):
                state["per_hour"] = 3600.0 * (last.get("completed", 0) + last.get("failed", 0)) / last["seconds"]
        except (ValueError, IndexError, TypeError, AttributeError):
            pass
    failures = s["failures"]
    waiting = _journal_only(args.file, s["status"])
    remaining_hours, learnt_from = _remaining_core_hours(attrs, s)
    if args.json:
        who = {k: live.get(k) for k in ("pid", "host", "updated")} if live else {}
        print(json.dumps({"file": str(args.file), "name": str(attrs.get("name", "")), "live": active,
                          "writer": dict(who, state=writer["state"], judged_by=writer["how"],
                                         age_seconds=writer["age"]),
                          **state, "tasks": totals["tasks"], "in_journal_only": waiting,
                          "remaining_core_hours": remaining_hours,
                          "groups": [{"variant": k[0], "N": k[1], "E": k[2], "done": d, "failed": f, "pending": p}
                                     for k, d, f, p in groups],
                          "gpu_workers": live.get("gpu_workers") if active else None,
                          "gpu_packings": s["devices"], "gpu_busy": s["busy"], "suspended": s["suspended"],
                          "failures": failures, "core_hours": totals["core_hours"],
                          "precision": ({"round": int(s["rounds"][max(s["rounds"])]["round"]),
                                         "last_decision": s["rounds"][max(s["rounds"])]}
                                        if s["rounds"] else None)}, indent=1))
        return 0
    if s["rounds"]:
        print(f"{args.file}: campaign {attrs.get('name', '?')!s}, {totals['tasks']} tasks given out by its rounds "
              f"(of {totals['rows']} seeds up to max_seeds)")
    else:
        print(f"{args.file}: campaign {attrs.get('name', '?')!s}, {totals['tasks']} tasks")
    print("  " + progress_text(state))
    for line in precision_lines(s["rounds"], totals):
        print("  " + line)
    if writer["state"] in ("running", "dead"):
        print("  " + writer["text"])
    else:
        print(f"  no run is writing it (last run ended {attrs.get('end_time') or 'without a clean stop'})")
    if waiting:
        print(f"  {waiting} more finished task(s) are in its journal only so far ({args.file}.journal); "
              + ("the run writes them into the store at its next flush" if active else
                 "the next run writes them into the store (counted here as pending)"))
    if remaining_hours is not None and totals["pending"] + totals["failed"]:
        print(f"  estimated remaining work {remaining_hours:.3g} core-hours "
              f"(cost model learnt from {learnt_from} finished packing(s))")
    gpu_now = live.get("gpu_workers") if active else None
    if s["devices"] or gpu_now:
        print("  " + "; ".join(([f"GPU workers now: {gpu_now}"] if gpu_now else []) +
                               ([("GPU packings: " + ", ".join(f"{n} on {d}" for d, n in sorted(s["devices"].items())))]
                                if s["devices"] else [])))
    for device, b in sorted(s["busy"].items()):
        print(f"  GPU busy on {device}: {100 * b['busy_fraction']:.1f}% ({b['block_seconds']:.4g} block-seconds over "
              f"{b['slot_seconds']:.4g} slot-seconds; {b['gpus']} GPU(s), {b['runs']} run(s), {b['packings']} packings)")
    if s["suspended"]["tasks"]:
        print(f"  suspended GPU packings: {s['suspended']['tasks']} ({s['suspended']['steps']} FIRE steps so far), "
              "kept in the store; the next run goes on from them")
    width = max(7, max(len(k[0]) for k, *_ in groups)) if groups else 7
    print(f"  {'variant':<{width}} {'N':>7} {'E':>9} {'done':>6} {'failed':>6} {'pending':>7}")
    for (v, n, e), d, f, p in groups:
        print(f"  {v:<{width}} {n:>7d} {e:>9.2g} {d:>6d} {f:>6d} {p:>7d}")
    if failures:
        print(f"  failures ({len(failures)}):")
        for r in failures:
            print(f"    {r['id']}  {r['variant']} N={r['N']} E={r['E']:g} seed={r['seed']}  "
                  f"attempts={r['attempts']} host={r['host']} rank={r['rank']}: {r['message']}")
            if args.tracebacks and r["traceback"]:
                print("      " + r["traceback"].rstrip().replace("\n", "\n      "))
    return 0


#: Rows read at a time: memory stays bounded whatever the number of tasks.
BLOCK = 1 << 16
#: At most this many finished rows (evenly spaced) teach the cost model behind the estimate.
FIT_ROWS = 20000


def _scan(path):
    """One pass over the task table in blocks of rows: counts per (variant, N, E) cell in
    order of appearance, totals, the failed rows' details and an evenly spaced sample of
    finished rows (N, E, wall, variant) for the cost model. Memory: one block, the cells,
    the failures and the sample; the status column (one byte a task) is read first, to
    space the sample."""
    # imported when the command runs: they bring h5py, which `campaign --help` (every command's
    # module imported to build the parser) need not load
    from campaign.results.finished import given_rows
    from campaign.storage.reader import read_retrying

    return read_retrying(path, lambda f: _scan_open(f, given_rows))


def _scan_open(f, given_rows):
    t = f["tasks"]
    status_all = t["status"][:]
    T = len(status_all)
    given = given_rows(f, T)  # a precision campaign: the seeds its rounds gave out (else every row)
    rounds = read_rounds(f)[0]
    wall_seconds = 0.0
    n_done = int(np.count_nonzero(status_all == DONE))
    stride = max(1, -(-n_done // FIT_ROWS))
    failure_recs = {tid: dict(f["failures"][tid].attrs) for tid in f["failures"]} if "failures" in f else {}
    for tid, rec in failure_recs.items():
        problem = failure_problem(rec, has_sums(f))
        if problem is not None:
            raise StoreDamaged(damaged_message(f.filename, f"failures/{tid}", problem))
    cells, failures = {}, []
    sample = {"N": [], "E": [], "wall": [], "variant": []}
    done_seen = 0
    # GPU packings record what ran them beside the host ("node12 cuda:NVIDIA H100 ..."): counted per
    # device, read only for a spec that asks for them
    written = stored_spec(f)
    devices = {} if written is not None and has_gpu_tasks(written) else None
    clock = None  # the device clock's scalars, when the store has them
    if devices is not None and all(f"device_{k}" in f["scalars"] for k in ("start", "end", "seconds", "slots")):
        clock = {k: f["scalars"][f"device_{k}"] for k in ("start", "end", "seconds", "slots")}
    busy = GpuBusy(run_spans(f.attrs.get("runs", "[]")))
    spec = stored_spec(f, verified=True)
    for lo in range(0, T, BLOCK):
        hi = min(lo + BLOCK, T)
        st = np.where(given[lo:hi] | (status_all[lo:hi] != PENDING), status_all[lo:hi], -1)  # -1: not given out
        v, N, E = t["variant"][lo:hi], t["N"][lo:hi], t["E"][lo:hi]
        check_identities(f.filename, spec, v, N, E, lo)
        change = np.flatnonzero((v[1:] != v[:-1]) | (N[1:] != N[:-1]) | (E[1:] != E[:-1])) + 1
        for a, b in zip(np.r_[0, change].tolist(), np.r_[change, hi - lo].tolist()):
            key = (v[a].decode(errors="replace"), int(N[a]), float(E[a]))
            c = cells.setdefault(key, [0, 0, 0])
            part = st[a:b]
            c[0] += int(np.count_nonzero(part == DONE))
            c[1] += int(np.count_nonzero(part == FAILED))
            c[2] += int(np.count_nonzero(part == PENDING))
        done = np.flatnonzero(st == DONE)
        if len(done):
            w = t["wall"][lo:hi][done]
            wall_seconds += float(np.sum(w[np.isfinite(w)]))
        if devices is not None and len(done):
            hosts = t["host"][lo:hi][done]
            for h in hosts:
                device = h.decode(errors="replace").partition(" ")[2]
                if device:
                    devices[device] = devices.get(device, 0) + 1
            if clock is not None:
                busy.add(hosts, t["rank"][lo:hi][done], *(clock[k][lo:hi][done] for k in ("start", "end", "seconds",
                                                                                          "slots")))
        pick = done[(np.arange(done_seen, done_seen + len(done)) % stride) == 0]
        done_seen += len(done)
        if len(pick):
            wall = t["wall"][lo:hi]
            sample["N"].append(N[pick])
            sample["E"].append(E[pick])
            sample["wall"].append(wall[pick])
            sample["variant"].append(v[pick])
        bad = np.flatnonzero(st == FAILED)
        if len(bad):
            cols = {k: t[k][lo:hi][bad] for k in ("id", "seed", "attempts", "host", "rank", "error")}
            for k, i in enumerate(bad):
                tid = cols["id"][k].decode()
                rec = failure_recs.get(tid, {})
                failures.append({"id": tid, "variant": v[i].decode(errors="replace"), "N": int(N[i]),
                                 "E": float(E[i]), "seed": int(cols["seed"][k]), "attempts": int(cols["attempts"][k]),
                                 "host": cols["host"][k].decode(errors="replace"), "rank": int(cols["rank"][k]),
                                 "message": str(rec.get("message", cols["error"][k].decode(errors="replace"))),
                                 "traceback": str(rec.get("traceback", ""))})
    totals = {"done": n_done, "failed": int(np.count_nonzero(status_all == FAILED)),
              "pending": int(np.count_nonzero((status_all == PENDING) & given)),
              "tasks": int(np.count_nonzero(given | (status_all != PENDING))), "rows": T,
              "core_hours": wall_seconds / 3600.0}
    sample = {k: (np.concatenate(x) if x else np.zeros(0)) for k, x in sample.items()}
    return {"attrs": {k: f.attrs[k] for k in f.attrs}, "cells": cells, "totals": totals,
            "failures": failures, "sample": sample, "status": status_all, "devices": devices or {},
            "busy": busy.result(), "suspended": _suspended(f, status_all), "rounds": rounds}


def precision_lines(rounds, totals) -> list:
    """What ``campaign status`` says of a precision campaign: its round, the last decision, each
    target's error against its goal, the core-hours spent (priced from force evaluations, and
    measured) and those the plan projects."""
    if not rounds:
        return []
    last = rounds[max(rounds)]
    k = int(last["round"])
    action = last["action"]
    state = {"pilot": "the pilot round", "continue": f"round {k}",
             "met": f"ended after round {k - 1}: every target met",
             "budget": f"ended after round {k - 1}: budget spent",
             "max_seeds": f"ended after round {k - 1}: max_seeds reached",
             "unreachable": f"ended after round {k - 1}: a target out of reach",
             "limited": f"ended after round {k - 1}: a target limited by its sizes"}.get(action, action)
    out = [f"precision targets: {state} ({len(rounds)} decision(s) kept)"]
    for t in last.get("targets", []):
        who = "" if t["variant"] == "default" else f" ({t['variant']})"
        err = "no value" if t.get("error") is None else f"{t['error']:.3g}"
        proj = "" if t.get("projected") is None else f", projected {t['projected']:.3g} after the round"
        mark = " met" if t.get("met") else ""
        out.append(f"  {t['key']}{who}: error {err} against goal {t['goal']:g}{mark} (at decision {k}{proj})")
    spent = last.get("spent_core_hours")
    rnd, to = last.get("round_core_hours"), last.get("to_targets_core_hours")
    line = f"  core-hours: {totals['core_hours']:.3g} measured"
    if spent is not None:
        line += f"; priced from force evaluations {spent:.3g} spent before decision {k}"
        if rnd:
            line += f", {rnd:.3g} in its round"
    if to is not None and action == "continue":
        line += f"; projected to reach every target: {to:.3g} more"
    out.append(line)
    if action in STOPS and last.get("message"):
        out.append("  " + last["message"])
    return out


def _suspended(f, status):
    """Suspended GPU packings the store keeps for pending tasks: ``{"tasks", "steps"}`` (FIRE steps
    so far, summed); one that cannot be read is not counted (its task starts over)."""
    out = {"tasks": 0, "steps": 0}
    try:
        g = f["checkpoints"] if "checkpoints" in f else None
        names = list(g.keys()) if g is not None else []
    except Exception:  # noqa: BLE001 - `campaign verify` says what is damaged
        return out
    if not names:
        return out
    kept, pending = set(names), set()
    for lo in range(0, len(status), BLOCK):  # the ids of pending rows, a block at a time
        rows = np.flatnonzero(status[lo:lo + BLOCK] == PENDING)
        if len(rows):
            pending.update(kept.intersection(f["tasks/id"][lo:lo + BLOCK][rows].astype(str).tolist()))
    for tid in names:
        if tid not in pending:
            continue
        try:
            steps = int(g[tid].attrs["steps"])
        except Exception:  # noqa: BLE001
            continue
        out["tasks"] += 1
        out["steps"] += steps
    return out


def run_spans(runs_json) -> list:
    """``(start, end)`` in epoch seconds of each run of a store's ``runs`` attribute (a run without
    an end, killed or still running: until the next run's start, else open)."""
    try:
        runs = json.loads(runs_json)
    except (TypeError, ValueError):
        return []

    def epoch(text):
        try:
            return datetime.datetime.strptime(str(text), "%Y-%m-%dT%H:%M:%S%z").timestamp()
        except (TypeError, ValueError):
            return None

    starts = [epoch(r.get("start")) if isinstance(r, dict) else None for r in runs]
    out = []
    for k, r in enumerate(runs):
        if starts[k] is None:
            continue
        end = epoch(r.get("end"))
        if end is None:
            later = [s for s in starts[k + 1:] if s is not None]
            end = later[0] if later else math.inf
        out.append((starts[k], end))
    return sorted(out)


class GpuBusy:
    """The GPUs' busy fraction from the GPU packings' device clocks (``scalars/device_*``).

    A GPU is a worker's device: one (host column, rank) of the task table (``host`` is "node12
    cuda:NAME"; the device's label is what follows the host's name). Its packings are split by the
    run during which each ended (``runs``: ``run_spans``; the device clock counts epoch seconds: the
    host's in the emulation, ``%globaltimer`` on a GPU, which the driver starts from the host's
    clock; a packing that ended in no run's span makes a window of its own kind). In each (GPU,
    run) window, from its first packing's start (not before the run's) to its last packing's end:

        busy = sum of block-seconds / (resident slots x (last end - first start))

    and per device label the windows' block-seconds over their slot-seconds: the time between two
    runs (the next job waiting in the queue) is never counted as idle, the time inside a run is,
    tail included. A packing resumed from an earlier run counts at most the block-seconds that fit
    its own span inside the window (its device clock holds the earlier runs' too)."""

    def __init__(self, spans):
        self.spans = spans
        self.starts = np.array([a for a, _ in spans], np.float64)
        self.windows = {}  # (label, host, rank, run) -> [first start, last end, block-seconds, slots, packings]

    def add(self, hosts, ranks, start, end, seconds, slots):
        """GPU packings: their host column's values, ranks and device clocks (arrays alike)."""
        start, end, seconds, slots = (np.asarray(x, np.float64) for x in (start, end, seconds, slots))
        for k, h in enumerate(hosts):
            label = h.decode(errors="replace").partition(" ")[2] if isinstance(h, bytes) else str(h).partition(" ")[2]
            s, e, b, n = start[k], end[k], seconds[k], slots[k]
            if not label or not (np.isfinite(s) and np.isfinite(e) and np.isfinite(b) and e > s):
                continue
            run = self._run(e)
            lo = max(s, self.spans[run][0]) if run >= 0 else s
            key = (label, h, int(ranks[k]), run)
            w = self.windows.get(key)
            if w is None:
                w = self.windows[key] = [lo, e, 0.0, 1.0, 0]
            w[0], w[1] = min(w[0], lo), max(w[1], e)
            w[2] += min(b, e - lo)
            w[3] = max(w[3], n if np.isfinite(n) and n >= 1 else 1.0)
            w[4] += 1

    def _run(self, end) -> int:
        """The run during which a packing that ended at ``end`` ran (-1: none)."""
        k = int(np.searchsorted(self.starts, end + 1.0, side="right")) - 1
        if k >= 0 and end <= self.spans[k][1] + 1.0:
            return k
        return -1

    def result(self) -> dict:
        """Per device label: ``busy_fraction``, ``block_seconds``, ``slot_seconds``, ``gpus``,
        ``runs`` and ``packings``."""
        out = {}
        for (label, h, rank, run), (first, last, block, slots, n) in self.windows.items():
            d = out.setdefault(label, {"block_seconds": 0.0, "slot_seconds": 0.0, "gpus": set(), "runs": set(),
                                       "packings": 0})
            d["block_seconds"] += block
            d["slot_seconds"] += slots * (last - first)
            d["gpus"].add((h, rank))
            d["runs"].add(run)
            d["packings"] += n
        for d in out.values():
            d["busy_fraction"] = d["block_seconds"] / d["slot_seconds"] if d["slot_seconds"] > 0 else None
            d["gpus"], d["runs"] = len(d["gpus"]), len(d["runs"])
        return out


def _journal_only(path, status):
    """How many tasks the journal has records of that the store does not hold yet (finished by a
    run that is still to write them, or that stopped before it could: the next run replays them)."""
    idx = np.fromiter((i for i in task_indices(str(path) + ".journal") if 0 <= i < len(status)), np.int64)
    return int(np.count_nonzero(status[idx] == PENDING)) if len(idx) else 0


def _remaining_core_hours(attrs, s):
    """Core-hours of the unfinished tasks by the cost model learnt from (a sample of at most
    FIT_ROWS of) the finished ones. Per cell: the tasks of a (variant, N, E) cell cost the
    same, so the sum over the unfinished tasks is the count per cell times the cell's estimate."""
    spec = stored_spec(attrs)
    if spec is None:  # no estimate from a spec that does not read
        return None, 0
    if spec.n_tasks != s["totals"]["rows"]:
        return None, 0
    variants = {v.name: v for v in spec.variants}
    protocols = {v.name: dict(v.protocol) for v in spec.variants}
    smp = s["sample"]
    vnames = [x.decode(errors="replace") for x in smp["variant"]]
    if any(v not in protocols for v in vnames):
        return None, 0

    def parent(v, e):  # a ladder step starts from the next energy up of its variant
        if protocols[v].get("start") != "ladder":
            return None
        higher = [x for x in variants[v].E if x > e]
        return min(higher) if higher else None

    model = (CostModel.fit(smp["N"], smp["E"], smp["wall"], [protocols[v] for v in vnames],
                           [parent(v, float(e)) for v, e in zip(vnames, smp["E"])],
                           [variants[v].system.exponent for v in vnames]) if vnames
             else CostModel.prior())
    total = 0.0
    for (v, n, e), (done, failed, pending) in s["cells"].items():
        left = failed + pending
        if left and v in protocols:
            total += left * float(model.seconds(n, e, [protocols[v]], [parent(v, float(e))],
                                                [variants[v].system.exponent])[0])
    return total / 3600.0, model.n_points
