"""Record the simulated robot: a `.govrec` stream plus ground truth for evaluation.

Layout written by `record(config, out_dir)` (see docs/how-to/simulator.md)::

    DIR/frames.govrec          frames: rgb, optional depth, optional SimLSeg `ov` (minilm-l6-v2)
    DIR/scene.ply              the mesh, each face coloured by its label (palette in gt/)
    DIR/preview/               a few frames (rgb | label | depth) and a top-down map with the path
    DIR/gt/class_names.json    label id -> class name (ScanNet-20 first)
    DIR/gt/scene.json          seed, style, room bounds, light, instances (class, aabb, centroid);
                               on a floor, "floor": rooms (box, doorway, instance ids), corridors, visits
    DIR/gt/mesh.npz            vertices (V,3) f32, triangles (F,3) i32, face_label, face_instance
    DIR/gt/points.npz          surface samples: xyz (P,3) f32, label (P,) i32, instance (P,) i32,
                               n_views (P,) i32 = stream frames that see the point
    DIR/gt/stream.npz          per stream frame: K (F,4), world_from_cam (F,4,4), depth_m, label,
                               instance (F,H,W) (always, even when the recording has no depth),
                               room (F,) (a floor's room holding the camera, -1 in corridors; 0 in a room)
    DIR/gt/novel_views.npz     held-out views near the path, NOT in the stream: K, world_from_cam,
                               rgb, depth_m, label, instance, stream_index (nearest stream frame)

Every `.npz` is written without pickled objects (`np.load(..., allow_pickle=False)` reads it).
Surface samples leave out the ceiling (scanned meshes such as ScanNet's rarely have one, and it
is outside the ScanNet-20 set); everything else, wall and floor included, is sampled.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from clients.sim.floor_render import FloorRenderer
from clients.sim.paths import PATH_KINDS, camera_path
from clients.sim.raycast import RenderedView, SceneRenderer
from clients.sim.robot import default_intrinsics, obstacle_distance_field, robot_trajectory
from clients.sim.scenes import CLASS_NAMES, LABEL_OF, SCANNET20, STYLES, Scene, generate_scene
from clients.sim.scenes.floor import FLOOR_ROOMS, Floor, generate_floor
from clients.sim.tour import Tour, floor_tour
from govnesf._extras import require
from protocol.messages import Frame

OV_SPACE = "minilm-l6-v2"
RECORDING_NAME = "frames.govrec"
RGB_ENCODINGS = ("rgb8", "png", "jpeg")
FLOOR_PATH = "floor_tour"
MAX_GT_STREAM_BYTES = 2 * 2**30
"""`record` keeps the per-frame ground truth (depth, label, instance) in memory until the end."""


@dataclass(frozen=True)
class RecordConfig:
    """What to simulate and record."""

    seed: int
    """Scene seed (the room); >= 0."""
    style: str = "apartment"
    """Scene style, a key of `clients.sim.scenes.STYLES`."""
    frames: int = 300
    """Number of stream frames, 1..100000."""
    width: int = 160
    """Image width, pixels, 1..4096."""
    height: int = 120
    """Image height, pixels, 1..4096."""
    hfov_deg: float = 70.0
    """Horizontal field of view, degrees."""
    depth: bool = False
    """Put the rendered z-depth into the recorded frames."""
    ov: bool = True
    """Put SimLSeg open-vocabulary features (minilm-l6-v2) into the recorded frames."""
    trajectory_seed: int | None = None
    """Seed of the robot's path (start, direction, gaze); defaults to `seed`."""
    max_step_m: float = 0.08
    """Largest horizontal camera move between frames (the robot covers min(loop, frames x step))."""
    fps: float = 10.0
    """Nominal frame rate: frame k is stamped k / fps seconds after the first."""
    rgb_encoding: str = "rgb8"
    """Colour encoding in the recording: rgb8, png or jpeg."""
    novel_views: int = 8
    """Held-out views to render into gt/ (0 for none)."""
    points_per_m2: float = 500.0
    """Density of the ground-truth surface samples, points per square metre."""
    previews: int = 4
    """Number of preview frames written as PNG."""
    ov_stride: int | None = None
    """SimLSeg output stride (features are ceil(H / s) x ceil(W / s)); None: SimLSeg's default."""
    floor_rooms: int = 0
    """0: one room (`style`'s layout); 2..30: a floor of that many `style` rooms joined by corridors
    (`clients.sim.scenes.floor`), toured by `path` floor_tour."""
    path: str | None = None
    """Camera path: a room's `clients.sim.paths.PATH_KINDS` (None: loop, with `max_step_m`), or
    floor_tour for a floor (None on a floor: floor_tour)."""
    revisit_rooms: int = 2
    """floor_tour: how many of the first rooms the tour goes back to at its end."""

    @property
    def path_kind(self) -> str:
        """The camera path this config makes."""
        return self.path or ("floor_tour" if self.floor_rooms else "loop")

    def validate(self) -> None:
        """Raise ValueError naming the first bad field, its value and the allowed range."""
        checks = [
            (isinstance(self.seed, int) and self.seed >= 0, f"seed {self.seed!r} must be an int >= 0"),
            (self.style in STYLES, f"style {self.style!r} unknown; choose one of {sorted(STYLES)}"),
            (1 <= self.frames <= 100_000, f"frames {self.frames} out of range 1..100000"),
            (1 <= self.width <= 4096, f"width {self.width} out of range 1..4096"),
            (1 <= self.height <= 4096, f"height {self.height} out of range 1..4096"),
            (10.0 <= self.hfov_deg <= 150.0, f"hfov_deg {self.hfov_deg} out of range 10..150"),
            (self.fps > 0 and math.isfinite(self.fps), f"fps {self.fps} must be > 0"),
            (0.0 < self.max_step_m <= 1.0, f"max_step_m {self.max_step_m} out of range (0, 1]"),
            (self.rgb_encoding in RGB_ENCODINGS,
             f"rgb_encoding {self.rgb_encoding!r} unknown; choose one of {list(RGB_ENCODINGS)}"),
            (0 <= self.novel_views <= 1000, f"novel_views {self.novel_views} out of range 0..1000"),
            (0 < self.points_per_m2 <= 100_000,
             f"points_per_m2 {self.points_per_m2} out of range (0, 100000]"),
            (self.ov_stride is None or 1 <= self.ov_stride <= 64,
             f"ov_stride {self.ov_stride} out of range 1..64"),
            (0 <= self.previews <= 100, f"previews {self.previews} out of range 0..100"),
            (self.floor_rooms == 0 or FLOOR_ROOMS[0] <= self.floor_rooms <= FLOOR_ROOMS[1],
             f"floor_rooms {self.floor_rooms} out of range {FLOOR_ROOMS[0]}..{FLOOR_ROOMS[1]} (0: one room)"),
            (self.path_kind in ((FLOOR_PATH,) if self.floor_rooms else PATH_KINDS),
             f"path {self.path!r} unknown for a {'floor' if self.floor_rooms else 'room'}; choose one of "
             f"{[FLOOR_PATH] if self.floor_rooms else sorted(PATH_KINDS)}"),
            (self.revisit_rooms >= 0 and (not self.floor_rooms or self.revisit_rooms <= self.floor_rooms),
             f"revisit_rooms {self.revisit_rooms} out of range 0..{self.floor_rooms or 'floor_rooms'}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(message)


@dataclass
class SimStream:
    """A scene, its renderer, the robot's poses and (optionally) SimLSeg."""

    config: RecordConfig
    scene: Scene
    renderer: SceneRenderer | FloorRenderer
    K: np.ndarray                # (4,) float64
    poses: np.ndarray            # (F, 4, 4) float64 world_from_cam
    simlseg: Any | None          # clients.sim.simlseg.SimLSeg when config.ov
    floor: Floor | None = None   # the floor, when config.floor_rooms
    tour: Tour | None = None     # its tour (the room of each frame)

    @classmethod
    def build(cls, config: RecordConfig) -> SimStream:
        config.validate()
        tseed = config.seed if config.trajectory_seed is None else config.trajectory_seed
        floor, tour = None, None
        renderer: SceneRenderer | FloorRenderer
        if config.floor_rooms:
            floor = generate_floor(config.seed, config.floor_rooms, config.style)
            tour = floor_tour(floor, config.frames, seed=tseed, revisit_rooms=config.revisit_rooms,
                              max_step_m=config.max_step_m)
            scene, poses, renderer = floor.scene, tour.poses, FloorRenderer(floor)
        else:
            scene = generate_scene(config.seed, config.style)
            if config.path_kind == "loop":
                poses = robot_trajectory(scene, config.frames, seed=tseed, max_step_m=config.max_step_m)
            else:
                poses = camera_path(scene, config.path_kind, config.frames, seed=tseed)
            renderer = SceneRenderer(scene)
        simlseg = None
        if config.ov:
            # lazy: pulls torch and the text encoder
            from clients.sim.simlseg import SimLSeg, SimLSegConfig
            from clients.sim.text import get_text_encoder

            sl_cfg = SimLSegConfig() if config.ov_stride is None else SimLSegConfig(stride=config.ov_stride)
            simlseg = SimLSeg(CLASS_NAMES, get_text_encoder(), seed=config.seed, config=sl_cfg)
        return cls(config, scene, renderer, default_intrinsics(config.width, config.height, config.hfov_deg),
                   poses, simlseg, floor, tour)

    def render(self, index: int) -> RenderedView:
        return self.renderer.render(self.K, self.poses[index], self.config.width, self.config.height)

    def frame(self, index: int, view: RenderedView) -> Frame:
        """The wire frame for stream frame `index` rendered as `view`."""
        cfg = self.config
        ov = None
        if self.simlseg is not None:
            ov = self.simlseg.features(view, frame_index=index, K=self.K)
        return Frame(
            seq=index, stamp_ns=int(round(index * 1e9 / cfg.fps)), width=cfg.width, height=cfg.height,
            K=self.K.copy(), world_from_cam=self.poses[index].copy(), rgb=view.rgb,
            depth_m=view.depth_m if cfg.depth else None, ov=ov, ov_space=OV_SPACE if ov is not None else None,
            rgb_encoding=cfg.rgb_encoding)

    def frames(self) -> Iterator[tuple[Frame, RenderedView]]:
        """Render and yield every stream frame in order (lazily)."""
        for k in range(self.config.frames):
            view = self.render(k)
            yield self.frame(k, view), view


def label_palette(n: int = len(CLASS_NAMES)) -> np.ndarray:
    """(n, 3) uint8 distinct colours per label id (golden-ratio hues, varied value)."""
    import colorsys

    out = np.zeros((n, 3), np.uint8)
    for i in range(n):
        h = (i * 0.61803398875) % 1.0
        s = 0.55 + 0.35 * ((i * 7) % 3) / 2
        v = 0.95 - 0.3 * ((i * 5) % 4) / 3
        out[i] = np.round(np.asarray(colorsys.hsv_to_rgb(h, s, v)) * 255)
    return out


def colourise_labels(label: np.ndarray) -> np.ndarray:
    """(H, W) int label image -> (H, W, 3) uint8 (black where -1)."""
    pal = np.concatenate([label_palette(), np.zeros((1, 3), np.uint8)])
    return pal[np.where(label >= 0, label, len(pal) - 1)]


def colourise_depth(depth_m: np.ndarray, max_m: float = 8.0) -> np.ndarray:
    """(H, W) metres -> (H, W, 3) uint8 grey, near bright, 0 (no hit) black."""
    g = np.where(depth_m > 0, 255.0 * (1.0 - np.clip(depth_m / max_m, 0.0, 1.0)) * 0.85 + 38, 0.0)
    return np.repeat(g[..., None], 3, axis=2).astype(np.uint8)


def count_views(xyz: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, depth_m: np.ndarray,
                counts: np.ndarray, tol_m: float = 0.02, tol_rel: float = 0.02) -> None:
    """Add 1 to `counts` (P,) for the points xyz (P, 3) that one view (depth_m (H, W)) sees.

    A point is seen when it projects inside the image in front of the camera and its z-depth
    is within max(tol_m, tol_rel * depth) of the rendered depth at its pixel.
    """
    h, w = depth_m.shape
    R = world_from_cam[:3, :3]
    t = world_from_cam[:3, 3]
    # (P, 3) camera coordinates; einsum, not `@`: BLAS is slow for an inner size of 3 on big arrays
    cam = np.einsum("pk,kj->pj", xyz.astype(np.float32, copy=False), R.astype(np.float32))
    cam -= (t @ R).astype(np.float32)
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.float32(K[0]) * cam[:, 0] / z + np.float32(K[2])
        v = np.float32(K[1]) * cam[:, 1] / z + np.float32(K[3])
    inside = (z > 1e-3) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    idx = np.flatnonzero(inside)
    zi = z[idx]
    d = depth_m[v[idx].astype(np.int64), u[idx].astype(np.int64)]
    seen = (d > 0) & (np.abs(d - zi) <= np.maximum(tol_m, tol_rel * d))
    counts[idx[seen]] += 1


def novel_view_poses(
    stream: SimStream, n: int, seed: int, clearance_m: float = 0.3
) -> tuple[np.ndarray, np.ndarray]:
    """Held-out poses near the path: (n, 4, 4) world_from_cam and (n,) nearest stream index.

    Each starts at an evenly spaced stream pose, moves up to 0.2 m sideways/forward and +-0.1 m
    in height (kept `clearance_m` from obstacles), and turns by up to +-12 deg yaw, +-6 deg pitch.
    """
    rng = np.random.default_rng([seed, 99])
    f = len(stream.poses)
    idx = np.clip(((np.arange(n) + 0.5) * f / max(n, 1)).astype(np.int64), 0, f - 1)
    dist, origin = obstacle_distance_field(stream.scene)
    out = np.empty((n, 4, 4))
    for k, i in enumerate(idx):
        pose = stream.poses[i].copy()
        for _ in range(20):
            off = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(-0.1, 0.1)])
            c = pose[:3, 3] + off
            g = np.floor((c[:2] - origin) / 0.05).astype(int)
            if (0 <= g).all() and g[0] < dist.shape[0] and g[1] < dist.shape[1] and \
                    dist[g[0], g[1]] >= clearance_m + 0.05:
                pose[:3, 3] = c
                break
        yaw, pitch = np.radians(rng.uniform(-12, 12)), np.radians(rng.uniform(-6, 6))
        cz, sz = math.cos(yaw), math.sin(yaw)
        rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1.0]])
        cp, sp = math.cos(pitch), math.sin(pitch)
        rx = np.array([[1.0, 0, 0], [0, cp, -sp], [0, sp, cp]])    # about the camera x axis
        pose[:3, :3] = rz @ pose[:3, :3] @ rx
        out[k] = pose
    return out, idx


