"""The documentation site's pages: short, about the system as it is, all reachable, and the
generated reference pages true to the code (scripts/gen_docs.py; the site itself is built strictly
by `make docs`)."""

from __future__ import annotations

import dataclasses
import importlib.util
import re
import sys
from pathlib import Path
from types import ModuleType

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
MAX_LINES = 600


def _gen_docs() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gen_docs", ROOT / "scripts" / "gen_docs.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["gen_docs"] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def generated() -> dict[str, str]:
    """The generated reference pages, as the build writes them (path relative to docs/ -> text)."""
    gen = _gen_docs()
    return {path.relative_to(DOCS).as_posix(): text for path, text in gen.pages().items()}


@pytest.fixture(scope="module")
def pages(generated: dict[str, str]) -> dict[str, str]:
    """Every page of the site: the committed ones and the generated ones."""
    out = {p.relative_to(DOCS).as_posix(): p.read_text() for p in DOCS.rglob("*.md")}
    out.update(generated)
    return out


def _nav_paths(node: object) -> list[str]:
    if isinstance(node, str):
        return [node]
    if isinstance(node, list):
        return [p for item in node for p in _nav_paths(item)]
    if isinstance(node, dict):
        return [p for value in node.values() for p in _nav_paths(value)]
    return []


def test_no_page_over_the_line_limit(pages: dict[str, str]) -> None:
    long = {name: text.count("\n") + 1 for name, text in pages.items() if text.count("\n") + 1 > MAX_LINES}
    assert not long, f"pages over {MAX_LINES} lines (split them): {long}"


def test_pages_describe_the_system_not_its_history(pages: dict[str, str]) -> None:
    word = re.compile(r"\bsessions?\b", re.IGNORECASE)
    issue = re.compile(r"\bissues? \d+", re.IGNORECASE)
    found = [f"{name}:{i}: {line.strip()[:80]}" for name, text in pages.items()
             for i, line in enumerate(text.splitlines(), 1) if word.search(line) or issue.search(line)]
    assert not found, "pages that speak of sessions or issue numbers:\n" + "\n".join(found)


def test_every_page_is_in_the_nav(pages: dict[str, str]) -> None:
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    nav = _nav_paths(config["nav"])
    assert not (missing := sorted(set(nav) - set(pages))), f"nav entries without a page: {missing}"
    assert not (orphans := sorted(set(pages) - set(nav))), f"pages not reachable from the nav: {orphans}"


def test_readme_is_short_and_starts_with_the_two_commands() -> None:
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) < 200, f"README.md has {len(lines)} lines; the detail belongs on the site"
    commands = [line for line in lines if line.strip() and not line.startswith(("#", "```"))][:2]
    assert commands[0].startswith("make demo") and commands[1].startswith("make test"), commands


def test_cli_reference_lists_every_command(generated: dict[str, str]) -> None:
    from clients.cli import SUBCOMMANDS

    text = generated["reference/cli.md"] + generated["reference/cli-training.md"]
    for name in SUBCOMMANDS:
        assert f"## `govnesf {name}`" in text and f"usage: govnesf {name}" in text, name
    assert "### `govnesf sim record`" in text  # subcommands too


def test_config_reference_has_every_key_with_its_docstring(generated: dict[str, str]) -> None:
    """Every field of the node's config tree is a documented row; every training key is a row."""
    from mapper.node.config import NodeConfig
    from mapper.training.train import TrainConfig

    text = generated["reference/config.md"]
    rows = dict(re.findall(r"^\| `(\w+)` \| .*? \| .*? \| (.*) \|$", text, re.MULTILINE))
    queue: list[type] = [NodeConfig, TrainConfig]
    while queue:
        cls = queue.pop()
        for field in dataclasses.fields(cls):
            assert field.name in rows, f"{cls.__name__}.{field.name} missing from the config reference"
            if cls is not TrainConfig:
                documented = rows[field.name].strip() not in ("", "&nbsp;")
                assert documented, f"{cls.__name__}.{field.name} has no docstring"
            if field.default_factory is not dataclasses.MISSING:  # a sub-config: a TOML table
                value = field.default_factory()
                if dataclasses.is_dataclass(value):
                    queue.append(type(value))
                    assert f"### `[{field.name}]`" in text or f"`[{field.name}]`" in text, field.name
