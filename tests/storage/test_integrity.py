"""A damaged store is found, named and repaired (docs/STORE.md, "Checksums, verify and repair").

Damage is a flipped byte at a known place of a finished store (a compressed chunk of a scalar or a
histogram, a configuration's contiguous positions, a failure record's text, a status byte, a task id
chunk), found with h5py's low-level API; or at random offsets. Every reader must say "damaged" and
point at `campaign verify`; `campaign verify` must name the part and its tasks (exit 1); `--repair`
then `campaign run` must give a store equal, dataset by dataset and bit for bit, to a run that was
never damaged (run-dependent columns aside: wall time, rank, host, timings).
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from campaign import cli
from helpers import DAMAGE_SPEC, assert_same_contents, store_contents

ROOT = Path(__file__).resolve().parents[2]
SPEC = DAMAGE_SPEC
FAIL = "seed:1"  # the synthetic tasks of seed 1 fail: the store has failure records
BLOCK = 4        # rows per chunk in these tests (256 in real stores): 24 tasks make 6 blocks
def cli_run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err, err
    return code, out, err


def synth_run(capsys, spec, out):
    return cli_run(capsys, "run", spec, "--out", out, "--launcher", "inline", "--task-function", "synthetic",
                   "--quiet")


@pytest.fixture
def blocks(monkeypatch):
    import campaign.storage.store

    monkeypatch.setattr(campaign.storage.store, "BLOCK_ROWS", BLOCK)
    monkeypatch.setenv("CAMPAIGN_SYNTHETIC_FAIL", FAIL)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A finished synthetic store (6 blocks of 4 rows, configurations, 8 failed tasks)."""
    import campaign.storage.store

    d = tmp_path_factory.mktemp("ref")
    (d / "s.yaml").write_text(SPEC)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(campaign.storage.store, "BLOCK_ROWS", BLOCK)
        mp.setenv("CAMPAIGN_SYNTHETIC_FAIL", FAIL)
        assert cli.main(["run", str(d / "s.yaml"), "--out", str(d / "ref.h5"), "--launcher", "inline",
                         "--task-function", "synthetic", "--quiet"]) == 0
    return d / "s.yaml", d / "ref.h5"


def flip(path, offset, bit=4):
    with open(path, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ (1 << bit)]))


def chunk_middle(path, name, row):
    with h5py.File(path, "r") as f:
        ds = f[name]
        info = ds.id.get_chunk_info_by_coord((row,) + (0,) * (ds.ndim - 1))
    return info.byte_offset + info.size // 2


def status_and_ids(path):
    with h5py.File(path, "r") as f:
        return f["tasks/status"][:], [x.decode() for x in f["tasks/id"][:]]


def damage(path, kind):
    """Flip a byte of ``kind``; returns (the damaged object's name, the rows a repair must drop)."""
    st, ids = status_and_ids(path)
    if kind == "scalars":
        flip(path, chunk_middle(path, "scalars/A_G", 4))
        return "scalars/A_G", [r for r in range(4, 8) if st[r]]
    if kind == "histogram":
        flip(path, chunk_middle(path, "histograms/z_v/counts", 8))
        return "histograms/z_v/counts", [r for r in range(8, 12) if st[r]]
    if kind == "configuration":
        row = int(np.flatnonzero(st == 1)[5])
        with h5py.File(path, "r") as f:
            ds = f[f"configurations/{ids[row]}/positions"]
            off = ds.id.get_offset() + ds.id.get_storage_size() // 2
        flip(path, off)
        return f"configurations/{ids[row]}", [row]
    if kind == "failure":
        row = int(np.flatnonzero(st == 2)[2])
        text = f"synthetic failure of task {ids[row]}".encode()
        data = Path(path).read_bytes()
        assert data.count(text) == 2  # its message and traceback attributes: both enter its checksum
        flip(path, data.index(text) + 4, bit=0)
        return f"failures/{ids[row]}", [row]
    if kind == "status":
        row = int(np.flatnonzero(st == 1)[3])
        with h5py.File(path, "r") as f:
            off = f["tasks/status"].id.get_offset() + row
        flip(path, off, bit=1)  # done (1) reads as 3
        return "tasks/status", [row]
    if kind == "identity":
        flip(path, chunk_middle(path, "tasks/id", 12))
        return "tasks/id", []  # rewritten from the spec: no task is lost
    if kind == "name":
        data = Path(path).read_bytes()
        assert data.count(b"\x00sigma_max\x00") == 1  # the link name in the scalars group's heap
        flip(path, data.index(b"\x00sigma_max\x00") + 1, bit=0)  # 's' reads as 'r': still a valid name
        return "scalars/rigma_max", []  # renamed back by a repair: no task is lost
    raise ValueError(kind)


