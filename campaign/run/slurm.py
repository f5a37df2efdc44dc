"""SLURM submission scripts and dependency chains for a campaign.

``render_script`` fills the packaged template ``campaign/templates/campaign.sbatch`` from a
spec and the user's options; ``chain_commands`` gives the ``sbatch`` lines of a chain of jobs,
each resuming the same file after the previous one ends (``--dependency=afterany``).
"""

from __future__ import annotations

import math
import re
import shlex
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from campaign.errors import UserError

# How the ranks are started; all of them must end up in one MPI world (`campaign run` refuses a
# split launch). srun connects the tasks to the MPI library through the PMI it is told to use:
# `--mpi=pmi2` for the MPICH wheel the package installs (SLURM ships with MpiDefault=none, which
# connects nothing), `--mpi=pmix` for an MPI built against PMIx, none for a site MPI the cluster's
# MpiDefault already serves. No cpu binding: it needs a task plugin not every cluster has.
LAUNCHERS = {
    "srun": "srun --mpi=pmi2 --kill-on-bad-exit=1",
    "srun-pmix": "srun --mpi=pmix --kill-on-bad-exit=1",
    "srun-site": "srun --kill-on-bad-exit=1",
    "mpiexec": 'mpiexec -n "$SLURM_NTASKS"',
}

WARNING_SLACK = 30  # slurmctld's period of time-limit checks (PERIODIC_TIMEOUT), seconds

_TIME = re.compile(r"^(?:(\d+)-)?(\d+):([0-5]\d):([0-5]\d)$")


def parse_time(text: str) -> int:
    """``[D-]HH:MM:SS`` -> seconds; raises UserError on anything else."""
    match = _TIME.match(str(text).strip())
    if not match:
        raise UserError(f"a wall time must look like HH:MM:SS or D-HH:MM:SS; got {text!r}")
    days, hours, minutes, seconds = (int(g) if g else 0 for g in match.groups())
    total = ((days * 24 + hours) * 60 + minutes) * 60 + seconds
    if total <= 0:
        raise UserError(f"a wall time must be positive; got {text!r}")
    return total


