"""Shared test set-up.

* The tests' own modules (``references``: the oracles, ``helpers``: packing makers, fakes and
  store readers, ``synthetic_store``) are importable by their plain names from every test
  module, whichever import mode pytest runs with. No test module imports another
  (``tests/project/test_docs.py``).
* The quick suite and the full one: ``python -m pytest`` runs the tests not marked ``slow``
  (the README's test command: minutes); ``--full`` runs every test (``.ci/run``: the SLURM
  cluster, the full-disk and orphan runs, the CUDA simulator and the PTX compile, the long
  sweeps). ``-m EXPR`` selects by marker as usual (``-m slow``: the slow ones alone).
* One numba cache for the whole run: ``NUMBA_CACHE_DIR`` (unless set) is the checkout's
  ``.numba-cache``, inherited by every ``campaign`` subprocess a test starts, so that a kernel
  is compiled once per run, not once in this process and again in each subprocess (whose
  default is ``~/.cache/jamming-campaign/numba``). Tests of cold compilation give their
  subprocesses a directory of their own. Set here, before any test module imports numba.
"""

import os
import sys
from pathlib import Path

TESTS = str(Path(__file__).resolve().parent)
if TESTS not in sys.path:
    sys.path.insert(0, TESTS)

ROOT = Path(TESTS).parent
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))


def pytest_addoption(parser):
    parser.addoption("--full", action="store_true", default=False,
                     help="run every test, the ones marked slow too (as .ci/run does)")


def pytest_collection_modifyitems(config, items):
    """Without ``--full`` or ``-m``, leave out the tests marked ``slow`` (deselected, counted
    in pytest's closing line)."""
    if config.getoption("--full") or config.option.markexpr:
        return
    slow = [item for item in items if item.get_closest_marker("slow") is not None]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if item.get_closest_marker("slow") is None]
