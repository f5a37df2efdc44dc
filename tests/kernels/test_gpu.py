"""The GPU block (kernels.gpu) on the CPU: its emulation for whole packings, numba's CUDA simulator
for the kernel itself, the kernel compiled for a real GPU (sm_90 PTX), and GPU campaigns."""

import os
import subprocess
import sys
from functools import lru_cache
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from numba import njit

import kernels
from kernels import potential
from kernels.minimiser import _residual_core
from kernels.cells import _candidate_pairs_core
from kernels.gpu import BlockOverflow, Suspended, jam_batch
from kernels.gpu import batch as gpu_batch
from kernels.gpu import block as gpu_block, state as gpu_state
from kernels.gpu.state import (FX, FY, N_FL, N_IV, N_ST, NNB, R, ROWS, RX, RY, S_ALPHA, S_LX, S_LY,
                               S_NCX, S_NCY, S_NG, S_RESV, S_RMAX, S_SIN_TOL, S_SKIN, S_TE, S_XY)
from helpers import cuda_missing, require_cuda

ROOT = Path(__file__).resolve().parents[2]
MPIEXEC = Path(sys.executable).parent / "mpiexec"


def emulate(n, energies, seeds, threads=32, **kw):
    return jam_batch(n, energies, seeds, backend="emulate", threads=threads, **kw)


# --------------------------------------------------------------------------- whole packings

@pytest.mark.parametrize("n, energies, kw", [
    (64, [1e-3, 1e-7, 1e-11], {}),
    pytest.param(128, [1e-5], {"exponent": 2.5}, marks=pytest.mark.slow),
    (64, [1e-6], {"search": "halving", "sizes": ("lognormal", 0.2)}),
    pytest.param(1024, [1e-4], {}, marks=pytest.mark.slow),
])
def test_block_packings_are_jammed_in_the_window(n, energies, kw):
    """Every packing of the block: converged, E_G in [E, 1.1 E] recomputed from its positions,
    force-balanced on its non-rattlers, the network identities hold, its scalars recomputed
    by the CPU kernels."""
    ps = emulate(n, energies, list(range(len(energies))), **kw)
    alpha = kw.get("exponent", 2.0)
    for p, e in zip(ps, energies):
        assert p.status == "converged" and p.settings["device"] == "emulation"
        e_cpu = potential.energy(p.positions, p.radii, p.box, alpha) / n
        assert e <= e_cpu <= 1.1 * e and abs(e_cpu - p.energy) <= 1e-9 * e_cpu
        assert abs(potential.pressure(p.positions, p.radii, p.box, alpha) - p.pressure) <= 1e-9 * p.pressure
        pi, pj = _candidate_pairs_core(p.positions, p.radii, np.array([1.0, 1.0, 0.0]), 0.0)
        res, ng, _ = _residual_core(p.positions, p.radii, np.array([1.0, 1.0, 0.0]), pi, pj, alpha,
                                    np.empty((n, 2)))
        assert res < 1e-6 and ng == p.n_nonrattlers
        a = kernels.analyze(p.positions, p.radii, p.box, exponent=alpha)
        assert a.scalars["identities_ok"]
        assert np.all(p.positions >= 0) and np.all(p.positions < 1)


def test_block_is_deterministic_and_independent_of_its_batch():
    """The same packing gives the same bits alone, again, and inside a batch of others."""
    alone = emulate(64, [1e-6], [5])[0]
    again = emulate(64, [1e-6], [5])[0]
    batch = emulate(64, [1e-3, 1e-6, 1e-9], [4, 5, 6])[1]
    for p in (again, batch):
        assert p.positions.tobytes() == alone.positions.tobytes()
        assert p.radii.tobytes() == alone.radii.tobytes()
        assert p.force_evaluations == alone.force_evaluations


def test_block_starts_from_jams_random_start():
    """The block starts from the seed's random start of ``kernels.jam`` (same radii at scale 1,
    same species): only the trajectory differs."""
    from kernels.jamming import initial_state, DEFAULT_SPECIES

    p = emulate(64, [1e-4], [9])[0]
    pos0, rad0, spc = initial_state(64, np.random.SeedSequence(9), (1.0, 1.0), DEFAULT_SPECIES, 0.86)
    ratio = p.radii / rad0
    assert np.allclose(ratio, ratio[0], rtol=1e-14) and np.array_equal(p.species, spc)


def test_block_overflow_is_refused_not_wrong(monkeypatch):
    """A neighbour row beyond its slots fails that packing with the reason; the others go on."""
    monkeypatch.setattr(gpu_batch, "MAXNB", 4)
    out = emulate(64, [1e-4], [1])
    assert isinstance(out[0], BlockOverflow) and "neighbour row" in str(out[0])


