"""Wire protocol v1: every message type, defined once (schema-first), with validation.

This module is the only place that knows the wire layout. Each message type is a dataclass
with a class attribute `TYPE` (the wire ``type``), `to_wire()` (-> the msgpack map) and
`from_wire(obj)` (validating). Python field names are snake_case SI (`world_from_cam`,
`depth_m`); wire names are exactly those of docs/PROTOCOL.md (`T_world_cam`, `depth`).

Validation happens at construction (``__post_init__``), so a message built in Python and a
message decoded from the wire obey the same rules, and `ProtocolError("bad_request")` says what
was wrong, with the value received and the allowed range.

Example:
    >>> import numpy as np
    >>> msg = QueryPoints(texts=["chair"], id=7)
    >>> decode(encode(msg)) == msg
    True
    >>> decode(encode(Ack(seq=3, status="keyframe", map_version=1, id=7))).status
    'keyframe'
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Literal, Self, TypeVar

import msgpack
import numpy as np

from protocol.arrays import decode_image, decode_nd, encode_image, encode_nd
from protocol.errors import ERROR_CODES, ErrorCode, ProtocolError, RemoteError

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

ACK_STATUSES: tuple[str, ...] = ("keyframe", "accepted", "rejected")
"""`ack` statuses."""

NAME_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
"""Allowed `save`/`load` map names (besides which "." and ".." are refused)."""

Direction = Literal["request", "reply", "any"]
RequestId = int | str | None

_MISSING: Any = object()
_INT_MIN = -(2**63)
_INT_MAX = 2**64 - 1


# ----------------------------------------------------------------------------------------------
# Small typed readers for wire values. Each raises ProtocolError("bad_request", "<field>: ...").
# ----------------------------------------------------------------------------------------------


def _bad(what: str) -> ProtocolError:
    return ProtocolError("bad_request", what)


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _type_name(value: Any) -> str:
    return "bool" if isinstance(value, bool) else type(value).__name__


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _check_int(name: str, value: Any, lo: int | None = None, hi: int | None = None) -> int:
    if isinstance(value, np.integer):
        value = int(value)
    if not _is_int(value):
        raise _bad(f"{name}: expected an int, got {_type_name(value)} {_short(value)}")
    if not _INT_MIN <= value <= _INT_MAX:
        raise _bad(f"{name}: {_short(value)} does not fit in a 64-bit msgpack int")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        rng = f"{'' if lo is None else lo}..{'' if hi is None else hi}"
        raise _bad(f"{name}: {value} out of range {rng}")
    return int(value)


def _check_float(name: str, value: Any, *, finite: bool = True, lo: float | None = None) -> float:
    if isinstance(value, np.floating | np.integer):
        value = value.item()
    if not _is_number(value):
        raise _bad(f"{name}: expected a number, got {_type_name(value)} {_short(value)}")
    out = float(value)
    if finite and not math.isfinite(out):
        raise _bad(f"{name}: must be finite, got {out}")
    if lo is not None and not out >= lo:
        raise _bad(f"{name}: {out} out of range {lo}..")
    return out


def _check_bool(name: str, value: Any) -> bool:
    if isinstance(value, np.bool_):
        value = bool(value)
    if not isinstance(value, bool):
        raise _bad(f"{name}: expected a bool, got {_type_name(value)} {_short(value)}")
    return value


def _check_str(name: str, value: Any, *, max_chars: int, nonempty: bool = True) -> str:
    if not isinstance(value, str):
        raise _bad(f"{name}: expected a string, got {_type_name(value)} {_short(value)}")
    if nonempty and not value:
        raise _bad(f"{name}: must be a non-empty string")
    if len(value) > max_chars:
        raise _bad(f"{name}: {len(value)} characters, at most {max_chars} allowed")
    return value


def _check_texts(name: str, value: Any, *, min_count: int = 1, max_count: int = MAX_TEXTS) -> list[str]:
    if not isinstance(value, list | tuple):
        raise _bad(f"{name}: expected a list of strings, got {_type_name(value)} {_short(value)}")
    if not min_count <= len(value) <= max_count:
        raise _bad(f"{name}: {len(value)} strings, allowed {min_count}..{max_count}")
    return [_check_str(f"{name}[{i}]", t, max_chars=MAX_TEXT_CHARS) for i, t in enumerate(value)]


def _check_id(value: Any) -> RequestId:
    if value is None:
        return None
    if isinstance(value, np.integer):
        value = int(value)
    if _is_int(value):
        return _check_int("id", value)
    if isinstance(value, str):
        return _check_str("id", value, max_chars=MAX_ID_CHARS, nonempty=False)
    raise _bad(f"id: expected an int or a string, got {_type_name(value)} {_short(value)}")


def _check_timing(name: str, value: Any) -> dict[str, float]:
    if not isinstance(value, Mapping):
        raise _bad(f"{name}: expected a map of str -> number, got {_type_name(value)}")
    out: dict[str, float] = {}
    for key, ms in value.items():
        if not isinstance(key, str):
            raise _bad(f"{name}: keys must be strings, got {_type_name(key)} {_short(key)}")
        out[key] = _check_float(f"{name}.{key}", ms, finite=False)
    return out


def _check_str_map(name: str, value: Any) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise _bad(f"{name}: expected a map, got {_type_name(value)}")
    for key in value:
        if not isinstance(key, str):
            raise _bad(f"{name}: keys must be strings, got {_type_name(key)} {_short(key)}")
    return dict(value)


def _check_array(
    name: str, value: Any, dtype: str, shape: tuple[int | None, ...], *, coerce: bool = False
) -> np.ndarray:
    """Check (or, with `coerce`, convert to) an ndarray of `dtype` and `shape` (None = any)."""
    if coerce:
        try:
            value = np.ascontiguousarray(value, dtype=dtype)
        except (TypeError, ValueError) as exc:
            raise _bad(f"{name}: cannot convert to a {dtype} array: {exc}") from None
    if not isinstance(value, np.ndarray):
        raise _bad(f"{name}: expected a numpy array, got {_type_name(value)}")
    if value.dtype != np.dtype(dtype):
        raise _bad(f"{name}: expected dtype {dtype}, got {value.dtype}")
    mismatch = value.ndim != len(shape) or any(
        w is not None and g != w for g, w in zip(value.shape, shape, strict=True)
    )
    if mismatch:
        want = "(" + ", ".join("*" if w is None else str(w) for w in shape) + ")"
        raise _bad(f"{name}: expected shape {want}, got {value.shape}")
    return value


def _check_camera(name_k: str, K: Any, name_pose: str, world_from_cam: Any) -> tuple[np.ndarray, np.ndarray]:
    """Validate intrinsics K = [fx, fy, cx, cy] (4,) and a (4, 4) world_from_cam pose."""
    K = _check_array(name_k, K, "float64", (4,), coerce=True)
    if not np.all(np.isfinite(K)):
        raise _bad(f"{name_k}: values must be finite, got {K.tolist()}")
    if not (K[0] > 0 and K[1] > 0):
        raise _bad(f"{name_k}: fx and fy must be > 0, got fx={K[0]} fy={K[1]}")
    pose = _check_array(name_pose, world_from_cam, "float64", (4, 4), coerce=True)
    if not np.all(np.isfinite(pose)):
        raise _bad(f"{name_pose}: values must be finite, got {pose.reshape(-1).tolist()}")
    last = pose[3]
    if np.max(np.abs(last - np.array([0.0, 0.0, 0.0, 1.0]))) > LAST_ROW_TOL:
        raise _bad(f"{name_pose}: last row must be [0, 0, 0, 1], got {last.tolist()}")
    rot = pose[:3, :3]
    err = float(np.max(np.abs(rot.T @ rot - np.eye(3))))
    if err > ORTHONORMAL_TOL:
        raise _bad(
            f"{name_pose}: rotation block is not orthonormal: max|R^T R - I| = {err:.3g} "
            f"> tolerance {ORTHONORMAL_TOL}"
        )
    det = float(np.linalg.det(rot))
    if det <= 0:
        raise _bad(f"{name_pose}: rotation block has det {det:.3g}; must be > 0 (a rotation, no reflection)")
    return K, pose


def _wire_numbers(name: str, value: Any, count: int) -> np.ndarray:
    """A wire list of `count` numbers -> (count,) float64 (finiteness is checked by the caller)."""
    if not isinstance(value, list | tuple):
        raise _bad(f"{name}: expected a list of {count} numbers, got {_type_name(value)} {_short(value)}")
    if len(value) != count:
        raise _bad(f"{name}: expected {count} numbers, got {len(value)}")
    for i, x in enumerate(value):
        if not _is_number(x):
            raise _bad(f"{name}[{i}]: expected a number, got {_type_name(x)} {_short(x)}")
    return np.array([float(x) for x in value], dtype=np.float64)


def _equal(a: Any, b: Any) -> bool:
    """Exact structural equality, arrays included (same dtype, shape and values; NaN == NaN)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
            return False
        if a.dtype != b.dtype or a.shape != b.shape:
            return False
        return bool(np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


# ----------------------------------------------------------------------------------------------
# Message base
# ----------------------------------------------------------------------------------------------


class _Wire:
    """Read access to a decoded wire map with typed, field-named errors."""

    def __init__(self, obj: Any, type_: str) -> None:
        if not isinstance(obj, dict):
            raise _bad(f"message must be a map, got {_type_name(obj)}")
        for key in obj:
            if not isinstance(key, str):
                raise _bad(f"message keys must be strings, got {_type_name(key)} {_short(key)}")
        _check_header(obj)
        if obj["type"] != type_:
            raise _bad(f"type: expected {type_!r}, got {obj['type']!r}")
        self.obj: dict[str, Any] = obj
        self.type = type_

    def has(self, key: str) -> bool:
        return key in self.obj

    def req(self, key: str) -> Any:
        if key not in self.obj:
            raise _bad(f"{self.type}: missing required field {key!r}")
        return self.obj[key]

    def opt(self, key: str, default: Any = None) -> Any:
        """An optional field; an explicit nil counts as absent."""
        value = self.obj.get(key, _MISSING)
        return default if value is _MISSING or value is None else value

    def id(self) -> RequestId:
        return _check_id(self.obj.get("id"))


def _check_header(obj: dict[str, Any]) -> None:
    if "v" not in obj:
        raise _bad("missing protocol version 'v' (this node speaks v=1)")
    v = obj["v"]
    if not _is_int(v):
        raise _bad(f"v: expected an int protocol version, got {_type_name(v)} {_short(v)}")
    if v != PROTOCOL_VERSION:
        raise ProtocolError(
            "unsupported_version", f"protocol version v={v} is not supported; this node speaks v=1"
        )
    if "type" not in obj:
        raise _bad("missing message 'type'")
    if not isinstance(obj["type"], str):
        raise _bad(f"type: expected a string, got {_type_name(obj['type'])} {_short(obj['type'])}")


class Message:
    """Base of every wire message: equality with arrays compared exactly, wire header helpers."""

    TYPE: ClassVar[str]

    def __eq__(self, other: object) -> bool:
        if type(self) is not type(other):
            return NotImplemented
        return all(_equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))  # type: ignore[arg-type]

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
                text = _short(value)
            parts.append(f"{f.name}={text}")
        return f"{type(self).__name__}({', '.join(parts)})"

    def _head(self) -> dict[str, Any]:
        head: dict[str, Any] = {"v": PROTOCOL_VERSION, "type": self.TYPE}
        msg_id = getattr(self, "id", None)
        if msg_id is not None:
            head["id"] = msg_id
        return head

    def to_wire(self) -> dict[str, Any]:  # pragma: no cover - every subclass overrides
        raise NotImplementedError

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:  # pragma: no cover - every subclass overrides
        raise NotImplementedError


