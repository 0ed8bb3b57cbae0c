"""Valid sample messages and hypothesis strategies shared by the protocol tests."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from protocol.messages import (
    Ack,
    Direction,
    Error,
    Frame,
    Load,
    MapUpdated,
    Message,
    ObjectCandidate,
    Ok,
    Points,
    QueryPoints,
    RecordingHeader,
    Render,
    RenderResult,
    Save,
    Segmentation,
    SegmentPoints,
    Status,
    StatusRequest,
)

H, W = 6, 8
K = np.array([10.0, 11.0, 4.0, 3.0])


def pose(tx: float = 1.0) -> np.ndarray:  # (4, 4) world_from_cam: 90 deg about z, then a shift
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    world_from_cam[:3, 3] = [tx, 2.0, 0.5]
    return world_from_cam


def rgb_image(h: int = H, w: int = W, seed: int = 0) -> np.ndarray:  # (h, w, 3) uint8
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def frame(**kw: Any) -> Frame:
    args: dict[str, Any] = dict(
        seq=3, stamp_ns=1_700_000_000_000_000_000, width=W, height=H, K=K, world_from_cam=pose(),
        rgb=rgb_image(), id=11,
    )
    args.update(kw)
    return Frame(**args)


def frame_wire(**kw: Any) -> dict[str, Any]:
    """A valid frame's wire map (with depth and ov), then `kw` keys replaced."""
    rng = np.random.default_rng(1)
    wire = frame(
        depth_m=rng.uniform(0.5, 4.0, (H, W)).astype(np.float32),
        ov=rng.standard_normal((2, 3, 5)).astype(np.float16),
        ov_space="minilm-l6-v2",
    ).to_wire()
    wire.update(kw)
    return wire


def pack(obj: Any) -> bytes:
    out = msgpack.packb(obj, use_bin_type=True)
    assert isinstance(out, bytes)
    return out


def samples() -> list[Message]:
    """One valid instance of every message type."""
    return [
        frame(),
        Ack(seq=3, status="accepted", map_version=2, reason="too close to keyframe 2", id=1),
        Error(code="busy", message="try again", id="q1"),
        QueryPoints(texts=["chair", "red mug"], negatives=["wall"], min_score=0.2, max_points=10, id=2),
        Points(
            map_version=4,
            xyz=np.zeros((2, 3), np.float32),
            score=np.array([0.5, 0.25], np.float32),
            label=np.array([0, 1], np.int32),
            objects=[ObjectCandidate("chair", np.array([1.0, 2.0, 0.5]), np.zeros(3), np.ones(3), 0.5, 2)],
            timing_ms={"query": 1.5},
            id=2,
        ),
        SegmentPoints(
            xyz=np.ones((3, 3), np.float32), texts=["a", "b"], method="average_depth", use_depth=True
        ),
        Segmentation(
            label=np.array([0, -1, 1], np.int32), score=np.zeros(3, np.float32), timing_ms={"x": 2.0}
        ),
        Render(width=W, height=H, K=K, world_from_cam=pose(), outputs=["rgb", "depth"], id=5),
        RenderResult(rgb=rgb_image(), timing_ms={"render": 3.0}, id=5),
        StatusRequest(id=6),
        Status(
            map_version=1, keyframes=2, frames_received=3, frames_rejected=0, ov_space="minilm-l6-v2",
            memory_bytes=1024, uptime_s=1.5, extra={"device": "cpu"}, id=6,
        ),
        Save(name="kitchen-1", id=7),
        Load(name="kitchen.v2", id=8),
        Ok(id=7, message="saved"),
        MapUpdated(map_version=3, keyframes=2),
        RecordingHeader(created_ns=5, meta={"scene": "room0"}),
    ]


# Optional keys of each sample's wire map: removing them still decodes (see test_missing_fields).
OPTIONAL_KEYS: dict[type[Message], set[str]] = {
    Frame: {"camera"},
    Ack: {"reason"},
    QueryPoints: {"negatives", "min_score", "max_points", "objects"},
    Points: {"objects", "timing_ms"},
    SegmentPoints: {"method", "use_depth"},
    Segmentation: {"timing_ms"},
    RenderResult: {"rgb", "timing_ms"},
    Status: {"ov_space", "device"},
    Ok: {"message"},
    RecordingHeader: {"meta"},
}

