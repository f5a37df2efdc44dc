"""Variants compared with a reference packing by packing (campaign.results.tradeoff, campaign reduce)."""

from types import SimpleNamespace

import numpy as np
import pytest

from campaign.results import tradeoff
from helpers import LADDER_SPEC, FakeComm, synthetic_run


class _Fin(SimpleNamespace):
    def __len__(self):
        return len(self.N)


def _fin(rows):
    """A stand-in for reading.Finished from rows of (variant, N, E, seed, {scalar: value})."""
    names = sorted({k for r in rows for k in r[4]})
    return _Fin(variant=np.array([r[0] for r in rows], dtype=object), N=np.array([r[1] for r in rows]),
                E=np.array([r[2] for r in rows], float), seed=np.array([r[3] for r in rows]),
                scalars={n: np.array([r[4].get(n, np.nan) for r in rows], float) for n in names})


def _packings(rng, n_seeds=8, Ns=(32, 64), Es=(1e-6, 1e-4)):
    """Reference packings: random scalars with a realistic structure."""
    out = {}
    for N in Ns:
        for E in Es:
            for s in range(n_seeds):
                ng = int(N - rng.integers(0, 4))
                out[(N, E, s)] = {"A_G": 0.44 + 0.01 * rng.standard_normal(), "delta_Z": 0.05 * rng.random(),
                                  "psi_O": 0.36 + 0.02 * rng.standard_normal(), "N_G": ng,
                                  "N_C": 2 * (2 * ng - 1 + int(rng.integers(0, 3))),
                                  "force_evaluations": float(rng.integers(1000, 5000)), "jam_seconds": 0.01}
    return out


def test_a_known_shift_and_a_known_cost_are_measured_exactly():
    rng = np.random.default_rng(1)
    ref = _packings(rng)
    for k, v in ref.items():
        v["E_G"] = k[1] * 1.02
    rows = [("default", *k, dict(v)) for k, v in ref.items()]
    rows += [("fast", *k, dict(v, A_G=v["A_G"] + 0.003, force_evaluations=v["force_evaluations"] / 4,
                                 N_C=v["N_C"] + 2, E_G=k[1] * 1.07)) for k, v in ref.items()]
    recs, notes = tradeoff.compare(_fin(rows), {}, "default", n_boot=200)
    assert notes == []
    r0, r1 = recs
    assert r0["variant"] == "default" and r0["cost_ratio_fe"] == 1.0 and r0["dev_A_G"] == 0.0
    assert r1["n_pairs"] == len(ref)
    assert r1["cost_ratio_fe"] == pytest.approx(0.25, rel=1e-12)
    assert r1["dev_A_G"] == pytest.approx(0.003, rel=1e-9)
    assert r1["dev_A_G_err"] == pytest.approx(0.0, abs=1e-12)  # every pair differs by exactly the shift
    assert r1["dev_iso_excess"] == pytest.approx(1.0)  # one more contact (N_C counts it twice)
    assert r1["dev_delta_Z"] == 0.0 and r1["dev_psi_O"] == 0.0
    assert r1["dev_E_rel"] == pytest.approx(0.05, rel=1e-9)  # 7% into the window instead of 2%
    # the spread: pooled within-cell standard deviation of A_G over the reference's packings
    cells = {}
    for (N, E, s), v in ref.items():
        cells.setdefault((N, E), []).append(v["A_G"])
    ss = sum(((np.array(c) - np.mean(c)) ** 2).sum() for c in cells.values())
    dof = sum(len(c) - 1 for c in cells.values())
    assert r1["bias_rel_A_G"] == pytest.approx(0.003 / np.sqrt(ss / dof), rel=1e-9)
    assert r1["score"] >= abs(r1["bias_rel_A_G"])


def test_only_packings_done_in_both_are_compared():
    rng = np.random.default_rng(2)
    ref = _packings(rng)
    keys = sorted(ref)
    rows = [("default", *k, dict(ref[k])) for k in keys[::2]]  # the reference lacks half of them
    rows += [("v", *k, dict(ref[k], A_G=ref[k]["A_G"] + (0.01 if i % 2 else 0.0))) for i, k in enumerate(keys)]
    recs, _ = tradeoff.compare(_fin(rows), {}, "default", n_boot=0)
    v = recs[1]
    assert v["n_packings"] == len(keys) and v["n_pairs"] == len(keys[::2])
    assert v["dev_A_G"] == 0.0  # the shifted packings have no reference partner