# ----------------------------------------------------------------------------------------------
# Ingest: frame / ack
# ----------------------------------------------------------------------------------------------


@dataclass(eq=False, repr=False)
class Frame(Message):
    """One camera frame sent to the ingest endpoint (wire type ``frame``)."""

    TYPE: ClassVar[str] = "frame"

    seq: int
    """Sender's sequence number, >= 0."""
    stamp_ns: int
    """Capture time, nanoseconds (sender's clock)."""
    width: int
    """Image width, pixels, 1..4096."""
    height: int
    """Image height, pixels, 1..4096."""
    K: np.ndarray  # (4,) float64 [fx, fy, cx, cy], pixels, for the image as sent
    """Intrinsics [fx, fy, cx, cy] in pixels; fx, fy > 0."""
    world_from_cam: np.ndarray  # (4, 4) float64, camera-to-world, metres (wire: T_world_cam)
    """Camera-to-world pose (OpenCV optical camera, world +z up), metres."""
    rgb: np.ndarray  # (H, W, 3) uint8
    """Colour image, R, G, B."""
    camera: str = "cam0"
    """Camera name."""
    depth_m: np.ndarray | None = None  # (H, W) float32 metres, 0 = no depth
    """Depth along the optical axis (z), metres; 0 where unknown (non-finite/negative become 0)."""
    ov: np.ndarray | None = None  # (h, w, d) float16/float32
    """Precomputed open-vocabulary feature map, any h, w; dtype kept as received."""
    ov_space: str | None = None
    """Embedding space of `ov` (e.g. ``"minilm-l6-v2"``); required iff `ov` is given."""
    rgb_encoding: str = "rgb8"
    """Encoding `to_wire` uses for `rgb`; after `from_wire`, the encoding that was received."""
    id: RequestId = None

    def __post_init__(self) -> None:
        self.seq = _check_int("seq", self.seq, 0)
        self.stamp_ns = _check_int("stamp_ns", self.stamp_ns)
        self.width = _check_int("width", self.width, 1, MAX_IMAGE_SIDE)
        self.height = _check_int("height", self.height, 1, MAX_IMAGE_SIDE)
        self.K, self.world_from_cam = _check_camera("K", self.K, "T_world_cam", self.world_from_cam)
        self.rgb = _check_array("rgb", self.rgb, "uint8", (self.height, self.width, 3))
        self.camera = _check_str("camera", self.camera, max_chars=MAX_NAME_CHARS)
        if self.rgb_encoding not in ("rgb8", "jpeg", "png"):
            raise _bad(f"rgb_encoding: {self.rgb_encoding!r} unknown; allowed rgb8, jpeg, png")
        if self.depth_m is not None:
            depth = _check_array("depth", self.depth_m, "float32", (self.height, self.width))
            valid = np.isfinite(depth) & (depth > 0)
            if not np.all(valid | (depth == 0)):
                depth = np.where(valid, depth, np.float32(0.0)).astype(np.float32)
            self.depth_m = depth
        if self.ov is not None:
            if not isinstance(self.ov, np.ndarray) or self.ov.dtype not in (np.float16, np.float32):
                got = self.ov.dtype if isinstance(self.ov, np.ndarray) else _type_name(self.ov)
                raise _bad(f"ov: expected a float16 or float32 array, got {got}")
            if self.ov.ndim != 3:
                raise _bad(f"ov: expected shape (h, w, d), got {self.ov.shape}")
            h, w, d = self.ov.shape
            if not (1 <= h <= MAX_OV_SIDE and 1 <= w <= MAX_OV_SIDE):
                raise _bad(f"ov: h, w = {h}, {w} out of range 1..{MAX_OV_SIDE}")
            if not 1 <= d <= MAX_OV_DIM:
                raise _bad(f"ov: feature dimension d = {d} out of range 1..{MAX_OV_DIM}")
            if not np.all(np.isfinite(self.ov)):
                raise _bad("ov: feature map contains NaN or Inf")
            if self.ov_space is None:
                raise _bad(
                    "ov_space: required when ov is sent (name the embedding space, e.g. 'minilm-l6-v2')"
                )
        if self.ov_space is not None:
            self.ov_space = _check_str("ov_space", self.ov_space, max_chars=MAX_NAME_CHARS)
            if self.ov is None:
                raise _bad("ov_space: sent without ov (send both or neither)")
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire.update(
            seq=self.seq,
            stamp_ns=self.stamp_ns,
            camera=self.camera,
            width=self.width,
            height=self.height,
            K=[float(x) for x in self.K],
            T_world_cam=[float(x) for x in self.world_from_cam.reshape(16)],
            rgb=encode_image(self.rgb, self.rgb_encoding),
        )
        if self.depth_m is not None:
            wire["depth"] = encode_nd(self.depth_m)
        if self.ov is not None:
            wire["ov"] = encode_nd(self.ov)
            wire["ov_space"] = self.ov_space
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        width = _check_int("width", w.req("width"), 1, MAX_IMAGE_SIDE)
        height = _check_int("height", w.req("height"), 1, MAX_IMAGE_SIDE)
        K = _wire_numbers("K", w.req("K"), 4)
        pose = _wire_numbers("T_world_cam", w.req("T_world_cam"), 16).reshape(4, 4)
        seq = w.req("seq")
        stamp_ns = w.req("stamp_ns")
        # Cheap checks first, so a bad header does not cost an image decode.
        _check_int("seq", seq, 0)
        _check_int("stamp_ns", stamp_ns)
        _check_camera("K", K, "T_world_cam", pose)
        msg_id = w.id()
        camera = _check_str("camera", w.opt("camera", "cam0"), max_chars=MAX_NAME_CHARS)
        if (w.opt("ov") is None) != (w.opt("ov_space") is None):
            raise _bad(
                "ov_space: required when ov is sent (name the embedding space, e.g. 'minilm-l6-v2')"
                if w.opt("ov_space") is None
                else "ov_space: sent without ov (send both or neither)"
            )
        rgb_obj = w.req("rgb")
        rgb = decode_image(rgb_obj, width=width, height=height, field="rgb")
        depth_m: np.ndarray | None = None
        if w.has("depth") and w.obj["depth"] is not None:
            raw = decode_nd(
                w.obj["depth"], field="depth", dtypes=("float32", "uint16"), shape=(height, width)
            )
            scale_obj = w.opt("depth_scale")
            scale = DEFAULT_DEPTH_SCALE
            if scale_obj is not None:
                scale = _check_float("depth_scale", scale_obj)
                if not scale > 0:
                    raise _bad(f"depth_scale: must be > 0 metres per unit, got {scale}")
            if raw.dtype == np.uint16:
                depth_m = (raw.astype(np.float64) * scale).astype(np.float32)
            else:
                depth_m = raw
        ov = None
        if w.has("ov") and w.obj["ov"] is not None:
            ov = decode_nd(w.obj["ov"], field="ov", dtypes=("float16", "float32"), ndim=3)
        ov_space = w.opt("ov_space")
        return cls(
            seq=seq,
            stamp_ns=stamp_ns,
            width=width,
            height=height,
            K=K,
            world_from_cam=pose,
            rgb=rgb,
            camera=camera,
            depth_m=depth_m,
            ov=ov,
            ov_space=ov_space,
            rgb_encoding=rgb_obj["encoding"],
            id=msg_id,
        )