def test_block_refuses_what_it_does_not_run():
    for kw in ({"minimizer": "cg"}, {"cell": "shear"}, {"endgame": "newton"}, {"route": "pressure"}):
        with pytest.raises(ValueError, match="device 'gpu' runs FIRE"):
            jam_batch(32, [1e-4], [0], backend="emulate", **kw)
    with pytest.raises(ValueError, match="power of two"):
        jam_batch(32, [1e-4], [0], backend="emulate", threads=3)
    with pytest.raises(ValueError, match="energy"):
        jam_batch(32, [1e-30], [0], backend="emulate")


def _resumed(n, energies, seeds, budget, **kw):
    """Each packing stopped every ``budget`` FIRE steps and resumed from its state, which goes
    through the arrays a store keeps, until it ends; returns the packings and each one's launches."""
    back = [None] * len(energies)
    done = [None] * len(energies)
    launches = [0] * len(energies)
    while any(d is None for d in done):
        todo = [k for k, d in enumerate(done) if d is None]
        out = emulate(n, [energies[k] for k in todo], [seeds[k] for k in todo], budget=budget,
                      resume=[back[k] for k in todo], **kw)
        for k, got in zip(todo, out):
            launches[k] += 1
            if isinstance(got, Suspended):
                stored = {name: np.array(a) for name, a in got.arrays().items()}
                back[k] = Suspended.from_arrays(stored, energies[k])
            else:
                done[k] = got
    return done, launches


def test_a_suspended_search_goes_on_with_the_bits_of_an_uninterrupted_one():
    """Stop and go: searches stopped at a step budget and resumed from their saved state end with
    the bits of the uninterrupted searches (positions, radii, energy, pressure, residual), the
    same minimisations and force evaluations; the device clock counts every launch."""
    energies, seeds = [1e-3, 1e-9], [3, 4]
    whole = emulate(64, energies, seeds, threads=16)
    parts, launches = _resumed(64, energies, seeds, 700, threads=16)
    assert launches[1] >= 3
    for a, b, m in zip(whole, parts, launches):
        assert a.status == b.status == "converged"
        assert a.positions.tobytes() == b.positions.tobytes() and a.radii.tobytes() == b.radii.tobytes()
        assert (a.energy, a.pressure, a.force_residual) == (b.energy, b.pressure, b.force_residual)
        assert (a.force_evaluations, a.iterations) == (b.force_evaluations, b.iterations)
        clock = b.settings["device_clock"]
        assert clock["launches"] == m and a.settings["device_clock"]["launches"] == 1
        assert clock["start"] < clock["end"] and 0 < clock["seconds"] <= clock["end"] - clock["start"]


def test_resumption_refuses_what_is_not_its_own():
    out = emulate(32, [1e-4], [1], threads=8, budget=50)
    sus = out[0]
    assert isinstance(sus, Suspended) and sus.steps == 50 and sus.force_evaluations >= 50
    with pytest.raises(ValueError, match="Suspended packing of N=32 at E=1e-05"):
        emulate(32, [1e-5], [1], threads=8, resume=[sus])
    with pytest.raises(ValueError, match="budget"):
        emulate(32, [1e-4], [1], threads=8, budget=0)
    arrays = sus.arrays()
    with pytest.raises(ValueError, match="velocities has shape"):
        Suspended.from_arrays(dict(arrays, velocities=arrays["velocities"][:, :5]), 1e-4)
    done = sus.state.copy()
    done[gpu_state.S_CMD] = gpu_state.C_DONE
    with pytest.raises(ValueError, match="not that of a suspended search"):
        Suspended.from_arrays(dict(arrays, state=done), 1e-4)


@lru_cache(maxsize=None)
def _pairs(pair):
    """A compiled loop calling the compiled ``pair(r, q, alpha)`` on arrays: energies and forces."""
    @njit
    def run(r, q, alpha):
        v, f = np.empty(r.size), np.empty(r.size)
        for k in range(r.size):
            v[k], f[k] = pair(r[k], q[k], alpha)
        return v, f

    return run


