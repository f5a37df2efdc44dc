"""Readers refuse what does not match what was written (docs/STORE.md, "Block checksums").

Two real small stores (synthetic tasks, blocks of 4 rows; one keeps configurations and has failed tasks).
The quick suite moves one chunk of one column a block off its place in the first store's chunk index:
the readers that read that column refuse it (exit 2, the paragraph naming it), the others read what they
read before, `verify` names it. The sweeps below are slow.
Damage: a bit of a chunk key's row offset in every chunk-index node of the file (HDF5's version-1
B-trees: the chunk is then listed off its place, or its block reads as never written), and single-bit
flips at random offsets (a fixed seed). After each: `status --json`, `reduce --json`, `export` (CSV; and
XYZ, `analyze` of a configuration for the store that keeps them) and `verify`. No traceback, exit codes
as documented (0 or 2 for the readers, 2 only with the damaged store's paragraph; 0 or 1 for verify), and
no reader exits 0 with an output other than the clean store's.

The same chunk-index damage in stores as 0.2.7 wrote them, without block checksums (tests/data): no
traceback from any reader, nor from `verify --repair`; what a reader refuses and every block of task
identities that is not the spec's, `verify` finds; most of the rest reads silently (nothing recorded
what the rows were: that is what the block checksums add); and once `verify --repair` added their
checksums, none of it reads silently.
"""

import contextlib
import io
import random
import shutil
import struct
from pathlib import Path

import h5py
import numpy as np
import pytest

from campaign import cli
from helpers import DAMAGE_SPEC

BLOCK = 4
SPECS = {
    "plain": """\
name: dmg
seed: 21
grid: {N_G: [16, 24, 32], E_G: [1.0e-3, 1.0e-5], seeds: 6}
observables: [scalars, connectivity]
bins: {z_g: {range: [-0.5, 12.5], count: 13}, z_v: {range: [2.5, 12.5], count: 10}}
""",
    "configs": DAMAGE_SPEC,
}


