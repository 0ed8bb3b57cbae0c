"""Wire protocol v1: every message type, declared once as a field table, with validation.

This module is the only place that knows the wire layout. Each message type is a dataclass
declared with `@message` whose fields are declared with `wire(...)`: the field's kind (its wire
type, validation and codec), wire name, unit and whether it is required. From that one
declaration (the machinery is protocol/fields.py) the class gets `FIELDS` (its field table,
which docs/reference/protocol.md shows row for row), `to_wire()` (-> the msgpack map), `from_wire(obj)`
(validating) and the checks run at construction. Python field names are snake_case SI
(`world_from_cam`, `depth_m`); wire names are exactly those of docs/reference/protocol.md
(`T_world_cam`, `depth`).

Validation happens at construction (``__post_init__``), so a message built in Python and a
message decoded from the wire obey the same rules, and `ProtocolError("bad_request")` says what
was wrong, with the value received and the allowed range. Checks that span fields (an `ov`
needs its `ov_space`) are each message's small `_check` hook.

Examples:
    >>> import numpy as np
    >>> msg = QueryPoints(texts=["chair"], id=7)
    >>> decode(encode(msg)) == msg
    True
    >>> decode(encode(Ack(seq=3, status="keyframe", map_version=1, id=7))).status
    'keyframe'
    >>> [f.row for f in Ack.FIELDS][:2]
    [('seq', 'int >= 0', '', 'yes'), ('status', 'str (keyframe, accepted, rejected)', '', 'yes')]
    >>> [f.wire for f in Frame.FIELDS if f.py == "world_from_cam"]
    ['T_world_cam']
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import fields
from typing import Any, ClassVar, Literal, TypeVar

import msgpack
import numpy as np

from protocol.arrays import decode_nd, encode_nd
from protocol.errors import ERROR_CODES, ErrorCode, ProtocolError, RemoteError
from protocol.fields import (
    Array,
    Bool,
    Ctx,
    Float,
    Id,
    Image,
    ImageEncoding,
    Int,
    Kind,
    LateImage,
    Objects,
    OneOf,
    Rest,
    Str,
    StrMap,
    Subset,
    Texts,
    Timing,
    Vector,
    WireField,
    bad,
    check_fields,
    check_str_map,
    equal,
    fields_from_wire,
    fields_to_wire,
    is_int,
    message,
    short,
    type_name,
    wire,
    wire_only,
)

PROTOCOL_VERSION = 1
"""The wire protocol version this module speaks (`v` in every message)."""

MAX_MESSAGE_BYTES = 256 * 1024 * 1024
"""Default largest encoded message `decode` accepts (bytes); larger ones get `too_large`."""

MAX_IMAGE_SIDE = 4096
"""Image width/height range is 1..MAX_IMAGE_SIDE pixels (frames and render requests)."""

MAX_OV_SIDE = 4096
"""Feature map `ov` height/width range is 1..MAX_OV_SIDE."""

MAX_OV_DIM = 4096
"""Feature map `ov` channel count range is 1..MAX_OV_DIM."""

MAX_TEXTS = 64
"""Most prompts in `texts` (and in `negatives`)."""

MAX_TEXT_CHARS = 1024
"""Longest single prompt, characters."""

MAX_NAME_CHARS = 128
"""Longest camera name / ov_space name, characters."""

MAX_ID_CHARS = 256
"""Longest string request id, characters."""

ORTHONORMAL_TOL = 1e-3
"""Tolerance on the rotation block of `T_world_cam`: max|R^T R - I| <= ORTHONORMAL_TOL.

Poses are often sent as float32 and composed from several transforms on the robot (odometry
times extrinsics), which leaves R^T R off the identity by ~1e-6..1e-4. 1e-3 accepts those while
still rejecting scaled, sheared or garbage matrices. det(R) must also be > 0 (no reflections).
"""

LAST_ROW_TOL = 1e-6
"""Tolerance on the last row of `T_world_cam`, which must be [0, 0, 0, 1]."""

DEFAULT_DEPTH_SCALE = 0.001
"""Metres per unit of uint16 wire depth when `depth_scale` is not sent (millimetres)."""

RENDER_OUTPUTS: tuple[str, ...] = ("rgb", "depth", "label", "score")
"""Outputs a `render` request may ask for."""

SEGMENT_METHODS: tuple[str, ...] = ("govnesf", "average", "average_depth")
"""`segment_points` methods."""

ANSWER_SOURCES: tuple[str, ...] = ("none", "window", "map")
"""Values of the optional `source` of `segmentation` and `render` replies, by code: 0 = no source
(unlabelled), 1 = the keyframe window, 2 = the global map's fused features."""

ACK_STATUSES: tuple[str, ...] = ("keyframe", "accepted", "rejected")
"""`ack` statuses."""

NAME_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
"""Allowed `save`/`load` map names (besides which "." and ".." are refused)."""

MAX_ROBOT_CHARS = 32
"""Longest robot name of a `frame`, characters."""

ROBOT_RE = re.compile(rf"[A-Za-z0-9_.\-]{{0,{MAX_ROBOT_CHARS}}}")
"""Allowed robot names of a `frame`: "" (the default robot) or 1..32 characters of [A-Za-z0-9_.-]."""