AckStatus = Literal["keyframe", "accepted", "rejected"]


@dataclass(eq=False, repr=False)
class Ack(Message):
    """Reply to every `frame` that was not an error (wire type ``ack``)."""

    TYPE: ClassVar[str] = "ack"

    seq: int
    """The acknowledged frame's `seq`."""
    status: AckStatus
    """``"keyframe"`` (added to the window), ``"accepted"`` (valid, not a keyframe), ``"rejected"``."""
    map_version: int
    """Map version after handling the frame, >= 0."""
    reason: str | None = None
    """Why the frame was rejected (required for ``"rejected"``), or a note."""
    id: RequestId = None

    def __post_init__(self) -> None:
        self.seq = _check_int("seq", self.seq, 0)
        if self.status not in ACK_STATUSES:
            raise _bad(f"status: {_short(self.status)} unknown; allowed: {', '.join(ACK_STATUSES)}")
        self.map_version = _check_int("map_version", self.map_version, 0)
        if self.reason is not None:
            self.reason = _check_str("reason", self.reason, max_chars=2**20, nonempty=False)
        if self.status == "rejected" and not self.reason:
            raise _bad("reason: required when status is 'rejected'")
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire.update(seq=self.seq, status=self.status, map_version=self.map_version)
        if self.reason is not None:
            wire["reason"] = self.reason
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        return cls(
            seq=w.req("seq"), status=w.req("status"), map_version=w.req("map_version"),
            reason=w.opt("reason"), id=w.id(),
        )


