"""Keyframe poses refined against the sparse map, for the triangulation worker
(:mod:`mapper.node.workers.triangulation`, ``triangulation.refine_poses``).

For a keyframe without depth, its features are matched (descriptors only: the pose is what is in
doubt, so no epipolar check) with its partners' features; a match whose partner keypoint was
triangulated (from the partner and ITS partners, never from this keyframe) is a 2D-3D
correspondence. :func:`mapper.geometry.pose_refine.refine_pose` refines the pose with them; the
worker then triangulates, sweeps and fuses the keyframe at the refined pose, and later keyframes
take it as a partner at that pose. The window, the ack and a saved map keep the pose as sent.

:class:`KeyframePoses` keeps the counts and the moves for ``status`` (``triangulation.poses``) and
the last refined poses (:meth:`KeyframePoses.refined`, for benchmarks).
"""

from __future__ import annotations

import threading
from collections import OrderedDict, deque
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from mapper.geometry.config import DenseFlowConfig, TriangulationConfig
from mapper.geometry.dense_flow import FlowView, flow_view, select_flow_partners
from mapper.geometry.pose_refine import PoseRefinement, refine_pose
from mapper.geometry.triangulation import Features
from mapper.geometry.window_adjust import PairMatches, adjust_poses, pair_matches

__all__ = ["KeyframePoses", "correspondences"]

KeyframeKey = tuple[str, int, int]
KEPT_POSES = 4096
"""Refined poses remembered for :meth:`KeyframePoses.refined` (128 bytes each)."""