def test_unusable_packings_count_in_the_cost_but_not_in_the_deviations():
    rng = np.random.default_rng(4)
    ref = _packings(rng)
    keys = sorted(ref)
    rows = [("default", *k, dict(ref[k])) for k in keys]
    # the variant: shifted by 0.002 where it converged; the unconverged ones are far off
    bad = {keys[1], keys[5], keys[6]}
    rows += [("v", *k, dict(ref[k], A_G=ref[k]["A_G"] + (0.5 if k in bad else 0.002),
                            force_evaluations=2 * ref[k]["force_evaluations"])) for k in keys]
    usable = np.array([not (r[0] == "v" and tuple(r[1:4]) in bad) for r in rows])
    usable[0] = False  # a reference packing left out: its pair is not compared either
    recs, _ = tradeoff.compare(_fin(rows), {}, "default", n_boot=0, usable=usable)
    r0, r1 = recs
    assert r0["n_excluded"] == 1 and r1["n_excluded"] == len(bad)
    assert r1["n_pairs"] == len(keys)
    assert r1["cost_ratio_fe"] == pytest.approx(2.0, rel=1e-12)  # every packing is paid for
    assert r1["dev_A_G"] == pytest.approx(0.002, rel=1e-9)  # none of the 0.5 shifts enters
    recs_all, _ = tradeoff.compare(_fin(rows), {}, "default", n_boot=0)
    assert recs_all[1]["n_excluded"] == 0 and recs_all[1]["dev_A_G"] > 0.01


def test_error_follows_the_noise_of_the_paired_differences():
    rng = np.random.default_rng(3)
    ref = _packings(rng, n_seeds=40, Ns=(32,), Es=(1e-6,))
    sigma = 0.01
    noise = sigma * rng.standard_normal(len(ref))
    rows = [("default", *k, dict(v)) for k, v in ref.items()]
    rows += [("noisy", *k, dict(v, psi_O=v["psi_O"] + d)) for (k, v), d in zip(ref.items(), noise)]
    r = tradeoff.compare(_fin(rows), {}, "default", n_boot=2000)[0][1]
    assert r["dev_psi_O"] == pytest.approx(noise.mean(), rel=1e-9)
    assert r["dev_psi_O_err"] == pytest.approx(noise.std(ddof=1) / np.sqrt(len(noise)), rel=0.15)


def test_pareto_front_and_table_deviations():
    rng = np.random.default_rng(4)
    ref = _packings(rng)
    rows = [("default", *k, dict(v)) for k, v in ref.items()]
    # (cost factor, A_G shift): "a" dominates "c" (cheaper and closer); "b" is cheapest
    for name, f, dA in (("a", 0.5, 0.001), ("b", 0.3, 0.01), ("c", 0.6, 0.002)):
        rows += [(name, *k, dict(v, A_G=v["A_G"] + dA, force_evaluations=v["force_evaluations"] * f))
                 for k, v in ref.items()]
    ex = {"default": {"A_G_star_E": 0.446, "A_G_star_E_err": 0.003},
          "a": {"A_G_star_E": 0.450, "A_G_star_E_err": 0.004}}
    recs, _ = tradeoff.compare(_fin(rows), ex, "default", n_boot=0)
    front = {r["variant"] for r in recs if r["on_front"]}
    assert front == {"default", "a", "b"}
    a = next(r for r in recs if r["variant"] == "a")
    assert a["dev_A_G_star_E"] == pytest.approx(0.004)
    assert a["dev_A_G_star_E_err"] == pytest.approx(0.005)
    assert np.isnan(next(r for r in recs if r["variant"] == "b")["dev_A_G_star_E"])
    text = tradeoff.table_markdown(recs)
    assert text.count("\n") == len(recs) + 1 and "default (ref)" in text
    assert all(line.count("|") == text.splitlines()[0].count("|") for line in text.splitlines())


def test_no_reference_no_comparison():
    rows = [("a", 16, 1e-3, 0, {"A_G": 0.4}), ("b", 16, 1e-3, 0, {"A_G": 0.41})]
    recs, notes = tradeoff.compare(_fin(rows), {}, "default")
    assert recs == [] and "reference variant 'default' has no finished packing" in notes[0]
    assert tradeoff.compare(_fin(rows[:1]), {}, "a") == ([], [])  # one variant: nothing to compare


def test_reduce_and_plot_a_campaign_with_variants(tmp_path, capsys, monkeypatch):
    """End to end: a synthetic campaign with a ladder variant, reduced and plotted by the CLI."""
    from campaign.cli import main
    from campaign.run.master import Master

    spec, tasks, ctx, store = synthetic_run(tmp_path, LADDER_SPEC)
    Master(FakeComm(ctx, 2), store, tasks).run()
    store.close()
    assert main(["reduce", str(tmp_path / "s.h5"), "--out", str(tmp_path / "red"), "--boot", "20"]) == 0
    out = capsys.readouterr().out
    assert "Variants against 'default'" in out and "| ladder |" in out
    csv = (tmp_path / "red" / "variants.csv").read_text().splitlines()
    assert csv[0].startswith("variant,reference,n_packings,n_excluded,n_pairs") and len(csv) == 3
    assert main(["reduce", str(tmp_path / "s.h5"), "--out", str(tmp_path / "red2"), "--reference", "ladder",
                 "--boot", "0"]) == 0
    assert "Variants against 'ladder'" in capsys.readouterr().out
    pytest.importorskip("matplotlib")
    from campaign.report import plots
    from campaign.results.reduce import Settings, reduce_campaign

    red = reduce_campaign([tmp_path / "s.h5"], Settings(n_boot=0), distributions=False)
    monkeypatch.setattr(plots, "FIGURES", {})  # only the campaign-wide figure
    written = plots.make_figures(red, tmp_path / "fig")
    assert [p.name for p in written] == ["pareto.png", "protocols.png"] and written[0].stat().st_size > 10_000
