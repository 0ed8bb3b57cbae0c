"""Do no harm: the node says whether it has settled (``status``'s ``pending`` / ``settled``, the
replies' ``settled``), waits for it when asked (``settle_timeout_s``, bounded), and answers the
learned method with averaging while an RGB-only window's geometry is pending (the reply's
``fallback``)."""

from __future__ import annotations

import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from clients.harness import DEMO_OV_SPACE, synthetic_frame
from mapper.node.backends.learned import LearnedBackend
from mapper.node.service import MapperNode
from mapper.ov.encoders import register_text_encoder, unregister_text_encoder
from protocol.messages import (
    Message,
    Points,
    QueryPoints,
    Segmentation,
    SegmentPoints,
    Status,
    StatusRequest,
    decode,
    encode,
)
from tests.node_helpers import DemoOneHotEncoder, in_process_node

TEXTS = ["sky", "dark", "light"]


class ConstantRuntime:
    """A learned model that labels every point with text 2 at cosine 0.99 (unlike the averaging)."""

    config = None
    load_error = None

    def segment(self, xyz: Any, texts: Sequence[str], *, use_depth: bool) -> tuple[Any, Any, dict]:
        n = np.asarray(xyz).shape[0]
        return np.full(n, 2, np.int32), np.full(n, 0.99, np.float32), {}

    def segment_cosines(
        self, xyz: Any, texts: Sequence[str], *, use_depth: bool
    ) -> tuple[Any, Any, Any, dict]:
        label, score, timing = self.segment(xyz, texts, use_depth=use_depth)
        cos = np.zeros((label.shape[0], len(texts)), np.float32)
        cos[:, 2] = 0.99
        return label, score, cos, timing


class Pending:
    """A worker's pending count that a test sets."""

    def __init__(self, n: int = 0) -> None:
        self.n = n

    def __call__(self) -> int:
        return self.n


@pytest.fixture(autouse=True)
def _encoder() -> Iterator[None]:
    register_text_encoder(DEMO_OV_SPACE, DemoOneHotEncoder)
    yield
    unregister_text_encoder(DEMO_OV_SPACE)


def _ask(node: MapperNode, msg: Message) -> Any:
    return decode(node.handle_query(encode(msg)), direction="reply")


def _streamed(tmp_path: Path, *, depth: bool, queries: dict[str, Any] | None = None) -> MapperNode:
    node = in_process_node(tmp_path, global_map={"integrate_queue": 0}, queries=queries or {})
    for seq in range(0, 20, 2):
        frame = synthetic_frame(seq, 20, 64, 48)
        if not depth:
            frame.depth_m = None
        node.handle_ingest(encode(frame))
    return node


def _points(node: MapperNode) -> np.ndarray:
    return np.asarray(node.state.global_map.snapshot().xyz[:100], np.float32)


def test_status_reports_pending_work_and_settled(tmp_path: Path) -> None:
    node = _streamed(tmp_path, depth=True)
    pending = Pending(3)
    node.ctx.register_pending("worker", pending)
    status = _ask(node, StatusRequest())
    assert isinstance(status, Status)
    # every source of background work is listed (evicted views: on by default), 0 where none waits
    assert status.extra["pending"] == {"integration": 0, "evicted_views": 0, "worker": 3}
    assert status.extra["settled"] is False
    pending.n = 0
    assert _ask(node, StatusRequest()).extra["settled"] is True


def test_a_settle_timeout_waits_for_the_background_work(tmp_path: Path) -> None:
    node = _streamed(tmp_path, depth=True)
    pending = Pending(1)
    node.ctx.register_pending("worker", pending)
    xyz = _points(node)
    unsettled = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method="average"))
    assert isinstance(unsettled, Segmentation) and unsettled.settled is False
    timer = threading.Timer(0.2, lambda: setattr(pending, "n", 0))
    timer.start()
    waited = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method="average", settle_timeout_s=20.0))
    timer.join()
    assert isinstance(waited, Segmentation) and waited.settled is True
    found = _ask(node, QueryPoints(texts=["dark"], settle_timeout_s=5.0))
    assert isinstance(found, Points) and found.settled is True


def test_the_settle_wait_is_bounded(tmp_path: Path) -> None:
    node = in_process_node(tmp_path, global_map={"integrate_queue": 0}, queries={"max_settle_wait_s": 0.1})
    for seq in range(0, 20, 2):
        node.handle_ingest(encode(synthetic_frame(seq, 20, 64, 48)))
    node.ctx.register_pending("stuck", Pending(1))
    reply = _ask(node, QueryPoints(texts=["dark"], settle_timeout_s=600.0))  # capped at 0.1 s
    assert isinstance(reply, Points) and reply.settled is False


