"""``segment_points``' spatial order (``mapper.node.queries.spatial_order``, ``queries.spatial_sort``):
the averaging methods answer unordered points in Z-order of map voxels, with the same answers in the
request's order."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapper.map.query_kernels import morton_codes
from mapper.node.config import config_from_dict
from mapper.node.queries import spatial_order
from mapper.node.service import MapperNode
from mapper.ov.encoders import register_text_encoder, unregister_text_encoder
from protocol.messages import Frame, Segmentation, SegmentPoints, decode, encode

SPACE = "test-random-8"
D = 8
W, H = 40, 30
K = np.array([36.0, 36.0, 20.0, 15.0])


class FixedEncoder:
    space = SPACE
    dim = D

    def encode(self, texts: list[str]) -> np.ndarray:
        rng = np.random.default_rng(5)
        emb = rng.standard_normal((len(texts), D)).astype(np.float32)
        return emb / np.linalg.norm(emb, axis=1, keepdims=True)


@pytest.fixture(autouse=True)
def random_space() -> Iterator[None]:
    register_text_encoder(SPACE, FixedEncoder)
    yield
    unregister_text_encoder(SPACE)


def test_morton_codes_interleave_x_y_z() -> None:
    cells = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 0, 0], [3, 5, 6]], float)
    assert morton_codes(cells + 0.5, np.zeros(3), 1.0).tolist() == [0, 1, 2, 4, 7, 8, 0b110101011]
    # clipped to the grid: below the origin is cell 0, beyond 2^21 cells the last one
    clipped = morton_codes(np.array([[-5.0, 0, 0], [1e9, 0, 0]]), np.zeros(3), 1.0)
    assert clipped.tolist() == [0, 0x1249249249249249]
    with pytest.raises(ValueError, match="cell_m"):
        morton_codes(np.zeros((1, 3)), np.zeros(3), 0.0)


def test_spatial_order_sorts_only_incoherent_points() -> None:
    rng = np.random.default_rng(0)
    raster = np.stack(np.meshgrid(np.arange(0, 2, 0.01), np.arange(0, 1, 0.01), [1.0]), -1).reshape(-1, 3)
    raster = raster.astype(np.float32)
    assert spatial_order(raster, 0.05) is None  # consecutive points 1 cm apart: already coherent
    perm = rng.permutation(raster.shape[0])
    order = spatial_order(raster[perm], 0.05)
    assert order is not None and np.array_equal(np.sort(order), np.arange(raster.shape[0]))
    again = raster[perm][order]
    step = np.linalg.norm(again[1::2] - again[0:-1:2], axis=1)
    assert np.mean(step <= 0.05) > 0.9  # neighbours now
    assert spatial_order(again, 0.05) is None
    assert spatial_order(raster[perm][:3], 0.05) is None  # fewer than 4 points


def _frame(seq: int, eye_x: float, rng: np.random.Generator) -> Frame:
    pose = np.eye(4)
    pose[0, 3] = eye_x
    ov = rng.standard_normal((6, 8, D)).astype(np.float16)
    return Frame(seq=seq, stamp_ns=seq, width=W, height=H, K=K, world_from_cam=pose,
                 rgb=np.zeros((H, W, 3), np.uint8), depth_m=np.full((H, W), 2.0, np.float32), ov=ov,
                 ov_space=SPACE)  # fmt: skip


def _segment(node: MapperNode, method: Any, xyz: np.ndarray) -> Segmentation:
    msg = SegmentPoints(xyz=xyz, texts=["a", "b", "c", "d", "e"], method=method)
    reply = decode(node.handle_query(encode(msg)), direction="reply")
    assert isinstance(reply, Segmentation), reply
    return reply


@pytest.mark.parametrize("method", ["average", "average_depth"])
def test_shuffled_points_get_the_answers_of_the_ordered_ones(tmp_path: Path, method: str) -> None:
    rng = np.random.default_rng(1)
    nodes = {}
    for sort in (True, False):
        config = config_from_dict({"map_dir": str(tmp_path / str(sort)), "events_endpoint": "",
                                   "serve_model": False, "global_map": {"pixel_stride": 1},
                                   "queries": {"spatial_sort": sort}})
        nodes[sort] = MapperNode(config)
        for i in range(4):
            frame = _frame(i, 0.1 * i, np.random.default_rng(i))
            decode(nodes[sort].handle_ingest(encode(frame)), direction="reply")
    # points on the depth plane (z = 2), a raster (coherent), plus points off every view
    grid = np.stack(np.meshgrid(np.linspace(-0.9, 1.2, 60), np.linspace(-0.7, 0.7, 40), [2.0]), -1)
    xyz = np.concatenate([grid.reshape(-1, 3), rng.uniform(5, 9, (40, 3))]).astype(np.float32)
    perm = rng.permutation(xyz.shape[0])
    ordered = _segment(nodes[True], method, xyz)
    assert "spatial_sort" not in ordered.timing_ms  # coherent: answered as given
    shuffled = _segment(nodes[True], method, xyz[perm])
    assert "spatial_sort" in shuffled.timing_ms
    plain = _segment(nodes[False], method, xyz[perm])
    assert "spatial_sort" not in plain.timing_ms
    assert (ordered.label >= 0).sum() > 2000 and (ordered.label == -1).sum() >= 40
    assert len(set(ordered.label.tolist())) > 2  # the answers differ from point to point
    for reply in (shuffled, plain):
        np.testing.assert_array_equal(reply.label, ordered.label[perm])
        np.testing.assert_array_equal(reply.score, ordered.score[perm])
        np.testing.assert_array_equal(reply.source, ordered.source[perm])
    for node in nodes.values():
        node.stop()
