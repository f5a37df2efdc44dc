"""Shared helpers of the tests: packing makers, a fake communicator, store readers.

Test modules import these instead of importing each other (``tests/project/test_docs.py`` checks that
none does). The oracles the kernels are compared with are in ``references.py``.
"""

import importlib
import importlib.metadata
import importlib.util
import math
from collections import deque
from functools import lru_cache
from pathlib import Path

import h5py
import numpy as np
import pytest

from campaign.plan.parse import parse_spec
from campaign.plan.tasks import expand
from campaign.run.worker import SyntheticTask, run_task, synthetic_laws
from campaign.storage.store import Store, read_journal


RATIO = 1.4  # sigma_A / sigma_B (docs/PHYSICS.md)


def _forces_energy(pos, rad, box):
    d = pos[None, :, :] - pos[:, None, :]
    d -= box * np.round(d / box)
    r = np.sqrt((d**2).sum(-1))
    np.fill_diagonal(r, np.inf)
    s = rad[:, None] + rad[None, :]
    x = np.clip(1.0 - r / s, 0.0, None)
    f = x / s / r
    return -(f[:, :, None] * d).sum(1), 0.25 * (x**2).sum()


@lru_cache(maxsize=None)
def compressed_packing(n, seed, phi=0.9, box=(1.0, 1.0)):
    """A force-balanced bidisperse packing above jamming (FIRE on harmonic springs).

    Independent of ``kernels.jam``: a small numpy FIRE over all pairs, stopped when
    the largest net force is 1e-12 of the typical contact force. Returns read-only
    ``(positions, radii, box)``.
    """
    rng = np.random.default_rng([n, seed])
    box = np.asarray(box, dtype=float)
    rel = np.r_[np.full(n // 2, RATIO), np.ones(n - n // 2)]
    rad = rel * np.sqrt(phi * box.prod() / (np.pi * np.sum(rel**2)))
    pos = rng.random((n, 2)) * box
    v = np.zeros_like(pos)
    dt = 0.05 * rad.min()
    dtmax = 10 * dt
    alpha = 0.1
    npos = 0
    F, _ = _forces_energy(pos, rad, box)
    fscale = None
    for _ in range(50000):
        P = (F * v).sum()
        if P > 0:
            v = (1 - alpha) * v + alpha * F / np.linalg.norm(F) * np.linalg.norm(v)
            npos += 1
            if npos > 5:
                dt = min(dt * 1.1, dtmax)
                alpha *= 0.99
        else:
            npos = 0
            dt *= 0.5
            v[:] = 0
            alpha = 0.1
        v += dt * F
        pos += dt * v
        F, E = _forces_energy(pos, rad, box)
        if fscale is None:
            fscale = np.sqrt(2 * E / n) / rad.mean()
        if np.abs(F).max() < 1e-12 * max(fscale, 1e-300) + 1e-300:
            break
    pos = pos % box
    for a in (pos, rad, box):
        a.setflags(write=False)
    return pos, rad, box


def random_configuration(n, seed, phi=0.85, box=(1.0, 1.0)):
    """Uniformly random bidisperse disks (overlapping, not force balanced)."""
    rng = np.random.default_rng([7, n, seed])
    box = np.asarray(box, dtype=float)
    rel = np.r_[np.full(n // 2, RATIO), np.ones(n - n // 2)]
    rad = rel * np.sqrt(phi * box.prod() / (np.pi * np.sum(rel**2)))
    return rng.random((n, 2)) * box, rad, box


def triangular_crystal(nx, ny, overlap=1e-6, a=None):
    """Triangular crystal of equal disks, nx per row, ny rows (even), fitting its box."""
    assert ny % 2 == 0
    a = 1.0 / nx if a is None else a
    j, i = np.divmod(np.arange(nx * ny), nx)
    pos = np.stack([(i + 0.5 * (j % 2)) * a, j * a * np.sqrt(3) / 2], axis=1)
    box = np.array([nx * a, ny * a * np.sqrt(3) / 2])
    rad = np.full(nx * ny, 0.5 * a * (1 + overlap))
    return pos, rad, box


def jittered_crystal(nx, ny, seed, box=None, poly=0.05, jitter=0.03, overlap=0.15):
    """A generic network with every grain load-bearing: a triangular crystal with its
    centres moved by ``jitter`` lattice spacings (normal), radii ``0.5 a (1 + overlap)``
    times ``1 + poly U(-1, 1)`` (all distinct), stretched into ``box`` if given. No two
    contact angles coincide, and every grain keeps contacts all around (unlike random
    overlapping disks, which erode completely under the half-plane rattler rule)."""
    rng = np.random.default_rng([11, nx, ny, seed])
    pos, rad, b = triangular_crystal(nx, ny, overlap=overlap)
    pos = pos + jitter * (1.0 / nx) * rng.standard_normal(pos.shape)
    rad = rad * (1.0 + poly * rng.uniform(-1.0, 1.0, rad.size))
    if box is not None:
        box = np.asarray(box, dtype=float)
        pos = pos * (box / b)
        rad = rad * np.sqrt(box.prod() / b.prod())
        b = box
    return pos % b, rad, b


def three_touching_disks(radii):
    """Three mutually touching disks (relative overlap 1e-10) in a large box."""
    r = np.asarray(radii, dtype=float)
    s = 1 - 1e-10
    a, b, c = (r[1] + r[2]) * s, (r[0] + r[2]) * s, (r[0] + r[1]) * s  # sides opposite 0, 1, 2
    p0 = np.array([0.0, 0.0])
    p1 = np.array([c, 0.0])
    x = (b * b - a * a + c * c) / (2 * c)
    p2 = np.array([x, math.sqrt(b * b - x * x)])
    box = np.array([40.0, 40.0]) * r.max()
    return np.array([p0, p1, p2]) + box / 2, r, box


def random_dense(seed, n=64, phi=0.9):
    rng = np.random.default_rng(seed)
    box = np.array([1.0, 1.0])
    pos = rng.random((n, 2))
    rel = np.where(np.arange(n) < n // 2, 1.4, 1.0)
    rad = rel * np.sqrt(phi / (np.pi * np.sum(rel ** 2)))
    return pos, rad, box


def polygon_area(v):
    x, y = v[:, 0], v[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def clipped_area(poly, x0, y0, x1, y1):
    """Sutherland-Hodgman clipping of a polygon by an axis-aligned rectangle."""
    def edge(pts, inside, cut):
        out = []
        for k in range(len(pts)):
            p, q = pts[k - 1], pts[k]
            if inside(q):
                if not inside(p):
                    out.append(cut(p, q))
                out.append(q)
            elif inside(p):
                out.append(cut(p, q))
        return out

    def at_x(x):
        return lambda p, q: (x, p[1] + (q[1] - p[1]) * (x - p[0]) / (q[0] - p[0]))

    def at_y(y):
        return lambda p, q: (p[0] + (q[0] - p[0]) * (y - p[1]) / (q[1] - p[1]), y)

    pts = [tuple(v) for v in poly]
    for inside, cut in ((lambda p: p[0] >= x0, at_x(x0)), (lambda p: p[0] <= x1, at_x(x1)),
                        (lambda p: p[1] >= y0, at_y(y0)), (lambda p: p[1] <= y1, at_y(y1))):
        pts = edge(pts, inside, cut)
        if not pts:
            return 0.0
    return abs(polygon_area(np.array(pts)))


#: The ladder campaign of tests/run/test_ladder.py (also reduced by tests/results/test_tradeoff.py).
LADDER_SPEC = """\
name: lad
seed: 3
grid: {N_G: [16, 32], E_G: [1.0e-2, 1.0e-4, 1.0e-6, 1.0e-8], seeds: 3}
variants: [{name: ladder, start: ladder}]
observables: [scalars]
"""


#: A synthetic campaign with ladder children, configurations and (with CAMPAIGN_SYNTHETIC_FAIL=seed:1)
#: failure records: the damaged stores of tests/storage/test_integrity.py and tests/storage/test_reader_damage.py.
DAMAGE_SPEC = """\
name: integ
seed: 5
grid: {N_G: [16, 24], E_G: [1.0e-3, 1.0e-5], seeds: 3}
variants: [{name: lad, start: ladder}]
observables: [scalars, connectivity, void_areas]
bins: {z_g: {range: [-0.5, 12.5], count: 13}, z_v: {range: [2.5, 12.5], count: 10}, alpha_v: {range: [0, 2], count: 40}}
store: {configurations: true}
run: {retries: 0}
"""


def synthetic_run(tmp_path, text, name="s.h5"):
    """(spec, tasks, context, store) of a campaign whose tasks are the synthetic task function's."""
    spec = parse_spec(text)
    tasks = expand(spec)
    ctx = dict(spec.worker_context(), task_function="synthetic", bins={}, configurations=False)
    edges = SyntheticTask().histogram_edges(ctx)
    ctx["edges"] = {h: list(e) for h, e in edges.items()}
    return spec, tasks, ctx, Store(tmp_path / name, spec, tasks, edges)


class FakeComm:
    """n workers that run tasks in the master's process, answering in round-robin order."""

    launcher = "fake"

    def __init__(self, ctx, n, on_result=None, die=None, wall=1.0):
        self.ctx, self.n_workers, self.wall = ctx, n, wall
        self.max_queue = 0
        self.queued_before = []
        self.fn = SyntheticTask()
        self.queues = {w: deque() for w in range(1, n + 1)}
        self.sent = []
        self.on_result, self.die = on_result, die or {}
        self.turn = 0
        self.received = 0

    def send(self, w, payload):
        self.sent.append((w, payload))
        self.queued_before.append(len(self.queues[w]))
        self.queues[w].append(payload)
        self.max_queue = max(self.max_queue, len(self.queues[w]))

    def recv(self, timeout=None):
        busy = [w for w in sorted(self.queues) if self.queues[w]]
        if not busy:
            return None
        w = busy[self.turn % len(busy)]
        self.turn += 1
        payload = self.queues[w].popleft()
        if w in self.die and self.received >= self.die[w] and not hasattr(self, "lost"):
            self.lost = [payload["index"]] + [p["index"] for p in self.queues[w]]
            self.died_at = len(self.sent)
            self.queues[w].clear()
            self.received += 1
            return w, ("dead", f"worker {w} died")
        self.received += 1
        if self.on_result:
            self.on_result(self.received)
        summary = run_task(self.fn, payload, self.ctx, w)
        if self.wall is not None:
            summary["wall"] = self.wall
        return w, ("result", payload["index"], payload["attempt"], summary)

    def close(self, abandon=False):
        pass


SKIP_DATASETS = ("tasks/wall", "tasks/rank", "tasks/host", "checksums/tasks.wall", "checksums/tasks.rank",
                 "checksums/tasks.host")

SKIP_ATTRS = ("runs", "start_time", "end_time", "hosts", "versions", "git_commit")


def store_data_and_attrs(path):
    data, attrs = {}, {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                data[name] = obj[()]
            attrs.update({f"{name}@{k}": v for k, v in obj.attrs.items() if k not in ("rank", "host")})
        f.visititems(visit)
        attrs.update({k: v for k, v in f.attrs.items() if k not in SKIP_ATTRS})
    return data, attrs


def durable_packings(path):
    """Every finished task of the durable record: ``{index: run id}`` for the journal's
    records (run id of the run that computed it; a task twice in the journal fails), and
    the store's committed rows (``None``: the store does not say which run)."""
    out = {}
    p = Path(str(path) + ".journal")
    if p.exists():
        recs, _ = read_journal(p.read_bytes())
        for m, _ in recs:
            if m.get("type") == "task":
                assert m["index"] not in out, "a finished task was recorded twice in the journal"
                out[m["index"]] = m["run_id"]
    if Path(path).exists():
        try:
            with h5py.File(path, "r", locking=False) as f:
                status = f["tasks/status"][:]
        except OSError:
            status = np.zeros(0)  # unreadable: the next start salvages it (counted below if rows are lost)
        for i in np.flatnonzero(status != 0).tolist():
            out.setdefault(i, None)
    return out


SKIP_RUN_DATASETS = ("tasks/wall", "tasks/rank", "tasks/host", "scalars/jam_seconds", "scalars/analyze_seconds")
SKIP_RUN_DATASETS += tuple("checksums/" + k.replace("/", ".") for k in SKIP_RUN_DATASETS)  # their block checksums


def store_contents(path):
    """Every dataset and attribute h5py reads (run-dependent ones left out)."""
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
            out.update({f"{name}@{k}": v for k, v in obj.attrs.items() if k not in ("rank", "host")})
        f.visititems(visit)
    return out


def assert_same_contents(a, b):
    assert set(a) == set(b), sorted(set(a) ^ set(b))
    for k in a:
        if k in SKIP_RUN_DATASETS:
            continue
        x, y = np.asarray(a[k]), np.asarray(b[k])
        assert x.dtype == y.dtype and x.shape == y.shape, k
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), k


def processes():
    """``(pid, argv, env)`` of every process of this machine whose command line and environment
    can be read: argv a list of bytes, env a dict of bytes (for finding a campaign's processes)."""
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            argv = (d / "cmdline").read_bytes().split(b"\0")
            env = dict(kv.split(b"=", 1) for kv in (d / "environ").read_bytes().split(b"\0") if b"=" in kv)
        except OSError:
            continue
        yield int(d.name), argv, env


SHM = Path("/dev/shm")


def mpich_segments() -> set:
    """The shared-memory segments of MPICH's jobs on this machine."""
    return {p.name for p in SHM.glob("mpich_shm_*")} if SHM.is_dir() else set()


def remove_segments_of_killed_jobs(before: set):
    """A job killed with SIGKILL leaves MPICH's shared-memory segment in /dev/shm (a running job
    keeps its own mapped): remove the ones that appeared since ``before`` and no process maps."""
    new = mpich_segments() - before
    if not new:
        return
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                maps = (d / "maps").read_text()
            except OSError:
                continue
            new = {n for n in new if n not in maps}
    for n in new:
        (SHM / n).unlink(missing_ok=True)


def reseal(f, *names):
    """Rewrite the block checksums of the datasets ``names`` of the open store ``f`` after a test
    changed their rows by hand (a change the readers would otherwise refuse as damage)."""
    from campaign.storage.checksums import SUMS_ROWS, sums_name, write_sums

    for name in names:
        if sums_name(name) in f:
            ds = f[sums_name(name)]
            write_sums(ds, 0, f[name][:], int(ds.attrs[SUMS_ROWS]))


def cuda_extra_installed() -> bool:
    """Whether the ``cuda`` extra is installed: its CUDA assembler's wheel (nvidia-cuda-nvcc), which
    neither numba nor the ``gpu`` extra brings."""
    try:
        importlib.metadata.distribution("nvidia-cuda-nvcc")
    except importlib.metadata.PackageNotFoundError:
        return False
    return True


def require_cuda(config, missing, installed=None):
    """Go on when ``missing`` (why a CUDA tool a test needs cannot be used) is None; else skip the test
    with that reason, but fail it under ``--full`` with the ``cuda`` extra installed (``installed``,
    default ``cuda_extra_installed()``; .ci/run installs it): there the tool must be found, and a
    skip would let a suite pass that never ran the test."""
    if missing is None:
        return
    if config.getoption("--full") and (cuda_extra_installed() if installed is None else installed):
        pytest.fail(f"the cuda extra is installed, yet {missing}", pytrace=False)
    pytest.skip(missing)


def cuda_missing(compiler=False):
    """Why the CUDA kernel cannot run here (None when it can). Under numba's CUDA simulator it needs
    ``numba.cuda`` only: numba-cuda's (the ``gpu`` and ``cuda`` extras) or numba's own, which numba
    0.68 still ships. Compiled to PTX (``compiler``) it needs numba-cuda and its libNVVM: the
    ``cuda`` extra's CUDA compiler libraries, which .ci/run installs and the quick suite does not."""
    if not compiler:
        try:
            importlib.import_module("numba.cuda")
        except Exception as exc:  # noqa: BLE001 - any reason it cannot be imported
            return f"needs numba.cuda: pip install '.[cuda]' ({exc})"
        return None
    if importlib.util.find_spec("numba_cuda") is None:
        return "needs numba-cuda and the CUDA compiler libraries: pip install '.[cuda]' (.ci/run does)"
    try:
        from cuda.pathfinder import load_nvidia_dynamic_lib

        load_nvidia_dynamic_lib("nvvm")
    except Exception as exc:  # noqa: BLE001 - any reason it cannot be loaded
        return f"needs libNVVM (the cuda extra's CUDA compiler libraries): {exc}"
    return None


def fit_cells(groups, n_boot, seed):
    """The reducer's way on cells of one size: packings resampled within each cell
    (``bootstrap.cell_moments``), each cell weighted by the within-cell variance pooled over the
    cells, in the data and in every replica. ``groups``: per cell, its packings' (x, y) as (n, 2)."""
    from campaign.results import bootstrap, fits

    rng = bootstrap.generator(seed)
    means, covs = zip(*(bootstrap.cell_moments(g, bootstrap.seed_weights(rng, len(g), n_boot)) for g in groups))
    means, covs = np.stack(means, -1), np.stack(covs, -1)  # (1 + n_boot, 2, cells), (1 + n_boot, 2, 2, cells)
    n = np.array([len(g) for g in groups], float)
    pooled = (covs[:, 1, 1] * (n - 1)).sum(-1) / (n - 1).sum()  # (1 + n_boot,)
    err = np.sqrt(pooled[:, None] / n)
    return fits.fit_power_law(means[0, 0], means[0, 1], err[0], boot_x=means[1:, 0], boot_y=means[1:, 1],
                              boot_err=err[1:])


# --------------------------------------------------------------------------- the CLI, as a user runs it
REPO = Path(__file__).resolve().parents[1]


def campaign_cli(*args, **kw):
    """``python -m campaign ARGS`` with this repository's package first on the path (a completed
    process; ``check=True`` and the like pass through)."""
    import os
    import subprocess
    import sys

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return subprocess.run([sys.executable, "-m", "campaign", *map(str, args)], env=env, capture_output=True,
                          text=True, timeout=600, **kw)


def sound(store):
    """`campaign verify`: no damage."""
    verify = campaign_cli("verify", store)
    assert verify.returncode == 0 and "no damage" in verify.stdout + verify.stderr, verify.stdout + verify.stderr


def complete_and_sound(store, tasks: int):
    """`campaign status`: every one of ``tasks`` done; `campaign verify`: no damage."""
    import json

    status = json.loads(campaign_cli("status", store, "--json", check=True).stdout)
    assert (status["done"], status["failed"], status["remaining"]) == (tasks, 0, 0)
    sound(store)


def synthetic_draw(tasks, laws=None):
    """``draw(rows) -> {scalar: values}`` of the synthetic packings that follow known laws
    (``campaign.run.worker.synthetic_laws``) for a precision campaign run in memory
    (``campaign.precision.planner.run_in_memory``)."""
    names = ("E_G", "delta_Z", "A_G", "psi_O", "force_evaluations")

    def draw(rows):
        got = [synthetic_laws(tasks[r].N, tasks[r].E, tasks[r].entropy, laws) for r in rows]
        out = {k: np.array([g[k] for g in got]) for k in names}
        out["jam_status"], out["identities_ok"] = np.zeros(len(rows)), np.ones(len(rows))
        return out
    return draw


def uniform_reduced(spec_text, seeds, laws=None):
    """A uniform campaign of ``seeds`` per cell of a precision spec on the known laws, reduced as a
    decision reduces: ``(cells, table)``."""
    from campaign.precision import errormodel, planner

    spec = parse_spec(spec_text)
    tasks = expand(spec)
    cells = errormodel.campaign_cells(spec, tasks)
    rows = np.flatnonzero(cells.tasks_of(np.full(cells.C, seeds)))
    table = planner.reduce_rows(cells, {"schema": "jamming-campaign/1"}, rows, np.ones(len(rows), np.int8),
                                synthetic_draw(tasks, laws)(rows))
    return cells, table


#: a precision campaign of three sizes, seven energies in the fit range (tests/precision)
PRECISION_SPEC = """\
name: prec
seed: 5
grid:
  N_G: [64, 128, 256]
  E_G: {log_range: [1.0e-12, 1.0e-4], per_decade: 1}
precision:
  target: {A_G_star_E: 1.5e-3, psi_O_star: 3.0e-3}
  pilot: 3
  max_seeds: 40
observables: [scalars]
"""

#: the same grid with five sizes and one target: ``FIVE_SIZES.format(name=..., seed=..., max_seeds=...)``
FIVE_SIZES = """\
name: {name}
seed: {seed}
grid:
  N_G: [64, 128, 256, 512, 1024]
  E_G: {{log_range: [1.0e-12, 1.0e-4], per_decade: 1}}
precision:
  target: {{A_G_star_E: 1.0e-3}}
  pilot: 3
  max_seeds: {max_seeds}
observables: [scalars]
"""
