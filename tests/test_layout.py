"""The tests mirror the source: each subpackage of ``mapper`` is tested under
``tests/mapper/<subpackage>/`` (``test_<behaviour>.py``, in subfolders where the subpackage has them),
so "where is X tested" has one answer.

The test folders hold no ``__init__.py`` (``pythonpath = ["."]`` in pyproject.toml; tests import each
other as ``tests.mapper.runtime.test_model_runtime``), so pytest imports every test file by its basename:
two files of the same name anywhere under tests/ would fail the collection.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TESTS = ROOT / "tests"

SUBPACKAGES = ("map", "kernels", "node", "runtime", "model", "geometry", "ov", "training")
"""The subpackages of ``mapper`` whose tests live in a folder of their own."""


@pytest.mark.parametrize("name", SUBPACKAGES)
def test_each_mapper_subpackage_has_its_test_folder(name: str) -> None:
    assert (ROOT / "mapper" / name / "__init__.py").is_file(), f"mapper/{name} is not a subpackage"
    folder = TESTS / "mapper" / name
    assert folder.is_dir(), f"mapper/{name} has no test folder {folder.relative_to(ROOT)}"
    assert sorted(folder.rglob("test_*.py")), f"{folder.relative_to(ROOT)} holds no test file"


def test_test_file_basenames_are_unique() -> None:
    counts = Counter(path.name for path in TESTS.rglob("test_*.py"))
    assert counts["test_layout.py"] == 1  # the walk sees the test files
    assert [name for name, n in counts.items() if n > 1] == []


def test_no_init_files_under_tests() -> None:
    assert sorted(p.relative_to(ROOT).as_posix() for p in TESTS.rglob("__init__.py")) == []
