"""``govnesf evaluate --rgb-only-node``: the node's real RGB-only pipeline on a held-out scene.

The other 3D rows of :mod:`mapper.training.evaluate` call the model directly on the recorded
frames. These rows instead stream the scene's frames WITHOUT depth (``rgb``, ``K``,
``world_from_cam``, ``ov``) into an in-process :class:`mapper.node.service.MapperNode` configured
from the shipped ``launch/node.toml`` (window large enough for every keyframe, the evaluated
checkpoint served) with the plugins ``govnesf serve`` installs (:mod:`mapper.node.cli`): the
learned-model handlers and rendered-depth points, triangulation, and the in-process OV backend
when configured. The workers run inline between frames. Then ``segment_points`` is asked, as a
robot would, for the evaluation's ground-truth points with the 20 class names as texts, for
``govnesf``, ``average``, ``govnesf`` with ``use_depth`` (Depth Guided Masking without depth:
the requested points hide one another in each keyframe, ``model.point_occlusion``; with it off,
the depth prior from plane-sweep stereo and the triangulated points, ``[stereo]``) and
``average_depth`` (the same test for averaging, ``queries.point_occlusion``), and each answer is
scored against the ground-truth labels.

Example::

    rows = node_rgb_only_rows(scene, "checkpoints/cpu-small.json", xyz, gt, settings)
    for name, (cm, extra) in rows.items(): ...

(:mod:`mapper.training.evaluate` wraps the results as its ``MethodResult``; this module does not
import it, so the two do not import each other.)
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from mapper.training.metrics import NUM_SCANNET_CLASSES, confusion_matrix

__all__ = ["NODE_ROWS", "NodeEvalSettings", "node_rgb_only_rows"]

NODE_ROWS = {
    ("govnesf", False): "Node RGB-only: govnesf",
    ("average", False): "Node RGB-only: average",
    ("govnesf", True): "Node RGB-only: govnesf + DGM",
    ("average_depth", True): "Node RGB-only: average_depth",
}
"""(segment_points method, use_depth) -> row name."""


class StreamScene(Protocol):
    """What is streamed of a scene (``mapper.training.evaluate.EvalScene`` has it)."""

    @property
    def class_names(self) -> list[str]: ...

    @property
    def rgb(self) -> np.ndarray: ...  # (F, H, W, 3) uint8

    @property
    def ov(self) -> np.ndarray: ...  # (F, h, w, D)

    @property
    def K(self) -> np.ndarray: ...  # (F, 4)

    @property
    def world_from_cam(self) -> np.ndarray: ...  # (F, 4, 4)

    @property
    def image_wh(self) -> tuple[int, int]: ...

    def __len__(self) -> int: ...


@dataclass(frozen=True)
class NodeEvalSettings:
    """How the scene is streamed into the node."""

    config_path: str | None = None
    """Node config TOML (None: the shipped ``launch/node.toml``, as ``govnesf serve``)."""
    ov_space: str = "minilm-l6-v2"
    """Embedding space of the recorded ``ov`` features (``govnesf sim record`` writes SimLSeg
    features in this space)."""
    device: str = "cpu"
    process_every: int = 10
    """Frames between inline passes of the node's workers (triangulation, rendered depth)."""
    frame_interval_ns: int = 100_000_000


def node_rgb_only_rows(
    scene: StreamScene,
    checkpoint: str | Path,
    xyz: np.ndarray,
    gt: np.ndarray,
    settings: NodeEvalSettings | None = None,
) -> dict[str, tuple[np.ndarray, dict[str, float]]]:
    """Stream ``scene`` without depth through a node serving ``checkpoint``; score its answers.

    Args:
        xyz: (P, 3) float32 evaluated ground-truth points; gt: (P,) int their labels.

    Returns:
        row name (:data:`NODE_ROWS`) -> (confusion matrix (20, 20) int64, extras): ``seconds`` (the
        query), ``stream_seconds``, ``keyframes``, ``triangulated_points``,
        ``rendered_depth_points``, ``global_map_points``, ``unanswered`` (share labelled -1;
        those points are scored as wrong).

    Raises:
        RuntimeError: the node could not load ``checkpoint`` or refused a query.
    """
    from mapper.node.config import load_config
    from mapper.node.serve import install_serve_stages
    from mapper.node.service import MapperNode
    from protocol.messages import Frame, Segmentation, SegmentPoints, decode, encode

    st = settings or NodeEvalSettings()
    n = len(scene)
    with tempfile.TemporaryDirectory(prefix="govnesf-eval-node-") as map_dir:
        config = load_config(st.config_path, {
            "map_dir": map_dir, "autosave_name": "", "save_on_exit": False,
            "window.max_keyframes": max(n, 1), "model.checkpoint": str(checkpoint),
            "model.device": st.device,
        })
        node = MapperNode(config)
        plugins = install_serve_stages(node)  # as `govnesf serve` builds it
        runtime = plugins.runtime
        if runtime is None or not runtime.ready:
            why = "serve_model is off" if runtime is None else runtime.load_error
            raise RuntimeError(f"the node could not load {checkpoint}: {why}")
        rendered, tri = plugins.rendered_depth, plugins.triangulation
        try:
            t0 = time.perf_counter()
            w, h = scene.image_wh
            for k in range(n):
                frame = Frame(
                    seq=k, stamp_ns=(k + 1) * st.frame_interval_ns, width=w, height=h,
                    K=np.asarray(scene.K[k], np.float64),
                    world_from_cam=np.asarray(scene.world_from_cam[k], np.float64),
                    rgb=np.ascontiguousarray(scene.rgb[k]), ov=np.ascontiguousarray(scene.ov[k]),
                    ov_space=st.ov_space,
                )
                node.handle_ingest(encode(frame))
                if (k + 1) % st.process_every == 0 or k == n - 1:
                    if tri is not None:
                        tri.process_pending()
                    if rendered is not None:
                        rendered.process_pending()
            stream_s = time.perf_counter() - t0
            extra: dict[str, float] = {
                "stream_seconds": stream_s,
                "keyframes": float(len(node.state.window) + node.state.keyframes_evicted),
                "triangulated_points": float(tri.stats()["global_map_points"]) if tri is not None else 0.0,
                "rendered_depth_points": float(rendered.stats()["points"]) if rendered is not None else 0.0,
                "global_map_points": float(len(node.state.global_map.snapshot())),
            }
            texts = list(scene.class_names[:NUM_SCANNET_CLASSES])
            pts = np.ascontiguousarray(xyz, np.float32)
            out: dict[str, tuple[np.ndarray, dict[str, float]]] = {}
            for (method, use_depth), name in NODE_ROWS.items():
                t0 = time.perf_counter()
                msg = SegmentPoints(xyz=pts, texts=texts, method=method, use_depth=use_depth)  # type: ignore[arg-type]
                reply: Any = decode(node.handle_query(encode(msg)), direction="reply")
                secs = time.perf_counter() - t0
                if not isinstance(reply, Segmentation):
                    raise RuntimeError(f"segment_points ({method}, use_depth={use_depth}): {reply}")
                label = reply.label.astype(np.int64)
                gt_i = np.asarray(gt, np.int64)
                # points the node leaves unanswered (-1) count as wrong: scored as the next class
                scored = np.where(label >= 0, label, (gt_i + 1) % NUM_SCANNET_CLASSES)
                out[name] = (
                    confusion_matrix(gt_i, scored),
                    {"seconds": secs, "seconds_per_100k": secs * 1e5 / max(len(gt), 1),
                     "unanswered": float((label < 0).mean()) if len(label) else 0.0, **extra},
                )
            return out
        finally:
            node.stop()
