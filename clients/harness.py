"""The harness the end-to-end tests (``tests/e2e``, ``tests/clients/test_rerun_log.py``) and the
benchmarks (``benchmarks/speed/ingest_rate.py``, ``semantic_map.py``, ``rendered_depth_points.py``) share
with the demo (``clients/demo.py``): inputs to stream into a node, a node to stream them into, and
the ground truth to score its answers against.

* Synthetic frames: :func:`synthetic_frame` / :func:`synthetic_frames` (a camera circling a
  checkerboard floor, with tiny ``demo-checker`` OV features) and :func:`write_synthetic_recording`
  (the same frames as a ``.govrec`` file).
* A real node: :func:`free_endpoints` (free loopback ports) and :class:`NodeProcess` (``govnesf
  serve`` in a subprocess, killed on exit).
* The simulated robot and its ground truth: :func:`sim_stream` (a ``clients.sim`` room and the
  robot's frames), :func:`chair_distance`, :func:`mean_iou` and :func:`label_by_nearest`.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from clients.client import MapperClient
from protocol.messages import Frame
from protocol.recording import RecordingWriter

REPO_ROOT = Path(__file__).resolve().parent.parent

# ---------------------------------------------------------------------------------------------
# synthetic frames: a camera circling a checkerboard floor (z = 0), looking at the origin

CHECKER_SIZE_M = 0.5
DEMO_OV_SPACE = "demo-checker"
DEMO_OV_DIM = 8


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) world_from_cam for an OpenCV camera at ``eye`` (3,) looking at ``target`` (3,),
    world +z up (x right, y down, z forward in the camera)."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    world_from_cam = np.eye(4)
    world_from_cam[:3, 0], world_from_cam[:3, 1], world_from_cam[:3, 2] = right, down, forward
    world_from_cam[:3, 3] = eye
    return world_from_cam


def render_floor(
    width: int, height: int, K: np.ndarray, world_from_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast the checkerboard floor. Returns rgb (H, W, 3) uint8, depth_m (H, W) float32
    (0 where a ray misses the floor) and the floor cell parity (H, W) int (-1 = sky)."""
    fx, fy, cx, cy = K
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)  # pixel centres
    dirs_cam = np.stack([(cols - cx) / fx, (rows - cy) / fy, np.ones_like(cols)], axis=-1)  # (H, W, 3)
    dirs_world = dirs_cam @ world_from_cam[:3, :3].T
    eye = world_from_cam[:3, 3]
    dz = dirs_world[..., 2]
    hits = dz < -1e-6
    t = np.where(hits, -eye[2] / np.where(hits, dz, -1.0), 0.0)  # = depth along +z (dirs_cam z = 1)
    points = eye + t[..., None] * dirs_world
    cell = np.floor(points[..., :2] / CHECKER_SIZE_M).astype(np.int64)
    parity = np.where(hits, (cell[..., 0] + cell[..., 1]) % 2, -1)
    quadrant = (points[..., 0] > 0).astype(np.int64) + 2 * (points[..., 1] > 0)
    palette = np.array([[200, 60, 60], [60, 160, 60], [60, 90, 200], [210, 180, 60]], np.float64)
    base = palette[quadrant] * np.where(parity == 1, 1.0, 0.45)[..., None]
    shade = np.clip(1.0 - 0.04 * t, 0.4, 1.0)[..., None]  # darker with distance
    sky = np.array([150.0, 190.0, 235.0]) * (0.7 + 0.3 * (rows / height))[..., None]
    rgb = np.where(hits[..., None], base * shade, sky)
    depth_m = np.where(hits, t, 0.0).astype(np.float32)
    return np.clip(rgb, 0, 255).astype(np.uint8), depth_m, parity