@dataclass(eq=False, repr=False)
class Error(Message):
    """Error reply to any request (wire type ``error``)."""

    TYPE: ClassVar[str] = "error"

    code: ErrorCode
    """One of `protocol.errors.ERROR_CODES`."""
    message: str
    """What was wrong, with the value received and the allowed range."""
    id: RequestId = None

    def __post_init__(self) -> None:
        if self.code not in ERROR_CODES:
            raise _bad(f"code: {_short(self.code)} unknown; allowed: {', '.join(ERROR_CODES)}")
        self.message = _check_str("message", self.message, max_chars=2**20, nonempty=False)
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire.update(code=self.code, message=self.message)
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        return cls(code=w.req("code"), message=w.req("message"), id=w.id())


# ----------------------------------------------------------------------------------------------
# Query endpoint
# ----------------------------------------------------------------------------------------------


@dataclass(eq=False, repr=False)
class QueryPoints(Message):
    """"Find the chair": request map points matching texts (wire type ``query_points``)."""

    TYPE: ClassVar[str] = "query_points"

    texts: list[str]
    """1..64 non-empty prompts."""
    negatives: list[str] | None = None
    """Background prompts (0..64); None = the mapper's default set."""
    min_score: float | None = None
    """Drop points whose best similarity is below this (finite)."""
    max_points: int | None = None
    """Return at most this many points (>= 1), best first."""
    objects: bool = True
    """Also group points into object candidates."""
    id: RequestId = None

    def __post_init__(self) -> None:
        self.texts = _check_texts("texts", self.texts)
        if self.negatives is not None:
            self.negatives = _check_texts("negatives", self.negatives, min_count=0)
        if self.min_score is not None:
            self.min_score = _check_float("min_score", self.min_score)
        if self.max_points is not None:
            self.max_points = _check_int("max_points", self.max_points, 1)
        self.objects = _check_bool("objects", self.objects)
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire["texts"] = list(self.texts)
        if self.negatives is not None:
            wire["negatives"] = list(self.negatives)
        if self.min_score is not None:
            wire["min_score"] = self.min_score
        if self.max_points is not None:
            wire["max_points"] = self.max_points
        wire["objects"] = self.objects
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        return cls(
            texts=w.req("texts"), negatives=w.opt("negatives"), min_score=w.opt("min_score"),
            max_points=w.opt("max_points"), objects=w.opt("objects", True), id=w.id(),
        )