@pytest.mark.parametrize("exponent", gpu_state.EXPONENTS)
def test_the_blocks_pair_is_the_potential_bit_for_bit(exponent):
    """The pair the block compiles for a fixed exponent (no pow for 2 and 2.5; ``make_block``'s, here
    as the emulation compiles it) gives the bits of the potential's compiled pair
    (``kernels.potential.pair_energy_force_inv``), each called from compiled code, at distances
    inside and beyond contact."""
    pair = gpu_batch.emulated_block(exponent).pair
    rng = np.random.default_rng(7)
    q = rng.uniform(10, 50, 2000)
    r = rng.uniform(0, 1.3, 2000) / q  # overlaps 1 - r q from 1 down to -0.3
    for alpha in ([exponent] if exponent else [2.2, 2.7, 3.0]):  # (None: the exponents but 2, 2.5)
        (v, f), (v_ref, f_ref) = _pairs(pair)(r, q, alpha), _pairs(potential.pair_energy_force_inv)(r, q, alpha)
        assert np.count_nonzero(f_ref) > 1000 and np.count_nonzero(f_ref == 0) > 100
        assert v.tobytes() == v_ref.tobytes() and f.tobytes() == f_ref.tobytes(), alpha
    with pytest.raises(ValueError, match="exponent"):
        gpu_block.pair_for(3.0)


# --------------------------------------------------------------------------- the phases

def _harness():
    """njit drivers of the emulated block's phases on one packing."""
    block = gpu_batch.emulated_block(2.0)
    rebuild, forces, residual = block.rebuild, block.forces, block.residual

    @njit
    def run(nt, xy, fl, nbr, ninv, iv, cells, sh):
        red = np.zeros((ROWS, nt))
        ok = rebuild(0, nt, nt, xy, fl, nbr, ninv, iv, cells, red, sh, True)
        forces(0, nt, nt, xy, fl, nbr, ninv, iv, red, sh)
        e = 0.5 * sh[S_TE]
        residual(0, nt, nt, xy, fl, nbr, ninv, iv, red, sh)
        return ok, e, sh[S_RESV], sh[S_NG]

    return run


def _phases(pos, rad, box, skin, nt=8, maxnb=40, alpha=2.0):
    n = len(rad)
    xy = np.array(pos, np.float64)
    fl = np.zeros((N_FL, n))
    fl[R] = rad
    nbr = np.zeros((maxnb, n), np.int32)
    ninv = np.zeros((maxnb, n))
    iv = np.zeros((N_IV, n), np.int32)
    cells = np.zeros((n + 1, 64), np.int32)
    sh = np.zeros(N_ST)
    sh[S_LX], sh[S_LY], sh[S_XY] = box
    sh[S_SKIN], sh[S_RMAX], sh[S_NCX], sh[S_NCY] = skin, rad.max(), 8, 8
    sh[S_ALPHA], sh[S_SIN_TOL] = alpha, np.sin(kernels.network.HALF_PLANE_TOL)
    out = _harness()(nt, xy, fl, nbr, ninv, iv, cells, sh)
    return out, xy, fl, nbr, iv


@pytest.mark.slow  # about a minute of the CUDA simulator: --full (the block tests below check the rows on whole packings)
@settings(max_examples=25, deadline=None)
@given(st.integers(8, 60), st.integers(0, 2**32 - 1), st.floats(0.0, 0.4), st.sampled_from([1, 4, 16]))
def test_rebuild_rows_are_the_brute_force_neighbours(n, seed, xy, nt):
    """Each disk's row holds exactly the disks within r_i + r_j + skin (nearest image in the
    tilted cell), in increasing index, whatever the thread count."""
    rng = np.random.default_rng(seed)
    box = np.array([1.0, 1.2, xy])
    pos = rng.random((n, 2)) * box[:2]
    rad = rng.uniform(0.02, 0.06, n)
    skin = 0.03
    (ok, *_), xy, fl, nbr, iv = _phases(pos, rad, box, skin, nt=nt)
    assert ok
    assert xy.tobytes() == np.stack([fl[RX], fl[RY]], 1).tobytes()  # the lists' reference, folded
    for i in range(n):
        want = []
        for j in range(n):
            if j == i:
                continue
            dx, dy = kernels.space.separation(xy[j, 0] - xy[i, 0], xy[j, 1] - xy[i, 1], box)
            if dx * dx + dy * dy < (rad[i] + rad[j] + skin) ** 2:
                want.append(j)
        assert nbr[:iv[NNB, i], i].tolist() == want


def test_phases_forces_and_residual_match_the_cpu_kernels():
    """Forces, energy and the rattler-aware residual of the block equal the CPU kernels' on a
    jammed packing (up to the summation order), with the same non-rattler count."""
    p = kernels.jam(128, 1e-6, 3)
    box = np.array([1.0, 1.0, 0.0])
    (ok, e, res, ng), _, fl, *_ = _phases(p.positions, p.radii, box, 0.3 * np.mean(p.radii))
    assert ok
    f = potential.forces(p.positions, p.radii, (1.0, 1.0))
    scale = np.abs(f).max()
    assert np.allclose(np.stack([fl[FX], fl[FY]], 1), f, atol=1e-9 * scale)
    assert abs(e - p.energy * 128) <= 1e-12 * e
    pi, pj = _candidate_pairs_core(p.positions, p.radii, box, 0.0)
    r_cpu, ng_cpu, _ = _residual_core(p.positions, p.radii, box, pi, pj, 2.0, np.empty((128, 2)))
    assert ng == ng_cpu == p.n_nonrattlers
    assert abs(res - r_cpu) <= 1e-6 * r_cpu + 1e-12