READERS = {  # which commands read what each damage touches (they must then say "damaged")
    "scalars": ("reduce", "export-csv", "export-xyz"),
    "histogram": ("reduce",),
    "configuration": ("export-xyz", "analyze"),
    "failure": ("status",),
    "status": (),
    "identity": ("status", "reduce", "export-csv"),
    "name": (),
}


def reader_argv(kind, path, tmp, ids, rows):
    return {"reduce": ["reduce", path, "--boot", "0", "--out", tmp / "red"],
            "export-csv": ["export", path, "--out", tmp / "x.csv"],
            "export-xyz": ["export", path, "--out", tmp / "x.xyz"],
            "analyze": ["analyze", path, "--group", f"/configurations/{ids[rows[0]] if rows else ids[0]}"],
            "status": ["status", path]}[kind]


@pytest.mark.parametrize("kind", list(READERS))
def test_damage_is_found_named_and_repaired(reference, blocks, tmp_path, capsys, kind):
    spec, ref = reference
    path = tmp_path / "d.h5"
    shutil.copy(ref, path)
    name, rows = damage(path, kind)
    _, ids = status_and_ids(ref)

    code, out, _ = cli_run(capsys, "verify", path)
    assert code == 1 and "DAMAGED" in out and name in out, out
    for r in rows[:3]:
        assert ids[r] in out  # the tasks it holds are named
    report = json.loads(cli_run(capsys, "verify", path, "--json")[1])
    assert not report["ok"] and any(d["object"] == name for d in report["damage"])
    assert report["tasks_lost"] == len(rows) and report["repairable"]

    for reader in READERS[kind]:
        code, _, err = cli_run(capsys, *reader_argv(reader, path, tmp_path, ids, rows))
        assert code == 2 and "is damaged" in err and "campaign verify" in err, (reader, err)
        assert "try again" not in err and name in err, (reader, err)
    assert not (tmp_path / "x.xyz").exists()  # a failed export leaves nothing

    code, out, _ = cli_run(capsys, "verify", path, "--repair")
    assert code == 0 and "REPAIRED" in out, out
    st, _ = status_and_ids(path)
    ref_st, _ = status_and_ids(ref)
    assert [int(r) for r in np.flatnonzero(st != ref_st)] == rows  # exactly those rows are pending again
    assert all(st[r] == 0 for r in rows)
    assert cli_run(capsys, "verify", path)[0] == 0

    code, _, err = synth_run(capsys, spec, path)
    assert code == 0 and f"this run: {sum(ref_st[r] == 1 for r in rows)} done" in err
    assert cli_run(capsys, "verify", path)[0] == 0
    assert_same_contents(store_contents(path), store_contents(ref))


def test_checksums_are_written(reference):
    from campaign.storage.checksums import config_crc, failure_crc

    _, ref = reference
    with h5py.File(ref, "r") as f:
        blocks = [f[f"tasks/{n}"] for n in ("id", "variant", "N", "E", "seed", "attempts", "wall", "rank", "host",
                                            "error")]
        blocks += [f[f"scalars/{n}"] for n in f["scalars"]]
        blocks += [f[f"histograms/{h}/{k}"] for h in f["histograms"] for k in ("counts", "edges")]
        assert all(ds.fletcher32 for ds in blocks)
        assert len(f["configurations"]) == 16 and len(f["failures"]) == 8
        for g in f["configurations"].values():
            assert int(g.attrs["crc32"]) == config_crc({k: g[k][()] for k in g})
        for g in f["failures"].values():
            assert int(g.attrs["crc32"]) == failure_crc(dict(g.attrs))