@dataclass(eq=False, repr=False)
class ObjectCandidate(Message):
    """One object candidate in a `points` reply (a map inside the message, not a message)."""

    TYPE: ClassVar[str] = "object"

    text: str
    """The prompt the object matched."""
    centroid: np.ndarray  # (3,) float64, world, metres
    """Centroid of the object's points, world frame, metres."""
    aabb_min: np.ndarray  # (3,) float64, world, metres
    """Axis-aligned box minimum corner, world frame, metres."""
    aabb_max: np.ndarray  # (3,) float64, world, metres
    """Axis-aligned box maximum corner, world frame, metres."""
    score: float
    """Object score (similarity), higher is better."""
    n_points: int
    """Number of map points in the object, >= 0."""

    def __post_init__(self) -> None:
        self.text = _check_str("text", self.text, max_chars=MAX_TEXT_CHARS, nonempty=False)
        for name in ("centroid", "aabb_min", "aabb_max"):
            arr = _check_array(name, getattr(self, name), "float64", (3,), coerce=True)
            if not np.all(np.isfinite(arr)):
                raise _bad(f"{name}: values must be finite, got {arr.tolist()}")
            setattr(self, name, arr)
        self.score = _check_float("score", self.score, finite=False)
        self.n_points = _check_int("n_points", self.n_points, 0)

    def to_wire(self) -> dict[str, Any]:
        return {
            "text": self.text,
            "centroid": [float(x) for x in self.centroid],
            "aabb_min": [float(x) for x in self.aabb_min],
            "aabb_max": [float(x) for x in self.aabb_max],
            "score": self.score,
            "n_points": self.n_points,
        }

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        m = _check_str_map("object", obj)
        for key in ("text", "centroid", "aabb_min", "aabb_max", "score", "n_points"):
            if key not in m:
                raise _bad(f"missing required field {key!r}")
        return cls(
            text=m["text"],
            centroid=_wire_numbers("centroid", m["centroid"], 3),
            aabb_min=_wire_numbers("aabb_min", m["aabb_min"], 3),
            aabb_max=_wire_numbers("aabb_max", m["aabb_max"], 3),
            score=m["score"],
            n_points=m["n_points"],
        )


def _object_from_wire(index: int, obj: Any) -> ObjectCandidate:
    try:
        return ObjectCandidate.from_wire(obj)
    except ProtocolError as exc:
        raise _bad(f"objects[{index}]: {exc.message}") from None


@dataclass(eq=False, repr=False)
class Points(Message):
    """Reply to `query_points` (wire type ``points``)."""

    TYPE: ClassVar[str] = "points"

    map_version: int
    xyz: np.ndarray  # (N, 3) float32, world frame, metres
    """Matching points, world frame, metres."""
    score: np.ndarray  # (N,) float32
    """Similarity of each point to its best-matching text."""
    label: np.ndarray  # (N,) int32
    """Index into the request's `texts`."""
    objects: list[ObjectCandidate] = field(default_factory=list)
    """Object candidates, sorted by score (best first)."""
    timing_ms: dict[str, float] = field(default_factory=dict)
    """Wall time per stage, milliseconds."""
    id: RequestId = None

    def __post_init__(self) -> None:
        self.map_version = _check_int("map_version", self.map_version, 0)
        self.xyz = _check_array("xyz", self.xyz, "float32", (None, 3), coerce=True)
        n = self.xyz.shape[0]
        self.score = _check_array("score", self.score, "float32", (n,), coerce=True)
        self.label = _check_array("label", self.label, "int32", (n,), coerce=True)
        if not isinstance(self.objects, list | tuple):
            raise _bad(f"objects: expected a list, got {_type_name(self.objects)}")
        for i, obj in enumerate(self.objects):
            if not isinstance(obj, ObjectCandidate):
                raise _bad(f"objects[{i}]: expected an ObjectCandidate, got {_type_name(obj)}")
        self.objects = list(self.objects)
        self.timing_ms = _check_timing("timing_ms", self.timing_ms)
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire.update(
            map_version=self.map_version,
            xyz=encode_nd(self.xyz),
            score=encode_nd(self.score),
            label=encode_nd(self.label),
            objects=[o.to_wire() for o in self.objects],
            timing_ms=dict(self.timing_ms),
        )
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        xyz = decode_nd(w.req("xyz"), field="xyz", dtypes=("float32",), shape=(None, 3))
        n = xyz.shape[0]
        objects = w.opt("objects", [])
        if not isinstance(objects, list):
            raise _bad(f"objects: expected a list, got {_type_name(objects)}")
        return cls(
            map_version=w.req("map_version"),
            xyz=xyz,
            score=decode_nd(w.req("score"), field="score", dtypes=("float32",), shape=(n,)),
            label=decode_nd(w.req("label"), field="label", dtypes=("int32",), shape=(n,)),
            objects=[_object_from_wire(i, o) for i, o in enumerate(objects)],
            timing_ms=w.opt("timing_ms", {}),
            id=w.id(),
        )


SegmentMethod = Literal["govnesf", "average", "average_depth"]


@dataclass(eq=False, repr=False)
class SegmentPoints(Message):
    """Label given world points with one of `texts` (wire type ``segment_points``)."""

    TYPE: ClassVar[str] = "segment_points"

    xyz: np.ndarray  # (N, 3) float32, world frame, metres
    """Points to label, world frame, metres (finite)."""
    texts: list[str]
    """The label set, 1..64 prompts."""
    method: SegmentMethod = "govnesf"
    """``"govnesf"`` (learned blending), ``"average"`` or ``"average_depth"``."""
    use_depth: bool = False
    """Depth Guided Masking for ``"govnesf"``."""
    id: RequestId = None

    def __post_init__(self) -> None:
        self.xyz = _check_array("xyz", self.xyz, "float32", (None, 3), coerce=True)
        if not np.all(np.isfinite(self.xyz)):
            raise _bad("xyz: points must be finite (got NaN or Inf)")
        self.texts = _check_texts("texts", self.texts)
        if self.method not in SEGMENT_METHODS:
            raise _bad(f"method: {_short(self.method)} unknown; allowed: {', '.join(SEGMENT_METHODS)}")
        self.use_depth = _check_bool("use_depth", self.use_depth)
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire.update(
            xyz=encode_nd(self.xyz), texts=list(self.texts), method=self.method, use_depth=self.use_depth
        )
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        return cls(
            xyz=decode_nd(w.req("xyz"), field="xyz", dtypes=("float32",), shape=(None, 3)),
            texts=w.req("texts"),
            method=w.opt("method", "govnesf"),
            use_depth=w.opt("use_depth", False),
            id=w.id(),
        )


