"""campaign validate SPEC: check a spec completely, print its task count and estimated cost."""

from __future__ import annotations

from collections import Counter
from dataclasses import replace
from pathlib import Path

from campaign.errors import UserError
from campaign.plan import calibration, targets
from campaign.plan.calibration import calibrated_on, machine
from campaign.plan.parse import load_spec
from campaign.plan.spec import resolve_protocol
from campaign.plan.tasks import energy_floor_problems, estimate, expand, task_cost
from campaign.run.walltime import remaining_seconds
from campaign.storage.checksums import read_rounds
from campaign.storage.layout import DONE
from campaign.storage.progress import fmt_duration

HELP = "check a campaign spec; print its task count and estimated cost"

#: `endgame: auto` is advised when it saves at least this share of a variant's estimate
AUTO_ADVICE = 0.05


def configure(parser):
    parser.add_argument("spec", nargs="?", default=None, help="campaign spec (YAML); default: the packaged quickstart")
    parser.add_argument("--calibration", metavar="FILE",
                        help="the cost model's calibration (written by campaign calibrate; default: "
                             "$CAMPAIGN_COST_CALIBRATION, else the packaged one)")


def main(args) -> int:
    with calibration.using(getattr(args, "calibration", None)) as cal:
        return _main(args, cal)


def _main(args, cal) -> int:
    spec = load_spec(args.spec)
    problems = energy_floor_problems(spec)
    if problems:
        raise UserError(f"{len(problems)} problem(s) in the spec:\n  " + "\n  ".join(problems))
    tasks = expand(spec)
    est = estimate(tasks, cal)
    longest = max(task_cost(t) for t in tasks)
    print(f"{spec.source}: valid")
    print(f"  name        {spec.name}")
    if all(v.E == spec.E for v in spec.variants):
        grid = f"{len(spec.variants)} variant(s) x {len(spec.N)} N_G x {len(spec.E)} E_G"
    else:  # variants with their own energies
        grid = f"{sum(len(v.E) for v in spec.variants)} (variant, E_G) x {len(spec.N)} N_G"
    if spec.precision is None:
        print(f"  tasks       {len(tasks)} = {grid} x {len(spec.seeds)} seed(s)")
    else:
        from campaign.precision.planner import first_round  # the planner only for a spec with targets

        first, how = first_round(spec, tasks)
        print(f"  tasks       {int(first.sum())} in round 0 ({grid}; {how}), at most "
              f"{len(tasks)} ({spec.precision.max_seeds} seeds in every cell)")
        print(f"  precision   {targets.describe(spec.precision)}")
    print(f"  variants    {', '.join(v.name for v in spec.variants)}")
    if any(v.system != spec.system for v in spec.variants):
        # several physical systems: each a sub-campaign with its own ids, table and figures
        print("  systems")
        for v in spec.variants:
            own = "" if v.system == spec.system else "  (overrides the spec's system)"
            print(f"    {v.name:<12} {v.system.label()}, box {v.system.box[0]:g} x {v.system.box[1]:g}{own}")
    for v in spec.variants:
        if v.E != spec.E:
            print(f"  E_G of {v.name}: {', '.join(f'{e:g}' for e in v.E)}")
    print(f"  N_G         {', '.join(str(n) for n in spec.N)}")
    print(f"  E_G         {', '.join(f'{e:g}' for e in spec.E)}")
    print(f"  observables {', '.join(spec.observables)}")
    print(f"  output      {spec.output}")
    for line in _endgames(spec, tasks):
        print(line)
    if spec.precision is None:
        print(f"  estimated cost {est.hours()}: {fmt_duration(est.seconds)} on one core; longest task "
              f"~{fmt_duration(longest)}; model calibrated by {cal.source} (campaign/plan/calibration.py)")
    else:
        for line in _precision_cost(spec, tasks, cal, est, longest, first):
            print(line)
    here, made_on = machine(), calibrated_on(cal)
    if made_on is not None and made_on != here:
        print(f"  note: the cost model was calibrated on another machine ({made_on}); this is {here}: its "
              "prices are off by the ratio of their speeds. `campaign calibrate --run --quick` here (minutes) "
              "makes a calibration for this machine (--calibration FILE)")
    if len(spec.variants) > 1:
        parts = [f"{v.name} {estimate([t for t in tasks if t.variant == v.name], cal).seconds / 3600:.3g}"
                 for v in spec.variants]
        print(f"  per variant (core-hours): {', '.join(parts)}")
    gpu = [v.name for v in spec.variants if dict(v.protocol).get("device") == "gpu"]
    if gpu:
        mine = [t for t in tasks if t.variant in gpu]
        if cal.gpu:
            hours = sum(cal.gpu_seconds(t.N, t.E, t.protocol, t.exponent) for t in mine) / 3600
            print(f"  device gpu  {len(mine)} task(s) of {', '.join(gpu)}: about {hours:.3g} GPU-hours on "
                  f"{cal.gpu['device']} in batches of {cal.gpu['batch']} (calibrate --gpu; above: as CPU core-hours)")
        else:
            print(f"  device gpu  {len(mine)} task(s) of {', '.join(gpu)}: priced above as CPU core-hours (the same "
                  "FIRE steps); `campaign calibrate --gpu` on a GPU prices them in GPU-hours (docs/GPU.md)")
    for line in _gpu_advice(spec, tasks, cal):
        print(line)
    # a precision campaign gives seeds to single cells: no ladder, and its store's rounds say what is left
    for line in _auto_advice(spec, tasks, cal) + (_fast_advice(spec, tasks, cal) if spec.precision is None else []):
        print(line)
    learnt = _learnt_remaining(spec, tasks) if spec.precision is None else None
    if learnt:
        print(f"  {spec.output}: {learnt}")
    return 0