@pytest.mark.parametrize("depth", [False, True], ids=["rgb-only", "depth"])
def test_learned_falls_back_to_averaging_while_rgb_only_geometry_is_pending(
    tmp_path: Path, depth: bool
) -> None:
    # the per-point mix toward a more decided averaging off: the geometry's fallback alone
    node = _streamed(tmp_path, depth=depth, queries={"learned_toward_average": 0.0})
    node.segment.register("govnesf", LearnedBackend(ConstantRuntime()))
    geometry = Pending(2)
    node.ctx.register_pending("triangulation", geometry, geometry=True)
    xyz = _points(node)
    average = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method="average"))
    early = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method="govnesf"))
    assert isinstance(early, Segmentation) and early.fallback is not None
    if depth:  # measured geometry: the learned model answers
        assert not early.fallback.any() and (early.label[early.source == 1] == 2).all()
    else:  # its geometry pending: the averaging answers, and says so
        assert early.fallback.all() and np.array_equal(early.label, average.label)
    geometry.n = 0
    settled = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method="govnesf"))
    assert isinstance(settled, Segmentation) and settled.fallback is not None and not settled.fallback.any()
    assert settled.settled is True and (settled.label[settled.source == 1] == 2).all()


def test_the_fallback_can_be_turned_off(tmp_path: Path) -> None:
    node = in_process_node(tmp_path, global_map={"integrate_queue": 0},
                           queries={"learned_fallback": "off", "learned_toward_average": 0.0})
    for seq in range(0, 20, 2):
        frame = synthetic_frame(seq, 20, 64, 48)
        frame.depth_m = None
        node.handle_ingest(encode(frame))
    node.segment.register("govnesf", LearnedBackend(ConstantRuntime()))
    node.ctx.register_pending("triangulation", Pending(2), geometry=True)
    reply = _ask(node, SegmentPoints(xyz=np.zeros((3, 3), np.float32), texts=TEXTS, method="govnesf"))
    assert isinstance(reply, Segmentation) and reply.fallback is not None and not reply.fallback.any()


def test_the_pending_fallback_also_covers_windows_with_depth(tmp_path: Path) -> None:
    node = in_process_node(tmp_path, global_map={"integrate_queue": 0},
                           queries={"learned_fallback": "pending", "learned_toward_average": 0.0})
    for seq in range(0, 20, 2):
        node.handle_ingest(encode(synthetic_frame(seq, 20, 64, 48)))
    node.segment.register("govnesf", LearnedBackend(ConstantRuntime()))
    features = Pending(1)
    node.ctx.register_pending("map_features", features)  # not geometry: "geometry" would not fall back
    xyz = _points(node)
    early = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method="govnesf"))
    assert isinstance(early, Segmentation) and early.fallback is not None and early.fallback.all()
    features.n = 0
    settled = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method="govnesf"))
    assert isinstance(settled, Segmentation) and settled.fallback is not None and not settled.fallback.any()


class UndecidedRuntime(ConstantRuntime):
    """A learned model that labels every point with text 2, barely ahead of text 1."""

    def segment_cosines(
        self, xyz: Any, texts: Sequence[str], *, use_depth: bool
    ) -> tuple[Any, Any, Any, dict]:
        label, score, cos, timing = super().segment_cosines(xyz, texts, use_depth=use_depth)
        cos[:, 1] = 0.98
        return label, score, cos, timing


@pytest.mark.parametrize("runtime", [ConstantRuntime, UndecidedRuntime], ids=["decided", "undecided"])
def test_learned_answers_move_toward_a_more_decided_averaging(tmp_path: Path, runtime: type) -> None:
    """``queries.learned_toward_average``: a learned answer barely decided takes the averaging's
    where the averaging is more decided, and the reply's ``fallback`` marks those points; a
    decided one (margin 0.99: no averaging's margin is 3 times that) stays."""
    node = in_process_node(tmp_path, global_map={"integrate_queue": 0},
                           queries={"learned_toward_average": 3.0, "learned_toward_average_ramp": 0.05,
                                    "map_radius_voxels": 0.0})
    for seq in range(0, 20, 2):
        node.handle_ingest(encode(synthetic_frame(seq, 20, 64, 48)))
    node.segment.register("govnesf", LearnedBackend(runtime()))
    xyz = _points(node)
    average = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method="average"))
    reply = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method="govnesf"))
    assert isinstance(average, Segmentation) and isinstance(reply, Segmentation)
    assert reply.fallback is not None
    seen = average.label >= 0
    assert seen.any() and (average.label[seen] != 2).any()
    if runtime is ConstantRuntime:
        assert (reply.label[seen] == 2).all() and not reply.fallback.any()
    else:
        # the averaging's answer where it is decided enough to move the label (text 2 at 0.99 over
        # text 1 at 0.98), and the fallback flags exactly those points
        moved = reply.label != 2
        assert moved.sum() > (seen & (average.label != 2)).sum() // 2
        assert np.array_equal(reply.label[moved], average.label[moved])
        assert np.array_equal(reply.fallback.astype(bool), moved)
