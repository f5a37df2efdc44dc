"""Hostile and broken input: `campaign validate` on mutated specs, `campaign analyze` on
mutated configuration files. Every run must end in time with exit 0 (valid) or 2 (a
user error, one message, no traceback); never a hang, a traceback or exit 1.

Most runs go through the CLI's ``main()`` in this process, under a timer that raises
if a run takes too long; a few go through real subprocesses.
"""

from __future__ import annotations

import io
import math
import os
import signal
import subprocess
import sys
import time
import zipfile
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from campaign import cli

ROOT = Path(__file__).resolve().parents[2]
LIMIT = 10.0  # seconds any one run may take ("a few seconds"; generous for a shared machine)
FAST = settings(max_examples=40, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

BASE = {
    "name": "hostile",
    "seed": 7,
    "system": {"box": [1.0, 1.0], "species": [{"name": "A", "fraction": 0.5, "radius": 1.4},
                                              {"name": "B", "fraction": 0.5, "radius": 1.0}],
               "potential": {"exponent": 2.0}},
    "grid": {"N_G": [16, 32], "E_G": [1.0e-3, 1.0e-6], "seeds": 3},
    "protocol": {"force_tolerance": 1.0e-6},
    "variants": [{"name": "loose", "force_tolerance": 1.0e-3}],
    "observables": ["scalars", "connectivity"],
    "store": {"configurations": False},
    "run": {"retries": 1},
}


class Slow(Exception):
    pass


@contextmanager
def time_limit(seconds):
    def fire(signum, frame):
        raise Slow(f"took more than {seconds} s")

    old = signal.signal(signal.SIGALRM, fire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def run_cli(argv):
    """(exit code, stderr, seconds) of one in-process CLI run under the time limit."""
    err, out = io.StringIO(), io.StringIO()
    t0 = time.monotonic()
    with time_limit(LIMIT), redirect_stderr(err), redirect_stdout(out):
        code = cli.main(argv)
    return code, err.getvalue(), time.monotonic() - t0


def assert_clean(code, err):
    assert code in (0, 2), (code, err)
    assert "Traceback" not in err and "internal error" not in err, err
    if code == 2:
        assert err.strip(), "exit 2 without a message"


# ----------------------------------------------------------------------------- specs

def _paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


PATHS = list(_paths(BASE))[1:]

weird_numbers = st.one_of(
    st.integers(min_value=-(10 ** 30), max_value=10 ** 30),
    st.sampled_from([0, -1, 2 ** 63, 2 ** 64 + 1, 10 ** 300, 10 ** 7, 10 ** 9]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e308, 5e-324, -0.0]),
)
scalars = st.one_of(weird_numbers, st.none(), st.booleans(), st.text(max_size=40),
                    st.sampled_from(["", "ñ", "日本語", "\u202e", "\x00", "🙂" * 10, "a" * 300]))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=3)),
                      max_leaves=12)


def _set(obj, path, value):
    import copy

    obj = copy.deepcopy(obj)
    if not path:
        return value
    cur = obj
    for k in path[:-1]:
        cur = cur[k]
    cur[path[-1]] = value
    return obj


def _delete(obj, path):
    import copy

    obj = copy.deepcopy(obj)
    cur = obj
    for k in path[:-1]:
        cur = cur[k]
    del cur[path[-1]]
    return obj


@st.composite
def mutated_specs(draw):
    spec = BASE
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["value", "value", "delete", "key", "nest"]))
        paths = list(_paths(spec))[1:]
        path = draw(st.sampled_from(paths))
        try:
            if kind == "value":
                spec = _set(spec, path, draw(values))
            elif kind == "delete":
                spec = _delete(spec, path)
            elif kind == "key":
                parent = path[:-1]
                target = spec
                for k in parent:
                    target = target[k]
                if isinstance(target, dict):
                    spec = _set(spec, parent + (draw(st.text(min_size=1, max_size=12)),), draw(values))
            else:  # nest the value deeper
                depth = draw(st.integers(1, 40))
                target = spec
                for k in path:
                    target = target[k]
                for _ in range(depth):
                    target = [target]
                spec = _set(spec, path, target)
        except (KeyError, IndexError, TypeError):
            pass
    text = yaml.safe_dump(spec, allow_unicode=True, sort_keys=False, width=10 ** 6)
    # textual mutations YAML dumping cannot produce: duplicate keys, anchors, junk
    tweak = draw(st.sampled_from(["none", "none", "dup", "anchor", "junk", "bytes"]))
    lines = text.splitlines()
    if tweak == "dup" and lines:
        k = draw(st.integers(0, len(lines) - 1))
        lines.insert(k, lines[k])
    elif tweak == "anchor" and len(lines) > 2:
        lines[1] = lines[1] + " &x" if ":" not in lines[1] else lines[1].replace(":", ": &x", 1)
    elif tweak == "junk":
        k = draw(st.integers(0, len(lines)))
        lines.insert(k, draw(st.text(max_size=30)))
    text = "\n".join(lines) + "\n"
    if tweak == "bytes":
        raw = bytearray(text.encode("utf-8", "surrogatepass"))
        for _ in range(draw(st.integers(1, 5))):
            if raw:
                raw[draw(st.integers(0, len(raw) - 1))] = draw(st.integers(0, 255))
        return bytes(raw)
    return text.encode("utf-8", "surrogatepass")