def synthetic_frame(
    seq: int,
    n_frames: int = 60,
    width: int = 160,
    height: int = 120,
    *,
    with_ov: bool = True,
    rgb_encoding: str = "rgb8",
) -> Frame:
    """Frame ``seq`` of a camera path once around the origin (radius 3 m, 1.5 m high), moving
    slowly near the start and end of the loop and fast in the middle."""
    phase = seq / max(n_frames, 1)
    angle = 2.0 * math.pi * (phase - math.sin(2.0 * math.pi * phase) / (2.0 * math.pi))
    eye = np.array([3.0 * math.cos(angle), 3.0 * math.sin(angle), 1.5])
    world_from_cam = look_at(eye, np.array([0.0, 0.0, 0.3]))
    K = np.array([0.9 * width, 0.9 * width, width / 2.0, height / 2.0])
    rgb, depth_m, parity = render_floor(width, height, K, world_from_cam)
    ov = ov_space = None
    if with_ov:
        # A tiny stand-in for an OV feature map at 1/8 resolution: one-hot of (sky, dark, light).
        small = parity[4::8, 4::8]
        ov = np.zeros((*small.shape, DEMO_OV_DIM), np.float16)
        ov[..., 0] = small == -1
        ov[..., 1] = small == 0
        ov[..., 2] = small == 1
        ov_space = DEMO_OV_SPACE
    return Frame(
        seq=seq,
        stamp_ns=1_000_000_000 + seq * 100_000_000,  # 10 Hz
        width=width,
        height=height,
        K=K,
        world_from_cam=world_from_cam,
        rgb=rgb,
        depth_m=depth_m,
        ov=ov,
        ov_space=ov_space,
        rgb_encoding=rgb_encoding,
    )


def synthetic_frames(
    n_frames: int = 60, width: int = 160, height: int = 120, **kwargs: object
) -> Iterator[Frame]:
    for seq in range(n_frames):
        yield synthetic_frame(seq, n_frames, width, height, **kwargs)  # type: ignore[arg-type]


def write_synthetic_recording(
    path: str | Path, n_frames: int = 60, width: int = 160, height: int = 120, *, with_ov: bool = True
) -> Path:
    """Write ``n_frames`` synthetic frames to a ``.govrec`` file; returns its path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"generator": "clients.harness", "scene": "checkerboard floor", "frames": n_frames}
    with RecordingWriter(path, meta) as writer:
        for frame in synthetic_frames(n_frames, width, height, with_ov=with_ov):
            writer.write(frame)
    return path


# ---------------------------------------------------------------------------------------------
# a node in a subprocess


def free_endpoints(count: int = 3) -> list[str]:
    """``count`` distinct ``tcp://127.0.0.1:PORT`` endpoints on currently free ports."""
    sockets = []
    try:
        for _ in range(count):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            sockets.append(s)
        return [f"tcp://127.0.0.1:{s.getsockname()[1]}" for s in sockets]
    finally:
        for s in sockets:
            s.close()


