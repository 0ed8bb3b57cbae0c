"""One scenario through a real node: render the frames, stream them, ask, score.

For each scenario the frames are rendered once (true poses: colour, depth, labels, SimLSeg
features), then corrupted as the scenario says (the sensor effect on the colour, the pose error
on the poses the node receives), and streamed into two nodes in turn (``govnesf serve`` over
loopback, :class:`clients.harness.NodeProcess`): the shipped defaults (``window``: 30 keyframes)
and the same node holding every keyframe (``all``: ``window.max_keyframes`` above the frame
count). Each node is asked, as fast as acks come back:

* right after the last ack (``after_ack``), ``segment_points`` at the ground-truth surface
  samples the stream saw, for ``govnesf``, ``average``, ``dgm`` (``govnesf`` with ``use_depth``)
  and, with depth, ``average_depth``; the 32 class names as texts;
* then ``status`` every 0.25 s until no background work is pending (:func:`pending_work`) twice
  in a row, at most ``settle_timeout_s``; the time from the last ack is ``settle_s``;
* once settled (``settled``), the same ``segment_points``; and on the ``window`` node,
  "find the chair" and two other classes of the room (the top object within
  :data:`FOUND_RADIUS_M` of an instance of the class), and ``render`` (colour, depth) at held-out
  poses near the path (true poses: a drifting map is judged where the room really is).

Scores use the true geometry: 3D mIoU over the classes present (harness.mean_iou; unlabelled
points count as wrong; each class seen asked at no fewer than ``min_class_points`` points), the
rendered depth's median relative error and PSNR where the simulator sees a surface.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from clients.harness import NodeProcess, chair_distance, mean_iou
from clients.matrix.scenarios import Scenario
from clients.sim.export import OV_SPACE, RecordConfig, SimStream, count_views, novel_view_poses
from clients.sim.paths import camera_path
from clients.sim.raycast import SceneRenderer
from clients.sim.robot import default_intrinsics
from clients.sim.scenes import CLASS_NAMES, LABEL_OF
from clients.sim.sensor import apply_exposure, blur_vector_px, exposure_gains, motion_blur, perturb_poses
from protocol.messages import Frame

FOUND_RADIUS_M = 0.35
"""An object query is answered when its top object lies this close to an instance of the class."""
OBJECT_CLASSES = ("table", "bed", "sofa", "desk", "cabinet", "bookshelf", "refrigerator", "toilet",
                  "monitor", "television", "door", "window")
"""Classes asked besides the chair (the first two the room has, in an order drawn per seed)."""
HARSH_OV = {"instance_confusion": 0.2, "instance_confusion_low_quality": 0.45, "region_confusion": 0.12,
            "region_confusion_low_quality": 0.45, "noise_std": 0.1, "noise_std_low_quality": 0.5}
"""SimLSeg settings of the ``harsh`` OV noise (the ``calibrated`` level is SimLSeg's default): about
twice the confusion and noise."""
NODE_CONFIGS = ("window", "all")
SETTLE_POLL_S = 0.25


@dataclass(frozen=True)
class RunSettings:
    """How scenarios are run."""

    gt_samples: int = 6000
    """Ground-truth surface samples per room, uniform by area (those the stream sees are asked)."""
    min_class_points: int = 50
    """Each class the stream sees is asked at no fewer points than this (while its seen surface
    gives them): samples on that class's own surfaces are added to the area-uniform ones. mIoU weighs
    every class alike, so a class with one area-uniform sample (a vase across a studio) would move
    the score by 1 / classes (5-7 points) on one point's label. 0 = area-uniform samples only."""
    novel_views: int = 3
    settle_timeout_s: float = 120.0
    request_timeout_s: float = 600.0
    node_start_timeout_s: float = 120.0
    log_dir: Path | None = None
    node_settings: tuple[str, ...] = ()
    """``KEY=VALUE`` node settings for every node (``govnesf serve --set``)."""


def methods_of(scenario: Scenario) -> list[tuple[str, str, bool]]:
    """(name, segment_points method, use_depth) asked in a scenario."""
    out = [("govnesf", "govnesf", False), ("average", "average", False), ("dgm", "govnesf", True)]
    if scenario.depth:
        out.append(("average_depth", "average_depth", True))
    return out


def pending_work(extra: dict[str, Any]) -> dict[str, int]:
    """Background work a ``status`` reply reports as not done yet (only the nonzero entries):
    keyframes acked but not in the global map (``integration.backlog``), and the ``pending``
    counts of the plugins that work after an ack (map features, triangulation, rendered depth,
    evicted views). A node that reports ``pending`` by source (and ``settled``) is read from that."""
    reported = extra.get("pending")
    if isinstance(reported, dict):
        return {str(k): int(v) for k, v in reported.items() if isinstance(v, int) and v > 0}
    out: dict[str, int] = {}
    integration = extra.get("integration")
    if isinstance(integration, dict) and integration.get("backlog"):
        out["integration"] = int(integration["backlog"])
    for key in ("map_features", "triangulation", "rendered_depth", "evicted_views"):
        part = extra.get(key)
        if isinstance(part, dict) and part.get("pending"):
            out[key] = int(part["pending"])
    return out


def psnr_db(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (dB, 8-bit peak) of ``pred`` against ``truth`` (H, W, 3) over the ``mask`` (H, W) pixels."""
    if not mask.any():
        return float("nan")
    diff = pred[mask].astype(np.float64) - truth[mask].astype(np.float64)
    mse = float(np.mean(diff**2))
    return float("inf") if mse == 0 else 10.0 * math.log10(255.0**2 / mse)


@dataclass
class Prepared:
    """A scenario's frames, ground truth and held-out poses (shared by both nodes)."""

    stream: SimStream
    frames: list[Frame]
    gt_xyz: np.ndarray
    gt_label: np.ndarray
    object_classes: list[str]
    novel_poses: np.ndarray
    render_s: float


def ground_truth_pool(scene: Any, settings: RunSettings, seed: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Candidate ground-truth points: ``gt_samples`` uniform by area (ceiling excluded), then, with
    ``min_class_points``, 4 x that many on each class's own surfaces. Returns xyz (P, 3) float32,
    label (P,) int32 and how many of them are the area-uniform ones (they come first)."""
    exclude = (LABEL_OF["ceiling"],)
    xyz, label, _ = scene.sample_surface(settings.gt_samples, seed=seed, exclude_labels=exclude)
    n_uniform = len(xyz)
    if settings.min_class_points > 0:
        parts_xyz, parts_label = [xyz], [label]
        for c in np.unique(scene.face_label):
            if int(c) in exclude:
                continue
            extra_xyz, extra_label, _ = scene.sample_surface(
                4 * settings.min_class_points, seed=seed + 1000 + int(c), only_labels=(int(c),))
            parts_xyz.append(extra_xyz)
            parts_label.append(extra_label)
        xyz, label = np.concatenate(parts_xyz), np.concatenate(parts_label)
    return xyz, label, n_uniform


def asked_points(label: np.ndarray, seen: np.ndarray, n_uniform: int, min_class_points: int) -> np.ndarray:
    """(P,) bool: the seen area-uniform points (the first ``n_uniform``), and for each class with fewer
    than ``min_class_points`` of them, its seen extra points (after them, in order) up to that many."""
    asked = np.zeros(len(label), bool)
    asked[:n_uniform] = seen[:n_uniform]
    if min_class_points <= 0 or len(label) == n_uniform:
        return asked
    have = np.bincount(label[asked], minlength=int(label.max()) + 1)
    extra = np.flatnonzero(seen[n_uniform:]) + n_uniform
    for c in np.unique(label[extra]):
        want = min_class_points - int(have[c])
        if want > 0:
            asked[extra[label[extra] == c][:want]] = True
    return asked


def prepare(scenario: Scenario, settings: RunSettings) -> Prepared:
    """Render the scenario's frames, corrupt them, and pick the ground truth to ask about."""
    from clients.sim.simlseg import SimLSeg, SimLSegConfig
    from clients.sim.text import get_text_encoder

    t0 = time.perf_counter()
    s = scenario
    config = RecordConfig(seed=s.seed, style=s.layout, frames=s.frames, width=s.width, height=s.height,
                          hfov_deg=s.hfov_deg, depth=s.depth, novel_views=0, previews=0)
    from clients.sim.scenes import generate_scene

    scene = generate_scene(s.seed, s.layout)
    poses = camera_path(scene, s.path, s.frames, seed=s.seed)
    K = default_intrinsics(s.width, s.height, s.hfov_deg)
    stride = max(4, s.width // 40)  # the OV grid stays about 40 cells wide, as a real 2D model's
    ov_cfg = SimLSegConfig(stride=stride)
    if s.ov_noise == "harsh":
        ov_cfg = dataclasses.replace(ov_cfg, **HARSH_OV)  # type: ignore[arg-type]
    simlseg = SimLSeg(CLASS_NAMES, get_text_encoder(), seed=s.seed, config=ov_cfg)
    stream = SimStream(config, scene, SceneRenderer(scene), K, poses, simlseg)
    sent_poses = perturb_poses(poses, s.pose_error, seed=s.seed)
    gains = exposure_gains(s.frames, seed=s.seed) if s.effect == "exposure" else None
    gt_xyz, gt_label, n_uniform = ground_truth_pool(scene, settings, s.seed)
    views = np.zeros(len(gt_xyz), np.int32)
    frames: list[Frame] = []
    for k in range(s.frames):
        view = stream.render(k)
        count_views(gt_xyz, K, poses[k], view.depth_m, views)
        ov = simlseg.features(view, frame_index=k, K=K)
        rgb = view.rgb
        if s.effect == "blur" and k > 0:
            rgb = motion_blur(rgb, blur_vector_px(K, poses[k - 1], poses[k]))
        if gains is not None:
            rgb = apply_exposure(rgb, float(gains[k]))
        frames.append(Frame(
            seq=k, stamp_ns=int(round(k * 1e8)), width=s.width, height=s.height, K=K.copy(),
            world_from_cam=sent_poses[k].copy(), rgb=rgb, depth_m=view.depth_m if s.depth else None,
            ov=ov, ov_space=OV_SPACE, rgb_encoding="jpeg" if s.effect == "jpeg" else "rgb8"))
    seen = asked_points(gt_label, views > 0, n_uniform, settings.min_class_points)
    present = {inst.class_name for inst in scene.instances}
    order = np.random.default_rng([s.seed, 7]).permutation(len(OBJECT_CLASSES))
    others = [OBJECT_CLASSES[i] for i in order if OBJECT_CLASSES[i] in present][:2]
    classes = (["chair"] if "chair" in present else []) + others
    novel, _ = novel_view_poses(stream, settings.novel_views, seed=s.seed)
    return Prepared(stream, frames, gt_xyz[seen].astype(np.float32), gt_label[seen].astype(np.int64),
                    classes, novel, time.perf_counter() - t0)


def _segment(client: Any, scenario: Scenario, prep: Prepared, timeout_s: float) -> dict[str, float]:
    out: dict[str, float] = {}
    texts = list(CLASS_NAMES)
    for name, method, use_depth in methods_of(scenario):
        seg = client.segment_points(prep.gt_xyz, texts, method=method, use_depth=use_depth,
                                    timeout_s=timeout_s)
        out[name] = 100.0 * mean_iou(seg.label.astype(np.int64), prep.gt_label, len(texts))[0]
    return out


def _settle(client: Any, timeout_s: float) -> tuple[bool, float, dict[str, int]]:
    """Poll ``status`` until nothing is pending twice in a row (or the timeout)."""
    t0 = time.perf_counter()
    quiet = 0
    last: dict[str, int] = {}
    while time.perf_counter() - t0 < timeout_s:
        last = pending_work(client.status(timeout_s=30.0).extra)
        quiet = quiet + 1 if not last else 0
        if quiet >= 2:
            return True, time.perf_counter() - t0, {}
        time.sleep(SETTLE_POLL_S)
    return False, time.perf_counter() - t0, last


def _objects(client: Any, prep: Prepared, timeout_s: float) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for cls in prep.object_classes:
        reply = client.query_points([f"find the {cls}"], objects=True, timeout_s=timeout_s)
        top = reply.objects[0].centroid if reply.objects else None
        dist = math.inf if top is None else chair_distance(top, prep.stream.scene, cls)
        out[f"find_{cls}_m"] = dist if math.isfinite(dist) else None
    found = [d is not None and d <= FOUND_RADIUS_M for d in out.values()]
    out["objects_asked"] = list(prep.object_classes)
    out["objects_found_share"] = float(np.mean(found)) if found else None
    out["chair_found"] = (out["find_chair_m"] is not None and out["find_chair_m"] <= FOUND_RADIUS_M
                          if "find_chair_m" in out else None)
    return out


def _renders(client: Any, prep: Prepared, timeout_s: float) -> dict[str, Any]:
    cfg = prep.stream.config
    rel, psnr = [], []
    for pose in prep.novel_poses:
        truth = prep.stream.renderer.render(prep.stream.K, pose, cfg.width, cfg.height)
        ok = (truth.depth_m > 0) & np.isfinite(truth.depth_m)
        reply = client.render(cfg.width, cfg.height, np.asarray(prep.stream.K, np.float64),
                              np.asarray(pose, np.float64), ["rgb", "depth"], timeout_s=timeout_s)
        if reply.depth_m is not None:
            d = reply.depth_m[ok]
            rel.append(np.abs(d - truth.depth_m[ok]) / truth.depth_m[ok])
        if reply.rgb is not None:
            psnr.append(psnr_db(reply.rgb, truth.rgb, ok))
    return {"render_depth_rel_err": float(np.median(np.concatenate(rel))) if rel else None,
            "render_psnr_db": float(np.mean(psnr)) if psnr else None}


@contextmanager
def node_client(scenario: Scenario, which: str, settings: RunSettings) -> Iterator[Any]:
    """A fresh node with the run's settings (``which``: ``window``, the defaults, or ``all``, every
    keyframe held), started; yields its client. Its log goes to ``settings.log_dir`` when set."""
    extra = ["--set", "save_on_exit=false", "--set", "load_autosave_on_start=false"]
    for item in settings.node_settings:
        extra += ["--set", item]
    if which == "all":
        extra += ["--set", f"window.max_keyframes={scenario.frames + 10}"]
    with tempfile.TemporaryDirectory(prefix="govnesf-matrix-") as tmp:
        log = Path(tmp) / "node.log"
        if settings.log_dir is not None:
            log = settings.log_dir / f"{scenario.name}-{which}.log"
        node = NodeProcess(Path(tmp) / "maps", log_path=log, extra_args=extra, events=False)
        with node:
            node.wait_ready(settings.node_start_timeout_s)
            with node.client(timeout_s=settings.request_timeout_s) as client:
                yield client


def stream(client: Any, prep: Prepared) -> None:
    """Send the prepared frames as fast as acks come back (4 in flight)."""
    for _ in client.send_frames(iter(prep.frames), window=4):
        pass


def run_node(scenario: Scenario, prep: Prepared, which: str, settings: RunSettings) -> dict[str, Any]:
    """Stream the prepared frames into a fresh node (``which``: ``window`` or ``all``); ask; score."""
    with node_client(scenario, which, settings) as client:
        t0 = time.perf_counter()
        stream(client, prep)
        out: dict[str, Any] = {"stream_s": time.perf_counter() - t0}
        t_ack = time.perf_counter()
        out["pending_at_ack"] = pending_work(client.status().extra)
        out["after_ack"] = _segment(client, scenario, prep, settings.request_timeout_s)
        out["after_ack_s"] = time.perf_counter() - t_ack
        settled, wait_s, left = _settle(client, settings.settle_timeout_s)
        out["settled_ok"] = settled
        out["settle_s"] = time.perf_counter() - t_ack if settled else None
        out["pending_at_timeout"] = left
        out["settled"] = _segment(client, scenario, prep, settings.request_timeout_s)
        status = client.status()
        out["keyframes"] = int(status.extra.get("frames_keyframe", 0))
        out["global_points"] = status.extra.get("global_points")
        if which == "window":
            out.update(_objects(client, prep, settings.request_timeout_s))
            out.update(_renders(client, prep, settings.request_timeout_s))
    return out


def run_scenario(scenario: Scenario, settings: RunSettings,
                 progress: Callable[[str], None] = lambda _: None) -> dict[str, Any]:
    """A scenario's row (JSON-able): its axes, and per node config its answers and timings."""
    t0 = time.perf_counter()
    prep = prepare(scenario, settings)
    progress(f"rendered {scenario.frames} frames in {prep.render_s:.0f} s; {len(prep.gt_xyz)} points asked")
    row: dict[str, Any] = {**scenario.as_dict(), "points": len(prep.gt_xyz), "render_s": prep.render_s}
    for which in NODE_CONFIGS:
        row[which] = run_node(scenario, prep, which, settings)
        settle = row[which]["settle_s"]
        progress(f"{which}: settled in {'n/a' if settle is None else f'{settle:.1f}'} s; mIoU settled "
                 + ", ".join(f"{k} {v:.1f}" for k, v in row[which]["settled"].items()))
    row["wall_s"] = time.perf_counter() - t0
    return row
