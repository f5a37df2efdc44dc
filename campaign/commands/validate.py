"""campaign validate SPEC: check a spec completely, print its task count and estimated cost."""

from __future__ import annotations

HELP = "check a campaign spec; print its task count and estimated cost"


def configure(parser):
    parser.add_argument("spec", nargs="?", default=None, help="campaign spec (YAML); default: the packaged quickstart")


def main(args) -> int:
    from campaign.storage.progress import fmt_duration
    from campaign.plan.spec import load_spec
    from campaign.errors import UserError
    from campaign.plan.tasks import energy_floor_problems, estimate_seconds, expand, task_cost

    spec = load_spec(args.spec)
    problems = energy_floor_problems(spec)
    if problems:
        raise UserError(f"{len(problems)} problem(s) in the spec:\n  " + "\n  ".join(problems))
    tasks = expand(spec)
    seconds = estimate_seconds(tasks)
    longest = max(task_cost(t) for t in tasks)
    print(f"{spec.source}: valid")
    print(f"  name        {spec.name}")
    if all(v.E == spec.E for v in spec.variants):
        grid = f"{len(spec.variants)} variant(s) x {len(spec.N)} N_G x {len(spec.E)} E_G"
    else:  # variants with their own energies
        grid = f"{sum(len(v.E) for v in spec.variants)} (variant, E_G) x {len(spec.N)} N_G"
    print(f"  tasks       {len(tasks)} = {grid} x {len(spec.seeds)} seed(s)")
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
    print(f"  estimated cost {seconds / 3600:.3g} core-hours ({fmt_duration(seconds)} on one core; "
          f"longest task ~{fmt_duration(longest)}; a rough model, see campaign/plan/tasks.py)")
    learnt = _learnt_remaining(spec, tasks)
    if learnt:
        print(f"  {spec.output}: {learnt}")
    return 0


def _learnt_remaining(spec, tasks):
    """What the spec's existing output file says is left, by the cost model learnt from it."""
    from pathlib import Path

    from campaign.errors import UserError
    from campaign.storage.store import DONE, read_summary
    from campaign.run.walltime import remaining_seconds

    if not spec.output or not Path(spec.output).exists():
        return None
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
