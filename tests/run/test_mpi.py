"""Real runs under mpiexec (rank 0 master, the others workers), compared with the other launchers."""

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers import mpich_segments, remove_segments_of_killed_jobs

pytestmark = pytest.mark.mpi

ROOT = Path(__file__).resolve().parents[2]
MPIEXEC = Path(sys.executable).parent / "mpiexec"
SPEC = """\
name: mpi
seed: 77
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6, 1.0e-9], seeds: 4}
variants: [{name: loose, force_tolerance: 1.0e-3}, {name: ladder, start: ladder}]
observables: [scalars, connectivity, fictitious]
run: {retries: 1}
"""
RUN_DEPENDENT = ("tasks/wall", "tasks/rank", "tasks/host", "checksums/tasks.wall", "checksums/tasks.rank",
                 "checksums/tasks.host")

# MPI is a dependency (the mpich wheel puts mpiexec next to the interpreter): never skip these.
assert MPIEXEC.exists(), f"no mpiexec next to {sys.executable}: pip install mpich (a dependency)"


def _env(**extra):
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic", PYTHONPATH=str(ROOT))
    env.update(extra)
    return env


def _campaign(args, n=None, env=None, timeout=60):
    cmd = [sys.executable, "-m", "campaign", *args]
    if n is not None:
        cmd = [str(MPIEXEC), "-n", str(n)] + cmd
    return subprocess.run(cmd, env=env or _env(), capture_output=True, text=True, timeout=timeout)


def _datasets(path):
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
        attrs = {k: f.attrs[k] for k in ("schema", "name", "spec_hash", "spec_yaml")}
        runs = f.attrs["runs"]
    return out, attrs, runs


def _same(a, b):
    assert set(a) == set(b)
    for k in a:
        if k not in RUN_DEPENDENT:
            assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), k


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mpi")
    spec = tmp / "s.yaml"
    spec.write_text(SPEC)
    out = {}
    for label, n, extra in (("inline", None, ["--launcher", "inline"]), ("local2", None, ["--workers", "2"]),
                            ("mpi2", 2, []), ("mpi3", 3, [])):
        path = tmp / f"{label}.h5"
        r = _campaign(["run", str(spec), "--out", str(path), *extra], n=n,
                      env=_env(CAMPAIGN_SYNTHETIC_FAIL="seed:3", CAMPAIGN_SYNTHETIC_FLAKY="seed:1"))
        assert r.returncode == 0, r.stderr
        out[label] = (path, r)
    return tmp, spec, out


def test_mpi_runs_complete_with_rank0_as_master(runs):
    _, _, out = runs
    for label, workers in (("mpi2", {1}), ("mpi3", {1, 2})):
        data, attrs, run_attr = _datasets(out[label][0])
        st = data["tasks/status"]
        # seed 3 always fails; in the ladder variant its chains stop at the top (E = 1e-3)
        assert (st == 1).sum() == 54 and (st == 2).sum() == 18
        assert set(data["tasks/rank"][st == 1]) == workers
        assert '"launcher": "mpi"' in run_attr and "MPICH" in run_attr
        with h5py.File(out[label][0], "r") as f:  # error records crossed MPI with traceback, rank, host
            recs = [dict(g.attrs) for g in f["failures"].values()]
        assert len(recs) == 18
        cascaded = [rec for rec in recs if "its ladder parent" in rec["message"]]
        assert len(cascaded) == 4  # E = 1e-6 and 1e-9 below each failed top, never run
        for rec in recs:
            if rec in cascaded:
                continue
            assert rec["rank"] in workers and rec["host"] and rec["attempts"] == 2
            assert "RuntimeError: synthetic failure" in rec["message"] and "Traceback" in rec["traceback"]
        # every ladder step started from its parent's packing, carried through MPI
        assert np.isfinite(data["scalars/start_checksum"]).sum() == 2 * 2 * 3


@pytest.mark.parametrize("label", ["local2", "mpi2", "mpi3"])
def test_results_identical_whatever_the_launcher(runs, label):
    _, _, out = runs
    ref, ref_attrs, _ = _datasets(out["inline"][0])
    got, attrs, _ = _datasets(out[label][0])
    _same(ref, got)
    assert attrs == ref_attrs


