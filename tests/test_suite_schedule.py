"""The suite's module schedule (tests/conftest.py): longest modules first, each module's tests in their own order."""
from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import conftest

TESTS = os.path.dirname(os.path.abspath(__file__))


def test_every_scheduled_module_exists():
    present = {f[:-3] for f in os.listdir(TESTS) if f.startswith("test_") and f.endswith(".py")}
    assert set(conftest.MODULE_SECONDS) <= present, set(conftest.MODULE_SECONDS) - present


def test_modules_run_longest_first_and_keep_their_tests_in_order():
    names = ["test_spatial", "test_tune", "test_unlisted", "test_api", "test_tune"]
    items = [SimpleNamespace(path=Path(TESTS) / f"{n}.py", n=i) for i, n in enumerate(names)]
    conftest.pytest_collection_modifyitems(None, None, items)
    assert [(i.path.stem, i.n) for i in items] == [("test_tune", 1), ("test_tune", 4), ("test_api", 3),
                                                    ("test_spatial", 0), ("test_unlisted", 2)]