class NodeProcess:
    """``govnesf serve`` in a subprocess on free loopback ports; a context manager that always
    kills the process on exit. ``wait_ready()`` polls ``status`` until the node answers."""

    def __init__(
        self,
        map_dir: str | Path,
        *,
        log_path: str | Path | None = None,
        extra_args: Sequence[str] = (),
        events: bool = True,
    ) -> None:
        self.ingest, self.query, events_ep = free_endpoints(3)
        self.events: str | None = events_ep if events else None
        self.map_dir = Path(map_dir)
        self.log_path = Path(log_path) if log_path else None
        self.command = [
            sys.executable, "-m", "clients.cli", "serve",
            "--ingest", self.ingest, "--query", self.query, "--events", self.events or "",
            "--map-dir", str(self.map_dir), *extra_args,
        ]  # fmt: skip
        self.process: subprocess.Popen[bytes] | None = None
        self._log_file: object = None

    def start(self) -> NodeProcess:
        """Spawn the process (once; a second call does nothing)."""
        if self.process is not None:
            return self
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
        env.setdefault("HF_HUB_OFFLINE", "1")
        out = open(self.log_path, "wb") if self.log_path else subprocess.DEVNULL  # noqa: SIM115
        self._log_file = out
        self.process = subprocess.Popen(self.command, cwd=REPO_ROOT, env=env, stdout=out, stderr=out)
        return self

    def wait_ready(self, timeout_s: float = 20.0) -> None:
        """Block until the node answers ``status``; raise RuntimeError if it exits or times out."""
        deadline = time.monotonic() + timeout_s
        with MapperClient(ingest=self.ingest, query=self.query, timeout_s=0.25, retries=0) as client:
            while time.monotonic() < deadline:
                if self.process is not None and self.process.poll() is not None:
                    raise RuntimeError(
                        f"node exited with code {self.process.returncode} during start-up{self._log_hint()}"
                    )
                try:
                    client.status()
                    return
                except TimeoutError:
                    continue
        raise RuntimeError(f"node did not answer status within {timeout_s:g} s{self._log_hint()}")

    def _log_hint(self) -> str:
        return f" (log: {self.log_path})" if self.log_path else ""

    def client(self, **kwargs: object) -> MapperClient:
        """A client connected to this node."""
        return MapperClient(ingest=self.ingest, query=self.query, **kwargs)  # type: ignore[arg-type]

    def signal(self, signum: int = signal.SIGINT, timeout_s: float = 15.0) -> int:
        """Send ``signum`` and wait for the exit code."""
        assert self.process is not None
        self.process.send_signal(signum)
        return self.process.wait(timeout=timeout_s)

    def kill(self) -> None:
        """Make sure the process is gone (kills it if still running)."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)
        if self._log_file not in (None, subprocess.DEVNULL):
            self._log_file.close()  # type: ignore[attr-defined]
            self._log_file = None

    def __enter__(self) -> NodeProcess:
        if self.process is None:
            self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.kill()


# ---------------------------------------------------------------------------------------------
# the simulated robot and its ground truth (the demo, tests/e2e and benchmarks)

DEMO_SEED = 3
"""Scene seed of the demo: an apartment room with two chairs at a table, a bed, a kitchen run."""


def sim_stream(
    seed: int = DEMO_SEED, frames: int = 240, width: int = 160, height: int = 120, *, depth: bool = True,
    ov: bool = True, style: str = "apartment",
) -> Any:
    """A ``clients.sim.export.SimStream`` (scene, renderer, robot poses, SimLSeg); its
    ``frames()`` yields ``(Frame, RenderedView)`` lazily."""
    from clients.sim.export import RecordConfig, SimStream

    return SimStream.build(RecordConfig(seed=seed, style=style, frames=frames, width=width, height=height,
                                        depth=depth, ov=ov, novel_views=0, previews=0))


def chair_distance(centroid: np.ndarray, scene: Any, class_name: str = "chair") -> float:
    """Distance (m) from ``centroid`` (3,) to the nearest ground-truth instance centroid of a class
    (inf when the scene has none)."""
    dists = [float(np.linalg.norm(np.asarray(centroid) - inst.centroid))
             for inst in scene.instances if inst.class_name == class_name]
    return min(dists, default=math.inf)


def mean_iou(pred: np.ndarray, gt: np.ndarray, n_classes: int) -> tuple[float, dict[int, float]]:
    """Mean IoU over the classes present in ``gt`` (N,) ints; ``pred`` (N,) -1 (unlabelled) counts
    as wrong. Returns (mIoU, {class: IoU})."""
    valid_pred = (pred >= 0) & (pred < n_classes)
    inter = np.bincount(gt[valid_pred & (pred == gt)], minlength=n_classes)
    gt_count = np.bincount(gt, minlength=n_classes)
    pred_count = np.bincount(pred[valid_pred], minlength=n_classes)
    union = gt_count + pred_count - inter
    present = np.flatnonzero(gt_count > 0)
    ious = {int(c): float(inter[c] / union[c]) for c in present}
    return (float(np.mean(list(ious.values()))) if ious else 0.0), ious


def label_by_nearest(query_xyz: np.ndarray, map_xyz: np.ndarray, map_label: np.ndarray,
                     max_dist_m: float) -> np.ndarray:
    """(N,) label of the nearest map point within ``max_dist_m``, else -1."""
    from scipy.spatial import cKDTree

    out = np.full(query_xyz.shape[0], -1, np.int64)
    if map_xyz.shape[0] == 0:
        return out
    dist, idx = cKDTree(map_xyz).query(query_xyz, distance_upper_bound=max_dist_m)
    hit = np.isfinite(dist)
    out[hit] = map_label[idx[hit]]
    return out