REQUESTS = (Frame, QueryPoints, SegmentPoints, Render, StatusRequest, Save, Load)


def direction_of(msg: Message) -> Direction:
    if isinstance(msg, REQUESTS):
        return "request"
    if isinstance(msg, RecordingHeader):
        return "any"
    return "reply"


# ---------------------------------------------------------------------------------------------
# Hypothesis strategies
# ---------------------------------------------------------------------------------------------

ids = st.one_of(st.none(), st.integers(-(2**63), 2**64 - 1), st.text(max_size=20))
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
small = st.floats(-1e3, 1e3, allow_nan=False)
# A prompt carries at least one non-whitespace character (protocol: whitespace-only prompts are refused).
prompts = st.text(min_size=1, max_size=12).filter(lambda t: bool(t.strip()))
texts = st.lists(prompts, min_size=1, max_size=6)
side = st.integers(1, 7)


@st.composite
def rotations(draw: st.DrawFn) -> np.ndarray:  # (3, 3) float64, det +1
    q = np.array(draw(st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4)))
    if np.linalg.norm(q) < 1e-3:
        q = np.array([1.0, 0.0, 0.0, 0.0])
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


@st.composite
def poses(draw: st.DrawFn) -> np.ndarray:  # (4, 4) world_from_cam
    out = np.eye(4)
    out[:3, :3] = draw(rotations())
    out[:3, 3] = draw(st.tuples(small, small, small))
    return out


intrinsics = st.tuples(
    st.floats(0.5, 1e4), st.floats(0.5, 1e4), st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)
).map(lambda k: np.array(k, dtype=np.float64))


def f32(shape: Any, lo: float = -1e6, hi: float = 1e6) -> st.SearchStrategy[np.ndarray]:
    return hnp.arrays(np.float32, shape, elements=st.floats(lo, hi, width=32))


@st.composite
def frames(draw: st.DrawFn) -> Frame:
    h, w = draw(side), draw(side)
    depth = draw(st.none() | f32((h, w), 0.0, 100.0))
    ov = None
    if draw(st.booleans()):
        dtype = draw(st.sampled_from([np.float16, np.float32]))
        shape = (draw(side), draw(side), draw(st.integers(1, 9)))
        ov = draw(hnp.arrays(dtype, shape, elements=st.floats(-100, 100, width=16)))
    return Frame(
        seq=draw(st.integers(0, 2**63)),
        stamp_ns=draw(st.integers(-(2**63), 2**63 - 1)),
        width=w,
        height=h,
        K=draw(intrinsics),
        world_from_cam=draw(poses()),
        rgb=draw(hnp.arrays(np.uint8, (h, w, 3))),
        camera=draw(st.text(min_size=1, max_size=10)),
        depth_m=depth,
        ov=ov,
        ov_space=None if ov is None else draw(st.text(min_size=1, max_size=20)),
        rgb_encoding=draw(st.sampled_from(["rgb8", "png"])),
        id=draw(ids),
    )