def test_a_run_meeting_a_damaged_chunk_stops_and_loses_nothing(reference, blocks, tmp_path, capsys):
    """A run adding rows to a block whose chunk fails its checksum stops (exit 2, no traceback) before
    writing it back; the journal keeps what it finished; repair + rerun gives the reference."""
    from campaign.plan.parse import parse_spec
    from campaign.storage.store import Store
    from campaign.plan.tasks import expand
    from campaign.run.worker import SyntheticTask, run_task

    spec_path, ref = reference
    spec = parse_spec(spec_path.read_text())
    tasks = expand(spec)
    fn = SyntheticTask()
    ctx = dict(spec.worker_context(), task_function="synthetic", configurations=True)
    edges = fn.histogram_edges(ctx)
    ctx["edges"] = edges
    path = tmp_path / "p.h5"
    firsts = [i for i in range(len(tasks)) if i % BLOCK == 0 and tasks[i].parent is None]
    st = Store(path, spec, tasks, edges)
    for i in firsts:
        st.record(i, run_task(fn, dict(tasks[i].payload(), attempt=1), ctx, rank=1), attempts=1)
    st.close()
    flip(path, chunk_middle(path, "scalars/A_G", firsts[1]))
    st = Store(path, spec, tasks, edges)
    i = firsts[1] + 1
    st.record(i, run_task(fn, dict(tasks[i].payload(), attempt=1), ctx, rank=1), attempts=1)
    from campaign.errors import StoreDamaged

    with pytest.raises(StoreDamaged, match="scalars/A_G.*verify .*--repair"):
        st.flush(force=True)
    st.abandon()
    assert cli_run(capsys, "verify", path, "--repair")[0] == 0
    code, _, err = synth_run(capsys, spec_path, path)  # replays the journal (task i), recomputes the rest
    assert code == 0, err
    assert_same_contents(store_contents(path), store_contents(ref))


def test_verify_refuses_while_a_run_writes_and_foreign_files(reference, tmp_path, capsys):
    from campaign.storage.journal import Journal

    _, ref = reference
    path = tmp_path / "d.h5"
    shutil.copy(ref, path)
    flip(path, chunk_middle(path, "scalars/A_G", 0))
    lock = Journal(Path(str(path) + ".journal"))  # as a run holds it
    try:
        code, _, err = cli_run(capsys, "verify", path, "--repair")
        assert code == 2 and "another run is writing" in err
    finally:
        lock.close()
    (tmp_path / "t.h5").write_text("not a store")
    code, _, err = cli_run(capsys, "verify", tmp_path / "t.h5")
    assert code == 2 and "not a readable HDF5 file" in err
    with h5py.File(tmp_path / "x.h5", "w") as f:
        f["data"] = [1, 2]
    code, _, err = cli_run(capsys, "verify", tmp_path / "x.h5")
    assert code == 2 and "not a campaign store" in err
    assert cli_run(capsys, "verify", tmp_path / "none.h5")[0] == 2
    data = bytearray(ref.read_bytes())
    data[40:48] = b"\xff" * 8  # the superblock's addresses
    (tmp_path / "sb.h5").write_bytes(bytes(data))
    code, out, _ = cli_run(capsys, "verify", tmp_path / "sb.h5", "--repair")
    assert code == 1 and "cannot be opened as HDF5" in out and "a repair cannot recover it" in out
    code, _, err = cli_run(capsys, "status", tmp_path / "sb.h5")
    assert code == 2 and "is damaged" in err


def test_stores_without_checksums_still_read(blocks, tmp_path, capsys, monkeypatch):
    """A store written before checksums (CAMPAIGN_NO_CHECKSUMS=1 writes one) reads everywhere; verify says
    what carries none, and still finds damage that deflate's own check sees."""
    (tmp_path / "s.yaml").write_text(SPEC)
    path = tmp_path / "old.h5"
    monkeypatch.setenv("CAMPAIGN_NO_CHECKSUMS", "1")
    assert synth_run(capsys, tmp_path / "s.yaml", path)[0] == 0
    monkeypatch.delenv("CAMPAIGN_NO_CHECKSUMS")
    with h5py.File(path, "r") as f:
        assert not f["scalars/A_G"].fletcher32 and "crc32" not in next(iter(f["configurations"].values())).attrs
    code, out, _ = cli_run(capsys, "verify", path)
    assert code == 0 and "carry no checksums" in out and "OK" in out
    report = json.loads(cli_run(capsys, "verify", path, "--json")[1])
    bare = report["without_checksums"]
    assert bare["configurations"] == 16 and bare["failures"] == 8 and "scalars/A_G" in bare["datasets"]
    for argv in (["status", path], ["reduce", path, "--boot", "0", "--out", tmp_path / "r"],
                 ["export", path, "--out", tmp_path / "o.xyz"]):
        assert cli_run(capsys, *argv)[0] == 0
    assert synth_run(capsys, tmp_path / "s.yaml", path)[0] == 0  # resumes (nothing left to do)
    flip(path, chunk_middle(path, "histograms/z_v/counts", 8))
    code, out, _ = cli_run(capsys, "verify", path)
    assert code == 1 and "histograms/z_v/counts rows 8-11" in out