@settings(FAST, max_examples=80)
@given(data=mutated_specs())
def test_validate_exits_0_or_2_in_time_on_mutated_specs(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("spec") / "s.yaml"
    path.write_bytes(data)
    code, err, _ = run_cli(["validate", str(path)])
    assert_clean(code, err)


def test_the_base_spec_is_valid(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump(BASE))
    code, err, _ = run_cli(["validate", str(p)])
    assert code == 0, err


HOSTILE = {
    "billion_laughs": (ROOT / "tests" / "bad_specs" / "billion_laughs.yaml").read_bytes(),
    "deep_flow": b"name: x\nseed: 1\ngrid: " + b"[" * 5000 + b"]" * 5000 + b"\n",
    "deep_block": b"name: x\nseed: 1\n" + b"".join(b" " * k + b"k%d:\n" % k for k in range(3000)),
    "huge_int": b"name: x\nseed: " + b"9" * 100000 + b"\ngrid: {N_G: [16], E_G: [1.0e-3], seeds: 1}\n",
    "nan_inf": b"name: x\nseed: 1\ngrid: {N_G: [.nan], E_G: [.inf, -.inf], seeds: .nan}\n",
    "random_bytes": bytes(np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8)),
    "max_tasks": b"name: x\nseed: 1\ngrid: {N_G: [16], E_G: [1.0e-3], seeds: 10000001}\n",
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(HOSTILE))
def test_hostile_spec_in_a_real_process(tmp_path, name):
    p = tmp_path / "s.yaml"
    p.write_bytes(HOSTILE[name])
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "campaign", "validate", str(p)], capture_output=True, text=True,
                       timeout=60, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and r.stderr.startswith("campaign validate: error:")
    assert time.monotonic() - t0 < 30


# ----------------------------------------------------------------------------- configurations

GOOD_TEXT = "4.0 4.0\n" + "".join(f"{x} {y} 0.55\n" for x, y in ((0.5, 0.5), (2.5, 0.5), (0.5, 2.5), (2.5, 2.5)))


def _npz_bytes(**arrays):
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _h5_bytes(tmp, **arrays):
    p = tmp / "x.h5"
    with h5py.File(p, "w") as f:
        for k, v in arrays.items():
            f[k] = v
    return p.read_bytes()


numbers_text = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr),
                         st.integers(-(10 ** 400), 10 ** 400).map(str),
                         st.sampled_from(["nan", "inf", "-inf", "1e999", "0x10", "", "  ", "ñ", "1,5", "#"]))


@st.composite
def config_files(draw, tmp):
    kind = draw(st.sampled_from(["text", "text", "random", "npz", "npz_cut", "h5", "h5_cut"]))
    rng = np.random.default_rng(draw(st.integers(0, 2 ** 32 - 1)))
    if kind == "random":
        suffix = draw(st.sampled_from([".txt", ".npz", ".h5", ""]))
        return suffix, bytes(rng.integers(0, 256, draw(st.integers(0, 3000)), dtype=np.uint8))
    if kind == "text":
        lines = GOOD_TEXT.splitlines()
        for _ in range(draw(st.integers(1, 3))):
            k = draw(st.integers(0, len(lines) - 1))
            cols = lines[k].split()
            if cols:
                cols[draw(st.integers(0, len(cols) - 1))] = draw(numbers_text)
            if draw(st.booleans()):
                cols = cols[: draw(st.integers(0, len(cols)))]
            lines[k] = " ".join(cols)
        return ".txt", ("\n".join(lines) + "\n").encode("utf-8", "surrogatepass")
    n = draw(st.integers(0, 6))
    pos = rng.random((n, 2)) * 4
    rad = np.full(n, 0.5)
    box = np.array([4.0, 4.0])
    bad = draw(st.sampled_from(["none", "nan", "shape", "dtype", "missing", "huge"]))
    arrays = {"positions": pos, "radii": rad, "box": box}
    if bad == "nan" and n:
        arrays["positions"][0, 0] = np.nan
    elif bad == "shape":
        arrays["positions"] = rng.random((n, 3))
    elif bad == "dtype":
        arrays["radii"] = np.array(["a"] * n)
    elif bad == "missing":
        del arrays[draw(st.sampled_from(sorted(arrays)))]
    elif bad == "huge":
        arrays["box"] = np.array([1e308, 1e308])
    if kind.startswith("npz"):
        data = _npz_bytes(**arrays)
        suffix = ".npz"
    else:
        data = _h5_bytes(tmp, **arrays)
        suffix = ".h5"
    if kind.endswith("_cut"):
        data = data[: draw(st.integers(0, max(0, len(data) - 1)))]
    return suffix, data


@pytest.fixture(scope="module")
def warm_kernels(tmp_path_factory):
    """Compile (or load from the cache) the analysis kernels before any timed run."""
    p = tmp_path_factory.mktemp("warm") / "c.txt"
    p.write_text(GOOD_TEXT)
    assert cli.main(["analyze", str(p), "--json"]) == 0


@FAST
@given(data=st.data())
def test_analyze_exits_0_or_2_in_time_on_broken_configurations(tmp_path_factory, warm_kernels, data):
    tmp = tmp_path_factory.mktemp("cfg")
    suffix, raw = data.draw(config_files(tmp))
    path = tmp / f"c{suffix}"
    path.write_bytes(raw)
    code, err, _ = run_cli(["analyze", str(path), "--json"])
    assert_clean(code, err)


@pytest.mark.slow
def test_analyze_of_a_truncated_npz_and_hdf5_in_a_real_process(tmp_path):
    arrays = {"positions": np.array([[0.5, 0.5], [2.5, 2.5]]), "radii": np.array([0.5, 0.5]),
              "box": np.array([4.0, 4.0])}
    for name, data in (("c.npz", _npz_bytes(**arrays)), ("c.h5", _h5_bytes(tmp_path, **arrays))):
        p = tmp_path / name
        p.write_bytes(data[: len(data) // 2])
        r = subprocess.run([sys.executable, "-m", "campaign", "analyze", str(p), "--json"], capture_output=True,
                           text=True, timeout=60, env=dict(os.environ, PYTHONPATH=str(ROOT)))
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
