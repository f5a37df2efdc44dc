"""campaign calibrate: fit the cost model's constants to packings timed on this machine.

Two sources, together or apart: ``--store FILE ...`` reads the finished packings of campaign
stores (each packing's ``jam_seconds + analyze_seconds``, its N, E_G, potential and protocol from
the store's spec), and ``--run`` (the default without ``--store``) times a small stratified set
here, one packing at a time on one core: N_G 128..4096 x E_G 1e-3..1e-15, FIRE, the Newton
endgame and a FIRE ladder back to back for each (N_G, E_G, seed), so that a change of load hits
the three alike. The fit (``campaign.plan.calibration.fit``) prints the constants with their
errors and writes the calibration file; ``--check`` instead compares a calibration with the
stores' measured times.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import socket
import sys
import time
from pathlib import Path

import numpy as np

from campaign.errors import UserError
from campaign.plan import calibration
from campaign.plan.calibration import BLOCKS, _fixed_factor, machine
from campaign.storage.layout import stored_spec
from kernels.names import DEFAULT_OBSERVABLES

HELP = "fit the cost model to packings timed here (--run) or in stores (--store); --check compares"

EPILOG = """\
Use the file it writes with CAMPAIGN_COST_CALIBRATION=FILE (every command) or --calibration FILE
(campaign validate, campaign slurm, campaign calibrate --check). Timings on a loaded machine are
inflated: --run records CPU seconds (and says how much of the wall time the process got); store
timings are wall seconds of one task on one worker.