Direction = Literal["request", "reply", "any"]
RequestId = int | str | None


# ----------------------------------------------------------------------------------------------
# Kinds of this protocol's own (the generic ones are in protocol/fields.py)
# ----------------------------------------------------------------------------------------------


class Intrinsics(Vector):
    """K = [fx, fy, cx, cy] (4 numbers), pixels; fx, fy > 0."""

    def __init__(self) -> None:
        super().__init__((4,))

    def check(self, name: str, value: Any, ctx: Ctx) -> np.ndarray:
        K = super().check(name, value, ctx)
        if not (K[0] > 0 and K[1] > 0):
            raise bad(f"{name}: fx and fy must be > 0, got fx={K[0]} fy={K[1]}")
        return K


class Pose(Vector):
    """A (4, 4) rigid transform sent as 16 row-major numbers: last row [0, 0, 0, 1] within
    `LAST_ROW_TOL`, rotation block orthonormal within `ORTHONORMAL_TOL` with det > 0."""

    def __init__(self) -> None:
        super().__init__((4, 4))

    def check(self, name: str, value: Any, ctx: Ctx) -> np.ndarray:
        pose = super().check(name, value, ctx)
        last = pose[3]
        if np.max(np.abs(last - np.array([0.0, 0.0, 0.0, 1.0]))) > LAST_ROW_TOL:
            raise bad(f"{name}: last row must be [0, 0, 0, 1], got {last.tolist()}")
        rot = pose[:3, :3]
        err = float(np.max(np.abs(rot.T @ rot - np.eye(3))))
        if err > ORTHONORMAL_TOL:
            raise bad(
                f"{name}: rotation block is not orthonormal: max|R^T R - I| = {err:.3g} "
                f"> tolerance {ORTHONORMAL_TOL}"
            )
        det = float(np.linalg.det(rot))
        if det <= 0:
            raise bad(f"{name}: rotation block has det {det:.3g}; must be > 0 (a rotation, no reflection)")
        return pose


class Depth(Array):
    """(H, W) depth in metres, float32; uint16 on the wire is scaled by the message's
    `depth_scale` (default `DEFAULT_DEPTH_SCALE`). Non-finite and negative depths become 0."""

    def __init__(self) -> None:
        super().__init__("float32", ("H", "W"), wire_dtypes=("float32", "uint16"), coerce=False)

    def check(self, name: str, value: Any, ctx: Ctx) -> np.ndarray:
        depth = super().check(name, value, ctx)
        valid = np.isfinite(depth) & (depth > 0)
        if not np.all(valid | (depth == 0)):
            depth = np.where(valid, depth, np.float32(0.0)).astype(np.float32)
        return depth

    def decode(self, name: str, raw: Any, ctx: Ctx) -> np.ndarray:
        depth = super().decode(name, raw, ctx)
        if depth.dtype == np.uint16:
            scale = ctx.values.get("depth_scale", DEFAULT_DEPTH_SCALE)
            depth = (depth.astype(np.float64) * scale).astype(np.float32)
        return depth


def all_finite(value: np.ndarray) -> bool:
    """Whether every element of a float16 or float32 array is finite. float16 by its bits (an
    exponent of all ones is Inf or NaN): numpy's ``isfinite`` has no fast path for half floats, and a
    384-d map at 160 x 120 took 26 ms a frame that way."""
    if value.dtype == np.float16:
        bits = np.ascontiguousarray(value).view(np.uint16)
        return not bool(np.any((bits & np.uint16(0x7C00)) == np.uint16(0x7C00)))
    return bool(np.all(np.isfinite(value)))


class FeatureMap(Kind):
    """A precomputed (h, w, d) OV feature map, float16 or float32 (kept as received), finite,
    1 <= h, w <= `MAX_OV_SIDE`, 1 <= d <= `MAX_OV_DIM`."""

    TYPE_DOC: ClassVar[str] = "nd float16/float32 [h,w,d]"
    rank: ClassVar[int] = 1

    def check(self, name: str, value: Any, ctx: Ctx) -> np.ndarray:
        if not isinstance(value, np.ndarray) or value.dtype not in (np.float16, np.float32):
            got = value.dtype if isinstance(value, np.ndarray) else type_name(value)
            raise bad(f"{name}: expected a float16 or float32 array, got {got}")
        if value.ndim != 3:
            raise bad(f"{name}: expected shape (h, w, d), got {value.shape}")
        h, w, d = value.shape
        if not (1 <= h <= MAX_OV_SIDE and 1 <= w <= MAX_OV_SIDE):
            raise bad(f"{name}: h, w = {h}, {w} out of range 1..{MAX_OV_SIDE}")
        if not 1 <= d <= MAX_OV_DIM:
            raise bad(f"{name}: feature dimension d = {d} out of range 1..{MAX_OV_DIM}")
        if not all_finite(value):
            raise bad(f"{name}: feature map contains NaN or Inf")
        return value

    def encode(self, value: Any, msg: Any) -> Any:
        return encode_nd(value)

    def decode(self, name: str, raw: Any, ctx: Ctx) -> np.ndarray:
        return decode_nd(raw, field=name, dtypes=("float16", "float32"), ndim=3)