scalars = st.one_of(st.none(), st.booleans(), st.integers(-(2**63), 2**63), finite, st.text(max_size=8))
free_values = st.recursive(
    scalars | st.binary(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=8,
)
timings = st.dictionaries(st.text(max_size=8), st.floats(0, 1e6))


@st.composite
def object_candidates(draw: st.DrawFn) -> ObjectCandidate:
    vec = st.tuples(small, small, small).map(np.array)
    return ObjectCandidate(
        text=draw(st.text(max_size=10)),
        centroid=draw(vec),
        aabb_min=draw(vec),
        aabb_max=draw(vec),
        score=draw(st.floats(allow_nan=False)),
        n_points=draw(st.integers(0, 10**6)),
    )


@st.composite
def points_replies(draw: st.DrawFn) -> Points:
    n = draw(st.integers(0, 6))
    return Points(
        map_version=draw(st.integers(0, 2**40)),
        xyz=draw(f32((n, 3))),
        score=draw(f32((n,), -1, 1)),
        label=draw(hnp.arrays(np.int32, (n,))),
        objects=draw(st.lists(object_candidates(), max_size=3)),
        timing_ms=draw(timings),
        id=draw(ids),
    )


@st.composite
def render_results(draw: st.DrawFn) -> RenderResult:
    h, w, t = draw(side), draw(side), draw(st.integers(1, 4))
    maybe = st.booleans()
    return RenderResult(
        rgb=draw(hnp.arrays(np.uint8, (h, w, 3))) if draw(maybe) else None,
        depth_m=draw(f32((h, w), 0, 100)) if draw(maybe) else None,
        label=draw(hnp.arrays(np.int32, (h, w))) if draw(maybe) else None,
        score=draw(f32((h, w, t), -1, 1)) if draw(maybe) else None,
        timing_ms=draw(timings),
        id=draw(ids),
    )


@st.composite
def renders(draw: st.DrawFn) -> Render:
    outputs = draw(st.lists(st.sampled_from(["rgb", "depth", "label", "score"]), min_size=1, unique=True))
    need_texts = "label" in outputs or "score" in outputs
    return Render(
        width=draw(st.integers(1, 4096)),
        height=draw(st.integers(1, 4096)),
        K=draw(intrinsics),
        world_from_cam=draw(poses()),
        outputs=outputs,
        texts=draw(texts) if need_texts else draw(st.none() | texts),
        id=draw(ids),
    )


status_reserved = {"v", "type", "id", "map_version", "keyframes", "frames_received", "frames_rejected",
                   "ov_space", "memory_bytes", "uptime_s"}
counts = st.integers(0, 2**63)
map_names = st.from_regex(r"[A-Za-z0-9_.\-]{1,64}", fullmatch=True).filter(lambda s: s not in (".", ".."))

STRATEGIES: list[st.SearchStrategy[Any]] = [
    frames(),
    st.builds(
        Ack, seq=counts, status=st.sampled_from(["keyframe", "accepted"]), map_version=counts,
        reason=st.none() | st.text(max_size=10), id=ids,
    ),
    st.builds(Ack, seq=counts, status=st.just("rejected"), map_version=counts,
              reason=st.text(min_size=1, max_size=10), id=ids),
    st.builds(
        Error,
        code=st.sampled_from(["bad_request", "unsupported_version", "too_large", "ov_space_mismatch",
                              "not_ready", "busy", "internal"]),
        message=st.text(max_size=30), id=ids,
    ),
    st.builds(
        QueryPoints, texts=texts, negatives=st.none() | st.lists(prompts, max_size=4),
        min_score=st.none() | finite, max_points=st.none() | st.integers(1, 2**40), objects=st.booleans(),
        id=ids,
    ),
    points_replies(),
    st.integers(0, 6).flatmap(lambda n: st.builds(
        SegmentPoints, xyz=f32((n, 3)), texts=texts,
        method=st.sampled_from(["govnesf", "average", "average_depth"]), use_depth=st.booleans(), id=ids,
    )),
    st.integers(0, 6).flatmap(lambda n: st.builds(
        Segmentation, label=hnp.arrays(np.int32, (n,)), score=f32((n,), -1, 1), timing_ms=timings, id=ids,
    )),
    renders(),
    render_results(),
    st.builds(StatusRequest, id=ids),
    st.builds(
        Status, map_version=counts, keyframes=counts, frames_received=counts, frames_rejected=counts,
        ov_space=st.none() | st.text(min_size=1, max_size=12), memory_bytes=counts,
        uptime_s=st.floats(0, 1e9),
        extra=st.dictionaries(st.text(max_size=8).filter(lambda k: k not in status_reserved), free_values,
                              max_size=4),
        id=ids,
    ),
    st.builds(Save, name=map_names, id=ids),
    st.builds(Load, name=map_names, id=ids),
    st.builds(Ok, id=ids, message=st.none() | st.text(max_size=10)),
    st.builds(MapUpdated, map_version=counts, keyframes=counts),
    st.builds(RecordingHeader, created_ns=st.integers(0, 2**63),
              meta=st.dictionaries(st.text(max_size=8), free_values, max_size=4)),
]

messages: st.SearchStrategy[Message] = st.one_of(*STRATEGIES)
