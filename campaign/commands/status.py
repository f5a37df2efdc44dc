"""campaign status FILE: progress of a campaign store, per (variant, N, E), and its failures.

Works while a run is writing the file (it opens it read-only, without locking). Whether a
run is writing it comes from the run's progress file (``campaign.storage.progress.writer_state``):
on the same host its process must still exist; from another host the file must have been
updated within the last ``STALE_SECONDS``.
"""

from __future__ import annotations

import json

HELP = "show the progress and failures recorded in a campaign store (also while it runs)"


def configure(parser):
    parser.add_argument("file", help="campaign store (HDF5) written by 'campaign run'")
    parser.add_argument("--tracebacks", action="store_true", help="print each failure's full traceback")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")


def main(args) -> int:
    from campaign.storage.progress import progress_text, read_sidecar, writer_state

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
                          "gpu_packings": s["devices"], "failures": failures}, indent=1))
        return 0
    print(f"{args.file}: campaign {attrs.get('name', '?')!s}, {totals['tasks']} tasks")
    print("  " + progress_text(state))
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
    import numpy as np

    from campaign.storage.store import DONE, FAILED, PENDING, read_retrying

    return read_retrying(path, lambda f: _scan_open(f, np, DONE, FAILED, PENDING))


def _scan_open(f, np, DONE, FAILED, PENDING):
    t = f["tasks"]
    status_all = t["status"][:]
    T = len(status_all)
    n_done = int(np.count_nonzero(status_all == DONE))
    stride = max(1, -(-n_done // FIT_ROWS))
    failure_recs = {tid: dict(f["failures"][tid].attrs) for tid in f["failures"]} if "failures" in f else {}
    for tid, rec in failure_recs.items():
        from campaign.storage.checksums import damaged_message, failure_problem, has_sums

        problem = failure_problem(rec, has_sums(f))
        if problem is not None:
            from campaign.errors import StoreDamaged

            raise StoreDamaged(damaged_message(f.filename, f"failures/{tid}", problem))
    cells, failures = {}, []
    sample = {"N": [], "E": [], "wall": [], "variant": []}
    done_seen = 0
    # GPU packings record what ran them beside the host ("node12 cuda:NVIDIA H100 ..."): counted per
    # device, read only for a spec that asks for them
    devices = {} if "gpu" in str(f.attrs.get("spec_yaml", "")) else None
    from campaign.storage.checksums import check_identities, stored_spec

    spec = stored_spec(f.attrs)
    for lo in range(0, T, BLOCK):
        hi = min(lo + BLOCK, T)
        st = status_all[lo:hi]
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
        if devices is not None and len(done):
            for h in t["host"][lo:hi][done]:
                device = h.decode(errors="replace").partition(" ")[2]
                if device:
                    devices[device] = devices.get(device, 0) + 1
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
              "pending": int(np.count_nonzero(status_all == PENDING)), "tasks": T}
    sample = {k: (np.concatenate(x) if x else np.zeros(0)) for k, x in sample.items()}
    return {"attrs": {k: f.attrs[k] for k in f.attrs}, "cells": cells, "totals": totals,
            "failures": failures, "sample": sample, "status": status_all, "devices": devices or {}}


def _journal_only(path, status):
    """How many tasks the journal has records of that the store does not hold yet (finished by a
    run that is still to write them, or that stopped before it could: the next run replays them)."""
    import numpy as np

    from campaign.storage.journal import task_indices

    idx = np.fromiter((i for i in task_indices(str(path) + ".journal") if 0 <= i < len(status)), np.int64)
    return int(np.count_nonzero(status[idx] == 0)) if len(idx) else 0


def _remaining_core_hours(attrs, s):
    """Core-hours of the unfinished tasks by the cost model learnt from (a sample of at most
    FIT_ROWS of) the finished ones. Per cell: the tasks of a (variant, N, E) cell cost the
    same, so the sum over the unfinished tasks is the count per cell times the cell's estimate."""
    from campaign.plan.costmodel import CostModel
    from campaign.errors import UserError
    from campaign.plan.spec import parse_spec

    try:
        spec = parse_spec(str(attrs["spec_yaml"]), "the file's spec")
    except (KeyError, UserError, TypeError, ValueError):  # no estimate from a spec that does not read
        return None, 0
    if spec.n_tasks != s["totals"]["tasks"]:
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