class MapName(Kind):
    """A `save`/`load` map name: `NAME_RE`, and not "." or ".."."""

    TYPE_DOC: ClassVar[str] = "str"

    def check(self, name: str, value: Any, ctx: Ctx) -> str:
        if not isinstance(value, str):
            raise bad(f"{name}: expected a string, got {type_name(value)} {short(value)}")
        if not NAME_RE.fullmatch(value) or value in (".", ".."):
            raise bad(
                f"{name}: {short(value)} is not a valid map name; use 1..64 characters from "
                "[A-Za-z0-9_.-], not '.' or '..'"
            )
        return value


class RobotName(Kind):
    """A `frame`'s robot name: `ROBOT_RE` ("" is the default robot)."""

    TYPE_DOC: ClassVar[str] = "str"

    def check(self, name: str, value: Any, ctx: Ctx) -> str:
        if not isinstance(value, str):
            raise bad(f"{name}: expected a string, got {type_name(value)} {short(value)}")
        if not ROBOT_RE.fullmatch(value):
            raise bad(
                f"{name}: {short(value)} is not a valid robot name; use 0..{MAX_ROBOT_CHARS} characters "
                "from [A-Za-z0-9_.-] (\"\" is the default robot)"
            )
        return value


COUNT = Int(lo=0)
SIDE = Int(1, MAX_IMAGE_SIDE)
NAME = Str(MAX_NAME_CHARS)
NOTE = Str(2**20, nonempty=False)
TEXTS = Texts(1, MAX_TEXTS, MAX_TEXT_CHARS)
TIMING = Timing()
ID = Id(MAX_ID_CHARS)


# ----------------------------------------------------------------------------------------------
# Message base
# ----------------------------------------------------------------------------------------------


def _check_header(obj: dict[str, Any]) -> None:
    if "v" not in obj:
        raise bad("missing protocol version 'v' (this node speaks v=1)")
    v = obj["v"]
    if not is_int(v):
        raise bad(f"v: expected an int protocol version, got {type_name(v)} {short(v)}")
    if v != PROTOCOL_VERSION:
        raise ProtocolError(
            "unsupported_version", f"protocol version v={v} is not supported; this node speaks v=1"
        )
    if "type" not in obj:
        raise bad("missing message 'type'")
    if not isinstance(obj["type"], str):
        raise bad(f"type: expected a string, got {type_name(obj['type'])} {short(obj['type'])}")


def _check_message(obj: Any, type_: str) -> dict[str, Any]:
    if not isinstance(obj, dict):
        raise bad(f"message must be a map, got {type_name(obj)}")
    for key in obj:
        if not isinstance(key, str):
            raise bad(f"message keys must be strings, got {type_name(key)} {short(key)}")
    _check_header(obj)
    if obj["type"] != type_:
        raise bad(f"type: expected {type_!r}, got {obj['type']!r}")
    return obj


_MessageT = TypeVar("_MessageT", bound="Message")  # typing.Self is Python >= 3.11


class Message:
    """Base of every wire message: validation, `to_wire` and `from_wire`, all derived from the
    class's field table (`@message` and `wire(...)`, protocol/fields.py). `_check` is the hook
    for rules that span fields. Equality compares arrays exactly."""

    TYPE: ClassVar[str]
    NESTED: ClassVar[bool] = False
    """A map inside a message (no `v`/`type` header), e.g. `ObjectCandidate`."""
    WIRE_ONLY: ClassVar[tuple[WireField, ...]] = ()
    """Wire keys without a Python attribute (see `protocol.fields.wire_only`)."""
    FIELDS: ClassVar[tuple[WireField, ...]] = ()
    """The field table, in declaration order (set by `@message`)."""
    WIRE_KEYS: ClassVar[frozenset[str]] = frozenset()
    ENCODE_ORDER: ClassVar[tuple[WireField, ...]] = ()
    DECODE_ORDER: ClassVar[tuple[WireField, ...]] = ()

    def __post_init__(self) -> None:
        check_fields(self)
        self._check()

    def _check(self) -> None:
        """Rules that span fields (run after every field is checked)."""

    def __eq__(self, other: object) -> bool:
        if type(self) is not type(other):
            return NotImplemented
        return all(equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))  # type: ignore[arg-type]

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        """Like the dataclass repr, but arrays are summarised (frames stay one short log line)."""
        parts = []
        for f in fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                text = f"<{value.dtype} {tuple(value.shape)}>" if value.size > 16 else repr(value.tolist())
            elif isinstance(value, list) and len(value) > 8:
                text = f"<list of {len(value)}>"
            else:
                text = short(value)
            parts.append(f"{f.name}={text}")
        return f"{type(self).__name__}({', '.join(parts)})"

    def to_wire(self) -> dict[str, Any]:
        """The msgpack map: `v`, `type`, `id`, then the fields (see `fields_to_wire`)."""
        head: dict[str, Any] = {} if self.NESTED else {"v": PROTOCOL_VERSION, "type": self.TYPE}
        return fields_to_wire(self, head)

    @classmethod
    def from_wire(cls: type[_MessageT], obj: Any) -> _MessageT:
        """Validate a decoded wire map and build the message (see `fields_from_wire`)."""
        if cls.NESTED:
            return cls(**fields_from_wire(cls, check_str_map(cls.TYPE, obj), ""))
        return cls(**fields_from_wire(cls, _check_message(obj, cls.TYPE), f"{cls.TYPE}: "))