def _cli(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli.main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module", params=list(SPECS))
def store(request, tmp_path_factory):
    import campaign.storage.store

    d = tmp_path_factory.mktemp(request.param)
    (d / "s.yaml").write_text(SPECS[request.param])
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(campaign.storage.store, "BLOCK_ROWS", BLOCK)
        mp.setenv("CAMPAIGN_SYNTHETIC_FAIL", "seed:1" if request.param == "configs" else "none")
        code, _, err = _cli("run", d / "s.yaml", "--out", d / "ref.h5", "--launcher", "inline", "--task-function",
                            "synthetic", "--quiet")
        assert code == 0, err
    with h5py.File(d / "ref.h5", "r") as f:
        group = "/configurations/" + sorted(f["configurations"])[0] if "configurations" in f else None
    clean = _readers(d / "ref.h5", d / "clean", group)
    assert all(code == 0 for code, _, _ in clean.values()), clean
    return d / "ref.h5", group, clean


def _readers(path, out, group):
    """Exit code, output and error output of every reader of ``path``: 0, or 2 with the paragraph of a
    damaged store (naming it, and `campaign verify` for the rest), never a traceback."""
    out = Path(out)
    out.mkdir(exist_ok=True)
    got = {}
    code, text, err = _cli("status", path, "--json")
    got["status"] = (code, text, err)
    code, text, err = _cli("reduce", path, "--json", "--boot", "0", "--out", out / "red")
    got["reduce"] = (code, text, err)
    csv = out / "x.csv"
    code, _, err = _cli("export", path, "--out", csv)
    got["export"] = (code, csv.read_bytes() if code == 0 else b"", err)
    if group is not None:
        xyz = out / "x.xyz"
        code, _, err = _cli("export", path, "--out", xyz)
        got["xyz"] = (code, xyz.read_bytes() if code == 0 else b"", err)
        code, text, err = _cli("analyze", path, "--group", group)
        got["analyze"] = (code, text.replace(str(path), "STORE"), err)
    for k, (code, value, err) in got.items():
        assert "Traceback" not in err, (k, err)
        assert code in (0, 2), (k, code, err)
        assert code == 0 or (f"error: {path} is damaged: " in err and f"`campaign verify {path}`" in err), (k, err)
    return got


def _status_figures(text):
    import json

    s = json.loads(text)
    for k in ("writer", "file"):
        s.pop(k, None)
    return json.dumps({k: v for k, v in s.items() if "time" not in k and "ago" not in k and k != "progress"},
                      sort_keys=True)


def _silent(clean, got):
    """Readers that exited 0 with another output than the clean store's."""
    bad = []
    for k, (code, value, _) in got.items():
        if code != 0:
            continue
        want = clean[k][1]
        if k == "status":
            value, want = _status_figures(value), _status_figures(want)
        if value != want:
            bad.append(k)
    return bad


def chunk_keys(data):
    """Offsets of a chunk key's row offset in every chunk-index node (v1 B-tree, type 1) in the
    file's bytes: the middle key of each node (the first of a node of one)."""
    out = []
    pos = data.find(b"TREE")
    while pos >= 0:
        kind, used = data[pos + 4], struct.unpack_from("<H", data, pos + 6)[0]
        if kind == 1 and used:
            for rank in (1, 2):
                key = 8 + 8 * (rank + 1)
                first = pos + 24
                offs = [first + i * (key + 8) + 8 for i in range(used + 1)]
                if offs[-1] + 8 * (rank + 1) > len(data):
                    continue
                rows = [struct.unpack_from("<Q", data, o)[0] for o in offs[:-1]]
                tail = [struct.unpack_from("<Q", data, o + 8 * rank)[0] for o in offs[:-1]]
                if all(r % BLOCK == 0 and r < 1 << 20 for r in rows) and not any(tail) and rows == sorted(rows):
                    out.append(offs[used // 2])
                    break
        pos = data.find(b"TREE", pos + 4)
    return out


def _flip(ref, p, offset, bit):
    """A copy ``p`` of the store ``ref`` with bit ``bit`` of byte ``offset`` flipped."""
    shutil.copy(ref, p)
    with open(p, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ (1 << bit)]))


def _trial(ref, group, clean, tmp, offset, bit, report=False):
    """Every reader and `verify` (its exit status; with ``report``, its report too) on a copy of ``ref``
    with one bit flipped."""
    p = tmp / "d.h5"
    _flip(ref, p, offset, bit)
    got = _readers(p, tmp / "o", group)
    code, out, err = _cli("verify", p, *(() if report else ("--quiet",)))
    assert code in (0, 1) and "Traceback" not in err, (offset, bit, code, err)
    return (got, code, out) if report else (got, code)


def chunk_index_node(data, chunks):
    """In the file's bytes ``data``: the chunk-index node (v1 B-tree, type 1, a leaf) of a dataset of rank
    1 whose chunks lie at the file addresses ``chunks``, as the offsets of each of its keys' row offset."""
    key = 8 + 8 * 2  # chunk size, filter mask; the row offset and the element offset
    pos = data.find(b"TREE")
    while pos >= 0:
        kind, level, used = data[pos + 4], data[pos + 5], struct.unpack_from("<H", data, pos + 6)[0]
        if kind == 1 and level == 0 and used:
            keys = [pos + 24 + i * (key + 8) for i in range(used)]
            children = [struct.unpack_from("<Q", data, k + key)[0] for k in keys]
            if sorted(children) == sorted(chunks):
                return [k + 8 for k in keys]
        pos = data.find(b"TREE", pos + 4)
    raise AssertionError("no chunk-index node lists those chunks")


def _plain_store(tmp_path, monkeypatch):
    """The "plain" spec's store (blocks of ``BLOCK`` rows, no failed task), run inline into tmp_path."""
    import campaign.storage.store

    monkeypatch.setattr(campaign.storage.store, "BLOCK_ROWS", BLOCK)
    monkeypatch.setenv("CAMPAIGN_SYNTHETIC_FAIL", "none")
    (tmp_path / "s.yaml").write_text(SPECS["plain"])
    ref = tmp_path / "ref.h5"
    code, _, err = _cli("run", tmp_path / "s.yaml", "--out", ref, "--launcher", "inline", "--task-function",
                        "synthetic", "--quiet")
    assert code == 0, err
    return ref


def test_a_chunk_listed_a_block_off_its_place_is_refused(tmp_path, monkeypatch):
    """The quick suite's damage: a small store (blocks of 4 rows) whose chunk index lists one chunk of
    scalars/A_G a block off its place (rows 16-19 where 20-23 are). The readers of that column,
    `reduce` and `export`, refuse the store: exit 2, the paragraph naming scalars/A_G and `campaign
    verify`; `status` reads what it read before; `verify` names the column (exit 1)."""
    ref = _plain_store(tmp_path, monkeypatch)
    clean = _readers(ref, tmp_path / "clean", None)
    assert all(code == 0 for code, _, _ in clean.values()), clean
    with h5py.File(ref, "r") as f:
        ds = f["scalars/A_G"]
        chunks = {ds.id.get_chunk_info(i).chunk_offset[0]: ds.id.get_chunk_info(i).byte_offset
                  for i in range(ds.id.get_num_chunks())}
    keys = chunk_index_node(ref.read_bytes(), list(chunks.values()))
    assert len(keys) == len(chunks) == 9  # 36 tasks
    rows = {struct.unpack_from("<Q", ref.read_bytes(), k)[0]: k for k in keys}
    assert sorted(rows) == sorted(chunks)
    damaged = tmp_path / "d.h5"
    _flip(ref, damaged, rows[16], int(np.log2(BLOCK)))  # the key of rows 16-19 now says 20-23
    got = _readers(damaged, tmp_path / "o", None)
    for reader in ("reduce", "export"):
        code, _, err = got[reader]
        assert code == 2 and "scalars/A_G" in err, (reader, code, err)
    assert got["status"][0] == 0 and not _silent(clean, got), _silent(clean, got)
    code, out, err = _cli("verify", damaged)
    assert code == 1 and "scalars/A_G" in out, (code, out, err)


@pytest.mark.slow
def test_every_chunk_index_damaged(store, tmp_path):
    """In every chunk-index node, one chunk key's row offset moved by one block (a chunk listed off its
    place): no reader exits 0 with another output than the clean store's, and what a reader refuses,
    verify names."""
    ref, group, clean = store
    keys = chunk_keys(Path(ref).read_bytes())
    assert len(keys) >= 10
    refused = 0
    bit = int(np.log2(BLOCK))
    for off in keys:
        got, verify = _trial(ref, group, clean, tmp_path, off, bit)
        assert not _silent(clean, got), (off, bit, _silent(clean, got), got)
        if any(code == 2 for code, _, _ in got.values()):
            refused += 1
            assert verify == 1, (off, bit)
    print("chunk-index damage:", len(keys), "nodes,", refused, "refused by a reader, 0 silent")
    assert refused >= len(keys) // 2  # most of it changes what a reader reads: all of that is refused


@pytest.mark.slow
def test_random_flips(store, tmp_path):
    ref, group, clean = store
    size = Path(ref).stat().st_size
    rng = random.Random(45)
    refused = 0
    for _ in range(25):
        off, bit = rng.randrange(size), rng.randrange(8)
        got, verify = _trial(ref, group, clean, tmp_path, off, bit)
        assert not _silent(clean, got), (off, bit, _silent(clean, got))
        refused += any(code == 2 for code, _, _ in got.values())
    print("random flips refused by a reader:", refused)


# --------------------------------------------------------------------------- stores written before block checksums

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module", params=["configs", "plain"])
def old_store(request, tmp_path_factory):
    """A store as 0.2.7 wrote it (the same specs, no block checksums: tests/data/v027_stores.py), and a copy
    that `campaign verify --repair` wrote anew with them; every reader gives the two the same outputs."""
    d = tmp_path_factory.mktemp("v027-" + request.param)
    for name in ("old", "new"):
        for suffix in ("", ".journal"):
            shutil.copy(DATA / f"v027-{request.param}.h5{suffix}", d / f"{name}.h5{suffix}")
    with h5py.File(d / "old.h5", "r") as f:
        assert "checksums" not in f and "block_checksums" not in f.attrs and f.attrs["package_version"] == "0.2.7"
        group = "/configurations/" + sorted(f["configurations"])[0] if "configurations" in f else None
    clean = _readers(d / "old.h5", d / "clean-old", group)
    assert all(code == 0 for code, _, _ in clean.values()), clean
    code, out, err = _cli("verify", d / "new.h5", "--repair")
    assert code == 0 and "PROTECTED: wrote" in out and "cannot be found" in out, (code, out, err)
    with h5py.File(d / "new.h5", "r") as f:
        assert "checksums" in f and f.attrs["block_checksums"].startswith("added")
    upgraded = _readers(d / "new.h5", d / "clean-new", group)
    assert not _silent(clean, upgraded), _silent(clean, upgraded)
    return d / "old.h5", d / "new.h5", group, clean


def _identities(path):
    """The task table's identity columns as read, and as the spec stored in the file gives them (None
    for a column that cannot be read)."""
    from campaign.plan.parse import parse_spec
    from campaign.plan.tasks import expand

    with h5py.File(path, "r") as f:
        tasks = expand(parse_spec(f.attrs["spec_yaml"]))
        want = {"id": [t.id for t in tasks], "variant": [t.variant for t in tasks], "N": [t.N for t in tasks],
                "E": [t.E for t in tasks], "seed": [t.seed for t in tasks]}
        got = {}
        for col in want:
            try:
                v = f[f"tasks/{col}"][:]
                got[col] = [x.decode().rstrip("\0") for x in v] if v.dtype.kind == "S" else v.tolist()
            except Exception:  # noqa: BLE001 - an index that cannot be read at all
                got[col] = None
    return got, want


@pytest.mark.slow
def test_v027_store_chunk_index_damaged(old_store, tmp_path):
    """A store without block checksums, one chunk key's row offset moved by a block in every chunk-index
    node: no reader ends in a traceback, a reader refuses only the paragraph of a damaged store, and
    `verify --repair`, which adds the checksums, ends with its report (0 or 1), never a traceback. What
    a reader refuses, `verify` finds; and every block of the task table whose identities (read here)
    are not the spec's (expanded here), `verify` finds and names. The rest mostly reads silently:
    nothing recorded what the rows were (the counts are printed; what a store with block checksums
    makes of the same damage, test_every_chunk_index_damaged asserts)."""
    old, _, group, clean = old_store
    keys = chunk_keys(Path(old).read_bytes())
    assert len(keys) >= 10
    refused = silent = found = identities = 0
    for off in keys:
        got, verify, report = _trial(old, group, clean, tmp_path, off, int(np.log2(BLOCK)), report=True)
        if any(code == 2 for code, _, _ in got.values()):
            refused += 1
            assert verify == 1, (off, report)
        ids, want = _identities(tmp_path / "d.h5")
        for col in want:
            if ids[col] != want[col]:
                identities += 1
                assert verify == 1 and f"tasks/{col}" in report, (off, col, report)
        silent += bool(_silent(clean, got))
        found += verify == 1
        code, out, err = _cli("verify", tmp_path / "d.h5", "--repair", "--quiet")
        assert code in (0, 1) and "Traceback" not in err, (off, code, err)
        assert code == 1 or "PROTECTED: wrote" in out, (off, out)
    assert identities, "no damage reached the task table's identities: the check above checked nothing"
    print(f"0.2.7 store, chunk-index damage: {len(keys)} nodes, {refused} refused by a reader, {identities} "
          f"identity column(s) read from another place, all found by verify; {silent} silent, {found} found "
          "by verify, 0 tracebacks")


@pytest.mark.slow
def test_upgraded_store_chunk_index_damaged(old_store, tmp_path):
    """The same store once `verify --repair` added its block checksums: chunk-index damage in every node is
    refused or changes nothing a reader reads, as in a store written with them."""
    _, new, group, clean = old_store
    keys = chunk_keys(Path(new).read_bytes())
    assert len(keys) >= 10
    refused = 0
    for off in keys:
        got, verify = _trial(new, group, clean, tmp_path, off, int(np.log2(BLOCK)))
        assert not _silent(clean, got), (off, _silent(clean, got), got)
        if any(code == 2 for code, _, _ in got.values()):
            refused += 1
            assert verify == 1, off
    print(f"upgraded 0.2.7 store, chunk-index damage: {len(keys)} nodes, {refused} refused by a reader, 0 silent")
    assert refused >= len(keys) // 2


def test_damage_seen_while_a_run_writes_is_read_again(tmp_path, monkeypatch):
    """A reader that meets a block of rows and its checksum mid-flush (a run writes the store) reads
    again before it believes the damage: `status` reads a store whose tasks/wall checksum is wrong for
    the first second, then right again (as a writer's flush leaves it), while the progress file says a
    run (this process) writes it; with the checksum left wrong it says damaged after its retries; with
    no run writing, the first read is final (no retry)."""
    import json
    import os
    import threading

    import campaign.storage.reader
    from campaign.storage.progress import Progress

    ref = _plain_store(tmp_path, monkeypatch)
    clean = _cli("status", ref, "--json")
    with h5py.File(ref, "r") as f:
        ds = f["checksums/tasks.wall"]
        assert ds.compression is None and not ds.fletcher32
        at = ds.id.get_offset() if ds.chunks is None else ds.id.get_chunk_info(0).byte_offset
    sleeps = []
    real_sleep = campaign.storage.reader.time.sleep
    monkeypatch.setattr(campaign.storage.reader.time, "sleep", lambda s: (sleeps.append(s), real_sleep(s)))

    def damage(path):  # one bit of the first block's checksum, flipped (twice: restored)
        fd = os.open(path, os.O_RDWR)
        try:
            b = os.pread(fd, 1, at)
            os.pwrite(fd, bytes([b[0] ^ 0x10]), at)
        finally:
            os.close(fd)

    store = tmp_path / "live.h5"
    shutil.copy(ref, store)
    damage(store)
    assert _cli("status", store, "--json")[0] == 2 and not sleeps  # no run writes it: believed at once
    Progress(36, sidecar=Path(str(store) + ".progress.json"), stream=io.StringIO(), enabled=False).write_sidecar()
    fix = threading.Timer(1.0, damage, (store,))
    fix.start()
    try:
        code, text, err = _cli("status", store, "--json")
    finally:
        fix.join()
    assert code == 0, err
    live, before = json.loads(text), json.loads(clean[1])
    assert live["live"] and not before["live"]
    assert sleeps and _status_figures(text).replace('"per_hour": null', "") == \
        _status_figures(clean[1]).replace(f'"per_hour": {before["per_hour"]}', "").replace('"live": false', '"live": true')
    damage(store)  # left damaged: believed after the retries
    sleeps.clear()
    code, _, err = _cli("status", store, "--json")
    assert code == 2 and "tasks/wall" in err and len(sleeps) == 9, (code, err, sleeps)