@dataclass(eq=False, repr=False)
class Segmentation(Message):
    """Reply to `segment_points` (wire type ``segmentation``)."""

    TYPE: ClassVar[str] = "segmentation"

    label: np.ndarray  # (N,) int32
    """Index into `texts`; -1 where no keyframe sees the point."""
    score: np.ndarray  # (N,) float32
    """Cosine similarity of the chosen label."""
    timing_ms: dict[str, float] = field(default_factory=dict)
    id: RequestId = None

    def __post_init__(self) -> None:
        self.label = _check_array("label", self.label, "int32", (None,), coerce=True)
        self.score = _check_array("score", self.score, "float32", (self.label.shape[0],), coerce=True)
        self.timing_ms = _check_timing("timing_ms", self.timing_ms)
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire.update(label=encode_nd(self.label), score=encode_nd(self.score), timing_ms=dict(self.timing_ms))
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        label = decode_nd(w.req("label"), field="label", dtypes=("int32",), ndim=1)
        return cls(
            label=label,
            score=decode_nd(w.req("score"), field="score", dtypes=("float32",), shape=(label.shape[0],)),
            timing_ms=w.opt("timing_ms", {}),
            id=w.id(),
        )


@dataclass(eq=False, repr=False)
class Render(Message):
    """Render a view from any pose (wire type ``render``, request)."""

    TYPE: ClassVar[str] = "render"

    width: int
    """Image width, pixels, 1..4096."""
    height: int
    """Image height, pixels, 1..4096."""
    K: np.ndarray  # (4,) float64 [fx, fy, cx, cy]
    world_from_cam: np.ndarray  # (4, 4) float64, camera-to-world (wire: T_world_cam)
    outputs: list[str]
    """Non-empty subset of ``["rgb", "depth", "label", "score"]`` without repeats."""
    texts: list[str] | None = None
    """Label set, required when ``"label"`` or ``"score"`` is requested."""
    id: RequestId = None

    def __post_init__(self) -> None:
        self.width = _check_int("width", self.width, 1, MAX_IMAGE_SIDE)
        self.height = _check_int("height", self.height, 1, MAX_IMAGE_SIDE)
        self.K, self.world_from_cam = _check_camera("K", self.K, "T_world_cam", self.world_from_cam)
        if not isinstance(self.outputs, list | tuple) or not self.outputs:
            raise _bad(
                f"outputs: expected a non-empty list, subset of {list(RENDER_OUTPUTS)}, "
                f"got {_short(self.outputs)}"
            )
        for out in self.outputs:
            if out not in RENDER_OUTPUTS:
                raise _bad(f"outputs: {_short(out)} unknown; allowed: {', '.join(RENDER_OUTPUTS)}")
        if len(set(self.outputs)) != len(self.outputs):
            raise _bad(f"outputs: repeated entries in {list(self.outputs)}")
        self.outputs = list(self.outputs)
        if self.texts is not None:
            self.texts = _check_texts("texts", self.texts)
        elif "label" in self.outputs or "score" in self.outputs:
            raise _bad("texts: required when outputs include 'label' or 'score'")
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire.update(
            width=self.width,
            height=self.height,
            K=[float(x) for x in self.K],
            T_world_cam=[float(x) for x in self.world_from_cam.reshape(16)],
            outputs=list(self.outputs),
        )
        if self.texts is not None:
            wire["texts"] = list(self.texts)
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        return cls(
            width=w.req("width"),
            height=w.req("height"),
            K=_wire_numbers("K", w.req("K"), 4),
            world_from_cam=_wire_numbers("T_world_cam", w.req("T_world_cam"), 16).reshape(4, 4),
            outputs=w.req("outputs"),
            texts=w.opt("texts"),
            id=w.id(),
        )


