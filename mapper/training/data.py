"""Training data for GOV-NeSF: scenes read from `govnesf sim record` exports, sampled as ray batches.

A scene directory (see docs/how-to/simulator.md) holds ``frames.govrec`` (rgb, depth, SimLSeg ov per frame)
and ``gt/`` (``novel_views.npz`` with held-out views and their labels, used for validation).
The mapper never imports the simulator: data generation is a separate step
(``scripts/make_train_data.sh``), training only reads these files.

One training example (``RaySampler.sample``) is a target frame of a scene, its N source frames
(the frames whose depth-backprojected surface points fall most inside the target's view, the
target itself excluded), volume bounds from the sources' depth points (``bounds_from_points``),
and R random pixel rays of the target with the target's colour and its OV feature (bilinear from
the coarse ov map at the pixel centre) as supervision. Sampling is a pure function of
``(seed, step, item)``: data-parallel ranks draw disjoint items of the same global batch, and a
resumed run draws exactly what an uninterrupted one would.

Scenes stay decoded in memory (rgb uint8, depth float32, ov float16: about 1 MB a frame at
160 x 120 with a 40 x 30 x 384 ov map).

Real RGB-D sequences (``govnesf import``, e.g. ICL-NUIM; ``scripts/make_real_data.sh``) have colour,
depth and poses but no ov maps: ``load_scene(..., require_ov=False)`` gives them an all-zero ov map
(``Scene.has_ov = False``; one shared zero frame, no memory per frame) and can resize them to the
training size (``image_wh``). ``RaySampler(..., extra_scenes=..., extra_weight=p)`` draws a fraction
p of the examples from such scenes; their ``TrainSample.has_ov`` is False and training gives every
OV term of those examples weight 0 (colour and geometry only).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from mapper.model.config import ModelConfig
from mapper.model.ops.cost_volume import VolumeBounds, bounds_from_points
from mapper.model.ops.geometry import (
    frustum_points,
    invert_pose,
    pixel_rays,
    project_points,
    sample_bilinear,
    scale_uv,
)
from mapper.model.supervision import ray_distance, surface_points, visibility_targets
from protocol.recording import read_recording

__all__ = [
    "NovelViews",
    "RaySampler",
    "Scene",
    "SourceBatch",
    "TrainSample",
    "ValidationView",
    "find_scenes",
    "load_scene",
    "overlap_scores",
    "resize_view",
    "select_sources",
    "source_batch",
    "validation_views",
]

_POINT_STRIDE_PX = 8
"""Depth pixels (every 8th row and column) back-projected per frame for overlap and bounds."""

DEFAULT_OV_DIM = 384
"""Dimension of the zero ov maps of a recording without ov when ``load_scene`` gets no ``ov_shape``
(SimLSeg's minilm-l6-v2 space; training passes the model's own)."""
OV_STRIDE_PX = 4
"""Image pixels per ov cell of those zero maps by default (SimLSeg's stride: 40 x 30 at 160 x 120)."""
_MIX_STREAM = 1
"""Extra entropy word of the random stream that decides whether an example comes from the extra
scenes (``RaySampler.extra_weight``); separate from the example's own stream, see ``sample``."""
_VOLUME_STREAM = 2
_SENSOR_STREAM = 3  # sensor effects and source pose error (mapper.training.augment)
_OV_NOISE_STREAM = 4  # the sources' OV maps made noisier (mapper.training.augment.ov_noise)
_SCALE_STREAM = 5  # the example's world scaled (RaySampler.world_scale_prob)
"""Extra entropy word of the random stream that draws an example's number of volume sources
(``RaySampler.volume_sources``); separate from the example's own stream."""


@dataclass
class NovelViews:
    """Held-out views of a scene (``gt/novel_views.npz``)."""

    K: np.ndarray  # (V, 4) float64
    world_from_cam: np.ndarray  # (V, 4, 4) float64
    rgb: np.ndarray  # (V, H, W, 3) uint8
    label: np.ndarray  # (V, H, W) int32, -1 = none


@dataclass
class Scene:
    """One recorded scene, decoded in memory."""

    name: str
    rgb: np.ndarray
    """(F, H, W, 3) uint8."""
    depth_m: np.ndarray
    """(F, H, W) float32 z-depth, 0 = none."""
    ov: np.ndarray
    """(F, h, w, D) float16 open-vocabulary maps."""
    K: np.ndarray
    """(F, 4) float64 [fx, fy, cx, cy]."""
    world_from_cam: np.ndarray
    """(F, 4, 4) float64."""
    points_m: np.ndarray
    """(F, M, 3) float32 world points back-projected from a strided depth grid (NaN = no depth)."""
    class_names: list[str]
    novel: NovelViews | None = None
    has_ov: bool = True
    """False for a recording without ov maps (a real RGB-D sequence): ``ov`` is all zeros (a
    read-only broadcast of one zero frame) and training masks every OV term of its examples."""

    @property
    def num_frames(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def image_wh(self) -> tuple[int, int]:
        return int(self.rgb.shape[2]), int(self.rgb.shape[1])

    @property
    def ov_dim(self) -> int:
        return int(self.ov.shape[-1])


def held_out_positions(num_frames: int, every: int, radius: int) -> np.ndarray:
    """(F,) bool: True for the frames within ``radius`` positions of a multiple of ``every``
    (0, every, 2 * every, ...): the held-out targets of ``benchmarks/studies/real_sequence.py`` (every
    ``--every``-th frame) and their neighbours. ``every`` = 0 holds out nothing.

    >>> np.flatnonzero(held_out_positions(23, 10, 1)).tolist()
    [0, 1, 9, 10, 11, 19, 20, 21]
    """
    if every < 0 or radius < 0:
        raise ValueError(f"held-out frames: every {every} and radius {radius} must be >= 0")
    if every == 0:
        return np.zeros(num_frames, dtype=bool)
    offset = np.arange(num_frames) % every
    return np.minimum(offset, every - offset) <= radius


def drop_frames(scene: Scene, drop: np.ndarray) -> Scene:
    """The scene without the frames where ``drop`` (F,) bool is True (e.g. the held-out poses of a
    real sequence that the evaluation renders: :func:`held_out_positions`), in the same order.

    Raises:
        ValueError: ``drop`` has the wrong length, or fewer than 2 frames would remain.
    """
    drop = np.asarray(drop, dtype=bool)
    if drop.shape != (scene.num_frames,):
        raise ValueError(f"drop_frames: mask of shape {drop.shape} for {scene.num_frames} frames")
    keep = np.flatnonzero(~drop)
    if keep.size < 2:
        raise ValueError(f"drop_frames: {scene.name} would keep {keep.size} frame(s); training needs 2")
    if scene.has_ov:
        ov = scene.ov[keep]
    else:  # keep the zero maps a read-only broadcast of one frame (no copy)
        ov = np.broadcast_to(scene.ov[:1], (keep.size, *scene.ov.shape[1:]))
    return replace(
        scene,
        rgb=scene.rgb[keep],
        depth_m=scene.depth_m[keep],
        ov=ov,
        K=scene.K[keep],
        world_from_cam=scene.world_from_cam[keep],
        points_m=scene.points_m[keep],
    )


def _backproject_grid(
    depth_m: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, stride: int
) -> np.ndarray:
    """(F, H, W) depth -> (F, M, 3) world points at the centres of every ``stride``-th pixel."""
    n, h, w = depth_m.shape
    rows = np.arange(stride // 2, h, stride)
    cols = np.arange(stride // 2, w, stride)
    z = depth_m[:, rows][:, :, cols].reshape(n, -1).astype(np.float64)  # (F, M)
    vv, uu = np.meshgrid(rows + 0.5, cols + 0.5, indexing="ij")
    u, v = uu.reshape(-1), vv.reshape(-1)
    fx, fy, cx, cy = (K[:, i : i + 1] for i in range(4))
    x = (u[None] - cx) / fx * z
    y = (v[None] - cy) / fy * z
    cam = np.stack([x, y, z], axis=-1)  # (F, M, 3)
    world = np.einsum("fij,fmj->fmi", world_from_cam[:, :3, :3], cam) + world_from_cam[:, None, :3, 3]
    world[~(np.isfinite(z) & (z > 0))] = np.nan
    return world.astype(np.float32)


def find_scenes(root: str | Path) -> list[Path]:
    """Scene folders under ``root`` (each with a ``frames.govrec``), sorted; ``root`` itself counts."""
    root = Path(root)
    if (root / "frames.govrec").is_file():
        return [root]
    if not root.is_dir():
        raise FileNotFoundError(f"data folder {root} does not exist (run scripts/make_train_data.sh)")
    scenes = sorted(p.parent for p in root.glob("*/frames.govrec"))
    if not scenes:
        raise FileNotFoundError(f"no scenes (*/frames.govrec) under {root}; run scripts/make_train_data.sh")
    return scenes


def _pixel_centre_index(src: int, dst: int) -> np.ndarray:
    """(dst,) source index of the pixel holding each destination pixel centre (centre-aligned
    nearest neighbour, like ``cv2.INTER_NEAREST_EXACT``)."""
    return np.minimum(((np.arange(dst) + 0.5) * (src / dst)).astype(np.int64), src - 1)


def resize_view(
    rgb: np.ndarray,
    depth_m: np.ndarray | None,
    K: np.ndarray,
    image_wh: tuple[int, int],
    label: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray | None]:
    """One view resized to ``image_wh`` = (W, H): colour by area averaging (``cv2.INTER_AREA``),
    depth and labels by nearest neighbour (no depth mixed across an edge), and ``K`` (4,) scaled.

    With pixel centres at integer + 0.5 (the project's convention) a resize maps image
    coordinates u -> u * W' / W exactly, so fx and cx scale alike (and fy, cy).

    >>> rgb, K = np.zeros((480, 640, 3), np.uint8), np.array([525.0, 525.0, 320.0, 240.0])
    >>> resize_view(rgb, None, K, (160, 120))[2].tolist()
    [131.25, 131.25, 80.0, 60.0]
    """
    h, w = rgb.shape[:2]
    w2, h2 = int(image_wh[0]), int(image_wh[1])
    if (w2, h2) == (w, h):
        return rgb, depth_m, np.asarray(K, np.float64), label
    sx, sy = w2 / w, h2 / h
    K2 = np.asarray(K, np.float64) * np.array([sx, sy, sx, sy])
    rgb2 = cv2.resize(rgb, (w2, h2), interpolation=cv2.INTER_AREA)
    rows, cols = _pixel_centre_index(h, h2), _pixel_centre_index(w, w2)
    depth2 = None if depth_m is None else np.ascontiguousarray(depth_m[rows][:, cols])
    label2 = None if label is None else np.ascontiguousarray(label[rows][:, cols])
    return rgb2, depth2, K2, label2


def load_scene(
    path: str | Path,
    *,
    with_novel_views: bool = False,
    require_ov: bool = True,
    image_wh: tuple[int, int] | None = None,
    ov_shape: tuple[int, int, int] | None = None,
) -> Scene:
    """Decode a recorded scene folder into memory.

    Args:
        require_ov: every frame must carry an ov map (simulated training / validation scenes).
            False also accepts a recording whose frames have none (a real RGB-D sequence): it
            gets all-zero ov maps of ``ov_shape`` and ``has_ov = False``. Depth is always required.
        image_wh: (W, H) to resize colour (area), depth (nearest) and intrinsics to (and the novel
            views); None keeps the recorded size. The ov maps keep their grid.
        ov_shape: (h, w, D) of the zero ov maps of a recording without ov (training passes the
            training scenes' grid and the model's ``ov_dim``); default the image size / 4 and
            ``DEFAULT_OV_DIM``.

    Raises:
        ValueError: a frame has no depth, or no ov map with ``require_ov`` (record with
            ``--depth`` and without ``--no-ov``), or only some frames have ov maps.
    """
    path = Path(path)
    reader = read_recording(path / "frames.govrec")
    rgb, depth, ov, Ks, poses = [], [], [], [], []
    without_ov: list[int] = []
    for i, frame in enumerate(reader.frames()):
        if frame.depth_m is None or (require_ov and frame.ov is None):
            need = "both (govnesf sim record --depth, without --no-ov)" if require_ov else "depth"
            hint = "" if frame.depth_m is None else "; a real RGB-D sequence without ov: require_ov=False"
            raise ValueError(
                f"{path}: frame {i} has depth={frame.depth_m is not None}, ov={frame.ov is not None}; "
                f"training needs {need}{hint}"
            )
        frame_rgb, frame_depth, frame_K = frame.rgb, frame.depth_m.astype(np.float32), frame.K
        if image_wh is not None:
            frame_rgb, resized, frame_K, _ = resize_view(frame_rgb, frame_depth, frame_K, image_wh)
            assert resized is not None
            frame_depth = resized
        rgb.append(frame_rgb)
        depth.append(frame_depth)
        if frame.ov is None:
            without_ov.append(i)
        else:
            ov.append(frame.ov.astype(np.float16))
        Ks.append(frame_K)
        poses.append(frame.world_from_cam)
    if reader.truncated:
        raise ValueError(f"{path / 'frames.govrec'} is truncated: {reader.error}")
    if not rgb:
        raise ValueError(f"{path / 'frames.govrec'} has no frames")
    if without_ov and ov:
        raise ValueError(
            f"{path}: {len(ov)} frames have ov maps and {len(without_ov)} (first: frame {without_ov[0]}) "
            "have none; a training scene has ov maps in every frame or in none"
        )
    K = np.stack(Ks).astype(np.float64)
    world_from_cam = np.stack(poses).astype(np.float64)
    depth_m = np.stack(depth)
    rgb_all = np.stack(rgb)
    has_ov = not without_ov
    if has_ov:
        ov_all = np.stack(ov)
    else:
        height, width = rgb_all.shape[1:3]
        default_shape = (max(1, height // OV_STRIDE_PX), max(1, width // OV_STRIDE_PX), DEFAULT_OV_DIM)
        oh, ow, od = ov_shape or default_shape
        ov_all = np.broadcast_to(np.zeros((1, oh, ow, od), np.float16), (len(rgb), oh, ow, od))
    names_path = path / "gt" / "class_names.json"
    meta_names = reader.header.meta.get("class_names") if isinstance(reader.header.meta, dict) else None
    class_names = json.loads(names_path.read_text()) if names_path.is_file() else list(meta_names or [])
    novel = None
    if with_novel_views:
        nv_path = path / "gt" / "novel_views.npz"
        if not nv_path.is_file():
            raise FileNotFoundError(f"{nv_path} missing: validation needs the recording's novel views")
        with np.load(nv_path, allow_pickle=False) as d:
            novel = NovelViews(
                K=d["K"].astype(np.float64),
                world_from_cam=d["world_from_cam"].astype(np.float64),
                rgb=d["rgb"],
                label=d["label"].astype(np.int32),
            )
        if image_wh is not None:
            rgbs, nKs, labels = [], [], []
            for v in range(len(novel.K)):
                v_rgb, _, v_K, v_label = resize_view(novel.rgb[v], None, novel.K[v], image_wh, novel.label[v])
                assert v_label is not None
                rgbs.append(v_rgb)
                nKs.append(v_K)
                labels.append(v_label)
            novel = NovelViews(
                K=np.stack(nKs),
                world_from_cam=novel.world_from_cam,
                rgb=np.stack(rgbs),
                label=np.stack(labels),
            )
    return Scene(
        name=path.name,
        rgb=rgb_all,
        depth_m=depth_m,
        ov=ov_all,
        K=K,
        world_from_cam=world_from_cam,
        points_m=_backproject_grid(depth_m, K, world_from_cam, _POINT_STRIDE_PX),
        class_names=class_names,
        novel=novel,
        has_ov=has_ov,
    )


# ---- source selection ----------------------------------------------------------------------------
def overlap_scores(
    scene: Scene, K: np.ndarray, world_from_cam: np.ndarray, *, max_depth_m: float = 8.0
) -> np.ndarray:
    """(F,) fraction of each frame's surface points that fall inside a target view.

    Args:
        K: (4,) intrinsics of the target (for the scene's image size); world_from_cam: (4, 4).
        max_depth_m: points farther than this from the target camera do not count.
    """
    cam_from_world = np.linalg.inv(world_from_cam)
    pts = scene.points_m.astype(np.float64)  # (F, M, 3)
    cam = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = cam[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = K[0] * cam[..., 0] / z + K[2]
        v = K[1] * cam[..., 1] / z + K[3]
    w, h = scene.image_wh
    seen = np.isfinite(z) & (z > 0.05) & (z < max_depth_m) & (u >= 0) & (u <= w) & (v >= 0) & (v <= h)
    valid = np.isfinite(pts).all(axis=-1).sum(axis=1)
    return seen.sum(axis=1) / np.maximum(valid, 1)


def select_sources(
    scene: Scene,
    K: np.ndarray,
    world_from_cam: np.ndarray,
    num_sources: int,
    *,
    exclude: int | None = None,
    pool_factor: float = 1.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Indices of the source frames for a target view, best overlap first.

    Args:
        num_sources: N (fewer if the scene has fewer frames).
        exclude: a frame index never chosen (the target itself when it is a stream frame).
        pool_factor: >= 1; N frames are drawn at random (``rng``) from the ceil(N * pool_factor)
            best (training augmentation); 1 takes the N best (deterministic).
    """
    if num_sources < 1:
        raise ValueError(f"num_sources {num_sources} out of range: must be >= 1")
    if pool_factor < 1.0:
        raise ValueError(f"pool_factor {pool_factor} out of range: must be >= 1")
    scores = overlap_scores(scene, K, world_from_cam)
    if exclude is not None:
        scores[exclude] = -np.inf
    order = np.argsort(-scores, kind="stable")
    available = scene.num_frames - (1 if exclude is not None else 0)
    if available < 1:
        raise ValueError(f"scene {scene.name} has no frame to use as a source")
    n = min(num_sources, available)
    pool = order[: min(available, max(n, math.ceil(n * pool_factor)))]
    if len(pool) > n and rng is not None:
        pool = pool[np.sort(rng.choice(len(pool), size=n, replace=False))]
    return pool[:n]


# ---- batches -----------------------------------------------------------------------------------------
@dataclass
class SourceBatch:
    """Source views as network inputs (float32 tensors) and the volume bounds over them."""

    rgb: Tensor  # (N, 3, H, W) in [0, 1]
    ov: Tensor  # (N, D, h, w)
    depth_m: Tensor  # (N, H, W)
    K: Tensor  # (N, 4)
    world_from_cam: Tensor  # (N, 4, 4)
    bounds: VolumeBounds
    indices: np.ndarray  # (N,) frame indices in the scene

    def to(self, device: torch.device | str) -> SourceBatch:
        return SourceBatch(
            self.rgb.to(device),
            self.ov.to(device),
            self.depth_m.to(device),
            self.K.to(device),
            self.world_from_cam.to(device),
            self.bounds,
            self.indices,
        )


def source_bounds(
    scene: Scene, idx: np.ndarray, cfg: ModelConfig, *, frustum_range_m: float | None = None,
    world_scale: float = 1.0,
) -> VolumeBounds:
    """The volume bounds (cfg.volume budget) over source frames ``idx`` (N,): from their depth
    points, or, with ``frustum_range_m``, from their viewing frusta up to that range (the node's
    ``model.max_range_m``, the same in any world), in the scene's world scaled by ``world_scale``."""
    w_from_c = np.array(scene.world_from_cam[idx], np.float64)
    w_from_c[:, :3, 3] *= world_scale
    if frustum_range_m is not None:
        w, h = scene.image_wh
        pts = torch.cat(
            [
                frustum_points(
                    torch.from_numpy(scene.K[i]).double(),
                    torch.from_numpy(pose),
                    w,
                    h,
                    min(0.2, 0.5 * frustum_range_m),
                    frustum_range_m,
                )
                for i, pose in zip(idx, w_from_c, strict=True)
            ]
        ).float().numpy()
    else:
        pts = scene.points_m[idx].reshape(-1, 3) * np.float32(world_scale)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:  # no depth at all: a box around the cameras
        centres = w_from_c[:, :3, 3]
        pts = np.concatenate([centres - 1.0, centres + 1.0]).astype(np.float32)
    vc = cfg.volume
    return bounds_from_points(
        torch.from_numpy(np.ascontiguousarray(pts, np.float32)),
        max_voxels=vc.max_voxels,
        min_voxel_size_m=vc.min_voxel_size_m,
        margin_m=vc.margin_m,
    )


def source_batch(
    scene: Scene, indices: np.ndarray, cfg: ModelConfig, *, frustum_range_m: float | None = None
) -> SourceBatch:
    """Tensors of the chosen source frames and volume bounds (cfg.volume budget) from their depth
    points, or, with ``frustum_range_m``, from their viewing frusta up to that range: what the node
    does for frames without depth (``mapper.runtime.model_runtime``), so a model trained on both
    does not learn that surfaces lie near the volume's faces."""
    idx = np.asarray(indices, dtype=np.int64)
    bounds = source_bounds(scene, idx, cfg, frustum_range_m=frustum_range_m)
    return SourceBatch(
        rgb=torch.from_numpy(scene.rgb[idx]).permute(0, 3, 1, 2).float() / 255.0,
        ov=torch.from_numpy(scene.ov[idx]).permute(0, 3, 1, 2).float(),
        depth_m=torch.from_numpy(scene.depth_m[idx]),
        K=torch.from_numpy(scene.K[idx]).float(),
        world_from_cam=torch.from_numpy(scene.world_from_cam[idx]).float(),
        bounds=bounds,
        indices=idx,
    )


@dataclass
class TrainSample:
    """One target view's rays with supervision, and its sources."""

    sources: SourceBatch
    origins: Tensor  # (R, 3)
    directions: Tensor  # (R, 3) unit
    target_rgb: Tensor  # (R, 3) in [0, 1]
    target_ov: Tensor  # (R, D)
    scene: str
    target: int
    seed: int
    """Seed for the stochastic parts of the step (stratified ray samples)."""
    target_t: Tensor | None = None
    """(R,) true distance along each ray to the surface (from the target's depth; 0 = none)."""
    has_ov: bool = True
    """False: the target's scene has no ov maps (``target_ov`` and the sources' ov are zeros);
    training gives every OV term of this example weight 0."""
    blend_sources: int = 0
    """> 0: only the first ``blend_sources`` of ``sources`` are blended; the cost volume (and its
    bounds) is built over all of them (``RaySampler.volume_sources``). 0: every source does both."""
    target_ov_point: Tensor | None = None
    """(R, D) the point-level OV target at each ray's true surface point when it is not the target
    frame's own feature (``RaySampler.point_ov_target = "visible_mean"``: the mean over every frame
    of the scene that sees the point, :func:`visible_mean_features`); None: ``target_ov``."""

    def to(self, device: torch.device | str) -> TrainSample:
        return TrainSample(
            self.sources.to(device),
            self.origins.to(device),
            self.directions.to(device),
            self.target_rgb.to(device),
            self.target_ov.to(device),
            self.scene,
            self.target,
            self.seed,
            None if self.target_t is None else self.target_t.to(device),
            self.has_ov,
            self.blend_sources,
            None if self.target_ov_point is None else self.target_ov_point.to(device),
        )


class RaySampler:
    """Deterministic training examples over in-memory scenes.

    ``sample(step, item)`` depends only on ``(seed, step, item)`` and the scenes, never on which
    process draws it or on what was drawn before.

    ``extra_scenes`` (e.g. real RGB-D sequences loaded with ``require_ov=False``) are drawn with
    probability ``extra_weight`` per example (0: never, and the examples are exactly those of a
    sampler without them).
    """

    def __init__(
        self,
        scenes: list[Scene],
        cfg: ModelConfig,
        *,
        rays_per_view: int,
        num_sources: int | None = None,
        pool_factor: float = 1.5,
        seed: int = 0,
        frustum_bounds_prob: float = 0.0,
        frustum_range_m: float = 4.0,
        photometric_prob: float = 0.0,
        photometric_strength: float = 0.2,
        extra_scenes: list[Scene] | None = None,
        extra_weight: float = 0.0,
        volume_sources: int = 0,
        point_ov_target: str = "frame",
        point_ov_rel_tol: float = 0.05,
        sensor_prob: float = 0.0,
        sensor_strength: float = 1.0,
        pose_noise_prob: float = 0.0,
        pose_noise_m: float = 0.02,
        pose_noise_deg: float = 1.0,
        ov_noise_prob: float = 0.0,
        ov_noise_strength: float = 1.0,
        world_scale_prob: float = 0.0,
        world_scale_max: float = 1.5,
    ) -> None:
        if not scenes:
            raise ValueError("RaySampler needs at least one scene")
        if point_ov_target not in POINT_OV_TARGETS:
            raise ValueError(f"point_ov_target {point_ov_target!r} must be one of {POINT_OV_TARGETS}")
        if not point_ov_rel_tol >= 0.0:
            raise ValueError(f"point_ov_rel_tol {point_ov_rel_tol} out of range: must be >= 0")
        if volume_sources < 0:
            raise ValueError(f"volume_sources {volume_sources} out of range: must be >= 0")
        for name, p in (("sensor_prob", sensor_prob), ("pose_noise_prob", pose_noise_prob),
                        ("ov_noise_prob", ov_noise_prob)):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} {p} out of range 0..1")
        if not (0.0 <= sensor_strength <= 4.0 and pose_noise_m >= 0.0 and pose_noise_deg >= 0.0):
            raise ValueError(f"sensor_strength {sensor_strength} (0..4), pose_noise_m {pose_noise_m} and "
                             f"pose_noise_deg {pose_noise_deg} (>= 0) out of range")
        if rays_per_view < 1:
            raise ValueError(f"rays_per_view {rays_per_view} out of range: must be >= 1")
        if not 0.0 <= frustum_bounds_prob <= 1.0:
            raise ValueError(f"frustum_bounds_prob {frustum_bounds_prob} out of range 0..1")
        if not frustum_range_m > 0.0:
            raise ValueError(f"frustum_range_m {frustum_range_m} out of range: must be > 0")
        if not 0.0 <= photometric_prob <= 1.0:
            raise ValueError(f"photometric_prob {photometric_prob} out of range 0..1")
        if not 0.0 <= photometric_strength < 1.0:
            raise ValueError(f"photometric_strength {photometric_strength} out of range: 0 <= s < 1")
        extra_scenes = list(extra_scenes or [])
        if not 0.0 <= extra_weight <= 1.0:
            raise ValueError(f"extra_weight {extra_weight} out of range 0..1")
        if extra_weight > 0 and not extra_scenes:
            raise ValueError(f"extra_weight {extra_weight} > 0 needs extra_scenes")
        for s in [*scenes, *extra_scenes]:
            if s.num_frames < 2:
                raise ValueError(f"scene {s.name} has {s.num_frames} frame(s); training needs >= 2")
            if s.ov_dim != cfg.fusion.ov_dim:
                hint = "" if s.has_ov else " (a scene without ov: load it with ov_shape=(h, w, ov_dim))"
                raise ValueError(
                    f"scene {s.name} has {s.ov_dim}-d ov features but the model expects "
                    f"{cfg.fusion.ov_dim} (fusion.ov_dim){hint}"
                )
        self.scenes = scenes
        self.extra_scenes = extra_scenes
        self.extra_weight = extra_weight
        """Probability that an example is drawn from ``extra_scenes`` instead of ``scenes``."""
        self.cfg = cfg
        self.rays_per_view = rays_per_view
        self.num_sources = num_sources or cfg.num_source_views
        self.pool_factor = pool_factor
        self.seed = seed
        self.frustum_bounds_prob = frustum_bounds_prob
        """Fraction of examples whose volume bounds come from the sources' frusta, not their depth."""
        self.frustum_range_m = frustum_range_m
        self.photometric_prob = photometric_prob
        """Fraction of examples whose colours are jittered (:func:`photometric_jitter`)."""
        self.photometric_strength = photometric_strength
        self.volume_sources = volume_sources
        """> the number of sources: each example's cost volume is built over N frames, N drawn
        uniformly from [num_sources, volume_sources]: the blend's sources and the next best
        overlapping frames (as the node's volume spans its whole window while each point blends a
        few views); 0 (or <= num_sources): over the blend's sources."""
        self.point_ov_target = point_ov_target
        """"frame": the point-level OV target is the target frame's own feature at the ray's pixel;
        "visible_mean": the mean over every frame that sees the ray's surface point
        (:func:`visible_mean_features`, depth agreement within ``point_ov_rel_tol``)."""
        self.point_ov_rel_tol = point_ov_rel_tol
        self.sensor_prob = sensor_prob
        """Fraction of examples whose source images get sensor effects
        (:func:`mapper.training.augment.sensor_effects` at ``sensor_strength``)."""
        self.sensor_strength = sensor_strength
        self.pose_noise_prob = pose_noise_prob
        """Fraction of examples whose source poses get a random rigid error
        (:func:`mapper.training.augment.perturb_poses`, ``pose_noise_m`` / ``pose_noise_deg`` std per
        axis, scaled per example by a uniform draw in [0, 1]); the target rays stay true."""
        self.pose_noise_m = pose_noise_m
        self.pose_noise_deg = pose_noise_deg
        if not 0.0 <= ov_noise_strength <= 4.0:
            raise ValueError(f"ov_noise_strength {ov_noise_strength} out of range 0..4")
        self.ov_noise_prob = ov_noise_prob
        """Fraction of examples whose sources' OV maps get noise and confused regions
        (:func:`mapper.training.augment.ov_noise` at ``ov_noise_strength``)."""
        self.ov_noise_strength = ov_noise_strength
        if not 0.0 <= world_scale_prob <= 1.0 or not 1.0 <= world_scale_max <= 4.0:
            raise ValueError(f"world_scale_prob {world_scale_prob} (0..1) or world_scale_max "
                             f"{world_scale_max} (1..4) out of range")
        self.world_scale_prob = world_scale_prob
        """Fraction of examples whose whole world (camera centres, depths, the target's rays and
        surface distances, the volume bounds) is scaled by a factor drawn log-uniformly in
        [1 / ``world_scale_max``, ``world_scale_max``]: the same images, a room of another size."""
        self.world_scale_max = world_scale_max

    def rng(self, step: int, item: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([self.seed, step, item]))

    def from_extra(self, step: int, item: int) -> bool:
        """Whether example ``item`` of ``step`` is drawn from the extra scenes: a draw of its own
        stream (``(seed, step, item, 1)``), made only when ``extra_weight > 0``, so the example's
        main stream, and every example drawn from the main scenes, is the same as without them."""
        if self.extra_weight <= 0:
            return False
        mix = np.random.default_rng(np.random.SeedSequence([self.seed, step, item, _MIX_STREAM]))
        return bool(mix.random() < self.extra_weight)

    def sample(self, step: int, item: int) -> TrainSample:
        """Example ``item`` of the global batch of ``step``."""
        rng = self.rng(step, item)
        pool = self.extra_scenes if self.from_extra(step, item) else self.scenes
        scene = pool[int(rng.integers(len(pool)))]
        target = int(rng.integers(scene.num_frames))
        K, pose = scene.K[target], scene.world_from_cam[target]
        src = select_sources(
            scene, K, pose, self.num_sources, exclude=target, pool_factor=self.pool_factor, rng=rng
        )
        frustum = self.frustum_bounds_prob > 0 and bool(rng.random() < self.frustum_bounds_prob)
        range_m = self.frustum_range_m if frustum else None
        blend_sources = 0
        if self.volume_sources > len(src):  # its own stream: examples without it are unchanged
            vrng = np.random.default_rng(np.random.SeedSequence([self.seed, step, item, _VOLUME_STREAM]))
            n_volume = int(vrng.integers(len(src), self.volume_sources + 1))
            best = select_sources(scene, K, pose, n_volume, exclude=target)
            more = [int(i) for i in best if int(i) not in set(src.tolist())][: n_volume - len(src)]
            if more:
                blend_sources = len(src)
                src = np.concatenate([src, np.asarray(more, dtype=src.dtype)])
        sources = source_batch(scene, src, self.cfg, frustum_range_m=range_m)
        w, h = scene.image_wh
        pix = rng.choice(w * h, size=min(self.rays_per_view, w * h), replace=False)
        rows, cols = pix // w, pix % w
        K_t = torch.from_numpy(K).float()
        pose_t = torch.from_numpy(pose).float()
        origins, dirs = pixel_rays(K_t, pose_t, w, h)  # (H, W, 3)
        r_t, c_t = torch.from_numpy(rows), torch.from_numpy(cols)
        uv = torch.stack([c_t + 0.5, r_t + 0.5], dim=-1).float()  # (R, 2)
        if scene.has_ov:
            ov_map = torch.from_numpy(scene.ov[target]).permute(2, 0, 1).float()  # (D, h, w)
            target_ov, _ = sample_bilinear(ov_map, scale_uv(uv, (w, h), (ov_map.shape[-1], ov_map.shape[-2])))
        else:  # no OV supervision (masked in training)
            target_ov = torch.zeros(len(pix), scene.ov_dim)
        target_rgb = torch.from_numpy(scene.rgb[target][rows, cols]).float() / 255.0
        ray_dirs = dirs[r_t, c_t]
        z = torch.from_numpy(scene.depth_m[target][rows, cols]).float()
        target_t = ray_distance(z, ray_dirs, pose_t[:3, 2])
        sample = TrainSample(
            sources=sources,
            origins=origins[r_t, c_t],
            directions=ray_dirs,
            target_rgb=target_rgb,
            target_ov=target_ov,
            scene=scene.name,
            target=target,
            seed=int(rng.integers(2**62)),
            target_t=target_t,
            has_ov=scene.has_ov,
            blend_sources=blend_sources,
        )
        if self.point_ov_target == "visible_mean" and scene.has_ov:  # no draw: the stream is unchanged
            keep = target_t > 0
            mean = target_ov.clone()
            if bool(keep.any()):
                pts = surface_points(sample.origins[keep], sample.directions[keep], target_t[keep])
                got, n_views = visible_mean_features(scene, pts, rel_tol=self.point_ov_rel_tol)
                sub = mean[keep]
                sub[n_views > 0] = got[n_views > 0]
                mean[keep] = sub
            sample.target_ov_point = mean
        # Drawn after everything else, so that examples without it are unchanged.
        if self.photometric_prob > 0 and bool(rng.random() < self.photometric_prob):
            src_rgb, tgt_rgb = photometric_jitter(sources.rgb, target_rgb, self.photometric_strength, rng)
            sample.sources.rgb, sample.target_rgb = src_rgb, tgt_rgb
        if self.sensor_prob > 0 or self.pose_noise_prob > 0:  # its own stream: the rest is unchanged
            self._degrade(sample, np.random.default_rng(np.random.SeedSequence([self.seed, step, item,
                                                                                _SENSOR_STREAM])))
        if self.ov_noise_prob > 0 and sample.has_ov:  # its own stream: the rest is unchanged
            rng_ov = np.random.default_rng(np.random.SeedSequence([self.seed, step, item, _OV_NOISE_STREAM]))
            if rng_ov.random() < self.ov_noise_prob:
                from mapper.training.augment import ov_noise

                sample.sources.ov = ov_noise(sample.sources.ov, rng_ov, self.ov_noise_strength)
        if self.world_scale_prob > 0:  # its own stream: the rest is unchanged
            rng_s = np.random.default_rng(np.random.SeedSequence([self.seed, step, item, _SCALE_STREAM]))
            if rng_s.random() < self.world_scale_prob:
                factor = float(np.exp(rng_s.uniform(-1.0, 1.0) * np.log(self.world_scale_max)))
                scale_world(sample, scene, self.cfg, factor, range_m)
        return sample

    def _degrade(self, sample: TrainSample, rng: np.random.Generator) -> None:
        """Sensor effects on the sources' colour and rigid error on their poses (as drawn)."""
        from mapper.training.augment import perturb_poses, sensor_effects

        sensor, pose = rng.random(2)
        if sensor < self.sensor_prob:
            sample.sources.rgb = sensor_effects(sample.sources.rgb, rng, self.sensor_strength)
        if pose < self.pose_noise_prob:
            scale = float(rng.random())
            sample.sources.world_from_cam = perturb_poses(
                sample.sources.world_from_cam, rng, scale * self.pose_noise_m, scale * self.pose_noise_deg)


def scale_world(
    sample: TrainSample, scene: Scene, cfg: ModelConfig, factor: float, frustum_range_m: float | None
) -> None:
    """``sample`` in its scene's world scaled by ``factor`` about the origin, in place: the sources'
    camera centres and depths, the target rays' origins and surface distances, and the volume
    bounds as :func:`source_batch` makes them there (frusta keep their range in metres, as the
    node's ``model.max_range_m``). Images, OV maps and ray directions are unchanged."""
    f = np.float32(factor)
    sources = sample.sources
    poses = sources.world_from_cam.clone()
    poses[:, :3, 3] *= f
    sources.world_from_cam = poses
    sources.depth_m = sources.depth_m * f
    sample.origins = sample.origins * f
    if sample.target_t is not None:
        sample.target_t = sample.target_t * f
    sources.bounds = source_bounds(scene, sources.indices, cfg, frustum_range_m=frustum_range_m,
                                   world_scale=factor)


POINT_OV_TARGETS = ("frame", "visible_mean")
"""``RaySampler.point_ov_target`` / ``TrainConfig.point_ov_target`` values."""


def visible_mean_features(
    scene: Scene,
    points: Tensor,  # (P, 3) world points (m)
    *,
    rel_tol: float = 0.05,
    chunk_frames: int = 32,
) -> tuple[Tensor, Tensor]:  # (P, D) float32 unit rows (zero where no frame sees it), (P,) int64
    """The mean of the unit OV features of every frame of ``scene`` that sees each point, its
    direction: a target for the point-level OV loss that is the consensus of the views that see the
    point instead of one frame's own (view-dependent) 2D prediction. A frame sees a point when it
    projects inside the image, in front of it, and the frame's depth agrees
    (:func:`mapper.model.supervision.visibility_targets`, ``rel_tol``); features are sampled
    bilinearly from the frames' OV maps. Also the number of frames that see each point."""
    pts = points.detach().float().cpu()
    if pts.ndim != 2 or pts.shape[-1] != 3:
        raise ValueError(f"points must have shape (P, 3), got {tuple(pts.shape)}")
    if not scene.has_ov:
        raise ValueError(f"scene {scene.name} has no ov maps")
    w, h = scene.image_wh
    total = torch.zeros(pts.shape[0], scene.ov_dim)
    count = torch.zeros(pts.shape[0], dtype=torch.int64)
    for start in range(0, scene.num_frames, chunk_frames):
        idx = np.arange(start, min(start + chunk_frames, scene.num_frames))
        K = torch.from_numpy(scene.K[idx]).float()
        poses = torch.from_numpy(scene.world_from_cam[idx]).float()
        depth = torch.from_numpy(scene.depth_m[idx]).float()
        visible, _ = visibility_targets(pts, K, poses, depth, (w, h), rel_tol=rel_tol)  # (P, n)
        uv, _ = project_points(pts.unsqueeze(0), K, invert_pose(poses))  # (n, P, 2)
        for j, f in enumerate(idx):
            sees = visible[:, j]
            if not bool(sees.any()):
                continue
            ov_map = torch.from_numpy(scene.ov[f]).permute(2, 0, 1).float()  # (D, h, w)
            map_wh = (ov_map.shape[-1], ov_map.shape[-2])
            feat, _ = sample_bilinear(ov_map, scale_uv(uv[j, sees], (w, h), map_wh))
            total[sees] += torch.nn.functional.normalize(feat, dim=-1)
            count[sees] += 1
    return torch.nn.functional.normalize(total, dim=-1), count


def photometric_jitter(
    source_rgb: Tensor, target_rgb: Tensor, strength: float, rng: np.random.Generator
) -> tuple[Tensor, Tensor]:
    """A camera's colour response, drawn once per example: gamma, per-channel gain (white balance)
    and offset shared by the sources and the target (what a real camera does to the whole
    sequence), plus a small per-source exposure gain (auto-exposure between frames).

    Args:
        source_rgb: (N, 3, H, W) in [0, 1]; target_rgb: (R, 3) in [0, 1]; strength in [0, 1).

    Returns:
        The jittered copies, clamped to [0, 1].

    >>> src, tgt = torch.full((2, 3, 1, 1), 0.5), torch.full((4, 3), 0.5)
    >>> a, b = photometric_jitter(src, tgt, 0.0, np.random.default_rng(0))
    >>> bool(torch.equal(a, src) and torch.equal(b, tgt))
    True
    """
    s = float(strength)
    gamma = float(np.exp(rng.uniform(-s, s)))
    gain = torch.from_numpy(1.0 + rng.uniform(-s, s, size=3)).float()  # (3,)
    offset = float(rng.uniform(-0.25 * s, 0.25 * s))
    per_view = torch.from_numpy(1.0 + rng.uniform(-0.25 * s, 0.25 * s, size=len(source_rgb))).float()

    def respond(rgb: Tensor, channel_dim: int) -> Tensor:
        shape = [1] * rgb.ndim
        shape[channel_dim] = 3
        return (rgb.clamp(0, 1) ** gamma * gain.reshape(shape) + offset).clamp(0, 1)

    src = (respond(source_rgb, 1) * per_view.reshape(-1, 1, 1, 1)).clamp(0, 1)
    return src, respond(target_rgb, -1)


@dataclass
class ValidationView:
    """A held-out novel view to render, with its sources and ground truth."""

    scene: Scene
    index: int
    K: Tensor  # (4,)
    world_from_cam: Tensor  # (4, 4)
    rgb: np.ndarray  # (H, W, 3) uint8
    label: np.ndarray  # (H, W) int32
    source_indices: np.ndarray  # (N,)


def validation_views(
    scenes: list[Scene], num_sources: int, *, views_per_scene: int | None = None
) -> list[ValidationView]:
    """Novel views of validation scenes with their N best-overlapping stream frames as sources.

    ``views_per_scene`` keeps that many evenly spaced novel views per scene (all when None).
    """
    out: list[ValidationView] = []
    for scene in scenes:
        if scene.novel is None:
            raise ValueError(f"scene {scene.name} was loaded without novel views (with_novel_views=True)")
        n_views = scene.novel.K.shape[0]
        keep = range(n_views)
        if views_per_scene is not None and views_per_scene < n_views:
            keep = np.linspace(0, n_views - 1, views_per_scene).round().astype(int).tolist()
        for v in keep:
            K, pose = scene.novel.K[v], scene.novel.world_from_cam[v]
            out.append(
                ValidationView(
                    scene=scene,
                    index=int(v),
                    K=torch.from_numpy(K).float(),
                    world_from_cam=torch.from_numpy(pose).float(),
                    rgb=scene.novel.rgb[v],
                    label=scene.novel.label[v],
                    source_indices=select_sources(scene, K, pose, num_sources),
                )
            )
    return out
