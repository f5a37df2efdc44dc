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
    ntasks_per_node: int = 32
    time: str = "24:00:00"
    partition: str | None = None
    account: str | None = None
    launcher: str = "srun"
    warn_seconds: int | None = None  # SLURM's USR1 warning before the limit
    margin_seconds: int | None = None  # the master's safety margin before the limit
    gpus_per_task: int = 0  # GPU jobs: every rank gets this many GPUs, every worker is a GPU worker

    def checked(self) -> "SlurmOptions":
        if self.nodes < 1:
            raise UserError(f"--nodes must be at least 1; got {self.nodes}")
        if self.ntasks_per_node < 1:
            raise UserError(f"--ntasks-per-node must be at least 1; got {self.ntasks_per_node}")
        if self.nodes * self.ntasks_per_node < 2:
            raise UserError("a campaign needs at least 2 MPI ranks (one master, one worker); "
                            f"got --nodes {self.nodes} x --ntasks-per-node {self.ntasks_per_node}")
        if self.launcher not in LAUNCHERS:
            raise UserError(f"--launcher must be one of {sorted(LAUNCHERS)}; got {self.launcher!r}")
        for flag, value in (("--partition", self.partition), ("--account", self.account)):
            if value is not None and not re.fullmatch(r"[A-Za-z0-9_.,:+-]+", value):
                raise UserError(f"{flag} must be a plain SLURM name; got {value!r}")
        if self.gpus_per_task < 0:
            raise UserError(f"--gpus-per-task must be >= 0; got {self.gpus_per_task}")
        seconds = parse_time(self.time)
        for flag, value in (("--warn", self.warn_seconds), ("--margin", self.margin_seconds)):
            if value is not None and not 0 <= value < seconds:
                raise UserError(f"{flag} must be between 0 and the wall time ({seconds} s); got {value}")
        return self

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


def _template() -> str:
    return resources.files("campaign").joinpath("templates/campaign.sbatch").read_text()


def render_script(*, name: str, spec: Path, out: Path, tasks: int, options: SlurmOptions) -> str:
    """The sbatch script text. Paths are made absolute: jobs start in other directories."""
    options = options.checked()
    optional = "".join(f"#SBATCH --{key}={value}\n" for key, value in
                       (("partition", options.partition), ("account", options.account),
                        ("gpus-per-task", options.gpus_per_task)) if value)
    return _template().format(
        name=name,
        job_name=re.sub(r"[^A-Za-z0-9_.-]", "_", name)[:64] or "campaign",
        tasks=tasks,
        nodes=options.nodes,
        ntasks_per_node=options.ntasks_per_node,
        time=options.time,
        optional_lines=optional,
        warn_seconds=options.warn,
        margin_seconds=options.margin,
        spec=shlex.quote(str(Path(spec).resolve())),
        out=shlex.quote(str(Path(out).resolve())),
        launch=LAUNCHERS[options.launcher],
        # GPU jobs: SLURM gives each rank its own GPUs (CUDA_VISIBLE_DEVICES); the workers use them
        gpus=f" --gpus {options.gpus_per_task}" if options.gpus_per_task else "",
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
class JobAdvice:
    """How many jobs of ``options.time`` a campaign of ``total`` core-seconds needs on
    ``workers`` ranks (the master's rank does not compute)."""
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
    """``total``: a ``campaign.plan.calibration.Estimate`` of the core-seconds left; ``longest``: the
    central estimate of the longest task."""
    options = options.checked()
    workers = max(1, options.nodes * options.ntasks_per_node - 1)
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


def advice_text(advice: JobAdvice, total, options: SlurmOptions, chain: int | None) -> str:
    lines = [f"estimated {total.hours()} for {advice.workers} worker(s) ({options.nodes} node(s) x "
             f"{options.ntasks_per_node} ranks, one of them the master): about {fmt_time(advice.wall)} of wall "
             f"time (up to {fmt_time(advice.wall_high)}); longest task up to {fmt_time(advice.longest_high)}"]
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