# ----------------------------------------------------------------------------------------------
# Ingest: frame / ack
# ----------------------------------------------------------------------------------------------


@message
class Frame(Message):
    """One camera frame sent to the ingest endpoint (wire type ``frame``)."""

    TYPE: ClassVar[str] = "frame"

    seq: int = wire(COUNT, doc="Sender's sequence number, >= 0.")
    stamp_ns: int = wire(Int(), unit="ns", doc="Capture time, nanoseconds (sender's clock).")
    width: int = wire(SIDE, unit="px", dim="W", doc="Image width, pixels, 1..4096.")
    height: int = wire(SIDE, unit="px", dim="H", doc="Image height, pixels, 1..4096.")
    K: np.ndarray = wire(
        Intrinsics(), unit="px", doc="(4,) float64 [fx, fy, cx, cy] for the image as sent; fx, fy > 0."
    )
    world_from_cam: np.ndarray = wire(
        Pose(), name="T_world_cam", unit="m",
        doc="(4, 4) float64 camera-to-world pose (OpenCV optical camera, world +z up), metres.",
    )
    rgb: np.ndarray = wire(Image(encoding_attr="rgb_encoding"), doc="(H, W, 3) uint8 colour image, R, G, B.")
    camera: str = wire(NAME, default="cam0", before="width", doc="Camera name.")
    robot: str = wire(
        RobotName(), default="", omit_default=True, before="width",
        doc='Robot name: each robot has its own keyframe window in the node; "" (the default, not sent) '
        "is the default robot.",
    )
    depth_m: np.ndarray | None = wire(
        Depth(), name="depth", unit="m", default=None,
        doc="(H, W) float32 depth along the optical axis (z); 0 = unknown (non-finite/negative become 0).",
    )
    ov: np.ndarray | None = wire(
        FeatureMap(), default=None, doc="Precomputed open-vocabulary feature map, dtype as received."
    )
    ov_space: str | None = wire(
        NAME, required="if ov", default=None, doc='Embedding space of `ov` (e.g. ``"minilm-l6-v2"``).'
    )
    rgb_encoding: str = wire(
        ImageEncoding("rgb"), default="rgb8",
        doc="Encoding `to_wire` uses for `rgb`; after `from_wire`, the encoding that was received.",
    )
    id: RequestId = wire(ID, default=None)

    WIRE_ONLY: ClassVar[tuple[WireField, ...]] = (
        wire_only(
            "depth_scale", Float(positive=True), unit="m/unit", default=DEFAULT_DEPTH_SCALE,
            doc="Metres per unit of uint16 `depth` (ignored for float32 depth).",
        ),
    )

    def _check(self) -> None:
        if self.ov is not None and self.ov_space is None:
            raise bad("ov_space: required when ov is sent (name the embedding space, e.g. 'minilm-l6-v2')")
        if self.ov_space is not None and self.ov is None:
            raise bad("ov_space: sent without ov (send both or neither)")


AckStatus = Literal["keyframe", "accepted", "rejected"]


@message
class Ack(Message):
    """Reply to every `frame` that was not an error (wire type ``ack``)."""

    TYPE: ClassVar[str] = "ack"

    seq: int = wire(COUNT, doc="The acknowledged frame's `seq`.")
    status: AckStatus = wire(
        OneOf(ACK_STATUSES),
        doc='``"keyframe"`` (added to the window), ``"accepted"`` (valid, not a keyframe), ``"rejected"``.',
    )
    map_version: int = wire(COUNT, doc="Map version after handling the frame.")
    reason: str | None = wire(
        NOTE, required="if status is rejected", default=None,
        doc='Why the frame was rejected (required for ``"rejected"``), or a note.',
    )
    id: RequestId = wire(ID, default=None)

    def _check(self) -> None:
        if self.status == "rejected" and not self.reason:
            raise bad("reason: required when status is 'rejected'")


@message
class Error(Message):
    """Error reply to any request (wire type ``error``)."""

    TYPE: ClassVar[str] = "error"

    code: ErrorCode = wire(OneOf(ERROR_CODES), doc="One of `protocol.errors.ERROR_CODES`.")
    message: str = wire(NOTE, doc="What was wrong, with the value received and the allowed range.")
    id: RequestId = wire(ID, default=None)


# ----------------------------------------------------------------------------------------------
# Query endpoint
# ----------------------------------------------------------------------------------------------


