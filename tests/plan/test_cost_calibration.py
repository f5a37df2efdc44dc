"""The calibrated cost model: its fit recovers known constants, its file is checked (bad ones exit 2),
`endgame: auto` resolves per (N, E) to the explicit tasks, and validate and slurm show the estimate's
interval and the advice."""

import json
import math

import numpy as np
import pytest

from campaign import cli
from campaign.errors import UserError
from campaign.plan import calibration, spec as spec_module
from campaign.plan.calibration import BLOCKS, Calibration, fit, from_dict, packaged
from campaign.plan.spec import auto_endgame, harmonic_energy, resolve_protocol
from campaign.plan.parse import parse_spec
from campaign.plan.tasks import estimate, expand, task_cost

SPEC = """\
name: t
seed: 7
grid: {N_G: [16, 32], E_G: [1.0e-3, 1.0e-6], seeds: 3}
observables: [scalars]
"""


def _calibration(endgame=(0.0, 0.0, 0.0, 0.0), sigma_sys=0.1) -> Calibration:
    base = packaged()
    blocks = dict(base.blocks)
    blocks["endgame"] = (np.array(endgame, float), np.eye(4) * 1e-4)
    return Calibration(base.L0, blocks, 0.3, sigma_sys, source="test")


def _write(tmp_path, cal, name="cal.json"):
    path = tmp_path / name
    cal.save(path)
    return path


# ---------------------------------------------------------------------- the fit

def test_fit_recovers_known_constants_from_synthetic_timings():
    """Log-normal timings around a known model (every block): the fit finds its constants within
    their errors, and the total of the campaign within the estimate's interval."""
    rng = np.random.default_rng(3)
    truth = {"fire": [-2.0, 1.7, 0.06, 3.0, 0.4], "endgame": [0.2, -0.1, -0.25, -0.1],
             "ladder": [-0.5, 0.1, -0.1, -0.01], "ladder_endgame": [0.0, 0.3, -0.2, -0.05]}
    L0, s = 6.0, 0.3
    true = Calibration(L0, {b: (np.array(v, float), np.zeros((len(v), len(v)))) for b, v in truth.items()}, s, 0.0)
    rows = {k: [] for k in ("N", "E", "exponent", "endgame", "parent_E", "seconds", "group")}
    energies = [10.0 ** -k for k in range(3, 16)]
    for N in (128, 256, 512, 1024, 2048, 4096):
        for k, E in enumerate(energies):
            kinds = [("none", math.nan, {}), ("newton", math.nan, {"endgame": "newton"})]
            if k:
                kinds += [("none", energies[k - 1], {"start": "ladder"}),
                          ("newton", energies[k - 1], {"start": "ladder", "endgame": "newton"})]
            for endgame, parent, proto in kinds:
                mean = true.seconds(N, E, proto, 2.0, None if parent != parent else parent)
                for _ in range(6):  # log-normal packings of that mean
                    rows["N"].append(N)
                    rows["E"].append(E)
                    rows["exponent"].append(2.0)
                    rows["endgame"].append(endgame)
                    rows["parent_E"].append(parent)
                    rows["seconds"].append(mean * math.exp(s * rng.normal() - s * s / 2))
                    rows["group"].append("synthetic")
    got = fit({k: np.asarray(v, dtype=object if k in ("endgame", "group") else float) for k, v in rows.items()},
              L0=L0)
    cal = got.calibration
    assert cal.L0 == L0 and cal.sigma_task == pytest.approx(s, rel=0.15)
    for block, want in truth.items():
        values, cov = cal.blocks[block]
        err = np.sqrt(np.diag(cov))
        assert np.all(np.abs(values - want) < 4 * err + 0.01), (block, values, want, err)
        assert np.all(err < 0.1), (block, err)
    # the campaign's true total (the means) lies within the fitted estimate's interval
    cells = [(6, N, E, {}, 2.0, None) for N in (512, 2048) for E in energies]
    est = cal.estimate(cells)
    assert est.low < true.estimate(cells).seconds < est.high


def test_a_fit_without_data_for_a_block_keeps_the_starting_constants():
    base = packaged()
    rows = {"N": [512.0, 512.0, 1024.0], "E": [1e-6, 1e-6, 1e-6], "exponent": [2.0] * 3,
            "endgame": np.array(["none"] * 3, dtype=object), "parent_E": [math.nan] * 3,
            "seconds": [0.2, 0.3, 0.9], "group": np.array(["g"] * 3, dtype=object)}
    got = fit({k: np.asarray(v) for k, v in rows.items()}, base)
    for block in ("endgame", "ladder", "ladder_endgame"):
        np.testing.assert_array_equal(got.calibration.blocks[block][0], base.blocks[block][0])
    assert got.calibration.L0 == base.L0  # too few energies to choose L0: the base's


