"""The ingest path (:mod:`mapper.node.ingest`): a resent frame is a duplicate only once it passed the
same validation as a new frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from clients.harness import synthetic_frame
from protocol.messages import Ack, Error, decode, encode
from tests.node_helpers import in_process_node


def _send(node, frame) -> object:  # type: ignore[no-untyped-def]
    return decode(node.handle_ingest(encode(frame)), direction="reply")


def test_a_resent_keyframe_is_acked_as_a_duplicate_and_not_added_twice(tmp_path: Path) -> None:
    node = in_process_node(tmp_path, global_map={"integrate_queue": 0})
    first = _send(node, synthetic_frame(0, 20, 40, 30))
    again = _send(node, synthetic_frame(0, 20, 40, 30))
    assert isinstance(first, Ack) and first.status == "keyframe"
    assert isinstance(again, Ack) and again.status == "accepted" and "duplicate" in (again.reason or "")
    assert len(node.state.window) == 1 and node.ctx.frames_duplicate == 1


def test_a_resent_keyframe_of_another_ov_space_is_refused_not_acked_as_a_duplicate(tmp_path: Path) -> None:
    node = in_process_node(tmp_path, global_map={"integrate_queue": 0})
    assert _send(node, synthetic_frame(0, 20, 40, 30)).status == "keyframe"  # type: ignore[attr-defined]
    resent = synthetic_frame(0, 20, 40, 30)
    resent.ov_space = "another-space"
    version = node.state.map_version
    reply = _send(node, resent)
    assert isinstance(reply, Error) and reply.code == "ov_space_mismatch"
    assert node.ctx.frames_duplicate == 0 and node.state.map_version == version
    assert len(node.state.window) == 1


def test_a_resent_keyframe_of_another_feature_dimension_is_rejected(tmp_path: Path) -> None:
    node = in_process_node(tmp_path, global_map={"integrate_queue": 0})
    first = synthetic_frame(0, 20, 40, 30)
    assert _send(node, first).status == "keyframe"  # type: ignore[attr-defined]
    resent = synthetic_frame(0, 20, 40, 30)
    assert resent.ov is not None
    resent.ov = np.concatenate([resent.ov, resent.ov], axis=2)
    reply = _send(node, resent)
    assert isinstance(reply, Ack) and reply.status == "rejected" and "dimension" in (reply.reason or "")
    assert node.ctx.frames_duplicate == 0 and len(node.state.window) == 1