@dataclass(eq=False, repr=False)
class RenderResult(Message):
    """Reply to `render` (wire type ``render``, reply). Absent outputs are None.

    On the wire the reply also carries ``width`` and ``height`` (a compatible extension) so
    that the rgb8 image can be decoded without the request at hand.
    """

    TYPE: ClassVar[str] = "render"

    rgb: np.ndarray | None = None  # (H, W, 3) uint8
    depth_m: np.ndarray | None = None  # (H, W) float32, expected termination depth, metres
    label: np.ndarray | None = None  # (H, W) int32, index into texts, -1 = nothing rendered
    score: np.ndarray | None = None  # (H, W, T) float32 cosine similarities
    timing_ms: dict[str, float] = field(default_factory=dict)
    id: RequestId = None

    def __post_init__(self) -> None:
        size: tuple[int, int] | None = None

        def check(name: str, value: Any, dtype: str, extra: tuple[int | None, ...]) -> np.ndarray | None:
            nonlocal size
            if value is None:
                return None
            hw: tuple[int | None, ...] = size if size is not None else (None, None)
            arr = _check_array(name, value, dtype, hw + extra, coerce=dtype != "uint8")
            size = (int(arr.shape[0]), int(arr.shape[1]))
            return arr

        self.rgb = check("rgb", self.rgb, "uint8", (3,))
        self.depth_m = check("depth", self.depth_m, "float32", ())
        self.label = check("label", self.label, "int32", ())
        self.score = check("score", self.score, "float32", (None,))
        if size is not None and not (1 <= size[0] <= MAX_IMAGE_SIDE and 1 <= size[1] <= MAX_IMAGE_SIDE):
            raise _bad(f"render: image size {size[1]}x{size[0]} out of range 1..{MAX_IMAGE_SIDE}")
        self.timing_ms = _check_timing("timing_ms", self.timing_ms)
        self.id = _check_id(self.id)

    @property
    def size(self) -> tuple[int, int] | None:
        """(height, width) of the rendered outputs, or None if there are none."""
        for arr in (self.rgb, self.depth_m, self.label, self.score):
            if arr is not None:
                return int(arr.shape[0]), int(arr.shape[1])
        return None

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        size = self.size
        if size is not None:
            wire["height"], wire["width"] = size
        if self.rgb is not None:
            wire["rgb"] = encode_image(self.rgb, "rgb8")
        if self.depth_m is not None:
            wire["depth"] = encode_nd(self.depth_m)
        if self.label is not None:
            wire["label"] = encode_nd(self.label)
        if self.score is not None:
            wire["score"] = encode_nd(self.score)
        wire["timing_ms"] = dict(self.timing_ms)
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        depth = label = score = rgb = None
        hw: tuple[int | None, int | None] = (None, None)
        if w.has("height") or w.has("width"):
            hw = (
                _check_int("height", w.req("height"), 1, MAX_IMAGE_SIDE),
                _check_int("width", w.req("width"), 1, MAX_IMAGE_SIDE),
            )
        if w.opt("depth") is not None:
            depth = decode_nd(w.obj["depth"], field="depth", dtypes=("float32",), shape=hw)
            hw = (depth.shape[0], depth.shape[1])
        if w.opt("label") is not None:
            label = decode_nd(w.obj["label"], field="label", dtypes=("int32",), shape=hw)
            hw = (label.shape[0], label.shape[1])
        if w.opt("score") is not None:
            score = decode_nd(w.obj["score"], field="score", dtypes=("float32",), shape=(*hw, None))
            hw = (score.shape[0], score.shape[1])
        if w.opt("rgb") is not None:
            height, width = hw
            if height is None or width is None:
                raise _bad("render: rgb sent without width/height (or another output to size it)")
            rgb = decode_image(w.obj["rgb"], width=width, height=height, field="rgb")
        return cls(
            rgb=rgb, depth_m=depth, label=label, score=score, timing_ms=w.opt("timing_ms", {}), id=w.id()
        )


@dataclass(eq=False, repr=False)
class StatusRequest(Message):
    """Ask the mapper for its status (wire type ``status``, request)."""

    TYPE: ClassVar[str] = "status"

    id: RequestId = None

    def __post_init__(self) -> None:
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        return self._head()

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        return cls(id=w.id())


_STATUS_KEYS = (
    "map_version", "keyframes", "frames_received", "frames_rejected", "ov_space", "memory_bytes", "uptime_s"
)


@dataclass(eq=False, repr=False)
class Status(Message):
    """The mapper's status (wire type ``status``, reply). Unknown wire keys land in `extra`."""

    TYPE: ClassVar[str] = "status"

    map_version: int
    """Incremented whenever the map changes."""
    keyframes: int
    """Keyframes in the window."""
    frames_received: int
    frames_rejected: int
    ov_space: str | None
    """Embedding space of the map, None before the first frame fixes it."""
    memory_bytes: int
    """Memory the map uses, bytes."""
    uptime_s: float
    """Seconds since the node started."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Further operator information (flat keys on the wire; see docs/PROTOCOL.md)."""
    id: RequestId = None

    def __post_init__(self) -> None:
        for name in ("map_version", "keyframes", "frames_received", "frames_rejected", "memory_bytes"):
            setattr(self, name, _check_int(name, getattr(self, name), 0))
        if self.ov_space is not None:
            self.ov_space = _check_str("ov_space", self.ov_space, max_chars=MAX_NAME_CHARS)
        self.uptime_s = _check_float("uptime_s", self.uptime_s, lo=0.0)
        self.extra = _check_str_map("extra", self.extra)
        clash = sorted(set(self.extra) & {"v", "type", "id", *_STATUS_KEYS})
        if clash:
            raise _bad(f"extra: keys {clash} clash with the status message's own fields")
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire.update(self.extra)
        wire.update(
            map_version=self.map_version,
            keyframes=self.keyframes,
            frames_received=self.frames_received,
            frames_rejected=self.frames_rejected,
            ov_space=self.ov_space,
            memory_bytes=self.memory_bytes,
            uptime_s=self.uptime_s,
        )
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        extra = {k: v for k, v in w.obj.items() if k not in ("v", "type", "id", *_STATUS_KEYS)}
        return cls(
            map_version=w.req("map_version"),
            keyframes=w.req("keyframes"),
            frames_received=w.req("frames_received"),
            frames_rejected=w.req("frames_rejected"),
            ov_space=w.opt("ov_space"),
            memory_bytes=w.req("memory_bytes"),
            uptime_s=w.req("uptime_s"),
            extra=extra,
            id=w.id(),
        )


def _check_map_name(value: Any) -> str:
    if not isinstance(value, str):
        raise _bad(f"name: expected a string, got {_type_name(value)} {_short(value)}")
    if not NAME_RE.fullmatch(value) or value in (".", ".."):
        raise _bad(
            f"name: {_short(value)} is not a valid map name; use 1..64 characters from "
            "[A-Za-z0-9_.-], not '.' or '..'"
        )
    return value


@dataclass(eq=False, repr=False)
class _MapNameRequest(Message):
    """A request that names a map in the mapper's map directory (``save`` and ``load``)."""

    name: str
    """Map name, ``[A-Za-z0-9_.-]{1,64}``, not "." or ".."."""
    id: RequestId = None

    def __post_init__(self) -> None:
        self.name = _check_map_name(self.name)
        self.id = _check_id(self.id)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire["name"] = self.name
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        return cls(name=w.req("name"), id=w.id())


@dataclass(eq=False, repr=False)
class Save(_MapNameRequest):
    """Save the map under `name` in the mapper's map directory (wire type ``save``)."""

    TYPE: ClassVar[str] = "save"