@message
class QueryPoints(Message):
    """"Find the chair": request map points matching texts (wire type ``query_points``)."""

    TYPE: ClassVar[str] = "query_points"

    texts: list[str] = wire(TEXTS, doc="1..64 non-empty prompts.")
    negatives: list[str] | None = wire(
        Texts(0, MAX_TEXTS, MAX_TEXT_CHARS), default=None,
        doc="Background prompts (0..64); None = the mapper's default set.",
    )
    min_score: float | None = wire(Float(), default=None, doc="Drop points whose best similarity is lower.")
    max_points: int | None = wire(Int(lo=1), default=None, doc="Return at most this many points, best first.")
    objects: bool = wire(Bool(), default=True, doc="Also group points into object candidates.")
    id: RequestId = wire(ID, default=None)
    settle_timeout_s: float | None = wire(
        Float(lo=0.0), unit="s", default=None,
        doc="Answer from the settled map: wait up to this long for the node's background work on the frames "
        "acked so far (extension; the node caps it at `queries.max_settle_wait_s`).",
    )
    region_min: np.ndarray | None = wire(
        Vector((3,)), unit="m", default=None, required="with region_max",
        doc="Only map points inside the axis-aligned box [region_min, region_max] (world; extension).",
    )
    region_max: np.ndarray | None = wire(
        Vector((3,)), unit="m", default=None, required="with region_min", doc="The box's maximum corner.",
    )

    def _check(self) -> None:
        if (self.region_min is None) != (self.region_max is None):
            raise bad("region_min and region_max: give both or neither")
        if self.region_min is not None and self.region_max is not None:
            low, high = np.asarray(self.region_min), np.asarray(self.region_max)
            if np.any(low > high):
                raise bad(f"region_min {low.tolist()} exceeds region_max {high.tolist()} on an axis")


@message
class ObjectCandidate(Message):
    """One object candidate in a `points` reply (a map inside the message, not a message)."""

    TYPE: ClassVar[str] = "object"
    NESTED: ClassVar[bool] = True

    text: str = wire(Str(MAX_TEXT_CHARS, nonempty=False), doc="The prompt the object matched.")
    centroid: np.ndarray = wire(Vector((3,)), unit="m", doc="Centroid of the object's points, world frame.")
    aabb_min: np.ndarray = wire(Vector((3,)), unit="m", doc="Axis-aligned box minimum corner, world frame.")
    aabb_max: np.ndarray = wire(Vector((3,)), unit="m", doc="Axis-aligned box maximum corner, world frame.")
    score: float = wire(Float(finite=False), doc="Object score (similarity), higher is better.")
    n_points: int = wire(COUNT, doc="Number of map points in the object.")


@message
class Points(Message):
    """Reply to `query_points` (wire type ``points``)."""

    TYPE: ClassVar[str] = "points"

    map_version: int = wire(COUNT, doc="Map version the points come from.")
    xyz: np.ndarray = wire(Array("float32", ("N", 3)), unit="m", doc="(N, 3) matching points, world frame.")
    score: np.ndarray = wire(Array("float32", ("N",)), doc="Similarity of each point to its best text.")
    label: np.ndarray = wire(Array("int32", ("N",)), doc="Index into the request's `texts`.")
    objects: list[ObjectCandidate] = wire(
        Objects(ObjectCandidate), default_factory=list, doc="Object candidates, sorted by score (best first)."
    )
    timing_ms: dict[str, float] = wire(TIMING, unit="ms", default_factory=dict, doc="Wall time per stage.")
    id: RequestId = wire(ID, default=None)
    settled: bool | None = wire(
        Bool(), default=None,
        doc="Whether the node had no background work pending for acked frames when it answered (extension).",
    )


SegmentMethod = Literal["govnesf", "average", "average_depth"]


@message
class SegmentPoints(Message):
    """Label given world points with one of `texts` (wire type ``segment_points``)."""

    TYPE: ClassVar[str] = "segment_points"

    xyz: np.ndarray = wire(
        Array("float32", ("N", 3), finite="points"), unit="m", doc="(N, 3) points to label, world frame."
    )
    texts: list[str] = wire(TEXTS, doc="The label set, 1..64 prompts.")
    method: SegmentMethod = wire(
        OneOf(SEGMENT_METHODS), default="govnesf",
        doc='``"govnesf"`` (learned blending), ``"average"`` or ``"average_depth"``.',
    )
    use_depth: bool = wire(Bool(), default=False, doc='Depth Guided Masking for ``"govnesf"``.')
    id: RequestId = wire(ID, default=None)
    settle_timeout_s: float | None = wire(
        Float(lo=0.0), unit="s", default=None,
        doc="Answer from the settled map: wait up to this long for the node's background work on the frames "
        "acked so far (extension; the node caps it at `queries.max_settle_wait_s`).",
    )


@message
class Segmentation(Message):
    """Reply to `segment_points` (wire type ``segmentation``)."""

    TYPE: ClassVar[str] = "segmentation"

    label: np.ndarray = wire(Array("int32", ("N",)), doc="Index into `texts`; -1 where no source answers.")
    score: np.ndarray = wire(Array("float32", ("N",)), doc="Cosine similarity of the chosen label.")
    timing_ms: dict[str, float] = wire(TIMING, unit="ms", default_factory=dict, doc="Wall time per stage.")
    id: RequestId = wire(ID, default=None)
    source: np.ndarray | None = wire(
        Array("uint8", ("N",)), default=None,
        doc="Per point, what answered: 0 none, 1 window, 2 map (`ANSWER_SOURCES`; extension).",
    )
    settled: bool | None = wire(
        Bool(), default=None,
        doc="Whether the node had no background work pending for acked frames when it answered (extension).",
    )
    fallback: np.ndarray | None = wire(
        Array("uint8", ("N",)), default=None,
        doc="Per point, 1 where averaging answered for the learned method (its geometry not ready, or "
        "the averaging far more decided at the point; extension).",
    )