@pytest.mark.slow
def test_sigkill_of_the_whole_mpi_job_then_resume(runs, tmp_path):
    import signal
    import time

    _, spec, out = runs
    path = tmp_path / "killed.h5"
    env = _env(CAMPAIGN_SYNTHETIC_FAIL="seed:3", CAMPAIGN_SYNTHETIC_FLAKY="seed:1", CAMPAIGN_SYNTHETIC_DELAY="0.02")
    cmd = [str(MPIEXEC), "-n", "3", sys.executable, "-m", "campaign", "run", str(spec), "--out", str(path)]

    segments = mpich_segments()  # the killed job's shared memory is removed below
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and not Path(str(path) + ".progress.json").exists():
        time.sleep(0.05)
    time.sleep(0.3)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait(timeout=30)

    remove_segments_of_killed_jobs(segments)
    from campaign.storage.store import read_journal

    recs, _ = read_journal(Path(str(path) + ".journal").read_bytes())
    assert 0 < sum(m.get("type") == "task" for m, _ in recs) < 72  # killed in the middle of the run
    r = _campaign(["run", str(spec), "--out", str(path)], n=3, env=env)
    assert r.returncode == 0, r.stderr
    ref, ref_attrs, _ = _datasets(out["inline"][0])
    got, attrs, _ = _datasets(path)
    _same(ref, got)
    assert attrs == ref_attrs


