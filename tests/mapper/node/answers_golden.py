"""A recorded stream and the node's answers to it, for the test that answers and renders stay equal
when the node's code is reorganised (``test_answers_unchanged.py``).

``python -m tests.mapper.node.answers_golden OUT.npz`` streams a small simulated room (seed 3,
32 frames at 80x60: the first 24 with depth, the rest without; window of 8 keyframes, so keyframes
leave it) into an in-process node built as ``govnesf serve`` builds it (the shipped ``cpu-small``
checkpoint, triangulation, the learned features written into the map, evicted views kept for the
averaging), runs the background workers in place after every frame (deterministic), then asks
``segment_points`` with every method, a ``render`` and a ``query_points`` and writes the answers.
The stored file was made with the code before the node was split by request, made again
when the map began answering from the evicted views' mean at a voxel (``evicted_view_cosines``),
again when ``govnesf``'s map answer began mixing that mean with the voxel's learned feature
(``queries.evicted_views_learned_weight``), and again when those learned features began using the
depth-tested view selection (``global_map.learned_features_depth_test``), and again when
``govnesf``'s answers began mixing the evicted views' own mean by their share of a point's views
(``queries.learned_evicted_views``; with it at 0 the answers equal the stored ones before), and
again when the evicted views' ``all`` channel began leaving out what a keyframe with depth cannot
see (``queries.evicted_views_occlusion``), and again when ``govnesf``'s answers began taking the
averaging's per point where the averaging's is far more decided (``queries.learned_toward_average``;
with it at 0 the answers equal the stored ones before), and again when ``govnesf``'s answers
without a depth test in a window with depth began mixing the evicted views' mean by their share too
(``queries.learned_evicted_views_blended``; with it at 0 the answers equal the stored ones before).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from clients.harness import sim_stream
from mapper.node.config import config_from_dict
from mapper.node.serve import install_serve_stages
from mapper.node.service import MapperNode
from protocol.messages import QueryPoints, Render, SegmentPoints, decode, encode

TEXTS = ["wall", "floor", "chair", "table", "bed", "sofa", "cabinet", "door"]
METHODS = [("govnesf", False), ("govnesf", True), ("average", False), ("average_depth", True)]


def _settle(node: MapperNode) -> None:
    """Every background worker's queued work, in place."""
    ctx = node.ctx
    ctx.drain_integrations()
    for _ in range(3):
        for provider in list(ctx.status_providers.values()):
            worker = getattr(provider, "__self__", None)
            if worker is not None and hasattr(worker, "process_pending"):
                worker.process_pending()
        if ctx.evicted_views is not None:
            ctx.evicted_views.process_pending()


def _ask(node: MapperNode, msg: Any) -> Any:
    reply = decode(node.handle_query(encode(msg)), direction="reply")
    assert not hasattr(reply, "code"), getattr(reply, "message", reply)
    return reply


def build_answers(work_dir: Path) -> dict[str, np.ndarray]:
    """The answers (name -> array) of a node to the recorded stream (module docstring)."""
    config = config_from_dict({
        "map_dir": str(work_dir), "autosave_name": "", "save_on_exit": False, "serve_model": True,
        "window": {"max_keyframes": 8},
        "global_map": {"integrate_queue": 0},
        "queries": {"evicted_views": "both", "workers": 0},
    })
    node = MapperNode(config)
    install_serve_stages(node)
    stream = sim_stream(seed=3, frames=32, width=80, height=60, depth=True)
    xyz: list[np.ndarray] = []
    for index, (frame, view) in enumerate(stream.frames()):
        if index >= 24:
            frame.depth_m = None
        elif index % 4 == 0:  # the evaluation points: surface points of some depth frames
            v, u = np.mgrid[2:60:6, 2:80:6]
            z = view.depth_m[v, u]
            fx, fy, cx, cy = frame.K
            cam = np.stack([(u + 0.5 - cx) / fx * z, (v + 0.5 - cy) / fy * z, z, np.ones_like(z)], -1)
            world = (frame.world_from_cam @ cam.reshape(-1, 4).T).T[:, :3]
            xyz.append(world[z.ravel() > 0].astype(np.float32))
        node.handle_ingest(encode(frame))
        _settle(node)
    points = np.concatenate(xyz)
    out: dict[str, np.ndarray] = {"xyz": points}
    for method, use_depth in METHODS:
        reply = _ask(node, SegmentPoints(xyz=points, texts=TEXTS, method=method, use_depth=use_depth))
        key = f"{method}{'_dgm' if use_depth and method == 'govnesf' else ''}"
        out[f"{key}_label"], out[f"{key}_score"] = reply.label, reply.score
        out[f"{key}_source"] = reply.source
    pose = np.asarray(next(iter(stream.frames()))[0].world_from_cam)
    render = _ask(node, Render(width=40, height=30, K=np.array([35.0, 35.0, 20.0, 15.0]), world_from_cam=pose,
                               outputs=["rgb", "depth", "label", "score"], texts=TEXTS))
    for name in ("rgb", "depth_m", "label", "score", "source"):
        out[f"render_{name}"] = getattr(render, name)
    found = _ask(node, QueryPoints(texts=["chair"]))
    out["query_xyz"], out["query_score"] = found.xyz, found.score
    out["query_object_centroids"] = np.array([o.centroid for o in found.objects], np.float64).reshape(-1, 3)
    return out


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as tmp:
        answers = build_answers(Path(tmp))
    np.savez_compressed(sys.argv[1], **answers)
    print({k: v.shape for k, v in answers.items()})
