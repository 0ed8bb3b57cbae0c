"""Every ``>>>`` example in protocol/, mapper/ and clients/ runs (one test per module).

The modules are found by walking the source: any module whose file contains ``>>>`` is imported by
its dotted name and its docstring examples run under doctest with ELLIPSIS and
NORMALIZE_WHITESPACE. A module whose examples are all marked ``# doctest: +SKIP`` (they need
weights or checkpoints a test run does not have) is reported as skipped; a module whose ``>>>``
doctest cannot see (not in a docstring) fails, so an example never silently stops running.
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("protocol", "mapper", "clients")
OPTIONS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def modules_with_examples() -> list[str]:
    """Dotted names of the project modules whose source contains ``>>>``, sorted."""
    names = []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            if ">>>" not in path.read_text(encoding="utf-8"):
                continue
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            elif (path.with_suffix("") / "__init__.py").is_file():
                continue  # a package of the same name shadows this file: it cannot be imported
            names.append(".".join(parts))
    return sorted(names)


MODULES = modules_with_examples()


def test_discovery_finds_the_known_modules() -> None:
    assert len(MODULES) >= 20
    for name in ("protocol.messages", "mapper.checks", "mapper.map.global_map", "clients.colors"):
        assert name in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name: str) -> None:
    module = importlib.import_module(name)
    tests = [t for t in doctest.DocTestFinder().find(module) if t.examples]
    assert tests, f"{name} contains '>>>' but doctest finds no example (is it outside a docstring?)"
    runner = doctest.DocTestRunner(optionflags=OPTIONS)
    report: list[str] = []
    for test in tests:
        runner.run(test, out=report.append)
    failed = f"{runner.failures} of {runner.tries} examples failed in {name}:\n"
    assert runner.failures == 0, failed + "".join(report)
    if runner.tries == 0:
        pytest.skip(f"every example in {name} is marked +SKIP")