# ---------------------------------------------------------------------- the file

def test_the_packaged_calibration_reads_and_round_trips(tmp_path):
    cal = packaged()
    assert set(cal.blocks) == set(BLOCKS) and cal.sigma_task > 0 and cal.L0 > 0
    again = calibration.load(_write(tmp_path, cal))
    for b in BLOCKS:
        np.testing.assert_array_equal(again.blocks[b][0], cal.blocks[b][0])
    # bigger and colder cost more
    assert cal.seconds(2048, 1e-9) > cal.seconds(1024, 1e-9) > cal.seconds(1024, 1e-3) > 0
    assert cal.seconds(1024, 1e-9, {"force_tolerance": 1e-3}) < cal.seconds(1024, 1e-9)


def _bad(data):
    d = packaged().to_dict()
    data(d)
    return d


BAD = {
    "missing_key": lambda d: d.pop("sigma_task"),
    "missing_block": lambda d: d.pop("endgame"),
    "wrong_type": lambda d: d.__setitem__("L0", "seven"),
    "wrong_length": lambda d: d["fire"]["values"].pop(),
    "non_finite": lambda d: d["fire"]["values"].__setitem__(0, float("nan")),
    "negative_sigma": lambda d: d.__setitem__("sigma_systematic", -0.1),
    "negative_variance": lambda d: d["ladder"]["covariance"][0].__setitem__(0, -1.0),
    "zero_L0": lambda d: d.__setitem__("L0", 0),
    "unknown_version": lambda d: d.__setitem__("version", 99),
    "wrong_schema": lambda d: d.__setitem__("schema", "something/else"),
    "renamed_constants": lambda d: d["fire"].__setitem__("names", ["a", "b", "c", "d", "e"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_calibration_file_is_refused_with_exit_2(case, tmp_path, capsys, monkeypatch):
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_bad(BAD[case]), allow_nan=True))
    assert cli.main(["validate", str(spec), "--calibration", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and str(bad) in err and "not a usable cost calibration" in err, err
    # the same file named by the environment: every command that prices tasks refuses it
    monkeypatch.setenv(calibration.ENV, str(bad))
    assert cli.main(["validate", str(spec)]) == 2
    assert cli.main(["slurm", str(spec), "--out", str(tmp_path / "x.sbatch")]) == 2
    assert cli.main(["run", str(spec), "--out", str(tmp_path / "x.h5")]) == 2
    assert "not a usable cost calibration" in capsys.readouterr().err
    assert not (tmp_path / "x.h5").exists()  # refused before the store was made


@pytest.mark.parametrize("text", ["", "{", "[1, 2]", "null"])
def test_a_calibration_that_is_not_a_json_object_is_refused(text, tmp_path, capsys):
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    assert cli.main(["validate", str(spec), "--calibration", str(bad)]) == 2
    assert cli.main(["validate", str(spec), "--calibration", str(tmp_path / "missing.json")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "does not exist" in err


def test_the_environment_and_the_option_choose_the_calibration(tmp_path, monkeypatch):
    slow = _calibration()
    slow.blocks["fire"][0][0] += math.log(10.0)  # ten times slower
    path = _write(tmp_path, slow)
    tasks = expand(parse_spec(SPEC))
    default = estimate(tasks).seconds
    with calibration.using(path):
        assert estimate(tasks).seconds == pytest.approx(10 * default, rel=1e-9)
    assert estimate(tasks).seconds == pytest.approx(default, rel=1e-12)
    monkeypatch.setenv(calibration.ENV, str(path))
    assert estimate(tasks).seconds == pytest.approx(10 * default, rel=1e-9)
    assert task_cost(tasks[0]) == pytest.approx(slow.seconds(tasks[0].N, tasks[0].E), rel=1e-12)


# ---------------------------------------------------------------------- endgame: auto

def test_auto_picks_newton_by_the_documented_map():
    for N in (64, 256, 512, 1000, 1024, 2048, 4096, 8192):
        for k in range(3, 17):
            E = 10.0 ** -k
            want = any(N >= n_min and E <= e_max for n_min, e_max in spec_module.AUTO_NEWTON)
            assert auto_endgame(N, E) == ("newton" if want else "none"), (N, E)
    # closeness to jamming by the overlap: an alpha = 3 packing at E is a harmonic one at E2
    assert harmonic_energy(1e-9, 2.0) == 1e-9
    assert harmonic_energy(1e-21, 3.0) == pytest.approx((1.5e-21) ** (2 / 3))
    N, e_max = spec_module.AUTO_NEWTON[0]
    E3 = (2.0 / 3.0) * e_max ** 1.5  # harmonic_energy(E3, 3) == e_max
    assert auto_endgame(N, E3 * 0.99, 3.0) == "newton" and auto_endgame(N, E3 * 1.5, 3.0) == "none"


def test_auto_tasks_are_the_explicit_tasks_they_resolve_to(monkeypatch):
    """Same ids, seeds and payloads (protocol included) as the explicit FIRE or Newton task."""
    monkeypatch.setattr(spec_module, "AUTO_NEWTON", ((32, 1e-5),))  # Newton at N = 32, E = 1e-6 only
    auto = expand(parse_spec(SPEC + "protocol: {endgame: auto}\n"))
    fire = {(t.N, t.E, t.seed): t for t in expand(parse_spec(SPEC))}
    newton = {(t.N, t.E, t.seed): t for t in expand(parse_spec(SPEC + "protocol: {endgame: newton}\n"))}
    assert len(auto) == len(fire) == 12
    for t in auto:
        which = "newton" if (t.N, t.E) == (32, 1e-6) else "none"
        twin = (newton if which == "newton" else fire)[(t.N, t.E, t.seed)]
        assert (t.id, t.words, t.protocol, t.payload()) == (twin.id, twin.words, twin.protocol, twin.payload())
        assert dict(t.protocol).get("endgame", "none") == which
    # deterministic: the same spec expands to the same tasks (any launcher, any number of workers)
    assert [t.id for t in expand(parse_spec(SPEC + "protocol: {endgame: auto}\n"))] == [t.id for t in auto]
    # a ladder of auto tasks switches endgame along its chain and keeps its parents
    ladder = expand(parse_spec(SPEC + "protocol: {endgame: auto, start: ladder}\n"))
    assert [t.parent for t in ladder] == [t.parent for t in expand(parse_spec(SPEC + "protocol: {start: ladder}\n"))]


def test_auto_is_checked_like_newton_and_may_not_repeat_another_variant(monkeypatch):
    with pytest.raises(UserError, match="endgame 'auto' finishes the FIRE minimisations"):
        parse_spec(SPEC + "protocol: {endgame: auto, minimizer: cg}\n")
    monkeypatch.setattr(spec_module, "AUTO_NEWTON", ((32, 1e-5),))
    with pytest.raises(UserError, match=r"variant 'auto' repeats packings of 'default' at 3 \(N_G, E_G\)"):
        parse_spec(SPEC + "variants: [{name: auto, endgame: auto}]\n")
    with pytest.raises(UserError, match="variant 'auto' repeats packings of 'newton' at 1"):
        parse_spec(SPEC + "protocol: {force_tolerance: 1.0e-7}\n"
                   "variants: [{name: newton, endgame: newton}, {name: auto, endgame: auto}]\n")
    # where auto never coincides (another tolerance), both run
    parse_spec(SPEC + "variants: [{name: auto, endgame: auto, force_tolerance: 1.0e-7}]\n")
    assert resolve_protocol((("endgame", "auto"),), 32, 1e-6) == (("endgame", "newton"),)
    assert resolve_protocol((("endgame", "auto"), ("window", 0.1)), 16, 1e-6) == (("window", 0.1),)


# ---------------------------------------------------------------------- validate and slurm

BIG = """\
name: big
seed: 1
grid: {N_G: [512, 4096], E_G: [1.0e-3, 1.0e-13], seeds: 4}
observables: [scalars]
"""


def test_validate_states_the_interval_and_advises_auto(tmp_path, capsys):
    spec = tmp_path / "big.yaml"
    spec.write_text(BIG)
    # an endgame that costs half of FIRE's time everywhere: auto saves at its Newton cells
    cal = _write(tmp_path, _calibration(endgame=(math.log(0.5), 0, 0, 0)))
    assert cli.main(["validate", str(spec), "--calibration", str(cal)]) == 0
    out = capsys.readouterr().out
    assert "estimated cost " in out and "core-hours (" in out and ", 68%)" in out, out
    assert "advice: this campaign would cost" in out and "`endgame: auto`" in out and "% less" in out, out
    # an energy ladder too, by the ladder's own endgame factor (here half of the ladder's FIRE)
    ladder = _calibration()
    d, cov = ladder.blocks["ladder"]
    ladder.blocks["ladder_endgame"] = (d + np.array([math.log(0.5), 0, 0, 0]), cov)
    lad = _write(tmp_path, ladder, "ladder.json")
    spec.write_text(BIG + "protocol: {start: ladder}\n")
    assert cli.main(["validate", str(spec), "--calibration", str(lad)]) == 0
    out = capsys.readouterr().out
    assert "advice: this campaign would cost" in out and "`endgame: auto`" in out, out
    ladder.blocks["ladder_endgame"] = (d, cov)
    assert cli.main(["validate", str(spec), "--calibration", str(_write(tmp_path, ladder, "s.json"))]) == 0
    assert "advice:" not in capsys.readouterr().out  # a ladder endgame no cheaper: none
    spec.write_text(BIG)
    # an endgame no cheaper than FIRE: no advice
    same = _write(tmp_path, _calibration(), "same.json")
    assert cli.main(["validate", str(spec), "--calibration", str(same)]) == 0
    assert "advice:" not in capsys.readouterr().out
    # a campaign that asks for auto says what it resolved to
    spec.write_text(BIG + "protocol: {endgame: auto}\n")
    assert cli.main(["validate", str(spec), "--calibration", str(cal)]) == 0
    out = capsys.readouterr().out
    assert "endgame: auto in 'default': Newton for 4 of 16 packings (N_G/E_G 4096/1e-13)" in out, out


SCAN = BIG.replace("E_G: [1.0e-3, 1.0e-13]", "E_G: [1.0e-3, 1.0e-8, 1.0e-13]")


def test_validate_prices_the_fast_protocol_for_energy_scans(tmp_path, capsys):
    """A scan of three energies or more of independent FIRE packings is told what the ladder
    with endgame auto would cost: the estimate of that very campaign, and its price in A_G."""
    spec = tmp_path / "scan.yaml"
    cal = _write(tmp_path, _calibration())
    fast = estimate(expand(parse_spec(SCAN + "protocol: {start: ladder, endgame: auto}\n")), calibration.load(cal))
    fire = estimate(expand(parse_spec(SCAN)), calibration.load(cal))
    assert fast.seconds < 0.95 * fire.seconds
    spec.write_text(SCAN)
    assert cli.main(["validate", str(spec), "--calibration", str(cal)]) == 0
    out = capsys.readouterr().out
    assert (f"advice: this campaign scans 3 energies: the fast protocol (`start: ladder`, `endgame: auto`) "
            f"would cost {fast.seconds / 3600:.3g} core-hours instead of {fire.seconds / 3600:.3g}") in out, out
    assert "A_G about 0.001 lower" in out and "not for the finite-size table" in out
    # per variant; none for a ladder, CG, the shear cell, or two energies
    for extra in ("protocol: {start: ladder}\n", "protocol: {minimizer: cg}\n", "protocol: {cell: shear}\n"):
        spec.write_text(SCAN + extra)
        assert cli.main(["validate", str(spec), "--calibration", str(cal)]) == 0
        assert "fast protocol" not in capsys.readouterr().out, extra
    spec.write_text(BIG)
    assert cli.main(["validate", str(spec), "--calibration", str(cal)]) == 0
    assert "fast protocol" not in capsys.readouterr().out
    spec.write_text(SCAN + "variants: [{name: tight, force_tolerance: 1.0e-7}]\n")
    assert cli.main(["validate", str(spec), "--calibration", str(cal)]) == 0
    out = capsys.readouterr().out
    assert "advice: 'default' scans 3 energies" in out and "advice: 'tight' scans 3 energies" in out, out


def test_the_interval_widens_with_the_constants_errors():
    tasks = expand(parse_spec(BIG))
    tight = _calibration(sigma_sys=0.0)
    loose = Calibration(tight.L0, {**tight.blocks, "fire": (tight.blocks["fire"][0], np.eye(5) * 0.04)},
                        tight.sigma_task, 0.0)
    a, b = estimate(tasks, tight), estimate(tasks, loose)
    assert a.seconds == b.seconds and a.low < a.seconds < a.high
    assert b.high / b.seconds > a.high / a.seconds
    assert a.high * a.low == pytest.approx(a.seconds ** 2)


def test_slurm_prints_the_estimate_and_the_chain_it_needs(tmp_path, capsys):
    spec = tmp_path / "big.yaml"
    spec.write_text(BIG)
    cal = _write(tmp_path, _calibration())
    total = estimate(expand(parse_spec(BIG)), calibration.load(cal))
    assert cli.main(["slurm", str(spec), "--nodes", "1", "--ntasks-per-node", "2", "--time", "00:20:00",
                     "--out", str(tmp_path / "x.sbatch"), "--chain", "1", "--calibration", str(cal)]) == 0
    err = capsys.readouterr().err
    assert f"estimated {total.hours()} for 1 worker(s)" in err, err
    jobs = math.ceil(total.high / (20 * 60 - 60 - 150))  # usable per job: the limit, start-up, margin
    assert "advice: --chain" in err and "may stop short" in err if jobs > 1 else "1 job(s)" in err, err
    assert cli.main(["slurm", str(spec), "--time", "1-00:00:00", "--out", str(tmp_path / "y.sbatch"),
                     "--calibration", str(cal)]) == 0
    assert "is enough for one job at the upper estimate" in capsys.readouterr().err