def test_gpu_and_cpu_packings_agree_in_the_mean():
    """GPU packings are other trajectories of the same protocol: cell means of A_G, Delta Z,
    Psi_O and phi agree with the CPU's within 3 combined standard errors (N_G 64, 1e-4, 16
    seeds each)."""
    seeds = list(range(16))
    gpu = emulate(64, [1e-4] * len(seeds), seeds)
    cpu = [kernels.jam(64, 1e-4, s) for s in seeds]
    for name in ("A_G", "delta_Z", "psi_O", "phi"):
        a = np.array([kernels.analyze(p.positions, p.radii, p.box).scalars[name] for p in gpu])
        b = np.array([kernels.analyze(p.positions, p.radii, p.box).scalars[name] for p in cpu])
        err = np.hypot(a.std(ddof=1) / np.sqrt(len(a)), b.std(ddof=1) / np.sqrt(len(b)))
        assert abs(a.mean() - b.mean()) <= 3 * err, (name, a.mean(), b.mean(), err)


# --------------------------------------------------------------------------- the CUDA kernel

@pytest.mark.slow
def test_kernel_compiles_for_a_real_gpu(request):
    """The batch kernel goes through numba-cuda's CUDA compiler to sm_90 PTX (libNVVM from the
    cuda extra's numba-cuda[cu13]; no GPU needed: the device's compute capability is given), as
    the launch compiles it: without contraction (every float64 multiply, add and subtract rounded
    on its own, ``.rn``, which the assembler never fuses; fused multiply-adds left only inside
    libdevice's functions; ``a x + y`` contracted by default, not so) and without link-time
    optimisation (whose code generation in nvJitLink would contract again); its block sums by warp
    shuffles, its clock the device's. Without the cuda extra it skips; with it, under --full, a
    compiler that cannot be loaded fails it (``require_cuda``)."""
    require_cuda(request.config, cuda_missing(compiler=True))
    code = """
import re
import numba.cuda.dispatcher as d
class Hopper:
    compute_capability = (9, 0)
d.get_current_device = lambda: Hopper()
from numba import cuda, float64, int32
from kernels.gpu import device
f3, f2, i3, i1 = float64[:, :, ::1], float64[:, ::1], int32[:, :, ::1], int32[::1]
sig = (i1, f3, f3, i3, f3, i3, i3, f2, f2)
k = device.kernel(256, 2.0)
assert k.targetoptions.get("lto") is False, k.targetoptions
def axpy(x, a, y):
    x[0] = a[0] * x[0] + y[0]
one = (float64[::1],) * 3
plain, _ = cuda.compile_ptx(axpy, one, device=False, cc=(9, 0))
with device._uncontracted():
    exact, _ = cuda.compile_ptx(axpy, one, device=False, cc=(9, 0))
    ptx, _ = cuda.compile_ptx(k.py_func, sig, device=False, cc=(9, 0))
assert "fma.rn.f64" in plain and "fma.rn.f64" not in exact, "the default contracts nothing: the check is void"
assert ".target sm_90" in ptx and "bar.sync" in ptx and "atom.global.add" in ptx, ptx[:400]
assert "shfl.sync.down" in ptx and "%globaltimer" in ptx
loose = re.findall(r"\\b(?:mul|add|sub)\\.f64", ptx)
assert not loose and re.findall(r"\\bmul\\.rn\\.f64", ptx), loose[:5]
print("ok", len(ptx))
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert r.returncode == 0 and r.stdout.startswith("ok"), r.stderr[-3000:]


REGISTERS = """
import sys
sys.path.insert(0, "benchmarks")
import gpu_ptx
ptxas = gpu_ptx.find_ptxas()
if ptxas is None:
    print("no ptxas")
    raise SystemExit(0)
loop = gpu_ptx.pair_loop(gpu_ptx.forces_ptx(2.0))
ptx = gpu_ptx.kernel_ptx(512, 2.0)
wide, narrow = gpu_ptx.assemble(ptxas, ptx, 128), gpu_ptx.assemble(ptxas, ptx, 64)
print(len(loop), wide["registers"], wide["spill_store_bytes"], wide["spill_load_bytes"],
      narrow["registers"], narrow["stack_bytes"])
