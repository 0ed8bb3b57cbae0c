"""``query_points`` with a ``region``: only the map points inside the axis-aligned box match, before
``max_points`` and the objects; a box given wrong is refused at the edge."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from clients.harness import DEMO_OV_SPACE, synthetic_frame
from mapper.ov.encoders import register_text_encoder, unregister_text_encoder
from protocol.messages import Error, Points, QueryPoints, decode, encode
from tests.node_helpers import DemoOneHotEncoder, in_process_node


@pytest.fixture(autouse=True)
def _encoder() -> Iterator[None]:
    register_text_encoder(DEMO_OV_SPACE, DemoOneHotEncoder)
    yield
    unregister_text_encoder(DEMO_OV_SPACE)


def _node(tmp_path: Path) -> Any:
    node = in_process_node(tmp_path, global_map={"integrate_queue": 0})
    for seq in range(0, 20, 2):
        node.handle_ingest(encode(synthetic_frame(seq, 20, 64, 48)))
    return node


def _ask(node: Any, msg: QueryPoints) -> Any:
    return decode(node.handle_query(encode(msg)), direction="reply")


def test_only_points_inside_the_region_match(tmp_path: Path) -> None:
    node = _node(tmp_path)
    everywhere = _ask(node, QueryPoints(texts=["dark"], objects=False))
    assert isinstance(everywhere, Points) and everywhere.xyz.shape[0] > 20
    low, high = np.array([-0.5, -0.5, -0.1]), np.array([0.5, 0.5, 0.1])
    inside = _ask(node, QueryPoints(texts=["dark"], objects=False, region_min=low, region_max=high))
    assert isinstance(inside, Points) and 0 < inside.xyz.shape[0] < everywhere.xyz.shape[0]
    assert np.all((inside.xyz >= low - 1e-6) & (inside.xyz <= high + 1e-6))
    in_box = np.all((everywhere.xyz >= low) & (everywhere.xyz <= high), axis=1)
    assert inside.xyz.shape[0] == int(in_box.sum())  # the same points as the full answer has there


def test_max_points_counts_within_the_region(tmp_path: Path) -> None:
    node = _node(tmp_path)
    low, high = np.array([-0.5, -0.5, -0.1]), np.array([0.5, 0.5, 0.1])
    msg = QueryPoints(texts=["dark"], objects=False, max_points=5, region_min=low, region_max=high)
    few = _ask(node, msg)
    assert isinstance(few, Points) and few.xyz.shape[0] == 5
    assert np.all((few.xyz >= low - 1e-6) & (few.xyz <= high + 1e-6))


def test_a_region_given_wrong_is_refused(tmp_path: Path) -> None:
    import msgpack

    node = _node(tmp_path)
    body = msgpack.unpackb(encode(QueryPoints(texts=["dark"])), raw=False)
    body["region_min"] = [1.0, 1.0, 1.0]
    reply = decode(node.handle_query(msgpack.packb(body, use_bin_type=True)), direction="reply")
    assert isinstance(reply, Error) and reply.code == "bad_request" and "region_max" in reply.message
    body["region_max"] = [0.0, 0.0, 0.0]
    reply = decode(node.handle_query(msgpack.packb(body, use_bin_type=True)), direction="reply")
    assert isinstance(reply, Error) and reply.code == "bad_request" and "exceeds" in reply.message
