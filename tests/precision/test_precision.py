"""Campaigns with precision targets (docs/PRECISION.md): the spec, the model of the errors against the
reducer's bootstrap, the rounds' decisions against an in-memory run of the same campaign, the same
store whatever the launcher or an interruption, and how a campaign ends (targets met, out of reach,
budget, max_seeds).

The packings are ``campaign.run.worker.SyntheticLawsTask``'s: scalars that follow known laws (A_G and
psi_O against E_G with finite-size terms, Delta Z ~ E_G^(1/4), force evaluations growing with N and
with closeness to jamming), so a campaign fits, extrapolates and decides in seconds.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers import PRECISION_SPEC, assert_same_contents, store_contents, synthetic_draw, uniform_reduced

from campaign.plan.parse import parse_spec
from campaign.plan.targets import FITS
from campaign.plan.tasks import expand
from campaign.precision import allocation as A
from campaign.precision import errormodel as M
from campaign.precision import planner as P
from campaign.storage.checksums import sums_name, write_sums
from campaign.storage.journal import read_journal
from campaign.storage.layout import BLOCK_ROWS

ROOT = Path(__file__).resolve().parents[2]
MPIEXEC = Path(sys.executable).parent / "mpiexec"

#: three sizes, seven energies in the fit range (1e-12 .. 1e-6) and two above it; four rounds or so
SPEC = PRECISION_SPEC


def _env(**extra):
    env = dict(os.environ, CAMPAIGN_TASK_FUNCTION="synthetic-laws", PYTHONPATH=str(ROOT))
    env.pop("CAMPAIGN_SYNTHETIC_LAWS", None)
    env.update(extra)
    return env


def _run(tmp_path, out, *extra, spec=SPEC, env=None, n=None, timeout=240):
    path = tmp_path / "spec.yaml"
    path.write_text(spec)
    cmd = [sys.executable, "-m", "campaign", "run", str(path), "--out", str(out), "--quiet", *extra]
    if n is not None:
        cmd = [str(MPIEXEC), "-n", str(n)] + cmd
    return subprocess.run(cmd, env=env or _env(), capture_output=True, text=True, timeout=timeout)


def _records(path):
    with h5py.File(path, "r") as f:
        g = f["precision"]
        return [json.loads(g[k][()].tobytes().decode()) for k in sorted(g)]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The campaign run inline (one process), its store and its run's output."""
    tmp = tmp_path_factory.mktemp("precision")
    out = tmp / "ref.h5"
    r = _run(tmp, out, "--launcher", "inline")
    assert r.returncode == 0, r.stderr
    return out, r.stderr


# --------------------------------------------------------------------------- the spec

def test_targets_and_budget_leave_the_hash_and_the_ids_alone():
    s = parse_spec(SPEC)
    assert s.n_tasks == 3 * 9 * 40 and s.seeds == tuple(range(40))
    other = parse_spec(SPEC.replace("A_G_star_E: 1.5e-3", "A_G_star_E: 1.0e-3").replace(
        "max_seeds: 40", "max_seeds: 40\n  budget: 2.5"))
    assert other.precision.budget == 2.5 and other.precision.target["A_G_star_E"] == 1.0e-3
    assert other.hash == s.hash  # a store's campaign goes on with tighter targets or a larger budget
    assert parse_spec(SPEC.replace("pilot: 3", "pilot: 4")).hash != s.hash
    assert parse_spec(SPEC.replace("max_seeds: 40", "max_seeds: 41")).hash != s.hash
    # a cell's seeds are the packings of a fixed grid with the same seeds: the same ids
    fixed = parse_spec(SPEC.split("precision:")[0].replace("per_decade: 1}", "per_decade: 1}\n  seeds: 40")
                       + "observables: [scalars]\n")
    assert [t.id for t in expand(fixed)] == [t.id for t in expand(s)]


def test_fixed_grid_specs_keep_their_hash():
    text = (ROOT / "campaigns" / "paper-small.yaml").read_text()
    s = parse_spec(text)
    assert s.precision is None and "precision" not in s.canonical()


# --------------------------------------------------------------------------- the model

