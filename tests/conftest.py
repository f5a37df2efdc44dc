"""Shared test set-up: the tests' own modules (``references``: the oracles, ``helpers``: packing
makers, fakes and store readers, ``synthetic_store``) are importable by their plain names from
every test module, whichever import mode pytest runs with. No test module imports another
(``tests/test_docs.py``)."""

import sys
from pathlib import Path

TESTS = str(Path(__file__).resolve().parent)
if TESTS not in sys.path:
    sys.path.insert(0, TESTS)
