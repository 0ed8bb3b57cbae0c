"""Keyframe window: selection by pose change per camera, bounded eviction, callbacks, serialisation."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from mapper.map.window import (
    Keyframe,
    KeyframeWindow,
    keyframes_from_arrays,
    keyframes_to_arrays,
    pose_change,
)
from mapper.node.config import WindowConfig


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _pose(x_m: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = _rot_z(yaw_deg)
    world_from_cam[0, 3] = x_m
    return world_from_cam


def _kf(seq: int, x_m: float = 0.0, yaw_deg: float = 0.0, camera: str = "cam0", ov: bool = False) -> Keyframe:
    return Keyframe(
        seq=seq,
        stamp_ns=1000 * seq,
        camera=camera,
        K=np.array([100.0, 100.0, 8.0, 6.0]),
        world_from_cam=_pose(x_m, yaw_deg),
        rgb=np.full((12, 16, 3), seq % 256, np.uint8),
        depth_m=np.full((12, 16), 2.0, np.float32),
        ov=np.ones((3, 4, 8), np.float16) if ov else None,
        ov_space="test-space" if ov else None,
    )


CFG = WindowConfig(max_keyframes=3, min_translation_m=0.1, min_rotation_deg=10.0)


def test_pose_change_translation_and_angle() -> None:
    t, r = pose_change(_pose(0.0, 0.0), _pose(0.3, 25.0))
    assert t == pytest.approx(0.3)
    assert r == pytest.approx(25.0)
    # the angle is that of the relative rotation, independent of a common rotation
    a, b = _pose(0, 170.0), _pose(0, -170.0)
    assert pose_change(a, b)[1] == pytest.approx(20.0)


def test_first_frame_is_keyframe_then_thresholds() -> None:
    window = KeyframeWindow(CFG)
    update = window.consider(_kf(0))
    assert update.added and update.evicted == () and math.isinf(update.translation_m)
    assert not window.consider(_kf(1, x_m=0.05, yaw_deg=5.0)).added  # below both thresholds
    assert window.consider(_kf(2, x_m=0.1)).added  # translation threshold is inclusive
    assert window.consider(_kf(3, x_m=0.1, yaw_deg=12.0)).added  # rotation alone is enough
    # compared against the *latest keyframe*, not the latest frame: small steps accumulate
    assert not window.consider(_kf(4, x_m=0.16, yaw_deg=12.0)).added
    assert window.consider(_kf(5, x_m=0.21, yaw_deg=12.0)).added
    assert [k.seq for k in window.keyframes] == [2, 3, 5]


def test_eviction_is_bounded_oldest_first_and_reported() -> None:
    window = KeyframeWindow(CFG)
    evicted_seqs: list[int] = []
    for i in range(10):
        update = window.consider(_kf(i, x_m=i * 1.0))
        assert update.added
        evicted_seqs.extend(k.seq for k in update.evicted)
        assert len(window) == min(i + 1, CFG.max_keyframes)
    assert evicted_seqs == list(range(7))
    assert [k.seq for k in window.keyframes] == [7, 8, 9]


def test_selection_is_per_camera() -> None:
    window = KeyframeWindow(WindowConfig(max_keyframes=10, min_translation_m=0.1, min_rotation_deg=10))
    assert window.consider(_kf(0, camera="left")).added
    assert window.consider(_kf(1, x_m=5.0, camera="right")).added  # first of its camera
    assert not window.consider(_kf(2, x_m=0.01, camera="left")).added
    assert not window.consider(_kf(3, x_m=5.01, camera="right")).added


def test_callbacks_fire_in_order_with_consistent_state() -> None:
    window = KeyframeWindow(WindowConfig(max_keyframes=2, min_translation_m=0.1, min_rotation_deg=10))
    held: set[int] = set()
    log: list[str] = []

    def on_add(k: Keyframe) -> None:
        held.add(k.seq)
        log.append(f"+{k.seq}")

    def on_evict(k: Keyframe) -> None:
        held.remove(k.seq)
        log.append(f"-{k.seq}")

    window.on_add.append(on_add)
    window.on_evict.append(on_evict)
    for i in range(4):
        window.consider(_kf(i, x_m=float(i)))
        assert held == {k.seq for k in window.keyframes}  # derived state mirrors the window
    assert log == ["+0", "+1", "+2", "-0", "+3", "-1"]
    removed, added = window.replace([_kf(10, 0.0), _kf(11, 1.0), _kf(12, 2.0)])
    assert [k.seq for k in removed] == [2, 3]
    assert [k.seq for k in added] == [11, 12]  # only the newest max_keyframes are kept
    assert held == {11, 12}
    # selection restarts from the loaded keyframes
    assert not window.consider(_kf(13, x_m=2.05)).added


def test_keyframe_arrays_are_read_only_and_nbytes() -> None:
    rgb = np.zeros((12, 16, 3), np.uint8)
    keyframe = Keyframe(0, 0, "cam0", np.ones(4), np.eye(4), rgb)
    with pytest.raises(ValueError):
        keyframe.rgb[0, 0, 0] = 1
    assert rgb.flags.writeable  # the caller's array is not changed
    assert keyframe.nbytes == 4 * 8 + 16 * 8 + rgb.nbytes
    assert (keyframe.width, keyframe.height) == (16, 12)


def test_serialisation_roundtrip() -> None:
    keyframes = [_kf(0), _kf(1, x_m=1.0, ov=True, camera="right")]
    arrays, entries = keyframes_to_arrays(keyframes)
    back = keyframes_from_arrays(arrays, entries)
    assert len(back) == 2
    for a, b in zip(keyframes, back, strict=True):
        assert (a.seq, a.stamp_ns, a.camera, a.ov_space) == (b.seq, b.stamp_ns, b.camera, b.ov_space)
        for name in ("K", "world_from_cam", "rgb", "depth_m"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert back[0].ov is None and back[1].ov is not None and back[1].ov.dtype == np.float16


def test_deserialisation_rejects_damaged_content() -> None:
    arrays, entries = keyframes_to_arrays([_kf(0)])
    bad = dict(arrays)
    bad["kf.0.rgb"] = np.zeros((4, 4), np.uint8)
    with pytest.raises(ValueError, match="keyframe 0: rgb"):
        keyframes_from_arrays(bad, entries)
    bad = dict(arrays)
    bad["kf.0.world_from_cam"] = np.full((4, 4), np.nan)
    with pytest.raises(ValueError, match="world_from_cam"):
        keyframes_from_arrays(bad, entries)
    with pytest.raises(ValueError, match="seq"):
        keyframes_from_arrays(arrays, [{"seq": "0", "stamp_ns": 0, "camera": "c"}])


def test_swap_keeps_position_and_latest_keyframe_and_fires_callbacks() -> None:
    import dataclasses

    window = KeyframeWindow(CFG)
    events: list[tuple[str, int, bool]] = []
    window.on_add.append(lambda k: events.append(("add", k.seq, k.ov is not None)))
    window.on_evict.append(lambda k: events.append(("evict", k.seq, k.ov is not None)))
    for i in range(3):
        window.consider(_kf(i, x_m=i * 1.0))
    events.clear()
    old = window.keyframes[2]  # the camera's latest keyframe
    new = dataclasses.replace(old, ov=np.zeros((2, 2, 4), np.float32), ov_space="s")
    assert window.swap(old, new)
    assert [k.seq for k in window.keyframes] == [0, 1, 2] and window.keyframes[2] is new
    assert events == [("evict", 2, False), ("add", 2, True)]
    assert not window.consider(_kf(3, x_m=2.0 + 0.01)).added  # selection still relative to seq 2
    assert not window.swap(old, new) and events == [("evict", 2, False), ("add", 2, True)]


def test_frames_larger_than_max_image_side_are_kept_shrunk_and_map_the_same_surface(tmp_path: Path) -> None:
    """A 2560 x 1920 frame with depth of a wall 2 m away: its keyframe is 1280 x 960 with K scaled,
    its depth by nearest sample; the global map puts the wall where the full frame says; the same
    frame sent again is recognised as a duplicate; ``status`` counts it."""
    from mapper.errors import ConfigError
    from mapper.node.config import config_from_dict
    from mapper.node.service import MapperNode
    from protocol.messages import Ack, Frame, StatusRequest, decode, encode

    w, h = 2560, 1920
    rng = np.random.default_rng(0)
    frame = Frame(seq=1, stamp_ns=5, width=w, height=h, K=np.array([2000.0, 2000.0, 1280.0, 960.0]),
                  world_from_cam=np.eye(4), rgb=rng.integers(0, 255, (h, w, 3), dtype=np.uint8),
                  depth_m=np.full((h, w), 2.0, np.float32))  # fmt: skip
    node = MapperNode(config_from_dict({"map_dir": str(tmp_path), "events_endpoint": "", "serve_model": False,
                                        "global_map": {"integrate_queue": 0}}))  # fmt: skip
    ack = decode(node.handle_ingest(encode(frame)), direction="reply")
    assert isinstance(ack, Ack) and ack.status == "keyframe"
    kf = node.state.window.keyframes[-1]
    assert (kf.width, kf.height) == (1280, 960) and kf.depth_m is not None and kf.depth_m.shape == (960, 1280)
    np.testing.assert_allclose(kf.K, [1000.0, 1000.0, 640.0, 480.0])
    xyz = node.state.global_map.snapshot().xyz
    assert len(xyz) > 1000 and np.allclose(xyz[:, 2], 2.0, atol=0.05)  # the wall, at 2 m
    half_x, half_y = 2.0 * (w / 2) / 2000.0, 2.0 * (h / 2) / 2000.0  # its extent in the full frame
    assert np.abs(xyz[:, 0]).max() <= half_x + 0.05 and np.abs(xyz[:, 0]).max() > half_x - 0.1
    assert np.abs(xyz[:, 1]).max() <= half_y + 0.05
    again = decode(node.handle_ingest(encode(frame)), direction="reply")
    assert isinstance(again, Ack) and again.status == "accepted" and "duplicate" in (again.reason or "")
    status = decode(node.handle_query(encode(StatusRequest())), direction="reply")
    assert status.extra["frames_downscaled"] == 1 and status.extra["frames_duplicate"] == 1  # keyframes only
    kept = MapperNode(config_from_dict({"map_dir": str(tmp_path), "events_endpoint": "", "serve_model": False,
                                        "window": {"max_image_side": 0}}))  # fmt: skip
    kept.handle_ingest(encode(frame))
    assert kept.state.window.keyframes[-1].width == w  # 0: as sent
    with pytest.raises(ConfigError, match="window.max_image_side"):
        config_from_dict({"window": {"max_image_side": 8}})


def test_a_large_ov_map_is_kept_area_averaged_to_max_ov_cells(tmp_path: Path) -> None:
    """``window.max_ov_cells``: a keyframe's OV map with more cells is kept area-averaged (aspect
    and dtype kept), the map and the answers use it as any OV map; a frame that is no keyframe is
    not touched; 0 keeps it as sent."""
    from mapper.errors import ConfigError
    from mapper.node.config import config_from_dict
    from mapper.node.service import MapperNode
    from protocol.messages import Ack, Frame, StatusRequest, decode, encode

    rng = np.random.default_rng(1)
    h, w = 120, 160
    ov = np.zeros((h, w, 4), np.float16)
    ov[:, : w // 2, 0] = 1.0  # left half: text 0; right half: text 1
    ov[:, w // 2:, 1] = 1.0
    frame = Frame(seq=1, stamp_ns=5, width=640, height=480, K=np.array([500.0, 500.0, 320.0, 240.0]),
                  world_from_cam=np.eye(4), rgb=rng.integers(0, 255, (480, 640, 3), dtype=np.uint8),
                  depth_m=np.full((480, 640), 2.0, np.float32), ov=ov, ov_space="test-space")  # fmt: skip
    node = MapperNode(config_from_dict({"map_dir": str(tmp_path), "events_endpoint": "", "serve_model": False,
                                        "global_map": {"integrate_queue": 0}}))  # fmt: skip
    assert isinstance(decode(node.handle_ingest(encode(frame)), direction="reply"), Ack)
    kf = node.state.window.keyframes[-1]
    assert kf.ov is not None and kf.ov.shape == (60, 80, 4) and kf.ov.dtype == np.float16
    np.testing.assert_array_equal(kf.ov[:, :40, 0], 1.0)  # area averages of whole halves: unchanged
    np.testing.assert_array_equal(kf.ov[:, 40:, 1], 1.0)
    status = decode(node.handle_query(encode(StatusRequest())), direction="reply")
    assert status.extra["frames_downscaled"] == 1
    same_place = dataclasses.replace(frame, seq=2, stamp_ns=6)  # not a keyframe: acked, not kept
    ack = decode(node.handle_ingest(encode(same_place)), direction="reply")
    assert isinstance(ack, Ack) and ack.status == "accepted"
    kept = MapperNode(config_from_dict({"map_dir": str(tmp_path), "events_endpoint": "", "serve_model": False,
                                        "window": {"max_ov_cells": 0}}))  # fmt: skip
    kept.handle_ingest(encode(frame))
    assert kept.state.window.keyframes[-1].ov.shape == (h, w, 4)  # 0: as sent
    with pytest.raises(ConfigError, match="window.max_ov_cells"):
        config_from_dict({"window": {"max_ov_cells": -1}})