def _top_down(stream: SimStream, px_per_m: float = 40.0) -> np.ndarray:
    """(H, W, 3) uint8 top-down label map (highest surface under the ceiling) with the path."""
    scene = stream.scene
    lo, hi = scene.room_min, scene.room_max
    nx, ny = int((hi[0] - lo[0]) * px_per_m), int((hi[1] - lo[1]) * px_per_m)
    xs = lo[0] + (np.arange(nx) + 0.5) / px_per_m
    ys = lo[1] + (np.arange(ny) + 0.5) / px_per_m
    gx, gy = np.meshgrid(xs, ys)                                  # image row = y
    origins = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, hi[2] - 0.01)], 1)
    dirs = np.tile([0.0, 0.0, -1.0], (gx.size, 1))
    _, face = stream.renderer.cast(origins, dirs)
    label = np.where(face >= 0, scene.face_label[np.maximum(face, 0)], -1).reshape(ny, nx)
    img = colourise_labels(label)
    img = (0.6 * img).astype(np.uint8)
    for k, pose in enumerate(stream.poses):
        c = pose[:3, 3]
        i, j = int((c[0] - lo[0]) * px_per_m), int((c[1] - lo[1]) * px_per_m)
        if 0 <= i < nx and 0 <= j < ny:
            img[max(j - 1, 0):j + 2, max(i - 1, 0):i + 2] = (255, 255, 255) if k else (255, 0, 0)
    return img[::-1].copy()  # +y up in the picture