"""


@pytest.mark.slow
def test_the_kernel_fits_its_register_budgets(request):
    """The block's budget, assembled by ptxas for sm_90 (benchmarks/gpu_ptx.py): a 512-thread
    block fits an SM at 128 registers a thread without a byte of spills, 64 registers (1024
    threads an SM, two such blocks; the default) spill at most a few hundred bytes of stack, and the forces' pair
    loop stays under 80 PTX instructions. Without the cuda extra it skips; with it, under --full,
    a compiler or a ptxas that cannot be found fails it (``require_cuda``)."""
    require_cuda(request.config, cuda_missing(compiler=True))
    r = subprocess.run([sys.executable, "-c", REGISTERS], capture_output=True, text=True, timeout=900,
                       cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert r.returncode == 0, r.stderr[-3000:]
    if r.stdout.strip() == "no ptxas":
        require_cuda(request.config, "no ptxas (the cuda extra's nvidia-cuda-nvcc, or PTXAS)")
    loop, wide, st, ld, narrow, stack = map(int, r.stdout.split())
    assert 0 < loop <= 80
    assert wide <= 128 and st == 0 and ld == 0
    assert narrow <= 64 and stack <= 256


class _Config:
    """What ``require_cuda`` asks of pytest's config: whether the run has ``--full``."""

    def __init__(self, full):
        self.full = full

    def getoption(self, name):
        assert name == "--full", name
        return self.full


def test_a_missing_cuda_tool_fails_under_full_where_the_cuda_extra_is_installed():
    """``require_cuda``, which the PTX tests above call: a CUDA tool that cannot be found skips the
    test, saying why, unless the suite runs with --full and the cuda extra installed (as .ci/run
    does): there it fails it."""
    def outcome(full, missing, installed):  # a skip must not escape: it would skip this test
        try:
            require_cuda(_Config(full), missing, installed=installed)
        except pytest.fail.Exception as exc:
            return "fails", str(exc)
        except pytest.skip.Exception as exc:
            return "skips", str(exc)
        return "goes on", ""

    assert outcome(True, None, True) == ("goes on", "")
    assert outcome(True, "no ptxas", True) == ("fails", "the cuda extra is installed, yet no ptxas")
    for full, installed in ((True, False), (False, True), (False, False)):
        assert outcome(full, "no ptxas", installed) == ("skips", "no ptxas"), (full, installed)


REDUCE = """
import numpy as np
from numba import cuda, njit, float64
from kernels.gpu import device
from kernels.gpu.batch import _noop
from kernels.gpu.block import make_shared_reduction
from kernels.gpu.state import ROWS, WARP, N_ST

dev = cuda.jit(device=True)
put_sum, put_max, total = dev(device._put_sum), dev(device._put_max), dev(device._total)

@cuda.jit
def kernel(vals, out):
    t = cuda.threadIdx.x
    red = cuda.shared.array((ROWS, WARP), dtype=float64)
    sh = cuda.shared.array(N_ST, dtype=float64)
    put_sum(red, 0, t, vals[0, t])
    put_sum(red, 1, t, vals[1, t])
    put_max(red, 2, t, vals[2, t])
    total(t, t + 1, cuda.blockDim.x, red, sh, 3, 2, 1)
    cuda.syncthreads()
    if t == 0:
        for k in range(3):
            out[k] = sh[3 + k]

ps, pm, tot = make_shared_reduction(njit, njit(_noop))

@njit
def emulated(vals, nt):
    red = np.zeros((ROWS, nt))
    sh = np.zeros(N_ST)
    for t in range(nt):
        ps(red, 0, t, vals[0, t])
        ps(red, 1, t, vals[1, t])
        pm(red, 2, t, vals[2, t])
    tot(0, nt, nt, red, sh, 3, 2, 1)
    return sh[3:6].copy()

rng = np.random.default_rng(11)
for nt in (1, 2, 8, 32, 64, 128):
    vals = rng.standard_normal((3, nt)) * 10.0 ** rng.integers(-9, 9, (3, nt))
    out = np.full(3, np.nan)
    kernel[1, nt](vals, out)
    want = emulated(vals, nt)
    assert out.tobytes() == want.tobytes(), (nt, out, want)
    assert want[2] == vals[2].max() and abs(want[0] - vals[0].sum()) <= 1e-12 * np.abs(vals[0]).sum()
print("ok")
"""