def test_bad_spec_under_mpi_exits_2_without_hanging(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nseed: 1\ngrid: {N_G: [], E_G: [1.0e-3], seeds: 1}\n")
    r = _campaign(["run", str(bad), "--out", str(tmp_path / "o.h5")], n=3, timeout=30)
    assert r.returncode == 2 and "grid.N_G: empty" in r.stderr


@pytest.mark.slow
def test_master_fault_aborts_the_job(tmp_path, runs):
    _, spec, _ = runs
    r = _campaign(["run", str(spec), "--out", str(tmp_path / "o.h5"), "--task-function", "no_such_module:fn"],
                  n=3, timeout=30)
    assert r.returncode != 0
    assert "aborting the job" in r.stderr and "no_such_module" in r.stderr


# ---------------------------------------------------------------------------- the real kernels

@pytest.mark.slow
def test_ci_campaign_with_the_kernels_is_identical_for_1_2_3_workers(tmp_path):
    """campaigns/ci.yaml end to end: in-process, 2 local workers and 3 MPI workers give the same file."""
    spec = ROOT / "campaigns" / "ci.yaml"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("CAMPAIGN_TASK_FUNCTION", None)
    files = {}
    for label, n, extra in (("w1", None, ["--launcher", "inline"]), ("w2", None, ["--workers", "2"]),
                            ("w3", 4, [])):
        path = tmp_path / f"{label}.h5"
        r = _campaign(["run", str(spec), "--out", str(path)] + extra, n=n, env=env, timeout=600)
        assert r.returncode == 0, r.stderr
        files[label] = path
    ref, ref_attrs, _ = _datasets(files["w1"])
    st = ref["tasks/status"]
    assert (st == 1).all(), "every ci packing must succeed"
    assert (ref["scalars/identities_ok"] == 1).all() and (ref["scalars/jam_status"] == 0).all()
    flags = [k for k in ref if k.startswith("scalars/identity_")]
    assert {"scalars/identity_euler", "scalars/identity_area_tiling", "scalars/identity_semicircle"} <= set(flags)
    assert all((ref[k][st == 1] == 1).all() for k in flags)
    assert (ref["scalars/force_residual"] <= 1e-3).all()
    assert len([k for k in ref if k.startswith("configurations/")]) == 4 * 24  # asked for in ci.yaml
    timing = [k for k in ref if k.endswith("_seconds")]  # the timings and their block checksums
    for label in ("w2", "w3"):
        got, attrs, _ = _datasets(files[label])
        assert attrs == ref_attrs
        for k in timing:  # wall-clock timings are the only scalars allowed to differ
            got[k] = ref[k]
        _same(ref, got)


SYSTEMS_SPEC = """\
name: systems
seed: 31
grid: {N_G: [24], E_G: [1.0e-4], seeds: 2}
variants:
  - {name: hertz, system: {potential: {exponent: 2.5}}, E_G: [1.0e-4, 1.0e-7]}
  - {name: poly, system: {sizes: {distribution: uniform, polydispersity: 0.2}}}
observables: [scalars]
store: {configurations: true}
"""


@pytest.mark.slow
def test_system_variants_under_mpi_jam_each_variants_system(tmp_path):
    """Each worker rank jams with its task's system: the same file as in-process, Hertz packings
    in their window under the Hertz potential, polydisperse radii all different."""
    import kernels

    spec = tmp_path / "s.yaml"
    spec.write_text(SYSTEMS_SPEC)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("CAMPAIGN_TASK_FUNCTION", None)
    files = {}
    for label, n, extra in (("inline", None, ["--launcher", "inline"]), ("mpi", 3, [])):
        files[label] = tmp_path / f"{label}.h5"
        r = _campaign(["run", str(spec), "--out", str(files[label])] + extra, n=n, env=env, timeout=600)
        assert r.returncode == 0, r.stderr
    ref, ref_attrs, _ = _datasets(files["inline"])
    got, attrs, _ = _datasets(files["mpi"])
    assert attrs == ref_attrs
    for k in [k for k in ref if k.endswith("_seconds")]:
        got[k] = ref[k]
    _same(ref, got)
    assert (ref["tasks/status"] == 1).all() and len(ref["tasks/status"]) == 2 + 4 + 2
    with h5py.File(files["mpi"], "r") as f:
        variant = [v.decode() for v in f["tasks/variant"][()]]
        for i, tid in enumerate(f["tasks/id"][()]):
            g = f[f"configurations/{tid.decode()}"]
            pos, rad, box = g["positions"][()], g["radii"][()], g["box"][()]
            E = f["tasks/E"][i]
            alpha = 2.5 if variant[i] == "hertz" else 2.0
            e = kernels.analyze(pos, rad, box, exponent=alpha).scalars["E_G"]
            assert E <= e <= 1.1 * E * (1 + 1e-9), (variant[i], E, e)
            distinct = len(np.unique(rad))
            assert distinct == (24 if variant[i] == "poly" else 2), (variant[i], distinct)


NEWTON_SPEC = """\
name: newton
seed: 5
grid: {N_G: [48, 96], E_G: [1.0e-7, 1.0e-12], seeds: 2}
protocol: {endgame: newton}
variants: [{name: fire, endgame: none}]
observables: [scalars]
store: {configurations: true}
"""


@pytest.mark.slow
def test_newton_endgame_is_identical_for_1_2_3_workers(tmp_path):
    """The Newton endgame is as deterministic as FIRE: in-process, 2 local workers and 3 MPI
    ranks store bit-identical packings; the endgame did factorise, and the FIRE variant keeps
    the ids (and the bits) of a campaign that never named an endgame."""
    spec = tmp_path / "s.yaml"
    spec.write_text(NEWTON_SPEC)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("CAMPAIGN_TASK_FUNCTION", None)
    files = {}
    for label, n, extra in (("w1", None, ["--launcher", "inline"]), ("w2", None, ["--workers", "2"]),
                            ("w3", 4, [])):
        files[label] = tmp_path / f"{label}.h5"
        r = _campaign(["run", str(spec), "--out", str(files[label])] + extra, n=n, env=env, timeout=600)
        assert r.returncode == 0, r.stderr
    ref, ref_attrs, _ = _datasets(files["w1"])
    assert (ref["tasks/status"] == 1).all() and (ref["scalars/jam_status"] == 0).all()
    newton = np.array([v == b"default" for v in ref["tasks/variant"]])
    fact = ref["scalars/factorizations"]
    assert (fact[newton] > 0).mean() >= 0.5 and np.isnan(fact[~newton]).all()
    for label in ("w2", "w3"):
        got, attrs, _ = _datasets(files[label])
        assert attrs == ref_attrs
        for k in [k for k in ref if k.endswith("_seconds")]:
            got[k] = ref[k]
        _same(ref, got)
    # the FIRE variant is the plain campaign: same ids, same packings
    plain = tmp_path / "plain.yaml"
    plain.write_text(NEWTON_SPEC.replace("protocol: {endgame: newton}\nvariants: [{name: fire, endgame: none}]\n", ""))
    r = _campaign(["run", str(plain), "--out", str(tmp_path / "plain.h5"), "--launcher", "inline"], env=env,
                  timeout=600)
    assert r.returncode == 0, r.stderr
    with h5py.File(tmp_path / "plain.h5", "r") as f, h5py.File(files["w1"], "r") as g:
        ids = [t.decode() for t in f["tasks/id"][()]]
        assert set(ids) == {t.decode() for t, v in zip(g["tasks/id"][()], g["tasks/variant"][()]) if v == b"fire"}
        for t in ids:
            assert f[f"configurations/{t}/positions"][()].tobytes() == g[f"configurations/{t}/positions"][()].tobytes()


@pytest.mark.slow
def test_large_ladder_starts_do_not_deadlock_under_mpi(tmp_path):
    """Ladder steps of 20000 disks (a 480 kB start, beyond MPI's eager limit) to one busy worker:
    the master's blocking send and the worker's result would wait for each other forever if the
    step were sent while the worker is busy (tests/run/test_ladder.py, the same with local workers)."""
    spec = tmp_path / "big.yaml"
    spec.write_text(SPEC.replace("N_G: [16, 32]", "N_G: [20000]").replace("seeds: 4", "seeds: 2")
                    .replace("variants: [{name: loose, force_tolerance: 1.0e-3}, {name: ladder, start: ladder}]",
                             "protocol: {start: ladder}"))
    r = _campaign(["run", str(spec), "--out", str(tmp_path / "big.h5")], n=2,
                  env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.2"), timeout=120)
    assert r.returncode == 0, r.stderr
    from campaign.storage.store import DONE

    with h5py.File(tmp_path / "big.h5", "r") as f:
        assert list(f["tasks/status"][:]) == [DONE] * 6
