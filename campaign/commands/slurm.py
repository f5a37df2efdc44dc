"""campaign slurm: write an sbatch script (and optionally a dependency chain) for a campaign."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

from campaign.errors import UserError
from campaign.plan import calibration
from campaign.plan.calibration import Estimate
from campaign.plan.parse import load_spec
from campaign.plan.tasks import expand
from campaign.run.slurm import (SlurmOptions, advice_text, advise, chain_commands, job_work, refuse_without_gpu_tasks,
                                render_script)
from campaign.storage.checksums import read_rounds
from campaign.storage.layout import DONE, PENDING

HELP = "write a SLURM batch script for a campaign (and print or submit a chain of resuming jobs)"


def configure(p):
    p.add_argument("spec", metavar="SPEC", help="campaign spec (YAML)")
    p.add_argument("--nodes", type=int, default=1, help="nodes (default 1)")
    p.add_argument("--ntasks-per-node", type=int, default=None,
                   help="MPI ranks per node of a CPU job, one per core (default 32)")
    p.add_argument("--time", default="24:00:00", help="wall time per job, [D-]HH:MM:SS (default 24:00:00)")
    p.add_argument("--partition", help="SLURM partition")
    p.add_argument("--account", help="SLURM account")
    p.add_argument("--gpus-per-node", type=int, default=0, metavar="G",
                   help="a GPU job: G GPUs per node (#SBATCH --gpus-per-node), one worker rank each (campaign run "
                        "--gpus G), and the master beside them on the first node without a GPU; the spec needs "
                        "`device: gpu` tasks (docs/CLUSTERS.md#gpu-jobs)")
    p.add_argument("--cpus-per-task", type=int, default=None, metavar="C",
                   help="a GPU job: C of the node's cores per rank (default 1; (G + 1) x C must fit a node)")
    p.add_argument("--launcher", choices=("srun", "srun-pmix", "srun-site", "mpiexec"), default="srun",
                   help="start the ranks with srun --mpi=pmi2 (default; the MPICH the package installs), "
                        "srun --mpi=pmix, srun with the cluster's default MPI plugin (a site MPI), or the MPI "
                        "library's mpiexec (see slurm/README.md)")
    p.add_argument("--warn", type=int, metavar="SECONDS",
                   help="ask SLURM for USR1 this long before the limit (default: a tenth of --time, 10 to 300 s)")
    p.add_argument("--margin", type=int, metavar="SECONDS",
                   help="the master starts no task that would end later than this before the limit "
                        "(default: the warning plus 30 s, SLURM's time-limit check period)")
    p.add_argument("--results", metavar="FILE", help="the campaign's HDF5 file (default: the spec's output)")
    p.add_argument("--out", metavar="FILE", help="write the script here instead of standard output")
    p.add_argument("--chain", type=int, metavar="M",
                   help="also print (or with --submit, submit) M jobs chained with --dependency=afterany")
    p.add_argument("--submit", action="store_true", help="submit the chain with sbatch instead of printing it")
    p.add_argument("--calibration", metavar="FILE",
                   help="the cost model's calibration for the estimate (written by campaign calibrate; default: "
                        "$CAMPAIGN_COST_CALIBRATION, else the packaged one)")
    p.add_argument("--no-estimate", action="store_true",
                   help="do not print the estimated cost and the advice on --time and --chain")


def main(args) -> int:
    with calibration.using(getattr(args, "calibration", None)) as cal:
        return _main(args, cal)


def _estimate(spec, results, cal, options):
    """What the tasks not done yet in ``results`` (all, when it does not exist or another spec wrote
    it) cost a job of ``options`` (``campaign.run.slurm.JobWork``), and how many they are."""
    from campaign.storage.reader import read_summary  # brings h5py: loaded when the command runs, not at --help

    tasks = expand(spec)
    if spec.precision is not None:
        return _precision_estimate(spec, tasks, results, cal, options)
    left = tasks
    if results.exists():
        try:
            s = read_summary(str(results), fields=("status",))
            if s["attrs"].get("spec_hash") == spec.hash and len(s["status"]) == len(tasks):
                left = [t for t in tasks if s["status"][t.index] != DONE]
        except UserError:
            pass
    if not left:
        return None, 0
    return job_work(left, cal, options), len(left)


def _precision_estimate(spec, tasks, results, cal, options):
    """A precision campaign's work for the chain: the tasks its rounds gave out and not done, plus what
    its last decision projects for reaching the targets; before the pilot, the prior's plan
    (``campaign.precision.planner.plan_from_prior``), else the pilot alone. The chain's jobs go on
    through the rounds: each resumes, decides when a round is complete and exits at once when the
    campaign has ended."""
    # imported here: the precision planner (the reducer's fits, the error model) is only for a spec with
    # precision targets, and the store's reader brings h5py, which `campaign --help` need not load
    from campaign.precision.errormodel import campaign_cells
    from campaign.precision.planner import first_round, plan_from_prior
    from campaign.storage.reader import open_store

    cells = campaign_cells(spec, tasks)
    status, last = None, None
    if results.exists():
        try:
            with open_store(results) as f:
                if f.attrs.get("spec_hash") == spec.hash:
                    status = f["tasks/status"][:]
                    got, _ = read_rounds(f)
                    last = got[max(got)] if got else None
        except (UserError, OSError, KeyError, ValueError):  # no estimate from a store that does not read
            status, last = None, None
    if last is not None:
        given = cells.tasks_of(last["early"])
        left = [t for t in tasks if given[t.index] and status[t.index] == PENDING]
    else:
        first, _ = first_round(spec, tasks)  # round 0: designed from the prior, or the uniform pilot
        left = [t for t in tasks if t.seed < first[t.index // spec.precision.max_seeds]]
    if last is None or last["action"] == "pilot":  # before the first decision: the prior's plan
        got = plan_from_prior(spec, tasks)  # priced by the calibration in force: cal
        extra = got.get("plan_seconds", 0.0) if got.get("ok") and got.get("reachable") else 0.0
    else:
        extra = (last.get("to_targets_core_hours") or 0.0) * 3600.0 if last["action"] == "continue" else 0.0
    if not left and extra <= 0:
        return None, 0
    work = job_work(left or [t for t in tasks if t.seed == 0], cal, options)
    seconds = (work.total.seconds if left else 0.0) + extra
    sigma = work.total.sigma
    return replace(work, total=Estimate(seconds, seconds * math.exp(-sigma), seconds * math.exp(sigma), sigma)), len(left)


def _main(args, cal) -> int:
    spec = load_spec(args.spec)
    results = Path(args.results or spec.output or f"results/{spec.name}.h5")
    options = SlurmOptions(nodes=args.nodes, ntasks_per_node=args.ntasks_per_node, time=args.time,
                           partition=args.partition, account=args.account, launcher=args.launcher,
                           warn_seconds=args.warn, margin_seconds=args.margin,
                           gpus_per_node=args.gpus_per_node, cpus_per_task=args.cpus_per_task).checked()
    if options.gpu:
        refuse_without_gpu_tasks(spec, f"--gpus-per-node {options.gpus_per_node}",
                                 "drop --gpus-per-node for a CPU job of one rank per core (--ntasks-per-node)")
    text = render_script(name=spec.name, spec=Path(args.spec), out=results, tasks=spec.n_tasks, options=options)
    if (args.chain or args.submit) and not args.out:
        raise UserError("--chain and --submit need --out FILE: the jobs submit the script file")
    if not args.no_estimate:
        work, n_left = _estimate(spec, results, cal, options)
        if work is None:
            print(f"{results}: every task is done; nothing left to run", file=sys.stderr)
        else:
            head = "" if n_left == spec.n_tasks else f"{n_left} of {spec.n_tasks} tasks left in {results}; "
            if spec.precision is not None:
                head = (f"precision targets: {n_left} task(s) given out and not done, and the rounds the last decision "
                        "(before the pilot: the prior, docs/PRECISION.md) projects to reach the targets; ")
            sys.stderr.write(head + advice_text(advise(work.total, work.longest, options), work, options,
                                                args.chain))
    if args.out:
        Path(args.out).write_text(text)
        Path(args.out).chmod(0o755)
        print(f"wrote {args.out}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    if args.chain or args.submit:
        snippet = chain_commands(Path(args.out).resolve(), args.chain or 1)
        if not args.submit:
            sys.stdout.write(snippet)
            return 0
        if shutil.which("sbatch") is None:
            raise UserError("--submit needs SLURM's sbatch on PATH; without it, drop --submit "
                            "and run the printed commands on the cluster's login node")
        return subprocess.run(["bash", "-c", snippet]).returncode
    return 0