@message
class Render(Message):
    """Render a view from any pose (wire type ``render``, request)."""

    TYPE: ClassVar[str] = "render"

    width: int = wire(SIDE, unit="px", doc="Image width, pixels, 1..4096.")
    height: int = wire(SIDE, unit="px", doc="Image height, pixels, 1..4096.")
    K: np.ndarray = wire(Intrinsics(), unit="px", doc="(4,) float64 intrinsics [fx, fy, cx, cy].")
    world_from_cam: np.ndarray = wire(
        Pose(), name="T_world_cam", unit="m", doc="(4, 4) float64 camera-to-world pose."
    )
    outputs: list[str] = wire(Subset(RENDER_OUTPUTS), doc="Non-empty subset of `RENDER_OUTPUTS`, no repeats.")
    texts: list[str] | None = wire(
        TEXTS, required="if outputs include label or score", default=None,
        doc='Label set, required when ``"label"`` or ``"score"`` is requested.',
    )
    id: RequestId = wire(ID, default=None)
    settle_timeout_s: float | None = wire(
        Float(lo=0.0), unit="s", default=None,
        doc="Answer from the settled map: wait up to this long for the node's background work on the frames "
        "acked so far (extension; the node caps it at `queries.max_settle_wait_s`).",
    )

    def _check(self) -> None:
        if self.texts is None and ("label" in self.outputs or "score" in self.outputs):
            raise bad("texts: required when outputs include 'label' or 'score'")


def _render_side(index: int) -> Callable[[RenderResult], int | None]:
    return lambda msg: None if msg.size is None else msg.size[index]


@message
class RenderResult(Message):
    """Reply to `render` (wire type ``render``, reply). Absent outputs are None.

    On the wire the reply also carries ``width`` and ``height`` (a compatible extension) so
    that the rgb8 image can be decoded without the request at hand.
    """

    TYPE: ClassVar[str] = "render"

    rgb: np.ndarray | None = wire(LateImage(), default=None, doc="(H, W, 3) uint8, sent as rgb8.")
    depth_m: np.ndarray | None = wire(
        Array("float32", ("H", "W")), name="depth", unit="m", default=None,
        doc="(H, W) float32 expected termination depth.",
    )
    label: np.ndarray | None = wire(
        Array("int32", ("H", "W")), default=None, doc="(H, W) int32 index into texts, -1 = nothing rendered."
    )
    score: np.ndarray | None = wire(
        Array("float32", ("H", "W", "T")), default=None, doc="(H, W, T) float32 cosine similarities."
    )
    timing_ms: dict[str, float] = wire(TIMING, unit="ms", default_factory=dict, doc="Wall time per stage.")
    id: RequestId = wire(ID, default=None)
    source: np.ndarray | None = wire(
        Array("uint8", ("H", "W")), default=None,
        doc="Per pixel, what answered `label`: 0 none, 1 window, 2 map (extension; with `label`).",
    )
    settled: bool | None = wire(
        Bool(), default=None,
        doc="Whether the node had no background work pending for acked frames when it answered (extension).",
    )

    WIRE_ONLY: ClassVar[tuple[WireField, ...]] = (
        wire_only(
            "height", SIDE, unit="px", required="with width", dim="H", before="rgb", value=_render_side(0),
            doc="H of the outputs (sizes an rgb8 image sent alone).",
        ),
        wire_only(
            "width", SIDE, unit="px", required="with height", dim="W", before="rgb", value=_render_side(1),
            doc="W of the outputs.",
        ),
    )

    def _check(self) -> None:
        size = self.size
        if size is not None and not (1 <= size[0] <= MAX_IMAGE_SIDE and 1 <= size[1] <= MAX_IMAGE_SIDE):
            raise bad(f"render: image size {size[1]}x{size[0]} out of range 1..{MAX_IMAGE_SIDE}")

    @property
    def size(self) -> tuple[int, int] | None:
        """(height, width) of the rendered outputs, or None if there are none."""
        for arr in (self.rgb, self.depth_m, self.label, self.score):
            if arr is not None:
                return int(arr.shape[0]), int(arr.shape[1])
        return None


@message
class StatusRequest(Message):
    """Ask the mapper for its status (wire type ``status``, request)."""

    TYPE: ClassVar[str] = "status"

    id: RequestId = wire(ID, default=None)


@message
class Status(Message):
    """The mapper's status (wire type ``status``, reply). Unknown wire keys land in `extra`."""

    TYPE: ClassVar[str] = "status"

    map_version: int = wire(COUNT, doc="Incremented whenever the map changes.")
    keyframes: int = wire(COUNT, doc="Keyframes in the window.")
    frames_received: int = wire(COUNT, doc="Frames received.")
    frames_rejected: int = wire(COUNT, doc="Frames rejected with an error reply.")
    ov_space: str | None = wire(
        NAME, required=False, send_nil=True, doc="Embedding space of the map; None until a frame fixes it."
    )
    memory_bytes: int = wire(COUNT, unit="bytes", doc="Memory the map uses.")
    uptime_s: float = wire(Float(lo=0.0), unit="s", doc="Seconds since the node started.")
    extra: dict[str, Any] = wire(
        Rest(), default_factory=dict, before="map_version",
        doc="Further operator information (flat keys on the wire; see docs/reference/protocol.md).",
    )
    id: RequestId = wire(ID, default=None)