def test_the_kernels_block_sums_are_the_emulations_bit_for_bit():
    """The kernel's block sums (warp shuffles, then the first warp over the warps' sums) give the
    bits of the emulation's trees over shared memory, for blocks of one thread to four warps:
    run under numba's CUDA simulator, with the shuffle kernels.gpu.device gives it."""
    r = subprocess.run([sys.executable, "-c", REDUCE], capture_output=True, text=True, timeout=300,
                       env=dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_ENABLE_CUDASIM="1"))
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-3000:]


SIM_SPEC = """\
name: gpu-tiny
seed: 7
grid: {N_G: [16], E_G: [1.0e-4], seeds: 1}
protocol: {device: gpu, gpu_threads: 2}
observables: [scalars]
store: {configurations: true}
"""


@pytest.mark.slow
@pytest.mark.skipif(cuda_missing() is not None, reason=str(cuda_missing()))
def test_tiny_gpu_campaign_under_the_cuda_simulator_equals_the_emulation(tmp_path):
    """A device: gpu campaign runs end to end with the CUDA kernel under numba's simulator, and
    its packing is the emulation's bit for bit (the kernel and the emulation are one code)."""
    spec = tmp_path / "gpu.yaml"
    spec.write_text(SIM_SPEC)
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(tmp_path / "g.h5"),
                        "--workers", "1", "--quiet"], env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    with h5py.File(tmp_path / "g.h5") as f:
        assert f["tasks/status"][0] == 1
        assert f["tasks/host"][0].decode().endswith(" cuda-simulator")
        seed = f["tasks/seed"][0]
        tid = f["tasks/id"][0].decode()
        pos = f[f"configurations/{tid}/positions"][()]
    from campaign.plan.parse import load_spec
    from campaign.plan.tasks import expand

    st = subprocess.run([sys.executable, "-m", "campaign", "status", str(tmp_path / "g.h5")], env=env,
                        capture_output=True, text=True, timeout=60)
    assert st.returncode == 0 and "GPU packings: 1 on cuda-simulator" in st.stdout, st.stdout + st.stderr
    task = expand(load_spec(spec))[0]
    p = jam_batch(16, [1e-4], [list(task.entropy)], backend="emulate", threads=2)[0]
    assert task.id == tid and task.seed == seed
    assert p.positions.tobytes() == np.asarray(pos, np.float64).tobytes()


# --------------------------------------------------------------------------- campaigns

def test_spec_device_keys_give_their_own_ids(tmp_path):
    from campaign.errors import UserError
    from campaign.plan.parse import load_spec
    from campaign.plan.tasks import expand

    def ids(protocol):
        spec = tmp_path / "s.yaml"
        spec.write_text(f"name: s\nseed: 1\ngrid: {{N_G: [16], E_G: [1.0e-3], seeds: 2}}\nprotocol: {protocol}\n")
        return [t.id for t in expand(load_spec(spec))]

    cpu = ids("{}")
    assert ids("{device: cpu}") == cpu
    gpu = ids("{device: gpu}")
    assert set(gpu).isdisjoint(cpu)
    # the block's version is part of a GPU packing's identity: another block, other packings
    import campaign.plan.parse as spec_module  # where a spec's identity keys are written

    block = spec_module.GPU_BLOCK
    try:
        spec_module.GPU_BLOCK = block + 1
        assert set(ids("{device: gpu}")).isdisjoint(gpu) and ids("{}") == cpu
    finally:
        spec_module.GPU_BLOCK = block
    assert ids("{device: gpu, gpu_threads: 256}") == gpu
    assert set(ids("{device: gpu, gpu_threads: 64}")).isdisjoint(gpu)
    for bad, msg in (("{device: gpu, gpu_threads: 48}", "power of two"),
                     ("{gpu_threads: 64}", "device 'gpu'"),
                     ("{device: gpu, cell: shear}", "device 'gpu' runs FIRE"),
                     ("{device: gpu, minimizer: cg}", "device 'gpu' runs FIRE"),
                     ("{device: gpu, start: ladder}", "device 'gpu' runs FIRE"),
                     ("{device: tpu}", "unknown device")):
        with pytest.raises(UserError, match=msg):
            ids(bad)


BATCH_SPEC = """\
name: gpu-batch
seed: 3
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 6}
protocol: {device: gpu}
observables: [scalars]
"""


def _stored(path):
    """Scalars but the batch size (NaN for a task run alone), the batch sizes, the statuses."""
    with h5py.File(path) as f:
        names = sorted(k for k in f["scalars"] if k != "batch_size")
        size = f["scalars/batch_size"][:] if "batch_size" in f["scalars"] else np.full(len(f["tasks/status"]), np.nan)
        return {k: f["scalars"][k][:] for k in names}, size, f["tasks/status"][:]


