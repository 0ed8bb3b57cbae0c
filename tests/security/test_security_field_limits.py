"""Per-field limits, read from docs/reference/protocol.md's "Size limits" table and checked at the boundary:
a message exactly at each documented limit decodes, one step beyond it is ``bad_request``, and
the node answers both (no internal error)."""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "protocol"))

from protocol_samples import frame  # noqa: E402

from mapper.node.config import config_from_dict  # noqa: E402
from mapper.node.service import MapperNode  # noqa: E402
from protocol.errors import ProtocolError  # noqa: E402
from protocol.messages import Error, Message, decode  # noqa: E402

DOC = (Path(__file__).resolve().parents[2] / "docs" / "reference" / "protocol.md").read_text()
TABLE = DOC[DOC.index("## Size limits") :].split("\n\n")[0]


def _row(name: str) -> str:
    for line in TABLE.splitlines():
        if line.startswith(f"| {name} |"):
            return line
    raise AssertionError(f"no {name!r} row in the Size limits table of docs/reference/protocol.md")


def _numbers(pattern: str, row: str) -> tuple[int, ...]:
    found = re.search(pattern, row)
    assert found, (pattern, row)
    return tuple(int(g) for g in found.groups())


IMAGE_MAX = _numbers(r"1\.\.(\d+)", _row("image width/height"))[0]
OV_SIDE_MAX, OV_DIM_MAX = _numbers(r"1\.\.(\d+) / 1\.\.(\d+)", _row("`ov` h, w / d"))
TEXTS_MAX, NEGATIVES_MAX, TEXT_CHARS_MAX = _numbers(
    r"1\.\.(\d+) `texts`, 0\.\.(\d+) `negatives`, each 1\.\.(\d+) characters", _row("prompts")
)
MAP_NAME_MAX, CAMERA_MAX, ID_MAX = _numbers(
    r"\{1,(\d+)\}`; camera / ov_space 1\.\.(\d+) characters; string ids <= (\d+)", _row("names")
)
ROBOT_MAX = _numbers(r"\{0,(\d+)\}", _row("robot names"))[0]


def _image_frame(width: int) -> dict[str, Any]:
    rgb = np.zeros((1, width, 3), np.uint8)
    return {
        "width": width,
        "height": 1,
        "rgb": {"encoding": "rgb8", "data": rgb.tobytes()},
        "K": [1.0, 1.0, 0.5, 0.5],
    }


def _ov(h: int, w: int, d: int, space: str = "minilm-l6-v2") -> dict[str, Any]:
    data = np.zeros((h, w, d), np.float16).tobytes()
    return {"ov": {"dtype": "float16", "shape": [h, w, d], "data": data}, "ov_space": space}


BASE_FRAME = frame().to_wire()
CASES: list[tuple[str, int, Callable[[int], dict[str, Any]]]] = [
    ("image width", IMAGE_MAX, lambda n: {**BASE_FRAME, **_image_frame(n)}),
    ("ov width", OV_SIDE_MAX, lambda n: {**BASE_FRAME, **_ov(1, n, 1)}),
    ("ov dim", OV_DIM_MAX, lambda n: {**BASE_FRAME, **_ov(1, 1, n)}),
    ("texts", TEXTS_MAX, lambda n: {"v": 1, "type": "query_points", "texts": ["chair"] * n}),
    (
        "negatives",
        NEGATIVES_MAX,
        lambda n: {"v": 1, "type": "query_points", "texts": ["a"], "negatives": ["b"] * n},
    ),
    ("text chars", TEXT_CHARS_MAX, lambda n: {"v": 1, "type": "query_points", "texts": ["x" * n]}),
    ("map name", MAP_NAME_MAX, lambda n: {"v": 1, "type": "load", "name": "m" * n}),
    ("camera", CAMERA_MAX, lambda n: {**BASE_FRAME, "camera": "c" * n}),
    ("robot", ROBOT_MAX, lambda n: {**BASE_FRAME, "robot": "r" * n}),
    ("ov_space", CAMERA_MAX, lambda n: {**BASE_FRAME, **_ov(1, 1, 2, "s" * n)}),
    ("string id", ID_MAX, lambda n: {"v": 1, "type": "status", "id": "i" * n}),
]


def _pack(wire: dict[str, Any]) -> bytes:
    out = msgpack.packb(wire, use_bin_type=True)
    assert isinstance(out, bytes)
    return out


@pytest.mark.parametrize("name, limit, build", CASES, ids=[c[0] for c in CASES])
def test_documented_limit_is_the_enforced_one(
    name: str, limit: int, build: Callable[[int], dict[str, Any]]
) -> None:
    at = _pack(build(limit))
    assert isinstance(decode(at, direction="request"), Message)
    beyond = _pack(build(limit + 1))
    with pytest.raises(ProtocolError) as info:
        decode(beyond, direction="request")
    assert info.value.code == "bad_request", info.value
    assert str(limit) in info.value.message or "invalid" in info.value.message, info.value.message
    node = MapperNode(config_from_dict({"map_dir": "/nonexistent-unused", "events_endpoint": ""}))
    for data in (at, beyond):
        for handle in (node.handle_ingest, node.handle_query):
            reply = decode(handle(data), direction="reply")
            assert not (isinstance(reply, Error) and reply.code == "internal"), reply
    assert node.state.error_counts["internal"] == 0