@message
class _MapNameRequest(Message):
    """A request that names a map in the mapper's map directory (``save`` and ``load``)."""

    name: str = wire(MapName(), doc='Map name, ``[A-Za-z0-9_.-]{1,64}``, not "." or "..".')
    id: RequestId = wire(ID, default=None)


@message
class Save(_MapNameRequest):
    """Save the map under `name` in the mapper's map directory (wire type ``save``)."""

    TYPE: ClassVar[str] = "save"


@message
class Load(_MapNameRequest):
    """Load the map `name` from the mapper's map directory (wire type ``load``)."""

    TYPE: ClassVar[str] = "load"


@message
class Ok(Message):
    """Success reply without a payload (wire type ``ok``), e.g. to `save`/`load`."""

    TYPE: ClassVar[str] = "ok"

    id: RequestId = wire(ID, default=None)
    message: str | None = wire(
        NOTE, default=None, doc="Optional human-readable note (e.g. where the map was saved)."
    )


@message
class MapUpdated(Message):
    """Event published on the events endpoint when the map changes (wire type ``map_updated``)."""

    TYPE: ClassVar[str] = "map_updated"

    map_version: int = wire(COUNT, doc="The new map version.")
    keyframes: int = wire(COUNT, doc="Keyframes in the window.")
    region_min: np.ndarray | None = wire(
        Vector((3,)), unit="m", default=None, required="with region_max",
        doc="The axis-aligned box (world) the change can touch: a new keyframe's depth points, or without "
        "depth its view frustum up to `global_map.max_depth_m`; absent when the whole map may have changed "
        "(a load) (extension).",
    )
    region_max: np.ndarray | None = wire(
        Vector((3,)), unit="m", default=None, required="with region_min", doc="The box's maximum corner.",
    )

    def _check(self) -> None:
        if (self.region_min is None) != (self.region_max is None):
            raise bad("region_min and region_max: give both or neither")


@message
class RecordingHeader(Message):
    """First message of a `.govrec` recording (wire type ``recording``)."""

    TYPE: ClassVar[str] = "recording"

    created_ns: int = wire(Int(), unit="ns", doc="When the recording was started, ns since the Unix epoch.")
    meta: dict[str, Any] = wire(
        StrMap(), default_factory=dict,
        doc="Free-form description (scene, camera, generator...); str keys, msgpack-able values.",
    )


# ----------------------------------------------------------------------------------------------
# Registry and (de)serialisation
# ----------------------------------------------------------------------------------------------

REQUEST_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls for cls in (Frame, QueryPoints, SegmentPoints, Render, StatusRequest, Save, Load)
}
"""Client -> mapper messages by wire type."""

REPLY_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (Ack, Error, Points, Segmentation, RenderResult, Status, Ok, MapUpdated)
}
"""Mapper -> client messages (replies and events) by wire type."""

OTHER_TYPES: dict[str, type[Message]] = {RecordingHeader.TYPE: RecordingHeader}
"""Messages that are neither requests nor replies (decoded only with direction="any")."""


def _resolve_any(type_: str, obj: dict[str, Any]) -> type[Message] | None:
    """Pick the class for a wire type without a known direction.

    ``status`` is the reply iff it carries ``map_version``; ``render`` is the request iff it
    carries ``outputs``. Every other type names one class.
    """
    if type_ == "status":
        return Status if "map_version" in obj else StatusRequest
    if type_ == "render":
        return Render if "outputs" in obj else RenderResult
    return REQUEST_TYPES.get(type_) or REPLY_TYPES.get(type_) or OTHER_TYPES.get(type_)


def _pack_default(value: Any) -> Any:
    """msgpack fallback for numpy scalars/arrays in free-form maps (`Status.extra`, header meta)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot serialise {type(value).__name__} {short(value)} to msgpack")


def encode(msg: Message) -> bytes:
    """Serialise a message to its wire bytes (one msgpack map, binary payloads as `bin`)."""
    packed = msgpack.packb(msg.to_wire(), use_bin_type=True, default=_pack_default)
    assert isinstance(packed, bytes)
    return packed


def _unpack(data: bytes | bytearray | memoryview, max_bytes: int) -> Any:
    """msgpack-unpack one message with limits derived from its size, so a hostile length prefix
    cannot make the unpacker allocate more than a small multiple of the message size."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise bad(f"message must be bytes, got {type_name(data)}")
    n = len(data)
    if n > max_bytes:
        raise ProtocolError("too_large", f"message is {n} bytes; the limit is {max_bytes} bytes")
    if n == 0:
        raise bad("empty message (expected one msgpack map)")
    try:
        return msgpack.unpackb(
            data,
            raw=False,
            use_list=True,
            strict_map_key=True,
            max_bin_len=n,
            max_str_len=n,
            max_array_len=n,
            max_map_len=n // 2,
            max_ext_len=n,
        )
    except msgpack.StackError:
        raise bad("message is not valid msgpack: nested too deeply") from None
    except ValueError as exc:
        if "map key" in str(exc):
            raise bad(f"message keys must be strings ({exc})") from None
        raise bad(f"message is not valid msgpack: {type(exc).__name__}: {short(str(exc))}") from None
    except Exception as exc:  # msgpack raises several unrelated types on malformed input
        raise bad(f"message is not valid msgpack: {type(exc).__name__}: {short(str(exc))}") from None