def test_a_scalar_added_by_a_writer_keeping_no_list_is_not_damage(reference, tmp_path, capsys):
    """An earlier version of the program resuming a store adds scalars without listing them."""
    from campaign.storage.checksums import write_scalar_names

    _, ref = reference
    path = tmp_path / "d.h5"
    shutil.copy(ref, path)
    with h5py.File(path, "r+") as f:
        write_scalar_names(f["scalars"], [n for n in f["scalars"] if n != "sigma_max"])
    assert cli_run(capsys, "verify", path)[0] == 0
    with h5py.File(path, "r+") as f:
        write_scalar_names(f["scalars"], list(f["scalars"]) + ["psi_X"])  # listed, but not there
    code, out, _ = cli_run(capsys, "verify", path)
    assert code == 1 and "lists 'psi_X', which it does not hold" in out


TRIALS = 30
HARNESS = r"""
import contextlib, io, json, os, random, shutil, sys
import h5py, numpy as np
import campaign.storage.store
from campaign import cli
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(sys.argv[1]))))  # tests/, for helpers
campaign.storage.store.BLOCK_ROWS = int(sys.argv[6])
ref, spec, d, n, seed = sys.argv[2], sys.argv[3], sys.argv[4], int(sys.argv[5]), int(sys.argv[7])
from helpers import DAMAGE_SPEC, assert_same_contents, store_contents
with h5py.File(ref, "r") as f:
    tid = sorted(f["configurations"])[0]
size, rng, want = os.path.getsize(ref), random.Random(seed), store_contents(ref)
for k in range(n):
    p = os.path.join(d, f"t{k}.h5")
    shutil.copy(ref, p)
    off, bit = rng.randrange(size), rng.randrange(8)
    with open(p, "r+b") as fh:
        fh.seek(off); b = fh.read(1); fh.seek(off); fh.write(bytes([b[0] ^ (1 << bit)]))
    res = {"offset": off}
    runs = ["run", spec, "--out", p, "--launcher", "inline", "--task-function", "synthetic", "--quiet"]
    for name, argv in (("verify", ["verify", p, "--quiet"]), ("status", ["status", p]),
                       ("reduce", ["reduce", p, "--boot", "0", "--out", p + "_r"]),
                       ("xyz", ["export", p, "--out", p + ".xyz"]),
                       ("analyze", ["analyze", p, "--group", "/configurations/" + tid]), ("run", runs),
                       ("repair", ["verify", p, "--repair", "--quiet"]), ("rerun", runs), ("verify2", ["verify", p])):
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = cli.main(argv)
            except SystemExit as exc:
                code = exc.code
        res[name] = [code, err.getvalue()[-2000:], out.getvalue()[-2000:]]
    if res["verify2"][0] == 0:
        try:
            assert_same_contents(store_contents(p), want)
            res["same"] = True
        except AssertionError as exc:
            res["same"] = str(exc)
    print(json.dumps(res), flush=True)
    for x in os.listdir(d):
        q = os.path.join(d, x)
        shutil.rmtree(q) if os.path.isdir(q) else os.unlink(q)
"""


@pytest.mark.slow
def test_random_byte_flips_never_crash_and_repair_restores(reference, tmp_path):
    """30 single-bit flips at random offsets of a finished store. Every command exits 0, 1 or 2, with a
    message when not 0 and never a traceback; the process never dies (a segfault would end it early).
    Wherever verify finds the store repairable, --repair and a rerun give back the reference store."""
    spec, ref = reference
    (tmp_path / "w").mkdir()
    env = dict(os.environ, CAMPAIGN_SYNTHETIC_FAIL=FAIL, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-c", HARNESS, __file__, ref, spec, tmp_path / "w", str(TRIALS), str(BLOCK),
                        "2024"], env=env, capture_output=True, text=True, timeout=600)
    trials = [json.loads(line) for line in p.stdout.splitlines() if line.startswith("{")]
    assert p.returncode == 0 and len(trials) == TRIALS, (p.returncode, p.stderr[-3000:])
    found = 0
    for t in trials:
        for name, (code, err, out) in ((k, v) for k, v in t.items() if isinstance(v, list)):
            assert code in (0, 1, 2), (t["offset"], name, code, err)
            assert "Traceback" not in err, (t["offset"], name, err)
            assert code == 0 or (err + out).strip(), (t["offset"], name)
            if code == 2:
                assert "try again" not in err, (t["offset"], name, err)
        found += t["verify"][0] == 1
        if t["repair"][0] == 0:
            assert t["verify2"][0] == 0 and t.get("same") is True, (t["offset"], t.get("same"), t["verify2"])
        else:
            assert "cannot" in t["repair"][2], (t["offset"], t["repair"])
    assert found >= 5  # a fair share of the flips hit something that matters


