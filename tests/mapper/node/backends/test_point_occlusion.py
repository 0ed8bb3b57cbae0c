"""``average_depth`` without input depth (``queries.point_occlusion``): keyframes without depth
count a point only where the request's own points do not hide it, the averaging counterpart of
``model.point_occlusion`` (tested in tests/mapper/runtime/test_rgb_bounds.py).

A node in-process (no sockets, no model) with the fake one-hot 4-d space of test_whole_map. Two
RGB-only keyframes look along +z from the origin and see class c0 everywhere; a third looks along
-x at the point (0, 0, 3) from the side and sees c1. The request holds a card of points at z = 1
that fills the first two keyframes' views and a few points at z = 3 behind it, which the third
sees past the card."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mapper.node.config import config_from_dict
from mapper.node.service import MapperNode
from protocol.messages import Error, Frame, Segmentation, SegmentPoints, decode, encode
from tests.mapper.node.answers.test_whole_map import SPACE, D, onehot_space  # noqa: F401 (the autouse fixture)

W, H = 32, 24
K = np.array([30.0, 30.0, 16.0, 12.0])
SIDE = np.array([[0, 0, -1, 3.0], [0, 1, 0, 0], [1, 0, 0, 3.0], [0, 0, 0, 1]], float)  # at (3, 0, 3), +z = -x


def _frame(seq: int, pose: np.ndarray, cls: int) -> Frame:
    ov = np.zeros((6, 8, D), np.float16)
    ov[..., cls] = 1.0
    return Frame(seq=seq, stamp_ns=seq, width=W, height=H, K=K, world_from_cam=pose,
                 rgb=np.zeros((H, W, 3), np.uint8), ov=ov, ov_space=SPACE)  # fmt: skip


def _node(tmp_path: Path, **queries: Any) -> MapperNode:
    config = config_from_dict(
        {"map_dir": str(tmp_path), "events_endpoint": "", "serve_model": False,
         "window": {"max_keyframes": 4, "min_translation_m": 0.01}, "queries": queries}
    )  # fmt: skip
    node = MapperNode(config)
    shifted = np.eye(4)
    shifted[0, 3] = 0.1
    for seq, (pose, cls) in enumerate([(np.eye(4), 0), (shifted, 0), (SIDE, 1)]):
        reply = decode(node.handle_ingest(encode(_frame(seq, pose, cls))), direction="reply")
        assert getattr(reply, "status", None) == "keyframe", reply
    return node


def _points() -> tuple[np.ndarray, np.ndarray]:
    g = np.arange(-0.6, 0.6 + 1e-9, 0.02)
    x, y = np.meshgrid(g, g)
    card = np.column_stack([x.ravel(), y.ravel(), np.ones(x.size)])
    core = np.array([[0.0, 0.0, 3.0], [0.05, 0.0, 3.0], [0.0, 0.05, 3.0]])
    return card.astype(np.float32), core.astype(np.float32)


def _segment(node: MapperNode, method: Any, xyz: np.ndarray) -> Segmentation | Error:
    msg = SegmentPoints(xyz=xyz, texts=["c0", "c1"], method=method, id=3)
    reply: Any = decode(node.handle_query(encode(msg)), direction="reply")
    return reply


def test_average_depth_without_depth_masks_views_in_which_other_requested_points_hide_a_point(
    tmp_path: Path,
) -> None:
    node = _node(tmp_path)
    try:
        card, core = _points()
        xyz = np.concatenate([card, core])
        plain, tested = _segment(node, "average", xyz), _segment(node, "average_depth", xyz)
        assert isinstance(plain, Segmentation) and isinstance(tested, Segmentation)
        rows = slice(len(card), None)
        assert (plain.label[rows] == 0).all()  # two views of c0 outvote the side view's c1
        assert (tested.label[rows] == 1).all()  # the card hides the core from both: the side view answers
        seen = plain.label[: len(card)] >= 0  # the card's points inside the c0 views (it overfills them)
        assert seen.sum() > 100
        assert (tested.label[: len(card)][seen] == 0).all()  # the card hides nothing of itself
        alone = _segment(node, "average_depth", core)  # asked alone, nothing hides the core
        assert isinstance(alone, Segmentation) and (alone.label == 0).all()
        for xyz in (np.zeros((0, 3), np.float32), np.tile(core[:1], (20, 1))):  # no points; one place
            reply = _segment(node, "average_depth", xyz)
            assert isinstance(reply, Segmentation) and reply.label.shape == (len(xyz),)
            if len(xyz):
                assert (reply.label == 0).all()  # coincident points hide nothing of one another
    finally:
        node.stop()


def test_average_depth_without_depth_or_point_occlusion_is_not_ready(tmp_path: Path) -> None:
    node = _node(tmp_path, point_occlusion=False)
    try:
        reply = _segment(node, "average_depth", np.concatenate(_points()))
        assert isinstance(reply, Error) and reply.code == "not_ready"
        assert "needs keyframes with both depth and ov" in reply.message
    finally:
        node.stop()
