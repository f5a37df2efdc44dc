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
    cells = _cells(s["variant"], s["N"], s["E"])
    groups = []
    for (v, n, e), rows in cells:
        st = status[rows] if isinstance(rows, np.ndarray) else status[rows[0]:rows[1]]
        groups.append([(v, n, e), int(np.count_nonzero(st == DONE)), int(np.count_nonzero(st == FAILED)),
                       int(np.count_nonzero(st == PENDING))])
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
    fr = s["failed"]
    variant = s["variant"]
    for k, i in enumerate(s["failed_rows"]):
        tid = fr["id"][k].decode()
        rec = s["failures"].get(tid, {})
        failures.append({"id": tid, "variant": variant[i].decode(errors="replace"), "N": int(s["N"][i]),
                         "E": float(s["E"][i]), "seed": int(fr["seed"][k]), "attempts": int(fr["attempts"][k]),
                         "host": fr["host"][k].decode(errors="replace"), "rank": int(fr["rank"][k]),
                         "message": str(rec.get("message", fr["error"][k].decode(errors="replace"))),
                         "traceback": str(rec.get("traceback", ""))})
    remaining_hours, learnt_from = _remaining_core_hours(attrs, status, s["wall"], cells, s["variant"],
                                                         s["N"], s["E"])
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


def _cells(variant, N, E):
    """((variant, N, E), (first, end)) for each run of equal keys; rows are in canonical order,
    so a cell is one run (a cell met again later gets its rows as an index array)."""
    import numpy as np

    T = len(N)
    if T == 0:
        return []
    change = np.flatnonzero((variant[1:] != variant[:-1]) | (N[1:] != N[:-1]) | (E[1:] != E[:-1])) + 1
    starts = np.r_[0, change]
    ends = np.r_[change, T]
    out, seen = [], {}
    for a, b in zip(starts.tolist(), ends.tolist()):
        key = (variant[a].decode(errors="replace") if isinstance(variant[a], bytes) else str(variant[a]),
               int(N[a]), float(E[a]))
        if key in seen:  # not canonical order (a file written by other means): merge
            k = seen[key]
            prev = out[k][1]
            prev = np.arange(*prev) if isinstance(prev, tuple) else prev
            out[k] = (key, np.r_[prev, np.arange(a, b)])
        else:
            seen[key] = len(out)
            out.append((key, (a, b)))
    return out


#: At most this many finished rows teach the cost model shown by status (evenly spaced).
FIT_ROWS = 20000


def _remaining_core_hours(attrs, status, wall, cells=None, variant=None, N=None, E=None):
    """Core-hours of the unfinished tasks by the cost model learnt from the finished ones.

    Per cell, not per task: the tasks of a (variant, N, E) cell cost the same, so the sum
    over the unfinished tasks is the count per cell times the cell's estimate.
    """
    import numpy as np

    from campaign.costmodel import CostModel
    from campaign.errors import UserError
    from campaign.spec import parse_spec

    try:
        spec = parse_spec(str(attrs["spec_yaml"]), "the file's spec")
    except (KeyError, UserError):
        return None, 0
    if spec.n_tasks != len(status) or cells is None:
        return None, 0
    protocols = {v.name: dict(v.protocol) for v in spec.variants}
    done = np.flatnonzero(status == 1)
    if len(done) > FIT_ROWS:
        done = done[np.linspace(0, len(done) - 1, FIT_ROWS).astype(np.int64)]
    vnames = [x.decode(errors="replace") for x in variant[done]]
    if any(v not in protocols for v in vnames):
        return None, 0
    if len(done):
        model = CostModel.fit(N[done], E[done], wall[done], [protocols[v] for v in vnames])
    else:
        model = CostModel.prior()
    total = 0.0
    for (v, n, e), rows in cells:
        st = status[rows] if isinstance(rows, np.ndarray) else status[rows[0]:rows[1]]
        left = int(np.count_nonzero(st != 1))
        if left and v in protocols:
            total += left * float(model.seconds(n, e, [protocols[v]])[0])
    return total / 3600.0, model.n_points