REAL_SPEC = """\
name: integreal
seed: 7
grid: {N_G: [16, 24], E_G: [1.0e-4], seeds: 2}
observables: [scalars, connectivity]
store: {configurations: true}
"""


def _campaign(*argv, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("CAMPAIGN_TASK_FUNCTION", None)
    p = subprocess.run([sys.executable, "-m", "campaign", *map(str, argv)], cwd=cwd, env=env, capture_output=True,
                       text=True, timeout=300)
    assert "Traceback" not in p.stderr, p.stderr
    return p.returncode, p.stdout, p.stderr


@pytest.mark.slow
def test_real_campaign_damaged_found_by_every_reader_and_repaired(tmp_path):
    """The kernels' packings, in real processes: a flipped byte in a configuration's positions (contiguous,
    uncompressed) and one in a compressed chunk of scalars/A_G. Before checksums, export and reduce gave the
    damaged packing out as good, or told the user to try again."""
    (tmp_path / "s.yaml").write_text(REAL_SPEC)
    ref, path = tmp_path / "ref.h5", tmp_path / "d.h5"
    assert _campaign("run", "s.yaml", "--out", ref, "--launcher", "inline", "--quiet", cwd=tmp_path)[0] == 0
    shutil.copy(ref, path)
    shutil.copy(str(ref) + ".journal", str(path) + ".journal")
    st, ids = status_and_ids(path)
    with h5py.File(path, "r") as f:
        ds = f[f"configurations/{ids[1]}/positions"]
        off = ds.id.get_offset() + ds.id.get_storage_size() // 2
    flip(path, off)
    code, out, err = _campaign("export", path, "--format", "xyz", "--out", "x.xyz", cwd=tmp_path)
    assert code == 2 and f"configurations/{ids[1]} does not match its checksum" in err and "campaign verify" in err
    code, out, err = _campaign("analyze", path, "--group", f"/configurations/{ids[1]}", cwd=tmp_path)
    assert code == 2 and "is damaged" in err
    flip(path, chunk_middle(path, "scalars/A_G", 0))
    code, out, err = _campaign("reduce", path, "--boot", "0", cwd=tmp_path)
    assert code == 2 and "scalars/A_G rows 0-3" in err and "fails its checksum" in err and "try again" not in err
    code, out, _ = _campaign("verify", path, cwd=tmp_path)
    assert code == 1 and "scalars/A_G rows 0-3" in out and f"configurations/{ids[1]}" in out
    assert "4 finished task(s) cannot be trusted" in out
    code, out, _ = _campaign("verify", path, "--repair", cwd=tmp_path)
    assert code == 0 and "4 task(s) are pending again" in out
    code, _, err = _campaign("run", "s.yaml", "--out", path, "--launcher", "inline", "--quiet", cwd=tmp_path)
    assert code == 0 and "this run: 4 done" in err
    assert _campaign("verify", path, cwd=tmp_path)[0] == 0
    assert_same_contents(store_contents(path), store_contents(ref))


def test_a_gpu_store_written_before_0_3_hashes_to_its_own_spec():
    """A store of 0.2.x with a `device: gpu` variant holds the first GPU block, which no protocol key
    named: its stored spec is read without the `gpu_block` key the present parser adds (else every
    such store verified as DAMAGED, data/gpu-equivalence-large.h5 among them), and a store of 0.3.0
    or later with it, so the two blocks' packings keep apart task ids."""
    from campaign.plan.parse import parse_spec
    from campaign.plan.spec import GPU_BLOCK
    from campaign.storage.layout import stored_spec

    text = ("name: g\nseed: 1\ngrid: {N_G: [64], E_G: [1.0e-6], seeds: 1}\n"
            "variants:\n  - {name: gpu, device: gpu}\n")
    old = parse_spec(text, first_gpu_block=True)
    new = parse_spec(text)
    assert old.hash != new.hash
    assert dict(v[:2] for v in new.canonical()["variants"])["gpu"]["gpu_block"] == GPU_BLOCK
    assert "gpu_block" not in dict(v[:2] for v in old.canonical()["variants"])["gpu"]
    for version, want in (("0.2.7", old.hash), ("0.1.0", old.hash), ("0.3.0", new.hash), ("0.4.0", new.hash),
                          (None, new.hash)):
        attrs = {"spec_yaml": text} | ({"package_version": version} if version else {})
        assert stored_spec(attrs).hash == want, version
