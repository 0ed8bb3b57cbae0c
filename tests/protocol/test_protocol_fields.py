"""docs/reference/protocol.md's field tables equal the code's (`Class.FIELDS`), message for message.

A table whose header starts ``| key | type | unit | required |`` follows a line
``Fields of `Class` (... wire type `t` ...):`` (or ``Fields of `A` and `B` (...)``); a key cell
may name several keys (``width, height``) that share the other columns. Backticks and runs of
spaces are ignored. Compared per key: type, unit, required (the meaning column is prose).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from protocol.messages import MESSAGE_TYPES, Message, ObjectCandidate, QueryPoints

DOC = Path(__file__).resolve().parents[2] / "docs" / "reference" / "protocol.md"
COLUMNS = ["key", "type", "unit", "required"]
CLASSES: tuple[type[Message], ...] = (*MESSAGE_TYPES, ObjectCandidate)

Table = dict[str, tuple[str, str, str]]
"""wire key -> (type, unit, required)."""


def _norm(text: str) -> str:
    return " ".join(text.replace("`", "").split())


def _cells(line: str) -> list[str]:
    return [_norm(c) for c in line.strip().strip("|").split("|")]


def doc_tables(text: str) -> dict[str, tuple[Table, str]]:
    """Class name -> (its field table, the caption line) for every field table in `text`."""
    lines = text.splitlines()
    out: dict[str, tuple[Table, str]] = {}
    caption = ""
    i = 0
    while i < len(lines):
        if not lines[i].startswith("|"):
            if lines[i].strip():
                caption = lines[i].strip() if lines[i].startswith("Fields of ") else ""
            i += 1
            continue
        block = []
        while i < len(lines) and lines[i].startswith("|"):
            block.append(lines[i])
            i += 1
        header = _cells(block[0])
        if header[: len(COLUMNS)] != COLUMNS:
            continue  # another kind of table (error codes, size limits)
        assert caption, f"field table {block[0]!r} has no 'Fields of `Class` (...):' line before it"
        table: Table = {}
        for line in block[2:]:
            cells = _cells(line)
            assert len(cells) == len(header), f"{caption}: row {line!r} has {len(cells)} cells"
            for key in (k.strip() for k in cells[0].split(",")):
                assert key not in table, f"{caption}: key {key!r} listed twice"
                table[key] = (cells[1], cells[2], cells[3])
        names = re.findall(r"`(\w+)`", caption.partition(" (")[0])
        assert names, f"caption {caption!r} names no class"
        for name in names:
            assert name not in out, f"two field tables for {name}"
            out[name] = (table, caption)
        caption = ""
    return out


def code_table(cls: type[Message]) -> Table:
    """The wire keys of `cls`'s field table (Python-only attributes such as `Status.extra`
    have no key of their own and are not listed)."""
    rows = [f.row for f in cls.FIELDS if f.wire is not None]
    table = {key: (_norm(type_), _norm(unit), _norm(required)) for key, type_, unit, required in rows}
    assert len(table) == len(rows), f"{cls.__name__}: a wire key is declared twice"
    return table


def differences(code: Table, doc: Table) -> list[str]:
    out = [f"{key}: in the code, not in the doc {code[key]}" for key in sorted(code.keys() - doc.keys())]
    out += [f"{key}: in the doc, not in the code {doc[key]}" for key in sorted(doc.keys() - code.keys())]
    out += [
        f"{key}: code (type, unit, required) = {code[key]}, doc = {doc[key]}"
        for key in sorted(code.keys() & doc.keys())
        if code[key] != doc[key]
    ]
    return out


TABLES = doc_tables(DOC.read_text())


def test_every_message_has_exactly_one_doc_table() -> None:
    assert set(TABLES) == {cls.__name__ for cls in CLASSES}


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_doc_table_equals_code_table(cls: type[Message]) -> None:
    doc, caption = TABLES[cls.__name__]
    assert f"`{cls.TYPE}`" in caption, f"{caption!r} should name the wire type `{cls.TYPE}`"
    problems = differences(code_table(cls), doc)
    assert not problems, f"docs/reference/protocol.md vs {cls.__name__}.FIELDS:\n" + "\n".join(problems)


def test_a_key_missing_on_either_side_is_reported() -> None:
    code = code_table(QueryPoints)
    doc = dict(TABLES["QueryPoints"][0])
    assert differences(code, doc) == []
    del doc["objects"]  # a field in the code the doc does not list
    doc["limit"] = ("int", "", "no")  # and one the doc lists that the code does not have
    doc["texts"] = ("[str]", "", "yes")  # and a row that disagrees
    problems = differences(code, doc)
    assert len(problems) == 3
    assert problems[0].startswith("objects: in the code") and problems[1].startswith("limit: in the doc")
    assert problems[2].startswith("texts: code")


def test_parser_reads_captions_and_shared_rows() -> None:
    text = "\n".join([
        "Fields of `Save` and `Load` (requests, wire types `save` and `load`):",
        "",
        "| key | type | unit | required | meaning |",
        "|---|---|---|---|---|",
        "| a, b | int >= 0 | `px` | if `c` | x |",
        "",
        "| code | when |",
        "|---|---|",
        "| x | y |",
    ])
    tables = doc_tables(text)
    assert set(tables) == {"Save", "Load"}
    assert tables["Save"][0] == {"a": ("int >= 0", "px", "if c"), "b": ("int >= 0", "px", "if c")}
    with pytest.raises(AssertionError, match="no 'Fields of"):
        doc_tables("\n".join(text.splitlines()[2:]))