def test_the_model_of_the_errors_matches_the_bootstrap():
    """On a uniform campaign of known laws, the Fisher model's error of every entry of the N_G -> inf
    row is the reducer's bootstrap error within 20% (the bootstrap's own scatter is ~5%); an intercept's
    with the reducer's sqrt(chi^2/dof) of its 1/N_G line, when above 1."""
    cells, table = uniform_reduced(SPEC.replace("max_seeds: 40", "max_seeds: 60"), 60)
    n = M.cell_counts(table, cells)
    row = table.extrapolated["default"]
    checked = 0
    for quantity, absc, ikey, bkey in FITS:
        law = M.build_law(table, cells, "default", quantity, absc)
        assert law.ok, law.why
        inv = law.inverse(n)
        line = table.shared_fits[("default", quantity, absc)][2]
        for key, k, infl in ((ikey, 0, np.sqrt(max(1.0, line.chi2_dof))), (bkey, 2, 1.0)):
            assert np.isfinite(row[f"{key}_err"]), key
            model = np.sqrt(inv[k, k]) * infl
            assert 0.8 < model / row[f"{key}_err"] < 1.25, (key, model, row[f"{key}_err"])
            checked += 1
    assert checked == 8


def test_an_absent_law_is_out_of_reach_for_every_exponent():
    """No dependence of A_G on E_G (c_A = 0): the exponent has no amplitude to be measured by,
    whatever exponent the data allow, so the best case at any seed count misses a goal."""
    text = SPEC.replace("A_G_star_E: 1.5e-3, psi_O_star: 3.0e-3", "beta_E: 0.02")
    cells, table = uniform_reduced(text, 30, {"c_A": 0.0})
    law = M.build_law(table, cells, "default", "A_G", "E_G")
    t = A.Target("default", "beta_E", 0.02, np.nan, np.nan, law)
    now = np.full(cells.C, 30.0)
    huge = np.where(cells.relevant({"beta_E": 1}), 1e4, 30.0)
    assert not A.best_case(t, huge, now) <= 0.02 ** 2  # undetermined (inf) or above the goal
    # the laws as they are: the same seeds measure the exponent to better than the goal
    cells, table = uniform_reduced(text, 30)
    t = A.Target("default", "beta_E", 0.02, np.nan, np.nan, M.build_law(table, cells, "default", "A_G", "E_G"))
    assert A.best_case(t, huge, now) < 0.02 ** 2


# --------------------------------------------------------------------------- runs

def test_the_rounds_decide_what_the_in_memory_campaign_decides(reference):
    """The store's decisions (one per round, kept in /precision) are those of the same campaign
    run in memory on the same packings: the master's rounds add nothing of their own."""
    out, err = reference
    recs = _records(out)
    spec = parse_spec(SPEC)
    tasks = expand(spec)
    cells = M.campaign_cells(spec, tasks)
    first, how = P.first_round(spec, tasks)
    assert how.startswith("designed from the prior") and recs[0]["allocated"] == [int(x) for x in first]
    mem, table = P.run_in_memory(cells, spec.precision.settings(), synthetic_draw(tasks),
                                 attrs={"schema": "jamming-campaign/1", "spec_yaml": SPEC}, first=(first, how))
    assert [r["round"] for r in recs] == list(range(len(recs))) and len(recs) >= 3
    assert [r["action"] for r in recs] == [r["action"] for r in mem]
    for a, b in zip(recs, mem):
        assert a["allocated"] == b["allocated"] and a["early"] == b["early"]
        assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    assert recs[-1]["action"] == "met" and "every target met" in err
    # the store holds exactly the seeds the rounds gave out
    with h5py.File(out, "r") as f:
        status = f["tasks/status"][:]
    assert np.array_equal(status == 1, cells.tasks_of(recs[-1]["early"]))
    row = table.extrapolated["default"]
    assert row["A_G_star_E_err"] <= 1.5e-3 and row["psi_O_star_err"] <= 3.0e-3