@pytest.mark.parametrize("launch", ["local", pytest.param("mpi", marks=pytest.mark.slow)])
def test_gpu_workers_take_batches_and_store_the_same_bits(tmp_path, launch):
    """GPU workers (--gpus) run tasks of one variant and N_G together; the store holds the same
    values as a run without GPU workers (synthetic tasks: the batching, not the kernels)."""
    spec = tmp_path / "b.yaml"
    spec.write_text(BATCH_SPEC)
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", CAMPAIGN_SYNTHETIC_DELAY="0.02",
               PYTHONPATH=str(ROOT))
    base = [sys.executable, "-m", "campaign", "run", str(spec), "--quiet"]
    r = subprocess.run(base + ["--out", str(tmp_path / "one.h5"), "--workers", "2"], env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    cmd = base + ["--out", str(tmp_path / "gpu.h5"), "--gpus", "1", "--gpu-batch", "6"]
    if launch == "mpi":
        cmd = [str(MPIEXEC), "-n", "3"] + cmd
    else:
        cmd += ["--workers", "2"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    one, size_one, status_one = _stored(tmp_path / "one.h5")
    gpu, size_gpu, status_gpu = _stored(tmp_path / "gpu.h5")
    assert np.all(status_one == 1) and np.all(status_gpu == 1)
    assert np.all(np.isnan(size_one))  # without --gpus every task runs alone
    assert np.nanmax(size_gpu) > 1 and np.nanmax(size_gpu) <= 6
    for k in one:
        if k in ("jam_seconds", "analyze_seconds"):
            continue
        assert one[k].tobytes() == gpu[k].tobytes(), k


def test_run_refuses_bad_gpu_options(tmp_path):
    spec = tmp_path / "b.yaml"
    spec.write_text(BATCH_SPEC)
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", PYTHONPATH=str(ROOT))
    for args, msg in ((["--gpus", "3", "--workers", "2"], "--gpus 3 needs as many workers"),
                      (["--gpu-batch", "0"], "--gpu-batch >= 1"),
                      (["--gpus", "-1"], "--gpus must be >= 0")):
        r = subprocess.run([sys.executable, "-m", "campaign", "run", str(spec), "--out", str(tmp_path / "x.h5"),
                            *args], env=env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and msg in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_gpu_worker_keeps_to_the_devices_it_was_given(monkeypatch):
    from campaign.run.worker import visible_device

    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert [visible_device(k) for k in range(3)] == ["0", "1", "2"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3")  # SLURM bound this rank to GPU 3
    assert visible_device(0) == "3" and visible_device(1) == "3"
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "4,6")
    assert [visible_device(k) for k in range(3)] == ["4", "6", "4"]


def test_validate_says_when_it_prices_for_another_machine(tmp_path):
    """A calibration records the machine it was made on; validate says when this is another, and
    that GPU tasks are priced as CPU core-hours."""
    import json

    from campaign.plan.calibration import machine

    spec = tmp_path / "b.yaml"
    spec.write_text(BATCH_SPEC)
    packaged = json.loads((ROOT / "campaign/plan/cost_calibration.json").read_text())

    def validate(info):
        cal = tmp_path / "cal.json"
        cal.write_text(json.dumps(dict(packaged, info=info)))
        r = subprocess.run([sys.executable, "-m", "campaign", "validate", str(spec), "--calibration", str(cal)],
                           capture_output=True, text=True, timeout=60, env=dict(os.environ, PYTHONPATH=str(ROOT)))
        assert r.returncode == 0, r.stderr
        return r.stdout

    other = validate({"machine": "Vax 11/780, 1 cores"})
    assert "calibrated on another machine (Vax 11/780, 1 cores); this is " + machine() in other
    assert "device gpu  24 task(s) of default: priced above as CPU core-hours" in other
    assert "calibrated on another machine" not in validate({"machine": machine()})
    assert "calibrated on another machine (Vax, 2 cores)" in validate({"host": "node7 (Vax, 2 cores)"})


def test_a_gpu_task_that_overflows_fails_with_its_reason(monkeypatch):
    """One task through the worker's task function: a block whose lists overflow is a failed task
    with the reason, not a crash of the worker."""
    from campaign.run.worker import KernelTask, run_task

    monkeypatch.setattr(gpu_batch, "MAXNB", 4)
    monkeypatch.setenv("CAMPAIGN_GPU_BACKEND", "emulate")
    context = {"system": {"box": [1.0, 1.0], "potential": {"exponent": 2.0},
                          "species": [["A", 0.5, 1.4], ["B", 0.5, 1.0]]},
               "observables": ["scalars"], "histograms": [], "edges": {}}
    payload = {"id": "t", "index": 0, "N": 32, "E": 1e-4, "seed": 0, "entropy": [1, 2],
               "protocol": {"device": "gpu", "gpu_threads": 8}}
    s = run_task(KernelTask(), payload, context)
    assert not s["ok"] and "BlockOverflow" in s["error"]["message"] and "neighbour row" in s["error"]["message"]
    monkeypatch.setattr(gpu_batch, "MAXNB", 32)
    s = run_task(KernelTask(), payload, context)
    assert s["ok"] and s["scalars"]["identities_ok"] == 1.0 and s["host"].endswith(" emulation")


@pytest.mark.slow
def test_calibrate_gpu_prices_gpu_tasks_in_gpu_hours(tmp_path):
    """campaign calibrate --gpu adds the block's measured step-time ratios to a calibration (here of
    the emulation: a GPU is not at hand); validate then prices device: gpu tasks in GPU-hours as the
    CPU's seconds times that ratio. Without a GPU, --gpu is refused."""
    import json

    from campaign.plan.calibration import load

    spec = tmp_path / "b.yaml"
    spec.write_text(BATCH_SPEC)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = tmp_path / "gcal.json"
    r = subprocess.run([sys.executable, "-m", "campaign", "calibrate", "--gpu"], env=env, capture_output=True,
                       text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2 and "needs a CUDA device" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "campaign", "calibrate", "--gpu", "--quick", "--gpu-batch", "2",
                        "--out", str(out)], env=dict(env, CAMPAIGN_GPU_BACKEND="emulate"), capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    cal = load(out)
    assert cal.gpu["device"] == "emulation" and cal.gpu["N"] == [256, 1024] and all(x > 0 for x in cal.gpu["ratio"])
    ratio = {n: float(np.interp(np.log(n), np.log(cal.gpu["N"]), cal.gpu["ratio"])) for n in (16, 32)}
    want = sum(cal.seconds(n, e, {}, 2.0) * ratio[n] for n in (16, 32) for e in (1e-3, 1e-6)) * 6 / 3600
    r = subprocess.run([sys.executable, "-m", "campaign", "validate", str(spec), "--calibration", str(out)], env=env,
                       capture_output=True, text=True, timeout=60)
    line = [ln for ln in r.stdout.splitlines() if "device gpu" in ln][0]
    assert f"about {want:.3g} GPU-hours on emulation in batches of 2" in line, line
    cpu_spec = tmp_path / "c.yaml"
    cpu_spec.write_text(BATCH_SPEC.replace("protocol: {device: gpu}", "protocol: {}"))
    r = subprocess.run([sys.executable, "-m", "campaign", "validate", str(cpu_spec), "--calibration", str(out)],
                       env=env, capture_output=True, text=True, timeout=60)
    assert f"'default' as `device: gpu` would take about {want:.3g} GPU-hours on emulation" in r.stdout, r.stdout
    bad = json.loads(out.read_text())
    bad["gpu"]["ratio"] = [1.0]
    out.write_text(json.dumps(bad))
    r = subprocess.run([sys.executable, "-m", "campaign", "validate", str(spec), "--calibration", str(out)], env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "'gpu' must give" in r.stderr


MIXED_SPEC = """\
name: mixed
seed: 5
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 5}
variants: [{name: gpu, device: gpu}]
observables: [scalars]
"""


@pytest.mark.parametrize("launch", ["local", pytest.param("mpi", marks=pytest.mark.slow)])
def test_gpu_tasks_go_to_gpu_workers(tmp_path, launch):
    """With GPU workers, device: gpu tasks run only on them (never emulated beside them on a CPU
    worker); CPU tasks run on the CPU workers, and on a GPU worker once no GPU task waits."""
    spec = tmp_path / "m.yaml"
    spec.write_text(MIXED_SPEC)
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", CAMPAIGN_SYNTHETIC_DELAY="0.01",
               PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-m", "campaign", "run", str(spec), "--out", str(tmp_path / "m.h5"), "--quiet",
           "--gpus", "1", "--gpu-batch", "4"]
    cmd = [str(MPIEXEC), "-n", "3"] + cmd if launch == "mpi" else cmd + ["--workers", "2"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    with h5py.File(tmp_path / "m.h5") as f:
        variant = f["tasks/variant"][:].astype(str)
        rank = f["tasks/rank"][:]
        assert np.all(f["tasks/status"][:] == 1)
    if launch == "local":
        assert set(rank[variant == "gpu"]) == {1} and 2 in set(rank[variant == "default"])
    else:  # under mpiexec --gpus makes every worker rank a GPU worker
        assert set(rank[variant == "gpu"]) <= {1, 2}