@dataclass(frozen=True)
class SlurmOptions:
    nodes: int = 1
    ntasks_per_node: int | None = None  # CPU jobs: ranks per node (None: 32); GPU jobs: set by gpus_per_node
    time: str = "24:00:00"
    partition: str | None = None
    account: str | None = None
    launcher: str = "srun"
    warn_seconds: int | None = None  # SLURM's USR1 warning before the limit
    margin_seconds: int | None = None  # the master's safety margin before the limit
    # GPU jobs: G GPUs per node, one worker rank each (every worker a GPU worker), and the master
    # beside them on the first node without a GPU of its own
    gpus_per_node: int = 0
    cpus_per_task: int | None = None  # GPU jobs: cores per rank (None: 1); a CPU job's ranks take one

    def checked(self) -> "SlurmOptions":
        if self.nodes < 1:
            raise UserError(f"--nodes must be at least 1; got {self.nodes}")
        if self.gpus_per_node < 0:
            raise UserError(f"--gpus-per-node must be >= 0; got {self.gpus_per_node}")
        if self.gpu and self.ntasks_per_node is not None:
            raise UserError("a GPU job has one worker rank per GPU: --gpus-per-node G sets the ranks (G on every "
                            "node, and the master beside them on the first); drop --ntasks-per-node")
        if not self.gpu and self.cpus_per_task not in (None, 1):
            raise UserError("--cpus-per-task is for GPU jobs (--gpus-per-node): a CPU job runs one single-threaded "
                            "rank per core; ask for more ranks with --ntasks-per-node")
        if self.cpus_per_task is not None and self.cpus_per_task < 1:
            raise UserError(f"--cpus-per-task must be at least 1; got {self.cpus_per_task}")
        if self.ntasks_per_node is not None and self.ntasks_per_node < 1:
            raise UserError(f"--ntasks-per-node must be at least 1; got {self.ntasks_per_node}")
        if self.ranks < 2:
            raise UserError("a campaign needs at least 2 MPI ranks (one master, one worker); "
                            f"got --nodes {self.nodes} x --ntasks-per-node {self.per_node}")
        if self.launcher not in LAUNCHERS:
            raise UserError(f"--launcher must be one of {sorted(LAUNCHERS)}; got {self.launcher!r}")
        for flag, value in (("--partition", self.partition), ("--account", self.account)):
            if value is not None and not re.fullmatch(r"[A-Za-z0-9_.,:+-]+", value):
                raise UserError(f"{flag} must be a plain SLURM name; got {value!r}")
        seconds = parse_time(self.time)
        for flag, value in (("--warn", self.warn_seconds), ("--margin", self.margin_seconds)):
            if value is not None and not 0 <= value < seconds:
                raise UserError(f"{flag} must be between 0 and the wall time ({seconds} s); got {value}")
        return self

    @property
    def gpu(self) -> bool:
        return self.gpus_per_node > 0

    @property
    def per_node(self) -> int:
        """Task slots per node: a CPU job's ranks, or a GPU job's G workers and room for the master."""
        if self.gpu:
            return self.gpus_per_node + 1
        return 32 if self.ntasks_per_node is None else self.ntasks_per_node

    @property
    def ranks(self) -> int:
        """MPI ranks: every slot of a CPU job; a GPU job's G per node and the master."""
        return self.nodes * self.gpus_per_node + 1 if self.gpu else self.nodes * self.per_node

    @property
    def workers(self) -> int:
        return self.ranks - 1

    @property
    def cpus(self) -> int:
        return self.cpus_per_task or 1

    @property
    def seconds(self) -> int:
        return parse_time(self.time)

    @property
    def warn(self) -> int:
        # A tenth of the job, 10 to 300 s: time for the tasks in flight to be collected and the file
        # flushed when the master's own clock was wrong (a changed limit).
        return self.warn_seconds if self.warn_seconds is not None else min(300, max(10, self.seconds // 10))

    @property
    def margin(self) -> int:
        # The master plans to be done this long before the limit. SLURM checks time limits every
        # WARNING_SLACK seconds and sends the warning at the first check within that much of it, so up
        # to WARNING_SLACK seconds early: a margin of warn + WARNING_SLACK lets a run end by its own
        # clock before the warning can interrupt it.
        return self.margin_seconds if self.margin_seconds is not None else self.warn + WARNING_SLACK


def has_gpu_tasks(spec) -> bool:
    """Whether any variant of ``spec`` runs ``device: gpu``."""
    return any(dict(v.protocol).get("device") == "gpu" for v in spec.variants)


def refuse_without_gpu_tasks(spec, flag: str, instead: str) -> None:
    """A GPU run of a spec without ``device: gpu`` tasks would leave its GPUs idle: UserError (exit 2)
    naming ``flag`` (the option that asked for GPUs) and ``instead`` (what to do without it)."""
    if has_gpu_tasks(spec):
        return
    raise UserError(f"{spec.source} has no `device: gpu` task: {flag} asks for GPU workers, and they would run "
                    "its CPU tasks one at a time on their cores while their GPUs stay idle (and a GPU job would be "
                    "priced as CPU work). Give a variant `device: gpu` (docs/GPU.md; its packings get their own "
                    f"task ids), or {instead}.")


def _template() -> str:
    return resources.files("campaign").joinpath("templates/campaign.sbatch").read_text()


def _gpu_layout(options: SlurmOptions) -> str:
    """The GPU job's comment on where its ranks go, and what makes SLURM or mpiexec put them there."""
    g, n = options.gpus_per_node, options.nodes
    lines = [f"# A GPU job: one worker rank per GPU ({g} per node, each a GPU worker: --gpus {g}) and the master",
             "# beside them on the first node, without a GPU of its own (the master only schedules and writes)."]
    if options.launcher == "mpiexec":
        lines += [f"# mpiexec puts {g} ranks on each node in turn (-ppn {g}) and the last one back on the first:",
                  f"# {g + 1} on the first node (the master, rank 0, and {g} workers)"
                  + (f", {g} on each other." if n > 1 else ".")]
    elif n > 1:
        lines += [f"# Every node holds {g + 1} task slots; srun spreads the {options.ranks} ranks evenly over the "
                  "nodes, first nodes",
                  f"# first: {g + 1} on the first (the master, rank 0, and {g} workers), {g} on each other, whose "
                  "spare slot",
                  "# stays idle (SLURM_NTASKS_PER_NODE is unset: srun would ignore it here, with a warning)."]
    else:
        lines += [f"# {g + 1} ranks on the node: the master (rank 0) and {g} workers."]
    lines += ["# Every rank sees its node's GPUs (SLURM's CUDA_VISIBLE_DEVICES); a worker takes the one its rank",
              f"# on the node picks (SLURM_LOCALID, or mpiexec's MPI_LOCALRANKID, mod {g}; the master is local",
              "# rank 0), so that no two workers of a node share a GPU. docs/CLUSTERS.md#gpu-jobs says why."]
    if options.launcher != "mpiexec" and n > 1:
        lines.append("unset SLURM_NTASKS_PER_NODE")
    return "\n".join(lines) + "\n"


def render_script(*, name: str, spec: Path, out: Path, tasks: int, options: SlurmOptions) -> str:
    """The sbatch script text. Paths are made absolute: jobs start in other directories."""
    options = options.checked()
    optional = "".join(f"#SBATCH --{key}={value}\n" for key, value in
                       (("partition", options.partition), ("account", options.account)) if value)
    if options.gpu:
        resources_ = [("nodes", options.nodes), ("ntasks", options.ranks), ("ntasks-per-node", options.per_node),
                      ("gpus-per-node", options.gpus_per_node), ("cpus-per-task", options.cpus)]
        threads_comment = (f"# {options.cpus} thread(s) per rank: its share of the node's cores (--cpus-per-task)."
                           if options.cpus > 1 else "# One thread per rank.")
        launch = LAUNCHERS[options.launcher]
        if options.launcher == "mpiexec":
            launch += f" -ppn {options.gpus_per_node}"
        else:  # since SLURM 22.05 srun does not take sbatch's --cpus-per-task (sbatch(1)): said again
            launch += f" --cpus-per-task={options.cpus}"
        layout = _gpu_layout(options)
    else:
        resources_ = [("nodes", options.nodes), ("ntasks-per-node", options.per_node), ("cpus-per-task", 1)]
        threads_comment = "# One thread per rank: the ensemble is the parallelism."
        launch, layout = LAUNCHERS[options.launcher], ""
    return _template().format(
        name=name,
        job_name=re.sub(r"[^A-Za-z0-9_.-]", "_", name)[:64] or "campaign",
        tasks=tasks,
        resource_lines="".join(f"#SBATCH --{key}={value}\n" for key, value in resources_),
        time=options.time,
        optional_lines=optional,
        warn_seconds=options.warn,
        margin_seconds=options.margin,
        spec=shlex.quote(str(Path(spec).resolve())),
        out=shlex.quote(str(Path(out).resolve())),
        threads_comment=threads_comment,
        threads=options.cpus,
        gpu_layout=layout,
        launch=launch,
        gpus=f" --gpus {options.gpus_per_node}" if options.gpu else "",
    )


def chain_commands(script: Path, length: int) -> str:
    """A POSIX shell snippet submitting ``length`` jobs, each after the previous one ends."""
    if length < 1:
        raise UserError(f"--chain must be at least 1; got {length}")
    script_q = shlex.quote(str(script))
    lines = ["set -e", f"job=$(sbatch --parsable {script_q})", 'echo "submitted $job"']
    for _ in range(length - 1):
        lines += [f'job=$(sbatch --parsable --dependency=afterany:"${{job%%;*}}" {script_q})',
                  'echo "submitted $job"']
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------- sizing the jobs

#: seconds of every job before its tasks run: srun starting the ranks, imports, the kernels
#: compiled or loaded from the numba cache (about 25 s of CPU per node, twice that with the
#: Newton endgame: README, docs/CLUSTERS.md)
STARTUP_SECONDS = 60


@dataclass(frozen=True)
class JobWork:
    """What a job's workers have to do: ``total`` (a ``campaign.plan.calibration.Estimate``) of
    worker-seconds (a CPU job: core-seconds; a GPU job priced by a GPU calibration: GPU-seconds of its
    ``device: gpu`` tasks plus core-seconds of its CPU tasks, which its GPU workers run on their
    cores), the central estimate of the longest task's wall seconds, and how to say it."""
    total: object
    longest: float
    gpu_tasks: int = 0          # device: gpu tasks among them
    cpu_tasks: int = 0
    device: str | None = None   # a GPU job priced by a GPU calibration: the device it was measured on
    batch: int = 0              # ... and its launch size
    priced: bool = True         # False: a GPU job without a GPU calibration (priced as CPU work)


def job_work(tasks, cal, options: SlurmOptions) -> JobWork:
    """Price ``tasks`` for a job of ``options`` with the calibration ``cal``.

    In a GPU job a ``device: gpu`` task costs its GPU-seconds (``Calibration.gpu_seconds``: its share
    of a full launch), and a launch lasts about as long as its packings' shares added up: the
    longest task is ``batch`` (the calibration's launch size) times the largest share. Without a GPU
    calibration the job is priced as CPU work, and ``priced`` says so."""
    from campaign.plan.calibration import Estimate
    from campaign.plan.tasks import estimate

    cpu = estimate(tasks, cal)
    gpu = [t for t in tasks if dict(t.protocol).get("device") == "gpu"]
    rest = [cal.seconds(t.N, t.E, t.protocol, t.exponent, t.parent_E) for t in tasks
            if dict(t.protocol).get("device") != "gpu"]
    if not options.gpu or not gpu or not cal.gpu:
        longest = max(cal.seconds(t.N, t.E, t.protocol, t.exponent, t.parent_E) for t in tasks)
        return JobWork(cpu, longest, len(gpu), len(rest), priced=not (options.gpu and gpu))
    batch = max(1, int(cal.gpu.get("batch") or 1))
    shares = [cal.gpu_seconds(t.N, t.E, t.protocol, t.exponent) for t in gpu]
    seconds = math.fsum(shares) + math.fsum(rest)
    total = Estimate(seconds, seconds * math.exp(-cpu.sigma), seconds * math.exp(cpu.sigma), cpu.sigma)
    return JobWork(total, max([batch * x for x in shares] + rest), len(gpu), len(rest), str(cal.gpu["device"]),
                   batch)


def _hours(total, unit: str) -> str:
    def g(x):
        return f"{x:.2g}" if x < 10 else f"{x:,.0f}"
    return f"{g(total.seconds / 3600)} {unit} ({g(total.low / 3600)} - {g(total.high / 3600)}, 68%)"


@dataclass(frozen=True)
class JobAdvice:
    """How many jobs of ``options.time`` a campaign of ``total`` worker-seconds needs on
    ``workers`` ranks (the master's rank does not compute; a GPU job: one worker per GPU)."""
    workers: int
    usable: float       # seconds of one job its tasks can use (limit - margin - start-up)
    per_job: float      # core-seconds one job gets done: a job's last tasks must end before its limit
    jobs: int           # at the central estimate
    jobs_high: int      # at the upper end of its 68% interval
    wall: float         # wall seconds of the whole campaign (central), start-ups aside
    wall_high: float
    longest_high: float  # the longest task at the upper end
    one_job_time: int    # a --time (seconds) that does it in one job at the upper estimate

    @property
    def fits(self) -> bool:
        return self.longest_high <= self.usable


def advise(total, longest: float, options: SlurmOptions) -> JobAdvice:
    """``total``: a ``campaign.plan.calibration.Estimate`` of the worker-seconds left (``job_work``);
    ``longest``: the central estimate of the longest task."""
    options = options.checked()
    workers = max(1, options.workers)
    ratio = total.high / total.seconds if total.seconds > 0 else 1.0
    longest_high = longest * ratio
    usable = max(0.0, options.seconds - options.margin - STARTUP_SECONDS)
    per_job = workers * max(usable - longest_high, usable / 2)
    jobs = max(1, math.ceil(total.seconds / per_job)) if per_job > 0 else 0
    jobs_high = max(1, math.ceil(total.high / per_job)) if per_job > 0 else 0
    wall = max(total.seconds / workers, longest)
    wall_high = max(total.high / workers, longest_high)
    need = wall_high + longest_high + STARTUP_SECONDS + 330  # 330: the largest default margin
    one_job = int(math.ceil(need / 300.0) * 300)
    return JobAdvice(workers, usable, per_job, jobs, jobs_high, wall, wall_high, longest_high, one_job)


def fmt_time(seconds: float) -> str:
    """Seconds as SLURM's ``[D-]HH:MM:SS``."""
    s = int(math.ceil(seconds))
    d, s = divmod(s, 86400)
    h, s = divmod(s, 3600)
    m, s = divmod(s, 60)
    return f"{d}-{h:02d}:{m:02d}:{s:02d}" if d else f"{h:02d}:{m:02d}:{s:02d}"


def advice_text(advice: JobAdvice, work: JobWork, options: SlurmOptions, chain: int | None) -> str:
    total = work.total
    if not options.gpu:
        lines = [f"estimated {total.hours()} for {advice.workers} worker(s) ({options.nodes} node(s) x "
                 f"{options.per_node} ranks, one of them the master): about {fmt_time(advice.wall)} of wall "
                 f"time (up to {fmt_time(advice.wall_high)}); longest task up to {fmt_time(advice.longest_high)}"]
        if work.gpu_tasks:
            lines.append(f"note: its {work.gpu_tasks} `device: gpu` task(s) run in the GPU block's CPU emulation "
                         "in a CPU job (priced above as CPU work); --gpus-per-node G writes a GPU job")
    elif not work.priced:
        return (f"estimated {total.hours()} as CPU work, its {work.gpu_tasks} `device: gpu` task(s) included: no "
                "GPU calibration prices them on a GPU (`campaign calibrate --gpu` on the GPU machine, then "
                "--calibration FILE; docs/GPU.md), so no advice on --time and --chain for this GPU job\n")
    else:
        mixed = (f"; its {work.cpu_tasks} CPU task(s) counted at a core's pace, on the GPU workers' cores"
                 if work.cpu_tasks else "")
        lines = [f"estimated {_hours(total, 'GPU-hours')} on {work.device} (campaign calibrate --gpu{mixed}) for "
                 f"{advice.workers} GPU worker(s) ({options.nodes} node(s) x {options.gpus_per_node} GPUs, the "
                 f"master beside them on the first node): about {fmt_time(advice.wall)} of wall time (up to "
                 f"{fmt_time(advice.wall_high)}); longest task up to {fmt_time(advice.longest_high)} (a GPU task "
                 f"lasts as long as its launch of {work.batch} packings)"]
    if not advice.fits:
        lines.append(f"warning: the longest task (up to {fmt_time(advice.longest_high)}) does not fit in a job of "
                     f"--time {options.time} ({fmt_time(advice.usable)} usable after the margin and start-up): "
                     f"it would never be started; raise --time")
        return "\n".join(lines) + "\n"
    jobs = (f"{advice.jobs} job(s)" if advice.jobs == advice.jobs_high
            else f"{advice.jobs} job(s), {advice.jobs_high} at the upper estimate")
    lines.append(f"with --time {options.time} ({fmt_time(advice.usable)} usable per job): {jobs}")
    if advice.jobs_high > 1 and (chain or 1) < advice.jobs_high:
        lines.append(f"advice: --chain {advice.jobs_high}" + (f" (--chain {chain} may stop short; a chain "
                                                             "can be lengthened later: the next job resumes)"
                                                             if chain else ""))
    if advice.one_job_time < options.seconds and advice.jobs_high == 1:
        lines.append(f"advice: --time {fmt_time(advice.one_job_time)} is enough for one job at the upper estimate")
    elif advice.jobs_high > 1 and advice.one_job_time <= 2 * 86400:
        lines.append(f"or one job of --time {fmt_time(advice.one_job_time)}")
    return "\n".join(lines) + "\n"