def _save_png(path: Path, image: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(image).save(path)


def write_ply(path: Path, scene: Scene) -> None:
    """The mesh as PLY with per-vertex colours from the label palette (vertices unshared)."""
    trimesh = require("trimesh", "sim", "the simulator's mesh export (trimesh)")

    v = scene.vertices[scene.triangles].reshape(-1, 3)
    faces = np.arange(len(v), dtype=np.int64).reshape(-1, 3)
    colours = np.repeat(label_palette()[scene.face_label], 3, axis=0)
    rgba = np.concatenate([colours, np.full((len(colours), 1), 255, np.uint8)], axis=1)
    trimesh.Trimesh(vertices=v, faces=faces, vertex_colors=rgba, process=False).export(path)


def scene_json(stream: SimStream) -> dict[str, Any]:
    scene, cfg = stream.scene, stream.config
    return {
        "generator": "govnesf-sim",
        "config": asdict(cfg),
        "seed": scene.seed, "style": scene.style,
        "room_min": scene.room_min.tolist(), "room_max": scene.room_max.tolist(),
        "light": {"position": scene.light.position.tolist(), "colour": scene.light.colour.tolist(),
                  "diffuse": scene.light.diffuse, "ambient": scene.light.ambient,
                  "falloff_m": scene.light.falloff_m},
        "structures": [[lo.tolist(), hi.tolist()] for lo, hi in scene.structures],
        "instances": [{"id": i.instance_id, "class_name": i.class_name, "label": i.label,
                       "aabb_min": i.aabb_min.tolist(), "aabb_max": i.aabb_max.tolist(),
                       "centroid": i.centroid.tolist(), "support_id": i.support_id}
                      for i in scene.instances],
        "K": stream.K.tolist(), "width": cfg.width, "height": cfg.height,
        "floor": None if stream.floor is None else floor_json(stream.floor, stream.tour),
    }


def floor_json(floor: Floor, tour: Tour | None) -> dict[str, Any]:
    """A floor's plan: rooms (interior box, doorway, band), corridors, spine, the tour's visits."""
    return {
        "rooms": [{"index": r.index, "band": r.band, "lo": r.lo.tolist(), "hi": r.hi.tolist(),
                   "door_xy": r.door_xy.tolist(), "door_width_m": r.doorway.width_m,
                   "instances": [i.instance_id for i in floor.scene.instances
                                 if (i.centroid[:2] >= r.lo).all() and (i.centroid[:2] <= r.hi).all()]}
                  for r in floor.rooms],
        "corridors": [c.tolist() for c in floor.corridors], "spine": floor.spine.tolist(),
        "visits": None if tour is None else tour.visits,
        "loop_share": None if tour is None else tour.loop_share,
        "step_m": None if tour is None else tour.step_m,
    }


@dataclass
class RecordSummary:
    out_dir: Path
    frames: int
    seconds: float
    seconds_render: float
    seconds_ov: float
    gt_points: int
    recording_bytes: int


def record(config: RecordConfig, out_dir: str | Path, *, progress: bool = True) -> RecordSummary:
    """Simulate, record and export ground truth into `out_dir` (created; must be empty or new)."""
    from tqdm import tqdm

    from protocol.recording import RecordingWriter

    config.validate()
    gt_bytes = config.frames * config.width * config.height * 8  # depth f32 + label i16 + instance i16
    if gt_bytes > MAX_GT_STREAM_BYTES:
        raise ValueError(
            f"frames x width x height = {config.frames} x {config.width} x {config.height} needs "
            f"{gt_bytes / 2**30:.1f} GiB of ground-truth images (gt/stream.npz); the limit is "
            f"{MAX_GT_STREAM_BYTES / 2**30:.0f} GiB: record fewer or smaller frames (or several runs)")
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"output folder {str(out)!r} exists and is not empty; choose a new one")
    t0 = time.perf_counter()
    stream = SimStream.build(config)
    scene, cfg = stream.scene, config
    out.mkdir(parents=True, exist_ok=True)
    (out / "gt").mkdir()
    (out / "preview").mkdir()

    n_pts = max(1, int(round(cfg.points_per_m2 * float(scene.face_areas()[
        scene.face_label != LABEL_OF["ceiling"]].sum()))))
    xyz, plabel, pinst = scene.sample_surface(n_pts, seed=cfg.seed, exclude_labels=(LABEL_OF["ceiling"],))
    n_views = np.zeros(n_pts, np.int32)

    f, h, w = cfg.frames, cfg.height, cfg.width
    gt_depth = np.zeros((f, h, w), np.float32)
    gt_label = np.zeros((f, h, w), np.int16)
    gt_inst = np.zeros((f, h, w), np.int16)
    preview_at = set(np.linspace(0, f - 1, cfg.previews).astype(int).tolist()) if cfg.previews else set()
    meta = {"generator": "govnesf-sim", "seed": cfg.seed, "style": cfg.style, "frames": f,
            "floor_rooms": cfg.floor_rooms, "path": cfg.path_kind,
            "width": w, "height": h, "hfov_deg": cfg.hfov_deg, "depth": cfg.depth,
            "ov_space": OV_SPACE if cfg.ov else "", "class_names": list(CLASS_NAMES)}
    t_render = t_ov = 0.0
    with RecordingWriter(out / RECORDING_NAME, meta) as writer:
        what = f"{cfg.style}/{cfg.seed}" + (f" floor of {cfg.floor_rooms}" if cfg.floor_rooms else "")
        bar = tqdm(range(f), desc=f"sim record {what}", unit="frame", disable=not progress)
        for k in bar:
            ta = time.perf_counter()
            view = stream.render(k)
            tb = time.perf_counter()
            frame = stream.frame(k, view)
            tc = time.perf_counter()
            t_render += tb - ta
            t_ov += tc - tb
            writer.write(frame)
            gt_depth[k], gt_label[k], gt_inst[k] = view.depth_m, view.label, view.instance
            count_views(xyz, stream.K, stream.poses[k], view.depth_m, n_views)
            if k in preview_at:
                strip = np.concatenate(
                    [view.rgb, colourise_labels(view.label), colourise_depth(view.depth_m)], 1)
                _save_png(out / "preview" / f"frame_{k:05d}.png", strip)

    np.savez_compressed(out / "gt" / "points.npz", xyz=xyz, label=plabel, instance=pinst, n_views=n_views)
    room = stream.tour.room if stream.tour is not None else np.zeros(f, np.int32)
    np.savez_compressed(out / "gt" / "stream.npz", K=np.tile(stream.K, (f, 1)), world_from_cam=stream.poses,
                        depth_m=gt_depth, label=gt_label, instance=gt_inst, room=room.astype(np.int32))
    np.savez_compressed(out / "gt" / "mesh.npz", vertices=scene.vertices, triangles=scene.triangles,
                        face_label=scene.face_label, face_instance=scene.face_instance)
    if cfg.novel_views:
        poses, idx = novel_view_poses(stream, cfg.novel_views, cfg.seed)
        views = [stream.renderer.render(stream.K, p, w, h) for p in poses]
        np.savez_compressed(
            out / "gt" / "novel_views.npz", K=np.tile(stream.K, (len(poses), 1)), world_from_cam=poses,
            rgb=np.stack([v.rgb for v in views]), depth_m=np.stack([v.depth_m for v in views]),
            label=np.stack([v.label for v in views]), instance=np.stack([v.instance for v in views]),
            stream_index=idx.astype(np.int32))
    (out / "gt" / "class_names.json").write_text(json.dumps(list(CLASS_NAMES), indent=1) + "\n")
    info = scene_json(stream)
    info["scannet20"] = list(SCANNET20)
    info["palette"] = label_palette().tolist()
    (out / "gt" / "scene.json").write_text(json.dumps(info, indent=1) + "\n")
    write_ply(out / "scene.ply", scene)
    _save_png(out / "preview" / "top_down.png", _top_down(stream))
    return RecordSummary(out, f, time.perf_counter() - t0, t_render, t_ov, n_pts,
                         (out / RECORDING_NAME).stat().st_size)
