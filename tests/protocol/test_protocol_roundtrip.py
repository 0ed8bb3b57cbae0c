"""Round trips: decode(encode(m)) == m for every message type, arrays compared exactly."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from protocol_samples import STRATEGIES, direction_of, frame, frames, rgb_image, samples

from protocol.messages import MESSAGE_TYPES, Frame, Message, decode, encode

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def test_samples_cover_every_message_type() -> None:
    assert {type(m) for m in samples()} == set(MESSAGE_TYPES)


@pytest.mark.parametrize("msg", samples(), ids=lambda m: type(m).__name__)
def test_sample_round_trip(msg: Message) -> None:
    data = encode(msg)
    assert decode(data, direction=direction_of(msg)) == msg
    assert decode(data) == msg  # direction "any" resolves status/render by their keys


@pytest.mark.parametrize("strategy", STRATEGIES, ids=lambda s: repr(s)[:40])
def test_round_trip_property(strategy: st.SearchStrategy[Message]) -> None:
    """Each message type's strategy on its own, so every type gets a fair number of examples."""

    @SETTINGS
    @given(strategy)
    def check(msg: Message) -> None:
        _check_round_trip(msg)

    check()


def _check_round_trip(msg: Message) -> None:
    back = decode(encode(msg), direction=direction_of(msg))
    assert type(back) is type(msg)
    assert back == msg
    assert decode(encode(back)) == msg  # and "any" picks the same class


@SETTINGS
@given(frames())
def test_frame_round_trip_exact_arrays(msg: Frame) -> None:
    back = decode(encode(msg), direction="request")
    assert isinstance(back, Frame)
    assert back.rgb.dtype == np.uint8 and np.array_equal(back.rgb, msg.rgb)
    assert np.array_equal(back.world_from_cam, msg.world_from_cam)
    if msg.ov is not None:
        assert back.ov is not None and back.ov.dtype == msg.ov.dtype
        assert back.ov.tobytes() == msg.ov.tobytes()
    assert back.rgb.flags.writeable


def test_jpeg_round_trip_is_close() -> None:
    # A smooth image: JPEG at quality 90 should stay within a few grey levels on average.
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w]
    rgb = np.stack([xx * 4, yy * 5, (xx + yy) * 2], axis=-1).clip(0, 255).astype(np.uint8)
    msg = frame(width=w, height=h, rgb=rgb, rgb_encoding="jpeg")
    back = decode(encode(msg))
    assert isinstance(back, Frame)
    assert back.rgb_encoding == "jpeg" and back.rgb.shape == (h, w, 3)
    err = np.abs(back.rgb.astype(int) - rgb.astype(int))
    assert err.mean() < 3.0
    assert back.seq == msg.seq and np.array_equal(back.K, msg.K)


def test_png_round_trip_is_exact() -> None:
    msg = frame(rgb=rgb_image(seed=5), rgb_encoding="png")
    assert decode(encode(msg)) == msg


def test_unknown_keys_are_ignored() -> None:
    msg = frame()
    wire = msg.to_wire()
    wire["future_field"] = {"anything": [1, 2]}
    from protocol_samples import pack

    assert decode(pack(wire)) == msg


def test_uint16_depth_is_converted_with_depth_scale() -> None:
    from protocol_samples import H, W, frame_wire, pack

    from protocol.arrays import encode_nd

    raw = np.arange(H * W, dtype=np.uint16).reshape(H, W) * 100
    back = decode(pack(frame_wire(depth=encode_nd(raw))))
    assert isinstance(back, Frame) and back.depth_m is not None
    assert back.depth_m.dtype == np.float32
    np.testing.assert_allclose(back.depth_m, raw * 0.001, rtol=1e-6)  # default: millimetres
    back = decode(pack(frame_wire(depth=encode_nd(raw), depth_scale=0.0002)))
    assert isinstance(back, Frame) and back.depth_m is not None
    np.testing.assert_allclose(back.depth_m, raw * 0.0002, rtol=1e-6)
    assert back.depth_m[0, 0] == 0.0  # 0 stays "no depth"


def test_invalid_depth_values_become_zero() -> None:
    from protocol_samples import H, W, frame_wire, pack

    from protocol.arrays import encode_nd

    depth = np.full((H, W), 2.0, np.float32)
    depth[0, :4] = [np.nan, np.inf, -np.inf, -1.0]
    back = decode(pack(frame_wire(depth=encode_nd(depth))))
    assert isinstance(back, Frame) and back.depth_m is not None
    assert back.depth_m[0, :4].tolist() == [0.0, 0.0, 0.0, 0.0]
    assert np.all(back.depth_m[1:] == 2.0)


def test_float32_pose_with_drift_is_accepted() -> None:
    # A pose composed in float32 on a robot: R^T R is off the identity by ~1e-7..1e-5.
    angle = 0.3
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = rot @ rot @ rot
    drifted = (world_from_cam.astype(np.float32) * np.float32(1.0 + 2e-5)).astype(np.float64)
    drifted[3] = [0, 0, 0, 1]
    back = decode(encode(frame(world_from_cam=drifted)))
    assert isinstance(back, Frame)
    assert np.array_equal(back.world_from_cam, drifted)
