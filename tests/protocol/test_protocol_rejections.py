"""Every way a message can be wrong gets a clear ProtocolError with the right code."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from protocol_samples import (
    OPTIONAL_KEYS,
    H,
    K,
    W,
    direction_of,
    frame,
    frame_wire,
    pack,
    pose,
    rgb_image,
    samples,
)

from protocol.arrays import encode_image, encode_nd
from protocol.errors import ProtocolError, RemoteError
from protocol.messages import (
    ORTHONORMAL_TOL,
    Ack,
    Direction,
    Error,
    Frame,
    Load,
    Message,
    ObjectCandidate,
    Points,
    QueryPoints,
    Render,
    Save,
    Status,
    StatusRequest,
    decode,
    decode_as,
    encode,
    error_reply,
    peek_id,
)


def rejects(
    data: bytes | dict[str, Any], code: str = "bad_request", match: str = "", direction: Direction = "any"
) -> ProtocolError:
    """Assert that `data` (bytes, or a wire map to pack) is rejected with `code`; return the error."""
    raw = pack(data) if isinstance(data, dict) else data
    with pytest.raises(ProtocolError) as info:
        decode(raw, direction=direction)
    assert info.value.code == code, info.value.message
    assert match in info.value.message, info.value.message
    return info.value


def valid_frame_decodes() -> None:
    assert isinstance(decode(pack(frame_wire())), Frame)


# --- envelope ----------------------------------------------------------------------------------


@pytest.mark.parametrize("payload", [[1, 2], 5, "frame", None, 1.5, b"xyz", True])
def test_payload_not_a_map(payload: Any) -> None:
    rejects(pack(payload), match="map")


@pytest.mark.parametrize(
    "data",
    [b"", b"\xc1", b"\x81", b"\x82\xa1v\x01", b"\xda\x00\x10abc", pack({"v": 1}) + b"\x00", b"\x81\xa1v\xc7"],
    ids=["empty", "never-used-byte", "map-without-entries", "truncated-map", "truncated-str", "trailing",
         "truncated-ext"],
)
def test_undecodable_msgpack(data: bytes) -> None:
    rejects(data)


def test_truncated_frame_bytes() -> None:
    data = encode(frame())
    for cut in (1, 10, len(data) // 2, len(data) - 1):
        rejects(data[:cut])


def test_non_string_keys() -> None:
    rejects(b"\x83\xa1v\x01\xa4type\xa6status\x01\x02", match="keys must be strings")  # {..., 1: 2}
    rejects(pack({"v": 1, "type": "status", b"raw": 2}), match="keys must be strings")


def test_deep_nesting() -> None:
    rejects(b"\x91" * 100_000 + b"\x00", match="nested too deeply")


def test_bytes_like_input() -> None:
    data = encode(StatusRequest(id=1))
    assert decode(bytearray(data)) == StatusRequest(id=1)
    assert decode(memoryview(data)) == StatusRequest(id=1)
    with pytest.raises(ProtocolError, match="message must be bytes, got str"):
        decode("text")  # type: ignore[arg-type]


def test_invalid_utf8_string() -> None:
    rejects(b"\x82\xa1v\x01\xa4type\xa2\xff\xfe")


def test_hostile_length_prefixes_do_not_allocate() -> None:
    # array32 / map32 / bin32 / str32 declaring ~4 G entries or bytes in a 5..6 byte message
    for data in (b"\xdd\xff\xff\xff\xff", b"\xdf\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff\x00",
                 b"\xdb\xff\xff\xff\xff\x00"):
        rejects(data)


def test_too_large_is_checked_before_unpacking() -> None:
    data = encode(frame())
    err = rejects_max(data, len(data) - 1)
    assert str(len(data)) in err.message and str(len(data) - 1) in err.message
    assert isinstance(decode(data, max_bytes=len(data)), Frame)
    # garbage that is also too large is reported as too_large: the size check comes first
    assert rejects_max(b"\xc1" * 100, 10).code == "too_large"


def rejects_max(data: bytes, max_bytes: int) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        decode(data, max_bytes=max_bytes)
    assert info.value.code == "too_large"
    return info.value


def test_version() -> None:
    rejects(frame_wire(v=2), code="unsupported_version", match="v=2")
    rejects(frame_wire(v=0), code="unsupported_version")
    wire = frame_wire()
    del wire["v"]
    rejects(wire, match="missing protocol version")
    rejects(frame_wire(v="1"), match="v:")
    rejects(frame_wire(v=True), match="v:")


def test_type() -> None:
    rejects(frame_wire(type="teleport"), match="unknown message type")
    rejects(frame_wire(type=3), match="type")
    wire = frame_wire()
    del wire["type"]
    rejects(wire, match="type")
    # a reply type sent to a request endpoint, and the other way round
    rejects(encode(Ack(seq=1, status="accepted", map_version=0)), direction="request", match="unknown")
    rejects(encode(frame()), direction="reply", match="unknown")
    rejects(encode(Save(name="x")), direction="reply")


def test_status_direction() -> None:
    data = encode(StatusRequest(id=1))
    assert isinstance(decode(data, direction="request"), StatusRequest)
    assert isinstance(decode(data), StatusRequest)
    rejects(data, direction="reply", match="map_version")  # a status reply needs its fields


# --- missing / ill-typed fields ----------------------------------------------------------------


def _cases() -> list[tuple[Message, str]]:
    out = []
    for msg in samples():
        for key in msg.to_wire():
            if key not in ("v", "type", "id") and key not in OPTIONAL_KEYS.get(type(msg), set()):
                out.append((msg, key))
    return out


@pytest.mark.parametrize("msg,key", _cases(), ids=lambda x: x if isinstance(x, str) else type(x).__name__)
def test_missing_required_field(msg: Message, key: str) -> None:
    wire = msg.to_wire()
    del wire[key]
    rejects(wire, direction=direction_of(msg))


@pytest.mark.parametrize("msg", samples(), ids=lambda m: type(m).__name__)
def test_optional_fields_may_be_left_out(msg: Message) -> None:
    wire = msg.to_wire()
    for key in OPTIONAL_KEYS.get(type(msg), set()):
        wire.pop(key, None)
    assert type(decode(pack(wire), direction=direction_of(msg))) is type(msg)


BAD_FRAME_FIELDS: list[tuple[str, Any, str]] = [
    ("seq", "3", "seq: expected an int"),
    ("seq", 3.0, "seq: expected an int"),
    ("seq", -1, "seq: -1 out of range 0.."),
    ("seq", True, "seq: expected an int, got bool"),
    ("stamp_ns", False, "stamp_ns: expected an int, got bool"),
    ("stamp_ns", 1.5e18, "stamp_ns"),
    ("width", True, "width: expected an int, got bool"),
    ("height", "6", "height: expected an int"),
    ("width", 0, "width: 0 out of range 1..4096"),
    ("width", 4097, "width: 4097 out of range 1..4096"),
    ("height", 0, "height: 0 out of range 1..4096"),
    ("height", 4097, "height: 4097 out of range 1..4096"),
    ("K", "fx fy cx cy", "K: expected a list of 4 numbers"),
    ("K", [10.0, 11.0, 4.0], "K: expected 4 numbers, got 3"),
    ("K", [10.0, 11.0, 4.0, "3"], "K[3]: expected a number"),
    ("K", [True, 11.0, 4.0, 3.0], "K[0]: expected a number, got bool"),
    ("K", [0.0, 11.0, 4.0, 3.0], "fx and fy must be > 0"),
    ("K", [10.0, -1.0, 4.0, 3.0], "fx and fy must be > 0"),
    ("T_world_cam", [1.0] * 15, "T_world_cam: expected 16 numbers, got 15"),
    ("T_world_cam", {"R": 1}, "T_world_cam: expected a list"),
    ("T_world_cam", [[1.0, 0.0, 0.0, 0.0]] * 4, "T_world_cam: expected 16 numbers, got 4"),
    ("rgb", b"\x00" * (H * W * 3), "rgb: expected a map"),
    ("rgb", {"encoding": "rgb8"}, "rgb: image is missing 'data'"),
    ("rgb", {"encoding": "bmp", "data": b""}, "rgb: encoding 'bmp' unknown"),
    ("rgb", {"encoding": "rgb8", "data": "text"}, "rgb.data: expected binary data"),
    ("camera", 5, "camera: expected a string"),
    ("camera", "", "camera: must be a non-empty string"),
    ("depth", [[1.0] * W] * H, "depth: expected a map"),
    ("depth_scale", "mm", "depth_scale: expected a number"),
    ("depth_scale", 0.0, "depth_scale: must be > 0"),
    ("depth_scale", float("inf"), "depth_scale: must be finite"),
    ("ov_space", 3, "ov_space: expected a string"),
    ("ov_space", "", "ov_space: must be a non-empty string"),
    ("id", [1], "id: expected an int or a string"),
    ("id", 1.5, "id: expected an int or a string"),
    ("id", True, "id: expected an int or a string, got bool"),
]


@pytest.mark.parametrize(
    "key,value,match", BAD_FRAME_FIELDS, ids=[f"{k}={v!r:.20}" for k, v, _ in BAD_FRAME_FIELDS]
)
def test_frame_field_rejected(key: str, value: Any, match: str) -> None:
    rejects(frame_wire(**{key: value}), match=match)


BOOL_AS_INT: list[tuple[Message, str, Any]] = [
    (Ack(seq=1, status="accepted", map_version=0), "map_version", True),
    (Ack(seq=1, status="accepted", map_version=0), "seq", False),
    (QueryPoints(texts=["a"]), "max_points", True),
    (QueryPoints(texts=["a"]), "objects", 1),  # and int-as-bool
    (QueryPoints(texts=["a"]), "min_score", True),
    (Render(width=W, height=H, K=K, world_from_cam=pose(), outputs=["rgb"]), "width", True),
    (Status(1, 2, 3, 4, None, 5, 6.0), "keyframes", True),
    (Status(1, 2, 3, 4, None, 5, 6.0), "uptime_s", True),
]


@pytest.mark.parametrize(
    "msg,key,value", BOOL_AS_INT, ids=[f"{type(m).__name__}.{k}" for m, k, _ in BOOL_AS_INT]
)
def test_bool_is_not_an_int(msg: Message, key: str, value: Any) -> None:
    wire = msg.to_wire()
    wire[key] = value
    rejects(wire, direction=direction_of(msg), match=key)


# --- arrays ----------------------------------------------------------------------------------


def test_depth_byte_length_mismatch() -> None:
    depth = encode_nd(np.ones((H, W), np.float32))
    rejects(frame_wire(depth={**depth, "data": depth["data"][:-1]}), match="needs 192 bytes")
    longer = {**depth, "data": depth["data"] + b"\x00" * 4}
    rejects(frame_wire(depth=longer), match="depth: data is 196 bytes")


def test_depth_shape_mismatch() -> None:
    rejects(frame_wire(depth=encode_nd(np.ones((W, H), np.float32))), match="depth: dimension 0 must be 6")
    rejects(frame_wire(depth=encode_nd(np.ones((H, W, 1), np.float32))), match="expected 2 dimensions")
    rejects(frame_wire(depth={"dtype": "float32", "shape": [H, True], "data": b""}), match="shape entries")
    rejects(frame_wire(depth={"dtype": "float32", "shape": [H, -W], "data": b""}), match="shape entries")
    rejects(frame_wire(depth={"dtype": "float32", "shape": "6x8", "data": b""}), match="shape must be a list")


@pytest.mark.parametrize("dtype", ["float64", "int32", "uint8", "float16"])
def test_depth_wrong_dtype(dtype: str) -> None:
    rejects(frame_wire(depth=encode_nd(np.ones((H, W), dtype))), match=f"depth: dtype {dtype} not allowed")


def test_unknown_dtype() -> None:
    nd = {"dtype": "complex64", "shape": [H, W], "data": b"\x00" * (H * W * 8)}
    rejects(frame_wire(depth=nd), match="not a wire dtype")
    rejects(frame_wire(depth={**nd, "dtype": ">f4"}), match="not a wire dtype")


def test_ov_checks() -> None:
    rejects(frame_wire(ov=encode_nd(np.ones((2, 3, 4), np.uint8))), match="ov: dtype uint8 not allowed")
    rejects(frame_wire(ov=encode_nd(np.ones((2, 3), np.float32))), match="ov: expected 3 dimensions")
    rejects(frame_wire(ov=encode_nd(np.ones((0, 3, 4), np.float32))), match="out of range 1..4096")
    rejects(frame_wire(ov=encode_nd(np.ones((1, 1, 4097), np.float16))), match="d = 4097 out of range")
    rejects(frame_wire(ov=encode_nd(np.full((1, 1, 4), np.nan, np.float32))), match="NaN or Inf")
    ov = encode_nd(np.ones((2, 3, 4), np.float32))
    rejects(frame_wire(ov={**ov, "data": ov["data"][:-2]}), match="ov: data is")


def test_ov_without_ov_space_and_the_reverse() -> None:
    wire = frame_wire()
    del wire["ov_space"]
    rejects(wire, match="ov_space: required when ov is sent")
    wire = frame_wire()
    del wire["ov"]
    rejects(wire, match="ov_space: sent without ov")
    rejects(frame_wire(ov_space=None), match="ov_space: required")


# --- camera and pose ---------------------------------------------------------------------------


@pytest.mark.parametrize("index", range(4))
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_K(index: int, bad: float) -> None:
    k = K.tolist()
    k[index] = bad
    rejects(frame_wire(K=k), match="K: values must be finite")


@pytest.mark.parametrize("index", [0, 5, 3, 7, 11, 12, 15])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_pose(index: int, bad: float) -> None:
    flat = pose().reshape(16).tolist()
    flat[index] = bad
    rejects(frame_wire(T_world_cam=flat), match="T_world_cam: values must be finite")


def _with_rotation(rot: np.ndarray) -> list[float]:
    world_from_cam = pose()
    world_from_cam[:3, :3] = rot
    return world_from_cam.reshape(16).tolist()


def test_non_orthonormal_rotation() -> None:
    rejects(frame_wire(T_world_cam=_with_rotation(np.eye(3) * 1.01)), match="not orthonormal")
    shear = np.eye(3)
    shear[0, 1] = 0.01
    rejects(frame_wire(T_world_cam=_with_rotation(shear)), match="not orthonormal")
    rejects(frame_wire(T_world_cam=_with_rotation(np.zeros((3, 3)))), match="not orthonormal")
    # just inside the tolerance is accepted
    almost = np.eye(3) * (1 + 0.4 * ORTHONORMAL_TOL)
    assert isinstance(decode(pack(frame_wire(T_world_cam=_with_rotation(almost)))), Frame)


def test_reflection_det_negative() -> None:
    err = rejects(frame_wire(T_world_cam=_with_rotation(np.diag([1.0, 1.0, -1.0]))), match="det")
    assert "-1" in err.message


@pytest.mark.parametrize("last", [[0, 0, 0, 2], [0.1, 0, 0, 1], [0, 0, 0, 0], [0, 0, 1e-5, 1]])
def test_bad_last_row(last: list[float]) -> None:
    flat = pose().reshape(16).tolist()
    flat[12:] = last
    rejects(frame_wire(T_world_cam=flat), match="last row must be [0, 0, 0, 1]")


def test_render_request_camera_is_validated_too() -> None:
    wire = Render(width=W, height=H, K=K, world_from_cam=pose(), outputs=["rgb"]).to_wire()
    rejects({**wire, "T_world_cam": _with_rotation(np.diag([1.0, -1.0, 1.0]))}, match="det")
    rejects({**wire, "K": [math.nan, 1, 1, 1]}, match="finite")
    rejects({**wire, "width": 4097}, match="width: 4097 out of range 1..4096")


# --- images ----------------------------------------------------------------------------------


def test_rgb_of_another_size() -> None:
    rejects(frame_wire(rgb=encode_image(rgb_image(H, W + 1))), match="rgb8 data is")
    rejects(frame_wire(rgb=encode_image(rgb_image(H - 1, W))), match=f"but {W}x{H}x3 needs {W * H * 3} bytes")
    # (a transposed rgb8 image has the same byte count: nothing on the wire can tell it apart)
    rejects(frame_wire(rgb=encode_image(rgb_image(H + 1, W), "png")), match="png image is 8x7")
    rejects(frame_wire(rgb=encode_image(rgb_image(H, W + 2), "jpeg")), match="jpeg image is 10x6")


def test_undecodable_images() -> None:
    rejects(frame_wire(rgb={"encoding": "jpeg", "data": b"not a jpeg"}), match="not a decodable jpeg")
    rejects(frame_wire(rgb={"encoding": "png", "data": b"\x89PNG\r\n\x1a\n"}), match="not a decodable png")
    rejects(frame_wire(rgb={"encoding": "jpeg", "data": b""}), match="not a decodable jpeg")
    png = encode_image(rgb_image(), "png")["data"]
    rejects(frame_wire(rgb={"encoding": "png", "data": png[:40]}), match="not a decodable png")
    jpeg = encode_image(rgb_image(), "jpeg")["data"]
    rejects(frame_wire(rgb={"encoding": "png", "data": jpeg}), match="not a decodable png")


def test_image_bomb_is_rejected_before_decoding() -> None:
    png = bytearray(encode_image(rgb_image(), "png")["data"])
    png[16:24] = (60000).to_bytes(4, "big") + (60000).to_bytes(4, "big")  # IHDR says 60000x60000
    rejects(frame_wire(rgb={"encoding": "png", "data": bytes(png)}), match="png image is 60000x60000")


# --- requests ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["../x", "", "a" * 65, "a/b", ".", "..", "x y", "é", 5, None])
def test_bad_map_names(name: Any) -> None:
    for cls in (Save, Load):
        wire = {"v": 1, "type": cls.TYPE, "name": name}
        rejects(wire, direction="request", match="name")
        with pytest.raises(ProtocolError):
            cls(name=name)


def test_good_map_names() -> None:
    for name in ("a" * 64, "kitchen-1.v2_final", "...", ".hidden"):
        assert decode(encode(Save(name=name))) == Save(name=name)


@pytest.mark.parametrize(
    "texts,match",
    [([], "0 strings, allowed 1..64"), (["t"] * 65, "65 strings, allowed 1..64"),
     ([1], "texts[0]: expected a string"), ([""], "texts[0]: must be a non-empty"),
     ("chair", "expected a list"), (["a", None], "texts[1]"),
     (["x" * 1025], "at most 1024"), (["chair", " \t\n"], "texts[1]: only whitespace")],
    ids=["empty", "65", "non-str", "empty-str", "str", "none", "long", "whitespace"],
)
def test_bad_texts(texts: Any, match: str) -> None:
    wires = [
        {"v": 1, "type": "query_points", "texts": texts},
        {"v": 1, "type": "segment_points", "texts": texts, "xyz": encode_nd(np.zeros((1, 3), np.float32))},
        {**Render(width=W, height=H, K=K, world_from_cam=pose(), outputs=["label"], texts=["a"]).to_wire(),
         "texts": texts},
    ]
    for wire in wires:
        rejects(wire, direction="request", match=match)


def test_query_points_fields() -> None:
    base = QueryPoints(texts=["a"]).to_wire()
    rejects({**base, "negatives": ["ok", 3]}, match="negatives[1]")
    rejects({**base, "negatives": ["n"] * 65}, match="negatives: 65 strings")
    rejects({**base, "min_score": math.nan}, match="min_score: must be finite")
    rejects({**base, "min_score": "high"}, match="min_score: expected a number")
    rejects({**base, "max_points": 0}, match="max_points: 0 out of range 1..")
    rejects({**base, "objects": "yes"}, match="objects: expected a bool")
    assert decode(pack({**base, "negatives": []})) == QueryPoints(texts=["a"], negatives=[])


def test_segment_points_fields() -> None:
    wire = {"v": 1, "type": "segment_points", "texts": ["a"], "xyz": encode_nd(np.zeros((2, 3), np.float32))}
    assert decode(pack(wire)).method == "govnesf"  # type: ignore[attr-defined]
    rejects({**wire, "method": "knn"}, match="method: 'knn' unknown")
    rejects({**wire, "use_depth": 1}, match="use_depth: expected a bool")
    rejects({**wire, "xyz": encode_nd(np.zeros((2, 3), np.float64))}, match="xyz: dtype float64 not allowed")
    rejects({**wire, "xyz": encode_nd(np.zeros((2, 2), np.float32))}, match="xyz: dimension 1 must be 3")
    inf = encode_nd(np.full((2, 3), np.inf, np.float32))
    rejects({**wire, "xyz": inf}, match="xyz: points must be finite")


def test_render_outputs() -> None:
    wire = Render(width=W, height=H, K=K, world_from_cam=pose(), outputs=["rgb"]).to_wire()
    rejects({**wire, "outputs": []}, match="outputs: expected a non-empty list")
    rejects({**wire, "outputs": ["normals"]}, match="outputs: 'normals' unknown")
    rejects({**wire, "outputs": ["rgb", "rgb"]}, match="repeated")
    rejects({**wire, "outputs": ["rgb", "label"]}, match="texts: required")
    rejects({**wire, "outputs": ["score"]}, match="texts: required")
    rejects({**wire, "outputs": "rgb"}, match="outputs")


# --- replies ---------------------------------------------------------------------------------


def test_reply_fields() -> None:
    ack = Ack(seq=1, status="accepted", map_version=0).to_wire()
    rejects({**ack, "status": "maybe"}, direction="reply", match="status: 'maybe' unknown")
    rejects({**ack, "status": "rejected"}, direction="reply", match="reason: required")
    err = Error(code="busy", message="m").to_wire()
    rejects({**err, "code": "oops"}, direction="reply", match="code: 'oops' unknown")
    pts = Points(0, np.zeros((2, 3), np.float32), np.zeros(2, np.float32), np.zeros(2, np.int32)).to_wire()
    three = encode_nd(np.zeros(3, np.int32))
    rejects({**pts, "label": three}, direction="reply", match="label: dimension 0 must be 2")
    rejects({**pts, "objects": [{"text": "a"}]}, direction="reply",
            match="objects[0]: missing required field 'centroid'")
    rejects({**pts, "timing_ms": {"a": "1"}}, direction="reply", match="timing_ms.a")
    obj = ObjectCandidate("a", np.zeros(3), np.zeros(3), np.ones(3), 0.5, 1).to_wire()
    rejects({**pts, "objects": [obj, {**obj, "centroid": [0, 0]}]}, direction="reply",
            match="objects[1]: centroid: expected 3 numbers, got 2")
    rejects({**pts, "objects": [{**obj, "n_points": -1}]}, direction="reply",
            match="objects[0]: n_points: -1")
    rejects({**pts, "objects": [{**obj, "aabb_max": [0, math.inf, 0]}]}, direction="reply",
            match="objects[0]: aabb_max: values must be finite")
    status = Status(1, 2, 3, 4, None, 5, 6.0).to_wire()
    rejects({**status, "uptime_s": -1.0}, direction="reply", match="uptime_s")
    rejects({**status, "frames_received": -1}, direction="reply", match="frames_received: -1 out of range")
    with pytest.raises(ProtocolError, match="clash"):
        Status(1, 2, 3, 4, None, 5, 6.0, extra={"keyframes": 3})


def test_render_reply_sizes() -> None:
    rgb = rgb_image()
    wire = {"v": 1, "type": "render", "rgb": encode_image(rgb), "timing_ms": {}}
    rejects(wire, direction="reply", match="without width/height")
    sized = {**wire, "depth": encode_nd(np.ones((H, W), np.float32))}
    back = decode(pack(sized), direction="reply")
    assert np.array_equal(back.rgb, rgb)  # type: ignore[attr-defined]
    rejects({**sized, "label": encode_nd(np.ones((H + 1, W), np.int32))}, direction="reply", match="label")


def test_errors_change_nothing_in_the_caller_objects() -> None:
    wire = frame_wire(K=[math.nan, 1, 1, 1])
    before = pack(wire)
    rejects(wire)
    assert pack(wire) == before


# --- helpers used by servers and clients -------------------------------------------------------


def test_peek_id() -> None:
    assert peek_id(encode(frame(id=42))) == 42
    assert peek_id(encode(QueryPoints(texts=["a"], id="req-7"))) == "req-7"
    assert peek_id(pack({"v": 1, "type": "query_points", "id": 9})) == 9  # invalid message, id still found
    assert peek_id(pack({"v": 2, "id": "x", "type": "nope"})) == "x"
    assert peek_id(pack({"id": True})) is None
    assert peek_id(pack({"id": [1]})) is None
    assert peek_id(pack({"v": 1})) is None
    assert peek_id(pack([1, 2])) is None
    assert peek_id(b"\xc1\x00") is None
    assert peek_id(b"") is None
    big = encode(frame(id=5))
    assert peek_id(big[: len(big) // 2]) in (5, None)  # truncated: best effort, never raises


def test_error_reply() -> None:
    exc = ProtocolError("bad_request", "width: 0 out of range 1..4096")
    reply = error_reply(exc, id=3)
    assert reply == Error(code="bad_request", message="width: 0 out of range 1..4096", id=3)
    assert decode(encode(reply), direction="reply") == reply
    assert error_reply(exc, id=True).id is None
    with pytest.raises(ValueError):
        ProtocolError("nope", "x")  # type: ignore[arg-type]


def test_decode_as() -> None:
    pts = Points(1, np.zeros((1, 3), np.float32), np.zeros(1, np.float32), np.zeros(1, np.int32), id=4)
    assert decode_as(encode(pts), Points) == pts
    with pytest.raises(RemoteError) as info:
        decode_as(encode(Error(code="not_ready", message="no keyframes yet", id=4)), Points)
    assert info.value.code == "not_ready" and info.value.id == 4 and "no keyframes" in info.value.message
    with pytest.raises(ProtocolError, match="expected a 'points' message"):
        decode_as(encode(Ack(seq=1, status="accepted", map_version=0)), Points)
    with pytest.raises(ProtocolError) as err:
        decode_as(encode(pts), Points, max_bytes=10)
    assert err.value.code == "too_large"


def test_constructing_invalid_messages_raises() -> None:
    with pytest.raises(ProtocolError, match="rgb: expected shape"):
        frame(rgb=rgb_image(H + 1, W))
    with pytest.raises(ProtocolError, match="rgb: expected dtype uint8"):
        frame(rgb=rgb_image().astype(np.float32))
    with pytest.raises(ProtocolError, match="depth: expected dtype float32"):
        frame(depth_m=np.ones((H, W)))
    with pytest.raises(ProtocolError, match="rgb_encoding"):
        frame(rgb_encoding="webp")