def test_a_decision_is_the_reduction_of_its_rounds(reference, tmp_path):
    """A decision's errors are `campaign reduce`'s on the packings of the rounds before it, bit for bit."""
    out, _ = reference
    recs = _records(out)
    spec = parse_spec(SPEC)
    cells = M.campaign_cells(spec, expand(spec))
    k = 2
    copy = tmp_path / "upto.h5"
    shutil.copy(out, copy)
    with h5py.File(copy, "r+") as f:  # the rows of later rounds back to pending (a store as it was then)
        status = f["tasks/status"][:]
        status[~cells.tasks_of(recs[k - 1]["allocated"])] = 0
        f["tasks/status"][:] = status
        sums = f[sums_name("tasks/status")]
        for lo in range(0, len(status), BLOCK_ROWS):  # the edited column's block checksums, written again
            write_sums(sums, lo, status[lo:lo + BLOCK_ROWS], BLOCK_ROWS)
    r = subprocess.run([sys.executable, "-m", "campaign", "reduce", str(copy), "--json", "--out", str(tmp_path / "r")],
                       env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    row = json.loads(r.stdout)["extrapolated"]["default"]
    for t in recs[k]["targets"]:
        assert row[f"{t['key']}_err"] == t["error"], t["key"]
        assert row[t["key"]] == t["value"], t["key"]


def test_a_store_reduced_again_in_parts(reference):
    """``planner.reduce_store_rows`` (the experiments' and bench_precision's reductions of a store's parts):
    each decision's rows give that decision's values and errors bit for bit, and the first n seeds of
    every cell are n packings a cell where the rounds gave out that many."""
    out, _ = reference
    recs = _records(out)
    spec = parse_spec(SPEC)
    cells = M.campaign_cells(spec, expand(spec))
    for k in range(1, len(recs)):
        given = cells.tasks_of(recs[k - 1]["allocated"])
        table = P.reduce_store_rows(out, lambda t: given[:len(t["status"])] & (t["status"] == 1))
        row = table.extrapolated["default"]
        for t in recs[k]["targets"]:
            got = (row[f"{t['key']}_err"], row[t["key"]])
            if t["error"] is None:  # the decision had no value
                assert not np.isfinite(got[0]), (k, t["key"], got)
            else:
                assert got == (t["error"], t["value"]), (k, t["key"])
    assert any(t["error"] is not None for t in recs[-1]["targets"])
    n = 3
    table = P.reduce_store_rows(out, lambda t: t["seed"] < n)
    held = np.minimum(np.asarray(recs[-1]["early"]), n)
    assert np.array_equal(M.cell_counts(table, cells), held)


@pytest.mark.slow
def test_the_same_store_from_two_local_workers(reference, tmp_path):
    out, _ = reference
    got = tmp_path / "two.h5"
    r = _run(tmp_path, got, "--workers", "2", env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.002"))
    assert r.returncode == 0, r.stderr
    assert_same_contents(store_contents(out), store_contents(got))


@pytest.mark.slow
@pytest.mark.mpi
def test_the_same_store_under_mpiexec(reference, tmp_path):
    out, _ = reference
    got = tmp_path / "mpi.h5"
    r = _run(tmp_path, got, n=3)
    assert r.returncode == 0, r.stderr
    assert_same_contents(store_contents(out), store_contents(got))


def _journal_rounds(path):
    p = Path(str(path) + ".journal")
    if not p.exists():
        return set()
    try:
        recs, _ = read_journal(p.read_bytes())
    except Exception:  # noqa: BLE001 - caught mid-write: look again
        return set()
    return {m["round"] for m, _ in recs if m.get("type") == "round"}


def test_a_kill_in_the_middle_of_a_round_then_resume(reference, tmp_path):
    """SIGKILL the master (and its workers) once round 1 is decided and some of its tasks are done;
    the rerun repeats no decision and ends with the uninterrupted run's store."""
    out, _ = reference
    got = tmp_path / "k.h5"
    path = tmp_path / "spec.yaml"
    path.write_text(SPEC)
    cmd = [sys.executable, "-m", "campaign", "run", str(path), "--out", str(got), "--quiet", "--workers", "2"]
    p = subprocess.Popen(cmd, env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.01"), stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 120
    while 1 not in _journal_rounds(got) and time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.05)
    assert 1 in _journal_rounds(got), "round 1 was never decided"
    time.sleep(0.5)  # some of round 1's tasks
    os.killpg(p.pid, signal.SIGKILL)
    p.wait(timeout=30)
    r = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr
    assert "round decision(s) of the store do not follow" not in r.stderr
    assert_same_contents(store_contents(out), store_contents(got))


@pytest.mark.slow
def test_sigkill_at_random_moments_through_the_rounds(reference, tmp_path):
    """Eight SIGKILLs at random moments of a two-worker run (start-up, mid-round, at a decision),
    each followed by a rerun; the last completes it: the uninterrupted run's store."""
    import random

    out, _ = reference
    got = tmp_path / "r.h5"
    path = tmp_path / "spec.yaml"
    path.write_text(SPEC)
    cmd = [sys.executable, "-m", "campaign", "run", str(path), "--out", str(got), "--quiet", "--workers", "2"]
    rng = random.Random(20261128)
    for _ in range(8):
        p = subprocess.Popen(cmd, env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.01"), stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)
        time.sleep(rng.uniform(0.5, 6.0))
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        p.wait(timeout=30)
    r = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr
    assert_same_contents(store_contents(out), store_contents(got))


def test_targets_met_by_the_pilot(tmp_path):
    """Packings that scatter little (a tenth of the usual spread): round 0 (designed from the prior)
    meets loose goals, the first decision ends the campaign."""
    spec = SPEC.replace("A_G_star_E: 1.5e-3, psi_O_star: 3.0e-3", "A_G_star_E: 0.01, psi_O_star: 0.01")
    out = tmp_path / "p.h5"
    r = _run(tmp_path, out, "--launcher", "inline", spec=spec,
             env=_env(CAMPAIGN_SYNTHETIC_LAWS=json.dumps({"sigma_A": 0.008, "sigma_P": 0.012})))
    assert r.returncode == 0, r.stderr
    recs = _records(out)
    assert [r_["action"] for r_ in recs] == ["pilot", "met"]
    assert "every target met" in r.stderr
    s = parse_spec(spec)
    cells = M.campaign_cells(s, expand(s))
    with h5py.File(out, "r") as f:
        done = int((f["tasks/status"][:] == 1).sum())
    # round 0, and the one early seed it gave each cell of the fit range
    first = P.first_round(s, expand(s))[0]
    assert done == int(first.sum()) + int(cells.relevant({"x": 1}).sum())
    r = _run(tmp_path, out, "--launcher", "inline", spec=spec,  # nothing left: no decision, no task
             env=_env(CAMPAIGN_SYNTHETIC_LAWS=json.dumps({"sigma_A": 0.008, "sigma_P": 0.012})))
    assert r.returncode == 0 and len(_records(out)) == 2


def test_a_target_out_of_reach_ends_the_run(tmp_path):
    """A_G that does not depend on E_G: beta_E has nothing to be measured by. Two decisions in a row
    find it out of reach, the run says so in a paragraph and exits 0."""
    spec = SPEC.replace("A_G_star_E: 1.5e-3, psi_O_star: 3.0e-3", "beta_E: 0.02")
    out = tmp_path / "u.h5"
    r = _run(tmp_path, out, "--launcher", "inline", spec=spec,
             env=_env(CAMPAIGN_SYNTHETIC_LAWS=json.dumps({"c_A": 0.0})))
    assert r.returncode == 0, r.stderr
    recs = _records(out)
    assert recs[-1]["action"] == "unreachable"
    assert any(t["out_of_reach"] for t in recs[-2]["targets"])
    assert "beta_E cannot reach its goal 0.02" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.slow
def test_the_budget_ends_the_run_and_says_what_the_targets_would_cost(tmp_path):
    spec = SPEC.replace("max_seeds: 40", "max_seeds: 40\n  budget: 0.01")
    out = tmp_path / "b.h5"
    r = _run(tmp_path, out, "--launcher", "inline", spec=spec)
    assert r.returncode == 0, r.stderr
    recs = _records(out)
    assert recs[-1]["action"] == "budget", [x["action"] for x in recs]
    assert "budget" in recs[-1]["message"]
    # rounds are given out when their estimated cost (the cells' mean so far) fits what is left; the
    # packings then cost what they cost, a few per cent either way
    spent = recs[-1]["spent_core_hours"] + recs[-1]["committed_core_hours"]
    assert 0.5 * 0.01 < spent <= 0.01 * 1.05
    # a larger budget: the same store goes on, with the decisions kept
    r = _run(tmp_path, out, "--launcher", "inline", spec=spec.replace("budget: 0.01", "budget: 1.0"))
    assert r.returncode == 0, r.stderr
    more = _records(out)
    assert more[:len(recs)] == recs and more[-1]["action"] == "met"


def test_status_shows_the_rounds(reference):
    out, _ = reference
    r = subprocess.run([sys.executable, "-m", "campaign", "status", str(out)], env=_env(), capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "precision targets: ended after round" in r.stdout
    assert "A_G_star_E: error" in r.stdout and "against goal 0.0015" in r.stdout
    assert "core-hours:" in r.stdout
    r = subprocess.run([sys.executable, "-m", "campaign", "status", str(out), "--json"], env=_env(),
                       capture_output=True, text=True, timeout=60)
    got = json.loads(r.stdout)
    assert got["precision"]["last_decision"]["action"] == "met" and got["remaining"] == 0


def test_validate_prices_the_pilot_and_the_targets(tmp_path, capsys):
    """Before the pilot, `campaign validate` plans from the prior (paper-small's packings); a system the
    prior does not hold needs the pilot; after it, the store's last decision says what is left."""
    from campaign import cli

    path = tmp_path / "v.yaml"
    path.write_text(SPEC + f"output: {tmp_path / 'none.h5'}\n")
    assert cli.main(["validate", str(path)]) == 0
    out = capsys.readouterr().out
    assert "in round 0 (1 variant(s) x 3 N_G x 9 E_G; designed from the prior" in out and "at most 1080" in out
    assert "reaching the targets: about" in out and "by the prior" in out and "seeds in every cell:" in out
    hertz = SPEC.replace("seed: 5\n", "seed: 5\nsystem: {potential: {exponent: 2.5}}\n")
    path.write_text(hertz + f"output: {tmp_path / 'none.h5'}\n")
    assert cli.main(["validate", str(path)]) == 0
    out = capsys.readouterr().out
    assert "reaching the targets: needs the pilot" in out
    assert "in round 0 (1 variant(s) x 3 N_G x 9 E_G; a uniform pilot of 3 seeds per cell" in out


def test_validate_and_slurm_read_the_last_decision(reference, tmp_path, capsys):
    from campaign import cli

    out, _ = reference
    path = tmp_path / "v.yaml"
    path.write_text(SPEC + f"output: {out}\n")
    assert cli.main(["validate", str(path)]) == 0
    assert f"{out}: ended (met) after round" in capsys.readouterr().out
    assert cli.main(["slurm", str(path), "--out", str(tmp_path / "s.sbatch")]) == 0
    assert "every task is done; nothing left to run" in capsys.readouterr().err


@pytest.mark.slow
def test_workers_do_not_wait_for_the_decisions(tmp_path):
    """Two workers, packings of 0.1-0.4 s: the workers' idle share of the run (one minus their task
    time over two workers' wall time) stays under 10%, decisions and round ends included."""
    out = tmp_path / "idle.h5"
    r = _run(tmp_path, out, "--workers", "2", env=_env(CAMPAIGN_SYNTHETIC_DELAY="0.1*N"), timeout=900)
    assert r.returncode == 0, r.stderr
    with h5py.File(out, "r") as f:
        wall = f["tasks/wall"][:][f["tasks/status"][:] == 1]
        runs = json.loads(f.attrs["runs"])
    assert len(runs) == 1 and len(_records(out)) >= 3
    idle = 1.0 - wall.sum() / (2 * runs[0]["seconds"])
    assert idle < 0.10, idle


def test_readers_count_only_the_seeds_given_out(reference, tmp_path):
    """The rows of seeds no round gave out are no tasks of the campaign: `campaign reduce` counts none
    of them pending, `campaign status` neither."""
    out, _ = reference
    recs = _records(out)
    r = subprocess.run([sys.executable, "-m", "campaign", "reduce", str(out), "--json", "--out", str(tmp_path / "r")],
                       env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    status = json.loads(r.stdout)["status"]
    assert status["pending"] == 0 and status["total"] == status["done"] == sum(recs[-1]["early"])
    r = subprocess.run([sys.executable, "-m", "campaign", "status", str(out), "--json"], env=_env(),
                       capture_output=True, text=True, timeout=60)
    got = json.loads(r.stdout)
    assert got["tasks"] == sum(recs[-1]["early"]) and got["remaining"] == 0
    assert sum(g["pending"] for g in got["groups"]) == 0


def test_a_target_limited_by_its_sizes_ends_the_run(tmp_path):
    """A_G with a 1/N_G^2 term that three sizes cannot follow (a_N2 = -300: 0.07 at N_G = 64): the line
    through them fails its chi^2 test once the cells fill, the reducer says the value is limited by its
    sizes, and two decisions in a row finding it so end the run with the reducer's paragraph (more
    seeds would not shrink an error inflated by sqrt(chi^2/dof)) instead of running to max_seeds."""
    spec = SPEC.replace("A_G_star_E: 1.5e-3, psi_O_star: 3.0e-3", "A_G_star_E: 1.0e-4")
    out = tmp_path / "l.h5"
    laws = _env(CAMPAIGN_SYNTHETIC_LAWS=json.dumps({"a_N2": -300.0}))
    r = _run(tmp_path, out, "--launcher", "inline", spec=spec, env=laws)
    assert r.returncode == 0, r.stderr
    recs = _records(out)
    assert recs[-1]["action"] == "limited", [x["action"] for x in recs]
    assert recs[-2]["targets"][0]["limited"] and recs[-1]["targets"][0]["limited"]
    assert "A_G_star_E cannot reach its goal 0.0001 with more seeds" in r.stderr
    assert "limited by its sizes: the 1/N_G line through N_G = 64, 128, 256" in r.stderr
    assert sum(recs[-1]["allocated"]) < 0.5 * 40 * len(recs[-1]["allocated"])  # far from max_seeds
    st = subprocess.run([sys.executable, "-m", "campaign", "status", str(out)], capture_output=True, text=True,
                        env=laws)
    assert "a target limited by its sizes" in st.stdout + st.stderr
    # the same law without the 1/N_G^2 term: no decision finds it limited
    r = _run(tmp_path, tmp_path / "n.h5", "--launcher", "inline", spec=spec.replace("max_seeds: 40", "max_seeds: 12"),
             env=_env())
    assert r.returncode == 0, r.stderr
    assert not any(t["limited"] for x in _records(tmp_path / "n.h5") for t in x.get("targets", []))


def test_what_each_round_projected_and_what_the_next_decision_measured(reference):
    """``planner.projections``: for every ``continue`` decision and target, the reducer's error then,
    the model's error projected after the round, and the error the next decision measured on the
    round's packings (a target without a value is planned on its exponent: no ratio), and the table
    names every one of them. On the reference run (round 0 from the prior: its first decision finds no
    value yet) and on the same campaign in memory from a uniform pilot (values from the first on)."""
    out, _ = reference
    spec = parse_spec(SPEC)
    tasks = expand(spec)
    cells = M.campaign_cells(spec, tasks)
    uniform, _ = P.run_in_memory(cells, spec.precision.settings(), synthetic_draw(tasks),
                                 attrs={"schema": "jamming-campaign/1", "spec_yaml": SPEC})

    def same(a, b):  # a record keeps a missing number as None
        return (np.isnan(a) and b is None) or a == b

    rows = []
    for recs in (_records(out), uniform):
        got = P.projections(recs)
        cont = [r for r in recs[:-1] if r["action"] == "continue"]
        assert len(got) == 2 * len(cont) and cont
        by = {(r["round"], t["key"]): t for r in recs for t in r["targets"]}
        for row in got:
            k = row["decision"]
            assert same(row["error"], by[(k, row["key"])]["error"])
            assert same(row["projected"], by[(k, row["key"])]["projected"])
            assert same(row["achieved"], by[(k + 1, row["key"])]["error"])  # the next decision's, not this one's
            if row["error"] is not None and np.isfinite(row["error"]) and np.isfinite(row["achieved"]):
                assert row["ratio"] == row["achieved"] / row["projected"]
            else:  # planned on its law's exponent, whose error is no measure of the target's
                assert np.isnan(row["ratio"])
        rows += got
    assert any(np.isfinite(r["ratio"]) for r in rows) and any(np.isnan(r["ratio"]) for r in rows)
    recs = uniform
    table = P.projections_markdown(rows).splitlines()
    assert len(table) == 2 + len(rows) and table[2].startswith(f"| {rows[0]['decision']} | A_G_star_E |")
    # a decision that ends the campaign projects nothing, and the last one has no next
    assert P.projections([{"round": 0, "action": "pilot", "targets": []}, recs[-1]]) == []