def decode(
    data: bytes | bytearray | memoryview, *, max_bytes: int = MAX_MESSAGE_BYTES, direction: Direction = "any"
) -> Message:
    """Parse and validate one wire message.

    Args:
        data: the message bytes (the last ZeroMQ frame).
        max_bytes: larger messages are rejected with ``too_large`` before unpacking.
        direction: ``"request"`` (client -> mapper: a mapper decodes with this), ``"reply"``
            (mapper -> client, events included: a client decodes with this) or ``"any"``
            (see `_resolve_any` for the two wire types used in both directions).
    Raises:
        ProtocolError: ``too_large``, ``unsupported_version`` (v present but not 1) or
            ``bad_request`` (everything else, with a message saying what was wrong).
    """
    obj = _unpack(data, max_bytes)
    if not isinstance(obj, dict):
        raise bad(f"message must be a msgpack map, got {type_name(obj)}")
    for key in obj:
        if not isinstance(key, str):
            raise bad(f"message keys must be strings, got {type_name(key)} {short(key)}")
    _check_header(obj)
    type_ = obj["type"]
    cls: type[Message] | None
    if direction == "request":
        cls = REQUEST_TYPES.get(type_)
        known = sorted(REQUEST_TYPES)
    elif direction == "reply":
        cls = REPLY_TYPES.get(type_)
        known = sorted(REPLY_TYPES)
    elif direction == "any":
        cls = _resolve_any(type_, obj)
        known = sorted({*REQUEST_TYPES, *REPLY_TYPES, *OTHER_TYPES})
    else:
        raise ValueError(f"direction must be 'request', 'reply' or 'any', got {direction!r}")
    if cls is None:
        raise bad(f"unknown message type {short(type_)}; known {direction} types: {', '.join(known)}")
    return cls.from_wire(obj)


M = TypeVar("M", bound=Message)


def decode_as(data: bytes | bytearray | memoryview, cls: type[M], *, max_bytes: int = MAX_MESSAGE_BYTES) -> M:
    """Decode a message that must be of class `cls` (e.g. a client expecting `Points`).

    Raises:
        RemoteError: the message is an `error` reply (and `cls` is not `Error`); carries the
            remote code, message and id.
        ProtocolError: the message is malformed, or of another type (``bad_request``).
    """
    obj = _unpack(data, max_bytes)
    if not isinstance(obj, dict):
        raise bad(f"message must be a msgpack map, got {type_name(obj)}")
    _check_header(obj)
    if obj["type"] == Error.TYPE and cls is not Error:
        err = Error.from_wire(obj)
        raise RemoteError(err.code, err.message, id=err.id)
    if obj["type"] != cls.TYPE:
        raise bad(f"expected a {cls.TYPE!r} message, got type {short(obj['type'])}")
    return cls.from_wire(obj)


def peek_id(data: bytes | bytearray | memoryview) -> RequestId:
    """Best effort: the request `id` of a message even when it fails to decode (for error replies).

    Scans the top-level map without materialising binary payloads; returns None when the
    message is not a map, has no id, or the id is not an int or a short string.
    """
    try:
        unpacker = msgpack.Unpacker(raw=False, max_buffer_size=max(len(data), 1), strict_map_key=False)
        unpacker.feed(data)
        n = unpacker.read_map_header()
        for _ in range(n):
            key = unpacker.unpack()
            if key == "id":
                value = unpacker.unpack()
                if isinstance(value, bool):
                    return None
                if isinstance(value, int) or (isinstance(value, str) and len(value) <= MAX_ID_CHARS):
                    return value
                return None
            unpacker.skip()
    except Exception:  # best effort by design: any parse failure means "no id"
        return None
    return None


def error_reply(exc: ProtocolError, id: RequestId = None) -> Error:
    """The `error` reply for a rejected request (echoing its `id`)."""
    valid = id is None or is_int(id) or (isinstance(id, str) and len(id) <= MAX_ID_CHARS)
    safe_id = id if valid else None
    return Error(code=exc.code, message=exc.message, id=safe_id)


MESSAGE_TYPES: tuple[type[Message], ...] = (
    Frame, Ack, Error, QueryPoints, Points, SegmentPoints, Segmentation, Render, RenderResult,
    StatusRequest, Status, Save, Load, Ok, MapUpdated, RecordingHeader,
)
"""Every message class (ObjectCandidate is a part of `Points`, not a message)."""

__all__ = [
    "ACK_STATUSES", "ANSWER_SOURCES", "DEFAULT_DEPTH_SCALE", "MAX_MESSAGE_BYTES", "MESSAGE_TYPES",
    "ORTHONORMAL_TOL", "PROTOCOL_VERSION", "RENDER_OUTPUTS", "REPLY_TYPES", "REQUEST_TYPES",
    "SEGMENT_METHODS",
    "Ack", "Direction", "Error", "ErrorCode", "Frame", "Load", "MapUpdated", "Message", "ObjectCandidate",
    "Ok", "Points", "QueryPoints", "RecordingHeader", "Render", "RenderResult", "RequestId", "Save",
    "SegmentMethod", "SegmentPoints", "Segmentation", "Status", "StatusRequest", "decode", "decode_as",
    "encode", "error_reply", "peek_id",
]