@dataclass(eq=False, repr=False)
class Load(_MapNameRequest):
    """Load the map `name` from the mapper's map directory (wire type ``load``)."""

    TYPE: ClassVar[str] = "load"


@dataclass(eq=False, repr=False)
class Ok(Message):
    """Success reply without a payload (wire type ``ok``), e.g. to `save`/`load`."""

    TYPE: ClassVar[str] = "ok"

    id: RequestId = None
    message: str | None = None
    """Optional human-readable note (e.g. where the map was saved)."""

    def __post_init__(self) -> None:
        self.id = _check_id(self.id)
        if self.message is not None:
            self.message = _check_str("message", self.message, max_chars=2**20, nonempty=False)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        if self.message is not None:
            wire["message"] = self.message
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        return cls(id=w.id(), message=w.opt("message"))


@dataclass(eq=False, repr=False)
class MapUpdated(Message):
    """Event published on the events endpoint when the map changes (wire type ``map_updated``)."""

    TYPE: ClassVar[str] = "map_updated"

    map_version: int
    keyframes: int

    def __post_init__(self) -> None:
        self.map_version = _check_int("map_version", self.map_version, 0)
        self.keyframes = _check_int("keyframes", self.keyframes, 0)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire.update(map_version=self.map_version, keyframes=self.keyframes)
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        return cls(map_version=w.req("map_version"), keyframes=w.req("keyframes"))


@dataclass(eq=False, repr=False)
class RecordingHeader(Message):
    """First message of a `.govrec` recording (wire type ``recording``)."""

    TYPE: ClassVar[str] = "recording"

    created_ns: int
    """When the recording was started, ns since the Unix epoch."""
    meta: dict[str, Any] = field(default_factory=dict)
    """Free-form description (scene, camera, generator...); str keys, msgpack-able values."""

    def __post_init__(self) -> None:
        self.created_ns = _check_int("created_ns", self.created_ns)
        self.meta = _check_str_map("meta", self.meta)

    def to_wire(self) -> dict[str, Any]:
        wire = self._head()
        wire.update(created_ns=self.created_ns, meta=dict(self.meta))
        return wire

    @classmethod
    def from_wire(cls, obj: dict[str, Any]) -> Self:
        w = _Wire(obj, cls.TYPE)
        return cls(created_ns=w.req("created_ns"), meta=w.opt("meta", {}))


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
    raise TypeError(f"cannot serialise {type(value).__name__} {_short(value)} to msgpack")


def encode(msg: Message) -> bytes:
    """Serialise a message to its wire bytes (one msgpack map, binary payloads as `bin`)."""
    packed = msgpack.packb(msg.to_wire(), use_bin_type=True, default=_pack_default)
    assert isinstance(packed, bytes)
    return packed


def _unpack(data: bytes | bytearray | memoryview, max_bytes: int) -> Any:
    """msgpack-unpack one message with limits derived from its size, so a hostile length prefix
    cannot make the unpacker allocate more than a small multiple of the message size."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise _bad(f"message must be bytes, got {_type_name(data)}")
    n = len(data)
    if n > max_bytes:
        raise ProtocolError("too_large", f"message is {n} bytes; the limit is {max_bytes} bytes")
    if n == 0:
        raise _bad("empty message (expected one msgpack map)")
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
        raise _bad("message is not valid msgpack: nested too deeply") from None
    except ValueError as exc:
        if "map key" in str(exc):
            raise _bad(f"message keys must be strings ({exc})") from None
        raise _bad(f"message is not valid msgpack: {type(exc).__name__}: {_short(str(exc))}") from None
    except Exception as exc:  # msgpack raises several unrelated types on malformed input
        raise _bad(f"message is not valid msgpack: {type(exc).__name__}: {_short(str(exc))}") from None


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
        raise _bad(f"message must be a msgpack map, got {_type_name(obj)}")
    for key in obj:
        if not isinstance(key, str):
            raise _bad(f"message keys must be strings, got {_type_name(key)} {_short(key)}")
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
        raise _bad(f"unknown message type {_short(type_)}; known {direction} types: {', '.join(known)}")
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
        raise _bad(f"message must be a msgpack map, got {_type_name(obj)}")
    _check_header(obj)
    if obj["type"] == Error.TYPE and cls is not Error:
        err = Error.from_wire(obj)
        raise RemoteError(err.code, err.message, id=err.id)
    if obj["type"] != cls.TYPE:
        raise _bad(f"expected a {cls.TYPE!r} message, got type {_short(obj['type'])}")
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
    valid = id is None or _is_int(id) or (isinstance(id, str) and len(id) <= MAX_ID_CHARS)
    safe_id = id if valid else None
    return Error(code=exc.code, message=exc.message, id=safe_id)


MESSAGE_TYPES: tuple[type[Message], ...] = (
    Frame, Ack, Error, QueryPoints, Points, SegmentPoints, Segmentation, Render, RenderResult,
    StatusRequest, Status, Save, Load, Ok, MapUpdated, RecordingHeader,
)
"""Every message class (ObjectCandidate is a part of `Points`, not a message)."""

__all__ = [
    "ACK_STATUSES", "DEFAULT_DEPTH_SCALE", "MAX_MESSAGE_BYTES", "MESSAGE_TYPES", "ORTHONORMAL_TOL",
    "PROTOCOL_VERSION", "RENDER_OUTPUTS", "REPLY_TYPES", "REQUEST_TYPES", "SEGMENT_METHODS",
    "Ack", "Direction", "Error", "ErrorCode", "Frame", "Load", "MapUpdated", "Message", "ObjectCandidate",
    "Ok", "Points", "QueryPoints", "RecordingHeader", "Render", "RenderResult", "RequestId", "Save",
    "SegmentMethod", "SegmentPoints", "Segmentation", "Status", "StatusRequest", "decode", "decode_as",
    "encode", "error_reply", "peek_id",
]
