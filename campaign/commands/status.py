"""campaign status FILE: progress of a campaign store, per (variant, N, E), and its failures.

Works while a run is writing the file (it opens it read-only, without locking).
"""

from __future__ import annotations

import json
import time

HELP = "show the progress and failures recorded in a campaign store (also while it runs)"


def configure(parser):
    parser.add_argument("file", help="campaign store (HDF5) written by 'campaign run'")
    parser.add_argument("--tracebacks", action="store_true", help="print each failure's full traceback")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")


def main(args) -> int:
    import numpy as np

    from campaign.progress import fmt_duration, progress_text, read_sidecar
    from campaign.store import DONE, FAILED, PENDING, read_summary

    s = read_summary(args.file)
    status = s["status"]
    variant = s["variant"].astype(str)
    N, E = s["N"], s["E"]
    groups = []
    seen = {}
    for i in range(len(status)):
        key = (variant[i], int(N[i]), float(E[i]))
        if key not in seen:
            seen[key] = len(groups)
            groups.append([key, 0, 0, 0])
        g = groups[seen[key]]
        g[1 + {DONE: 0, FAILED: 1, PENDING: 2}[int(status[i])]] += 1
    totals = {"done": int(np.sum(status == DONE)), "failed": int(np.sum(status == FAILED)),
              "pending": int(np.sum(status == PENDING)), "tasks": int(len(status))}
    live = read_sidecar(args.file)
    active = bool(live and live.get("active") and time.time() - live.get("updated", 0) < 60)
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
        except (ValueError, IndexError, TypeError):
            pass
    failures = []
    tid = s["id"].astype(str)
    for i in np.flatnonzero(status == FAILED):
        rec = s["failures"].get(tid[i], {})
        failures.append({"id": tid[i], "variant": variant[i], "N": int(N[i]), "E": float(E[i]),
                         "seed": int(s["seed"][i]), "attempts": int(s["attempts"][i]),
                         "host": s["host"][i].decode(errors="replace"), "rank": int(s["rank"][i]),
                         "message": str(rec.get("message", s["error"][i].decode(errors="replace"))),
                         "traceback": str(rec.get("traceback", ""))})
    remaining_hours, learnt_from = _remaining_core_hours(attrs, status, s["wall"])
    if args.json:
        print(json.dumps({"file": str(args.file), "name": str(attrs.get("name", "")), "live": active,
                          **state, "tasks": totals["tasks"], "remaining_core_hours": remaining_hours,
                          "groups": [{"variant": k[0], "N": k[1], "E": k[2], "done": d, "failed": f, "pending": p}
                                     for k, d, f, p in groups],
                          "failures": failures}, indent=1))
        return 0
    print(f"{args.file}: campaign {attrs.get('name', '?')!s}, {totals['tasks']} tasks")
    print("  " + progress_text(state))
    if active:
        print(f"  a run is writing it (pid {live.get('pid')} on {live.get('host')}, "
              f"updated {fmt_duration(time.time() - live['updated'])} ago)")
    else:
        print(f"  no run is writing it (last run ended {attrs.get('end_time') or 'without a clean stop'})")
    if remaining_hours is not None and totals["pending"] + totals["failed"]:
        print(f"  estimated remaining work {remaining_hours:.3g} core-hours "
              f"(cost model learnt from {learnt_from} finished packing(s))")
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


def _remaining_core_hours(attrs, status, wall):
    """Core-hours of the unfinished tasks by the cost model learnt from the finished ones."""
    from campaign.errors import UserError
    from campaign.spec import parse_spec
    from campaign.tasks import expand
    from campaign.walltime import remaining_seconds

    try:
        tasks = expand(parse_spec(str(attrs["spec_yaml"]), "the file's spec"))
    except (KeyError, UserError):
        return None, 0
    if len(tasks) != len(status):
        return None, 0
    seconds, n = remaining_seconds(tasks, status, wall)
    return seconds / 3600.0, n