--seeds selects packings of the stores by seed index (e.g. 0-9, even, odd), to calibrate on some
seeds and check on the others; FILE@SEL does it for one store (results/a.h5@0-9).
"""

#: the stratified set --run times: sizes, energies (each a ladder rung below the previous), seeds
PLAN = {"sizes": (128, 256, 512, 1024, 2048, 4096),
        "energies": (1e-3, 1e-5, 1e-7, 1e-9, 1e-11, 1e-13, 1e-15), "seeds": 2}
QUICK = {"sizes": (128, 512, 2048), "energies": (1e-3, 1e-7, 1e-11), "seeds": 1}
CALIBRATION_SEED = 314159


def configure(parser):
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("--store", nargs="+", metavar="FILE", default=[],
                        help="campaign stores whose finished packings to learn from (or to --check); "
                             "FILE@SEL takes only the seeds SEL of that store")
    parser.add_argument("--seeds", metavar="SEL", default=None,
                        help="only the stores' packings of these seed indices: A-B, even or odd")
    parser.add_argument("--run", action="store_true",
                        help="time the stratified set on this machine (the default without --store)")
    parser.add_argument("--quick", action="store_true",
                        help="a small set (N_G 128, 512, 2048; E_G 1e-3, 1e-7, 1e-11; one seed; about a minute)")
    parser.add_argument("--budget", type=float, metavar="MINUTES",
                        help="drop the largest sizes, then seeds, until the set fits this estimate")
    parser.add_argument("--out", metavar="FILE", default="cost_calibration.json",
                        help="calibration file to write (default: cost_calibration.json)")
    parser.add_argument("--check", action="store_true",
                        help="fit nothing: compare the calibration in force with the stores' measured times")
    parser.add_argument("--calibration", metavar="FILE",
                        help="the calibration to start from (--run/--store) or to check (default: "
                             "$CAMPAIGN_COST_CALIBRATION, else the packaged one)")
    parser.add_argument("--systematic", type=float, metavar="S",
                        help="the systematic scatter of ln(time) to record (default: the starting calibration's)")
    parser.add_argument("--quiet", action="store_true", help="no line per timed packing")
    parser.add_argument("--gpu", action="store_true",
                        help="on a machine with a GPU: time the GPU block against a CPU core (N_G 1024, 4096, "
                             "8192; --quick: 256, 1024) and add the ratios to the starting calibration, so that "
                             "validate prices device: gpu tasks in GPU-hours (docs/GPU.md)")
    parser.add_argument("--gpu-batch", type=int, default=132, metavar="B",
                        help="packings per launch for --gpu (default 132: one per SM of an H100)")


# ---------------------------------------------------------------------- selecting seeds

def _seed_filter(text):
    if text is None:
        return lambda s: np.ones(len(s), bool)
    t = text.strip().lower()
    if t in ("even", "odd"):
        r = 0 if t == "even" else 1
        return lambda s: np.asarray(s) % 2 == r
    try:
        a, b = (int(v) for v in t.split("-"))
    except ValueError:
        raise UserError(f"--seeds must be A-B (seed indices, inclusive), even or odd; got {text!r}") from None
    if a < 0 or b < a:
        raise UserError(f"--seeds {text!r}: expected 0 <= A <= B")
    return lambda s: (np.asarray(s) >= a) & (np.asarray(s) <= b)


# ---------------------------------------------------------------------- reading stores

def _store_records(path, seeds):
    """The store's finished packings as fit records, and what was skipped (their protocols are not
    in the model)."""
    from campaign.report.frames import Packings  # brings h5py: loaded when the command reads a store, not at --help

    with Packings(path, good=False) as pk:
        cols = pk.read_all()
        spec = stored_spec(pk.attrs, strict=True, name=f"{path} (its spec)")
    if spec is None:
        raise UserError(f"{path}: the store holds no spec (spec_yaml); cannot tell its packings' protocols")
    variants = {v.name: v for v in spec.variants}
    if "jam_seconds" not in cols:
        raise UserError(f"{path}: no jam_seconds scalar: the store's packings were not timed")
    keep = seeds(cols["seed"])
    _load_note(path, cols, keep)
    out = {k: [] for k in ("N", "E", "exponent", "endgame", "parent_E", "seconds", "group", "protocol")}
    skipped = 0
    analyze = cols.get("analyze_seconds", np.zeros(len(cols["N"])))
    for i in np.flatnonzero(keep):
        v = variants.get(cols["variant"][i])
        if v is None:
            skipped += 1
            continue
        N, E = int(cols["N"][i]), float(cols["E"][i])
        proto = dict(v.task_protocol(N, E))
        if proto.get("minimizer", "fire") != "fire" or "route" in proto or "stop" in proto:
            skipped += 1  # not in the model: priced as FIRE, not learnt from
            continue
        parent = v.parent_E(E)
        t = float(cols["jam_seconds"][i]) + float(np.nan_to_num(analyze[i]))
        out["N"].append(N)
        out["E"].append(E)
        out["exponent"].append(v.system.exponent)
        out["endgame"].append(proto.get("endgame", "none"))
        out["parent_E"].append(math.nan if parent is None else parent)
        out["seconds"].append(t / _fixed_factor(proto))  # the tolerance's and search's factors out
        out["group"].append(str(path))
        out["protocol"].append((tuple(sorted(proto.items())), v.name, parent, t))
    return out, skipped


#: a store whose median FIRE packing took this much longer per force evaluation than its fastest
#: tenth was probably timed on a loaded machine (paper-small: 1.05; one run beside a test suite: 1.31)
LOAD_WARNING = 1.15


def _load_note(path, cols, keep):
    """Seconds per force evaluation and disk are the same for every FIRE packing of one N on an idle
    core: their spread in a store measures the load it was timed under. Says so when it is large."""
    if "force_evaluations" not in cols:
        return
    fe = np.asarray(cols["force_evaluations"], float)
    ok = keep & (fe > 0) & np.isfinite(cols["jam_seconds"])
    if "factorizations" in cols:
        ok &= ~(np.nan_to_num(np.asarray(cols["factorizations"], float)) > 0)  # FIRE alone
    rate = np.asarray(cols["jam_seconds"], float) / np.maximum(fe, 1) / np.asarray(cols["N"], float)
    worst = []
    for N in np.unique(np.asarray(cols["N"])[ok]):
        r = rate[ok & (np.asarray(cols["N"]) == N)]
        if r.size >= 10:
            worst.append((float(np.median(r) / np.quantile(r, 0.1)), int(N)))
    if worst and max(worst)[0] > LOAD_WARNING:
        f, N = max(worst)
        print(f"note: {path}: at N_G = {N} the median FIRE packing took {f:.2f} times longer per force "
              "evaluation than the fastest tenth: timed under load? (1.05 on an idle machine)", file=sys.stderr)


# ---------------------------------------------------------------------- timing here

def _plan(args, cal):
    from kernels.jamming import DEFAULTS, energy_floor, initial_state  # numba: only when --run times packings

    plan = dict(QUICK if args.quick else PLAN)
    sizes, seeds = list(plan["sizes"]), plan["seeds"]

    def cells(sizes, seeds):
        out = []
        for N in sizes:
            _, radii, _ = initial_state(N, 0, (1.0, 1.0), ((0.5, 1.4), (0.5, 1.0)), DEFAULTS["phi_start"], None)
            floor = energy_floor(radii, (1.0, 1.0), 2.0, 1e-6)
            energies = [E for E in sorted(plan["energies"], reverse=True) if E >= floor]
            out += [(N, s, energies) for s in range(seeds)]
        return out

    def minutes(cs):
        total = 0.0
        for N, _, energies in cs:
            for k, E in enumerate(energies):
                parent = energies[k - 1] if k else None
                total += cal.seconds(N, E) + cal.seconds(N, E, {"endgame": "newton"})
                if parent is not None:
                    total += cal.seconds(N, E, {"start": "ladder"}, 2.0, parent)
        return total / 60

    chosen = cells(sizes, seeds)
    if args.budget is not None:
        if not args.budget > 0:
            raise UserError(f"--budget must be a positive number of minutes; got {args.budget}")
        while minutes(chosen) > args.budget and (len(sizes) > 2 or seeds > 1):
            if seeds > 1 and len(sizes) <= 3:
                seeds -= 1
            else:
                sizes.pop()
            chosen = cells(sizes, seeds)
    return chosen, minutes(chosen)


def _time_one(kernels, N, E, seed, protocol, start, observables):
    c0, w0 = time.process_time(), time.perf_counter()
    p = kernels.jam(N, E, [CALIBRATION_SEED, N, seed], start=start, **protocol)
    kernels.analyze(p.positions, p.radii, p.box, observables=observables, species=p.species)
    return p, time.process_time() - c0, time.perf_counter() - w0


def _run_records(args, cal):
    os.environ.setdefault("NUMBA_CACHE_DIR", str(Path.home() / ".cache" / "jamming-campaign" / "numba"))
    import kernels  # numba: imported once NUMBA_CACHE_DIR is set, and only to time packings here

    chosen, minutes = _plan(args, cal)
    n_packings = sum(3 * len(e) - 1 for _, _, e in chosen)
    print(f"timing {n_packings} packings here (N_G {', '.join(str(n) for n in sorted({c[0] for c in chosen}))}; "
          f"about {minutes:.0f} min by {cal.source}); compiling first", file=sys.stderr, flush=True)
    obs = list(DEFAULT_OBSERVABLES)
    for proto in ({}, {"endgame": "newton"}):  # compile (or load) before timing
        p = kernels.jam(64, 1e-4, [0], **proto)
        kernels.jam(64, 1e-5, [0], start=(p.positions, p.radii, p.species), **proto)
        kernels.analyze(p.positions, p.radii, p.box, observables=obs, species=p.species)
    out = {k: [] for k in ("N", "E", "exponent", "endgame", "parent_E", "seconds", "group", "protocol")}
    group = f"run:{socket.gethostname()}"
    cpu_total = wall_total = 0.0
    for N, seed, energies in chosen:
        parent = None
        for E in energies:
            runs = [("fire", {}, None), ("newton", {"endgame": "newton"}, None)]
            if parent is not None:
                runs.append(("ladder", {"start": "ladder"}, parent))
            for name, proto, start in runs:
                jam_proto = {k: v for k, v in proto.items() if k != "start"}
                st = None if start is None else (start[1].positions, start[1].radii, start[1].species)
                p, cpu, wall = _time_one(kernels, N, E, seed, jam_proto, st, obs)
                cpu_total, wall_total = cpu_total + cpu, wall_total + wall
                out["N"].append(N)
                out["E"].append(E)
                out["exponent"].append(2.0)
                out["endgame"].append(proto.get("endgame", "none"))
                out["parent_E"].append(math.nan if start is None else start[0])
                out["seconds"].append(cpu)
                out["group"].append(group)
                out["protocol"].append((tuple(sorted(proto.items())), name, None if start is None else start[0], cpu))
                if name == "fire":
                    fire_packing = p
                if not args.quiet:
                    print(f"  N_G {N:5d}  E_G {E:7.0e}  seed {seed}  {name:6s} {cpu:8.2f} s CPU "
                          f"({wall:.2f} s wall)", file=sys.stderr, flush=True)
            # the ladder's next rung starts from this energy's ladder packing (its top: FIRE's)
            parent = (E, p if parent is not None else fire_packing)
    share = cpu_total / wall_total if wall_total > 0 else 1.0
    return out, share


# ---------------------------------------------------------------------- printing

def _table(fit):
    cal = fit.calibration
    lines = [f"cost model ({sum(n for _, n in fit.counts.values())} packings; L0 = {cal.L0:g}, "
             f"sigma_task = {cal.sigma_task:.3f}, sigma_systematic = {cal.sigma_systematic:.3f})",
             f"  {'block':15s} {'constant':8s} {'value':>9s} {'error':>8s}   learnt from"]
    for block in BLOCKS:
        vals, cov = cal.blocks[block]
        err = np.sqrt(np.diag(cov))
        cells, packings = fit.counts.get(block, (0, 0))
        where = (f"{packings} packings in {cells} cells, rms {fit.rms[block]:.3f}" if packings
                 else "no data: the starting calibration's")
        for k, (name, v, e) in enumerate(zip(BLOCKS[block], vals, err)):
            lines.append(f"  {block if k == 0 else '':15s} {name:8s} {v:9.4f} {e:8.4f}   {where if k == 0 else ''}")
    return "\n".join(lines)


def _comparison(records, cal, by_variant=True):
    """Measured against estimated seconds per (group, variant, N), and in total."""
    groups = {}
    for N, E, a, proto, group in zip(records["N"], records["E"], records["exponent"], records["protocol"],
                                     records["group"]):
        protocol, variant, parent, t = proto
        key = (group, variant if by_variant else "", N)
        g = groups.setdefault(key, [0.0, {}])
        g[0] += t
        cell = (N, E, protocol, a, parent)
        g[1][cell] = g[1].get(cell, 0) + 1
    rows, total_t, total_cells = [], 0.0, {}
    for (group, variant, N), (t, cells) in sorted(groups.items()):
        est = cal.estimate((n, *c) for c, n in cells.items())
        rows.append((group, variant, N, sum(cells.values()), t, est))
        total_t += t
        for c, n in cells.items():
            total_cells[c] = total_cells.get(c, 0) + n
    return rows, total_t, cal.estimate((n, *c) for c, n in total_cells.items())


def _print_comparison(records, cal, title):
    rows, total_t, total = _comparison(records, cal)
    print(title)
    print(f"  {'store':24s} {'variant':14s} {'N_G':>6s} {'packings':>8s} {'measured h':>10s} "
          f"{'estimated h (68%)':>26s} {'est/meas':>8s}")
    for group, variant, N, n, t, est in rows:
        name = Path(group).name if not group.startswith("run:") else group
        print(f"  {name[:24]:24s} {variant[:14]:14s} {N:6d} {n:8d} {t / 3600:10.3g} "
              f"{est.seconds / 3600:9.3g} ({est.low / 3600:.3g} - {est.high / 3600:.3g}) {est.seconds / t:8.2f}")
    print(f"  {'total':24s} {'':14s} {'':6s} {sum(r[3] for r in rows):8d} {total_t / 3600:10.3g} "
          f"{total.seconds / 3600:9.3g} ({total.low / 3600:.3g} - {total.high / 3600:.3g}) "
          f"{total.seconds / total_t if total_t else float('nan'):8.2f}")


# ---------------------------------------------------------------------- main

#: --gpu: the sizes timed and the FIRE steps of each timing
GPU_PLAN = {"sizes": (1024, 4096, 8192), "steps": 1000}
GPU_QUICK = {"sizes": (256, 1024), "steps": 300}


def _gpu_ratios(args) -> dict:
    """GPU seconds per FIRE step per packing (a batch of ``--gpu-batch`` random starts, their
    first minimisation bounded at the plan's steps) over a CPU core's for the same starts, per size:
    the ``gpu`` block of a calibration. Needs a CUDA device; ``CAMPAIGN_GPU_BACKEND=emulate``
    times the CPU emulation instead (for tests: its ratios price nothing real)."""
    from kernels.gpu import describe, resolve_backend  # numba and the GPU backends: for --gpu only

    backend = resolve_backend(None)
    if backend != "cuda" and os.environ.get("CAMPAIGN_GPU_BACKEND") != "emulate":
        raise UserError("calibrate --gpu times the GPU block: it needs a CUDA device and numba-cuda "
                        "(pip install 'jamming-campaign[gpu]'); none is available here")
    if args.gpu_batch < 1:
        raise UserError(f"--gpu-batch must be at least 1, got {args.gpu_batch}")
    from kernels.gpu.batch import time_steps

    plan = GPU_QUICK if args.quick else GPU_PLAN
    sizes, ratios = [], []
    for n in plan["sizes"]:
        r = time_steps(n, args.gpu_batch, plan["steps"], backend)
        gpu, cpu = r["gpu"], r["cpu"]
        sizes.append(int(n))
        ratios.append(gpu / cpu)
        if not args.quiet:
            print(f"  N_G {n:6d}: {1e6 * gpu:9.2f} us per step per packing (batch {args.gpu_batch}) against "
                  f"{1e6 * cpu:8.1f} on a CPU core: {cpu / gpu:7.1f} cores", flush=True)
    return {"device": describe(backend), "batch": int(args.gpu_batch), "threads": 256,
            "steps": plan["steps"], "N": sizes, "ratio": ratios, "machine": machine()}


def main(args) -> int:
    seeds = _seed_filter(args.seeds)
    if args.check and not args.store:
        raise UserError("--check compares a calibration with stores: give --store FILE ...")
    if args.check and args.run:
        raise UserError("--check fits nothing and times nothing: drop --run")
    if args.systematic is not None and not (math.isfinite(args.systematic) and 0 <= args.systematic <= 5):
        raise UserError(f"--systematic must be between 0 and 5; got {args.systematic}")
    if args.gpu:  # the GPU ratios added to the starting calibration; nothing refitted
        if args.store or args.check or args.run:
            raise UserError("--gpu times the GPU block alone: drop --store, --check and --run")
        with calibration.using(args.calibration) as start:
            gpu = _gpu_ratios(args)
            cal = start.with_gpu(gpu)
        out = Path(args.out)
        try:
            cal.save(out)
        except OSError as exc:
            raise UserError(f"cannot write the calibration to {str(out)!r}: {exc}") from None
        print(f"wrote {out}: {start.source} with the GPU ratios of {gpu['device']}: use it with "
              f"CAMPAIGN_COST_CALIBRATION={out} or campaign validate SPEC --calibration {out}")
        return 0
    with calibration.using(args.calibration) as start:
        records = {k: [] for k in ("N", "E", "exponent", "endgame", "parent_E", "seconds", "group", "protocol")}
        skipped = 0
        for path in args.store:
            own = seeds
            if "@" in path and not Path(path).exists():
                path, sel = path.rsplit("@", 1)
                own = _seed_filter(sel)
            got, n_skip = _store_records(path, own)
            skipped += n_skip
            for k in records:
                records[k] += got[k]
        if args.store and not records["N"]:
            raise UserError("the stores hold no finished packing to learn from"
                            + (f" among seeds {args.seeds}" if args.seeds else ""))
        if args.check:
            _print_comparison(records, start, f"{start.source} against the measured times "
                                              f"(jam + analysis, one core; seeds {args.seeds or 'all'}):")
            if skipped:
                print(f"  ({skipped} packings of protocols the model does not price were left out)")
            return 0
        share = None
        if args.run or not args.store:
            got, share = _run_records(args, start)
            for k in records:
                records[k] += got[k]
        info = {"created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "host": _host(), "machine": machine(),
                "stores": list(args.store), "seeds": args.seeds or "all",
                "run": bool(args.run or not args.store), "packings": len(records["N"])}
        if share is not None:  # the load the run's timings saw
            info["cpu_share_of_wall"] = round(share, 3)
            try:
                info["load_average"] = [round(x, 2) for x in os.getloadavg()]
            except OSError:
                pass
        fit = calibration.fit({k: np.asarray(v, dtype=object if k in ("endgame", "group") else float)
                               for k, v in records.items() if k != "protocol"}, start,
                              sigma_systematic=args.systematic, info=info)
    out = Path(args.out)
    try:  # first: whatever happens to the printing
        fit.calibration.save(out)
    except OSError as exc:
        raise UserError(f"cannot write the calibration to {str(out)!r}: {exc}") from None
    print(_table(fit))
    if skipped:
        print(f"  ({skipped} packings of protocols the model does not price were left out)")
    if share is not None and share < 0.9:
        print(f"  note: this process got {share:.0%} of the wall time: the machine was loaded; CPU seconds "
              "were used, still an overestimate if the cores' caches were shared")
    _print_comparison(records, fit.calibration, "the fit against the measured times (jam + analysis, one core):")
    print(f"wrote {out}: use it with CAMPAIGN_COST_CALIBRATION={out} or "
          f"campaign validate SPEC --calibration {out}")
    return 0


def _host() -> str:
    return f"{platform.node()} ({machine()})"
