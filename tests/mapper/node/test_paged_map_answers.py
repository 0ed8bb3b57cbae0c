"""A node whose global map is bounded far below its size (``global_map.max_points``, small tiles)
answers ``query_points`` and ``segment_points`` as an unbounded one does: paged tiles are read
for queries and paged in for segment lookups; status counts resident, paged and total points; a
saved map holds the paged tiles."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from clients.harness import DEMO_OV_SPACE, synthetic_frame
from mapper.ov.encoders import register_text_encoder, unregister_text_encoder
from protocol.messages import (
    Load,
    Ok,
    Points,
    QueryPoints,
    Save,
    Segmentation,
    SegmentPoints,
    StatusRequest,
    decode,
    encode,
)
from tests.node_helpers import DemoOneHotEncoder, in_process_node

BOUNDED = {"max_points": 1500, "tile_m": 0.5, "prune_to_fraction": 0.5}


@pytest.fixture(autouse=True)
def _encoder() -> Iterator[None]:
    register_text_encoder(DEMO_OV_SPACE, DemoOneHotEncoder)
    yield
    unregister_text_encoder(DEMO_OV_SPACE)


def _node(tmp_path: Path, frames: int = 20, **global_map: Any) -> Any:
    """A node fed ``frames`` synthetic frames through a window of 4 keyframes, the views of the
    keyframes that leave it recorded per voxel as they leave (the evicted-view worker's work)."""
    node = in_process_node(tmp_path, global_map={"integrate_queue": 0, **global_map},
                           window={"max_keyframes": 4})
    for seq in range(frames):
        node.handle_ingest(encode(synthetic_frame(seq, 20, 64, 48)))
        node.ctx.evicted_views.process_pending()
    return node


def _ask(node: Any, msg: Any) -> Any:
    return decode(node.handle_query(encode(msg)), direction="reply")


def _status(node: Any) -> dict[str, Any]:
    return dict(_ask(node, StatusRequest()).extra)


def _rows(points: Points) -> np.ndarray:
    """The answer's (xyz, score, label) rows in a canonical order (ties in score may be ordered
    otherwise when the map's rows are)."""
    label = points.label[:, None].astype(np.float32)
    rows = np.concatenate([points.xyz, points.score[:, None], label], axis=1)
    return rows[np.lexsort(rows.T[::-1])]


def test_a_bounded_map_answers_as_an_unbounded_one(tmp_path: Path) -> None:
    full, bounded = _node(tmp_path / "a"), _node(tmp_path / "b", **BOUNDED)
    s_full, s_bounded = _status(full), _status(bounded)
    assert s_bounded["global_points_paged"] > 0 and s_bounded["global_points_pruned"] == 0
    assert s_bounded["global_points"] < s_full["global_points"]
    assert s_bounded["global_points_total"] == s_full["global_points_total"] == s_full["global_points"]
    assert s_full["global_points_paged"] == 0 and s_full["global_tile_store_bytes"] == 0
    assert s_bounded["evicted_views"]["voxels"] == s_full["evicted_views"]["voxels"] > 0
    for text in ("dark", "light"):
        want = _ask(full, QueryPoints(texts=[text], objects=True))
        got = _ask(bounded, QueryPoints(texts=[text], objects=True))
        assert isinstance(got, Points) and got.xyz.shape[0] > 100
        np.testing.assert_array_equal(_rows(got), _rows(want))
        assert len(got.objects) == len(want.objects)
        key = lambda o: tuple(np.round(o.centroid, 4))  # noqa: E731
        for a, b in zip(sorted(got.objects, key=key), sorted(want.objects, key=key), strict=True):
            assert a.n_points == b.n_points and a.text == b.text
            np.testing.assert_allclose(a.centroid, b.centroid, atol=1e-5)
    assert _status(bounded)["global_points"] == s_bounded["global_points"]  # queries page nothing in
    at = _ask(full, QueryPoints(texts=["dark", "light"], objects=False, max_points=100_000)).xyz[::5]
    for method in ("average", "average_depth"):
        msg = SegmentPoints(texts=["dark", "light", "sky"], xyz=at, method=method)
        want, got = _ask(full, msg), _ask(bounded, msg)
        assert isinstance(got, Segmentation) and np.count_nonzero(got.source == 2) > 0  # the map answers some
        np.testing.assert_array_equal(got.label, want.label)
        np.testing.assert_array_equal(got.source, want.source)
        np.testing.assert_allclose(got.score, want.score, atol=1e-6)
    assert _status(bounded)["global_points_paged_in"] > s_bounded["global_points_paged_in"]


def test_a_saved_bounded_map_holds_its_paged_tiles(tmp_path: Path) -> None:
    bounded = _node(tmp_path, **BOUNDED)
    before = _status(bounded)
    assert before["global_points_paged"] > 0
    assert isinstance(_ask(bounded, Save(name="paged")), Ok)
    unbounded = in_process_node(tmp_path, global_map={"integrate_queue": 0})
    assert isinstance(_ask(unbounded, Load(name="paged")), Ok)
    after = _status(unbounded)
    assert after["global_points"] == after["global_points_total"] == before["global_points_total"]
    again = in_process_node(tmp_path, global_map={"integrate_queue": 0, **BOUNDED})
    assert isinstance(_ask(again, Load(name="paged")), Ok)
    reloaded = _status(again)
    assert reloaded["global_points_total"] == before["global_points_total"]
    # loaded beyond the bound, it pages out again (the latest keyframe's tiles stay)
    assert reloaded["global_points_paged"] > 0
    assert reloaded["global_points"] + reloaded["global_points_paged"] == reloaded["global_points_total"]
    assert list((tmp_path / "maps" / ".tiles").glob("*.sqlite3"))  # in the map directory


def test_approximate_tile_skipping_answers_a_subset(tmp_path: Path) -> None:
    full = _node(tmp_path / "a")
    rough = _node(tmp_path / "b", **BOUNDED, tile_skip="centroids")
    assert _status(rough)["global_points_paged"] > 0
    for text in ("dark", "light"):
        want = _ask(full, QueryPoints(texts=[text], objects=False, max_points=100_000))
        got = _ask(rough, QueryPoints(texts=[text], objects=False, max_points=100_000))
        assert isinstance(got, Points) and 0 < got.xyz.shape[0] <= want.xyz.shape[0]
        assert {tuple(p) for p in got.xyz.tolist()} <= {tuple(p) for p in want.xyz.tolist()}