def correspondences(
    features: Features,
    partners: Sequence[tuple[np.ndarray, np.ndarray] | None],
    matched: Sequence[np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """``(uv (M, 2), xyz (M, 3))``: the keyframe's keypoints matched (``matched[p]``, (n, 2) index
    pairs keyframe -> partner p) to partner keypoints with a triangulated point (``partners[p]``:
    (feature indices (k,), xyz (k, 3)), or None); one per keypoint, from the first partner that has
    one (partners come best first)."""
    uv: list[np.ndarray] = []
    xyz: list[np.ndarray] = []
    used = np.zeros(len(features), bool)
    for points, pairs in zip(partners, matched, strict=True):
        if points is None or not len(pairs) or not len(points[0]):
            continue
        index, world = points
        lookup = np.full(int(max(index.max(), pairs[:, 1].max())) + 1, -1, np.int64)
        lookup[index] = np.arange(len(index))
        row = lookup[pairs[:, 1]]
        take = (row >= 0) & ~used[pairs[:, 0]]
        if not take.any():
            continue
        own = pairs[take, 0]
        used[own] = True
        uv.append(features.uv[own])
        xyz.append(world[row[take]])
    if not uv:
        return np.zeros((0, 2)), np.zeros((0, 3))
    return np.concatenate(uv), np.concatenate(xyz)


class KeyframePoses:
    """Refinement of the keyframes' poses and what ``status`` reports of it (thread-safe stats)."""

    def __init__(self, config: TriangulationConfig) -> None:
        self.config = config
        self._lock = threading.Lock()
        self.attempted = 0
        self.refined_count = 0
        self.rejected: dict[str, int] = {}
        self._moves: deque[tuple[float, float]] = deque(maxlen=1000)  # accepted (m, deg)
        self._poses: OrderedDict[KeyframeKey, np.ndarray] = OrderedDict()
        # pose_method = "window": the adjusted keyframes (key, view at the pose as sent, estimate)
        # and their matches (key a, key b, matches); only the refining thread touches them
        self._flow = DenseFlowConfig()
        self._window: deque[tuple[KeyframeKey, FlowView, np.ndarray]] = deque(maxlen=config.pose_window)
        self._pairs: list[tuple[KeyframeKey, KeyframeKey, PairMatches]] = []

    def refine(
        self, key: KeyframeKey, K: np.ndarray, world_from_cam: np.ndarray, features: Features,
        partners: Sequence[tuple[np.ndarray, np.ndarray] | None], matched: Sequence[np.ndarray],
    ) -> PoseRefinement:
        """Refine the keyframe ``key``'s pose from its matches with its partners' points."""
        uv, xyz = correspondences(features, partners, matched)
        return self._record(key, refine_pose(K, world_from_cam, uv, xyz, self.config))

    def refine_window(self, key: KeyframeKey, K: np.ndarray, world_from_cam: np.ndarray,
                      rgb: np.ndarray) -> PoseRefinement:
        """``pose_method = "window"``: add the keyframe to the adjusted window (its dense matches with
        up to ``pose_partners`` of the last ``pose_window`` keyframes), adjust the window jointly
        (:func:`mapper.geometry.window_adjust.adjust_poses`, started at the earlier estimates) and
        return the new keyframe's pose (as sent where it was not accepted)."""
        cfg = self.config
        view = flow_view(rgb, K, world_from_cam, self._flow.max_width)
        window = self._window
        estimates = [e for _, _, e in window]
        posed = [replace(v, world_from_cam=e).posed for (_, v, _), e in zip(window, estimates, strict=True)]
        chosen = select_flow_partners(view.posed, posed, replace(self._flow, max_partners=cfg.pose_partners))
        new_pairs = []
        for c in chosen:  # matched at the poses as sent (the warp needs only the rough rotation)
            m = pair_matches(view, window[c][1], 0, 0, cfg, self._flow)
            if m is not None:
                new_pairs.append((window[c][0], m))
        window.append((key, view, world_from_cam.copy()))
        self._pairs.extend((key, other, m) for other, m in new_pairs)
        index = {k: i for i, (k, _, _) in enumerate(window)}
        self._pairs = [(a, b, m) for a, b, m in self._pairs if a in index and b in index]
        pairs = [replace(m, a=index[a], b=index[b]) for a, b, m in self._pairs]
        sent = np.stack([v.world_from_cam for _, v, _ in window])
        out = adjust_poses(np.stack([v.K for _, v, _ in window]), sent, pairs, cfg,
                           start=np.stack([e for _, _, e in window]))
        for i, (k, v, _) in enumerate(window):
            window[i] = (k, v, out.world_from_cam[i])
        last = len(window) - 1
        accepted = bool(out.accepted[last])
        reason = out.reason[last]
        result = PoseRefinement(
            out.world_from_cam[last].copy() if accepted else np.asarray(world_from_cam, np.float64).copy(),
            accepted, reason, int(out.matches[last]), int(out.matches[last]),
            float(out.error_before_px[last]), float(out.error_after_px[last]),
            float(out.translation_m[last]), float(out.rotation_deg[last]),
        )
        return self._record(key, result)

    def _record(self, key: KeyframeKey, result: PoseRefinement) -> PoseRefinement:
        with self._lock:
            self.attempted += 1
            if result.accepted:
                self.refined_count += 1
                self._moves.append((result.translation_m, result.rotation_deg))
                self._poses[key] = result.world_from_cam
                while len(self._poses) > KEPT_POSES:
                    self._poses.popitem(last=False)
            else:
                self.rejected[result.reason] = self.rejected.get(result.reason, 0) + 1
        return result

    def refined(self) -> dict[KeyframeKey, np.ndarray]:
        """The last refined poses by keyframe (camera, seq, stamp_ns): (4, 4) world_from_cam."""
        with self._lock:
            return dict(self._poses)

    def clear(self) -> None:
        """Forget the refined poses (a map was replaced); the counts stay."""
        with self._lock:
            self._poses.clear()
            self._window.clear()
            self._pairs = []

    def stats(self) -> dict[str, Any]:
        """``status``: keyframes tried and refined, why the others kept their pose, and how far the
        refined ones moved (median and 90th percentile of the recent 1000)."""
        with self._lock:
            moves = np.array(self._moves, np.float64).reshape(-1, 2)
            out: dict[str, Any] = {
                "enabled": self.config.refine_poses, "attempted": self.attempted,
                "refined": self.refined_count, "kept_as_sent": dict(self.rejected),
            }
        for name, col, scale in (("translation_cm", 0, 100.0), ("rotation_deg", 1, 1.0)):
            values = moves[:, col] * scale
            out[f"median_{name}"] = round(float(np.median(values)), 3) if len(values) else 0.0
            out[f"p90_{name}"] = round(float(np.percentile(values, 90)), 3) if len(values) else 0.0
        return out