def _precision_cost(spec, tasks, cal, est, longest, first):
    """A precision campaign's price: its round 0 (``first``, seeds per cell) and its ceiling by the cost model; what reaching its
    targets would cost, from its store's last decision when its pilot has run, else from the prior
    (campaign.precision.planner.plan_from_prior), or why that needs the pilot."""
    # imported here: only a spec with precision targets needs the planner (and the reducer's fits it brings)
    from campaign.precision.planner import plan_from_prior

    p = spec.precision
    pilot = [t for t in tasks if t.seed < first[t.index // p.max_seeds]]
    pe = estimate(pilot, cal)
    out = [f"  estimated cost of round 0 {pe.hours()}; at most {est.hours()} (max_seeds in every cell); longest "
           f"task ~{longest / 60:.3g} min; model calibrated by {cal.source}"]
    done = _last_decision(spec)
    if done is not None:
        out.append(f"  {spec.output}: {done}")
        return out
    got = plan_from_prior(spec, tasks)  # priced by the calibration in force: cal
    if not got["ok"]:
        out.append(f"  reaching the targets: needs the pilot ({got['why']}); run it with `campaign run {spec.source}`: "
                   "its first decision says what the rest costs (campaign status)")
        return out
    errs = ", ".join(f"{k} {v:.2g}" for k, v in got["pilot_errors"].items())
    if not got["reachable"]:
        at_max = ", ".join(f"{k} {v:.2g}" for k, v in got["max_seeds_errors"].items())
        out.append(f"  reaching the targets: not within max_seeds by the prior (errors at max_seeds in every cell: "
                   f"{at_max}); the pilot decides (errors after it, by the prior: {errs})")
        return out
    line = (f"  reaching the targets: about {got['total_seconds'] / 3600:.3g} core-hours by the prior (the pilot "
            f"{got['pilot_seconds'] / 3600:.3g}, then {got['plan_seconds'] / 3600:.3g}; {got['packings']} packings)")
    if "uniform_seconds" in got:
        line += (f"; the same errors from {got['uniform_seeds']} seeds in every cell: "
                 f"{got['uniform_seconds'] / 3600:.3g} core-hours")
    out.append(line)
    out.append("    (the prior: paper-small's packings, docs/PRECISION.md; the rounds plan from the campaign's own "
               "packings, and a design from a prior is cheaper than the rounds reach: they re-estimate as they go)")
    return out


def _last_decision(spec):
    """What the spec's store says of its rounds (its last decision), or None without one."""
    if not spec.output or not Path(spec.output).exists():
        return None
    from campaign.storage.reader import open_store  # brings h5py: only when there is a store to read

    try:
        with open_store(spec.output) as f:
            if f.attrs.get("spec_hash") != spec.hash:
                return None
            got, _ = read_rounds(f)
    except (UserError, OSError, KeyError, ValueError):  # nothing to say of a store that does not read
        return None
    if not got:
        return None
    last = got[max(got)]
    to = last.get("to_targets_core_hours")
    spent = (last.get("spent_core_hours") or 0) + (last.get("committed_core_hours") or 0)
    if last["action"] in ("pilot",):
        return "its pilot is running; its first decision says what the rest costs"
    if last["action"] != "continue":
        return f"ended ({last['action']}) after round {last['round'] - 1}: {last['message']}"
    return (f"decision {last['round']}: {spent:.3g} core-hours given out so far"
            + (f", reaching every target about {to:.3g} more" if to is not None else ""))


def _endgames(spec, tasks):
    """What `endgame: auto` resolved to, per variant that asks for it."""
    out = []
    for v in spec.variants:
        if dict(v.protocol).get("endgame") != "auto":
            continue
        mine = [t for t in tasks if t.variant == v.name]
        newton = sorted({(t.N, t.E) for t in mine if dict(t.protocol).get("endgame") == "newton"})
        where = ", ".join(f"{n}/{e:g}" for n, e in newton[:8]) + (", ..." if len(newton) > 8 else "")
        out.append(f"  endgame: auto in {v.name!r}: Newton for {sum(dict(t.protocol).get('endgame') == 'newton' for t in mine)} "
                   f"of {len(mine)} packings" + (f" (N_G/E_G {where})" if newton else "") + ", FIRE alone elsewhere")
    return out


def _gpu_advice(spec, tasks, cal):
    """With a GPU calibration: what each CPU variant the GPU block can run (FIRE on the O'Hern route
    in a fixed cell from random starts) would take as ``device: gpu``, in GPU-hours."""
    if not cal.gpu:
        return []
    out = []
    for v in spec.variants:
        proto = dict(v.protocol)
        if "device" in proto or not _takes_newton(proto) or "start" in proto or "endgame" in proto:
            continue
        mine = [t for t in tasks if t.variant == v.name]
        cpu = sum(cal.seconds(t.N, t.E, t.protocol, t.exponent) for t in mine) / 3600
        gpu = sum(cal.gpu_seconds(t.N, t.E, t.protocol, t.exponent) for t in mine) / 3600
        out.append(f"  advice: {v.name!r} as `device: gpu` would take about {gpu:.3g} GPU-hours on "
                   f"{cal.gpu['device']} instead of {cpu:.3g} core-hours (its own task ids: docs/GPU.md)")
    return out


def _takes_newton(proto) -> bool:
    """Whether a protocol can take the Newton endgame: FIRE, the O'Hern route, the fixed cell, the
    CPU (the GPU block runs FIRE alone from random starts)."""
    return proto.get("minimizer", "fire") == "fire" and not {"stop", "route", "cell", "device"} & proto.keys()


def _repriced(mine, cal, key):
    """One variant's tasks ``mine`` priced as they are and as ``key(task) -> (N, E, protocol,
    exponent, parent_E)`` would have them: ``(seconds, {cell: count}, Estimate)``, or None unless
    the alternative saves at least ``AUTO_ADVICE`` of the time."""
    now = sum(cal.seconds(t.N, t.E, t.protocol, t.exponent, t.parent_E) for t in mine)
    cells = Counter(key(t) for t in mine)
    alt = cal.estimate((n, *k) for k, n in cells.items())
    if now <= 0 or alt.seconds > (1.0 - AUTO_ADVICE) * now:
        return None
    return now, cells, alt


def _auto_advice(spec, tasks, cal):
    """Where `endgame: auto` would save time by the calibrated model: FIRE's (or Newton's)
    estimate against auto's, per variant that could take it."""
    out = []
    for v in spec.variants:
        proto = dict(v.protocol)
        if proto.get("endgame") == "auto" or not _takes_newton(proto):
            continue
        bare = {k: x for k, x in proto.items() if k != "endgame"}
        if any(w is not v and w.system == v.system and {k: x for k, x in dict(w.protocol).items()
                                                        if k != "endgame"} == bare for w in spec.variants):
            continue  # a variant that differs from this one by its endgame only: auto would repeat its packings
        mine = [t for t in tasks if t.variant == v.name]
        priced = _repriced(mine, cal, lambda t: (t.N, t.E, resolve_protocol(dict(t.protocol, endgame="auto"), t.N,
                                                                            t.E, t.exponent), t.exponent, t.parent_E))
        if priced is None:
            continue
        now, cells, auto = priced
        n_newton = sum(n for k, n in cells.items() if dict(k[2]).get("endgame") == "newton")
        current = "the Newton endgame everywhere" if proto.get("endgame") == "newton" else "FIRE alone"
        where = f"{v.name!r}" if len(spec.variants) > 1 else "this campaign"
        out.append(f"  advice: {where} would cost {auto.seconds / 3600:.3g} core-hours with `endgame: auto` "
                   f"instead of {now / 3600:.3g} with {current} ({1 - auto.seconds / now:.0%} less; Newton "
                   f"for {n_newton} of {len(mine)} packings, FIRE for the rest). Its packings differ slightly "
                   "from FIRE's and get new task ids: docs/NEWTON.md")
    return out


def _fast_advice(spec, tasks, cal):
    """What the fast protocol for energy scans (`start: ladder` with `endgame: auto`) would cost,
    per variant of independent FIRE packings at three energies or more, with its price in
    accuracy (measured in docs/SPEED_ACCURACY.md)."""
    out = []
    for v in spec.variants:
        proto = dict(v.protocol)
        if len(v.E) < 3 or "start" in proto or not _takes_newton(proto):
            continue
        fast = replace(v, protocol=tuple(sorted({**proto, "start": "ladder", "endgame": "auto"}.items())))
        priced = _repriced([t for t in tasks if t.variant == v.name], cal,
                           lambda t: (t.N, t.E, fast.task_protocol(t.N, t.E), t.exponent, fast.parent_E(t.E)))
        if priced is None:
            continue
        now, _, alt = priced
        where = f"{v.name!r}" if len(spec.variants) > 1 else "this campaign"
        out.append(f"  advice: {where} scans {len(v.E)} energies: the fast protocol (`start: ladder`, "
                   f"`endgame: auto`) would cost {alt.seconds / 3600:.3g} core-hours instead of {now / 3600:.3g} "
                   f"({1 - alt.seconds / now:.0%} less). Its packings are made from the next higher "
                   "energy's, not independent: A_G about 0.001 lower (N_G 1024 - 4096), not for the "
                   "finite-size table (docs/SPEED_ACCURACY.md#the-fast-protocol-for-energy-scans)")
    return out


def _learnt_remaining(spec, tasks):
    """What the spec's existing output file says is left, by the cost model learnt from it."""
    if not spec.output or not Path(spec.output).exists():
        return None
    from campaign.storage.reader import read_summary  # brings h5py: only when there is a store to read
    try:
        s = read_summary(spec.output, fields=("status", "wall"))
    except UserError as exc:
        return f"exists but cannot be resumed: {exc}"
    if s["attrs"].get("spec_hash") != spec.hash or len(s["status"]) != len(tasks):
        return "exists, written by a different spec"
    seconds, n = remaining_seconds(tasks, s["status"], s["wall"])
    done = int((s["status"] == DONE).sum())
    return (f"{done} of {len(tasks)} done; remaining about {seconds / 3600:.3g} core-hours "
            f"(cost model learnt from {n} finished packing(s))")
