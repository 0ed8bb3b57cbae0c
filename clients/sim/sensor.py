"""Sensor effects and pose error for the simulated robot (the scenario matrix,
docs/how-to/scenario-matrix.md).

* :func:`motion_blur`: a linear blur along the image motion between two poses, over half the
  frame interval (a shutter open half the time);
* :func:`exposure_gains`: slowly varying per-frame exposure gains (auto-exposure hunting) with
  an occasional jump (a light switched, a window entering the view);
* :func:`apply_exposure`: an image times a gain, clipped to 8 bits;
* :func:`perturb_poses`: the poses a robot's odometry would report: per-frame noise
  (``noise_1cm`` / ``noise_3cm``) or a slow random-walk drift (``drift``). The node receives the
  perturbed poses; ground truth stays with the true ones. :func:`noisy_poses`: the same at any level.

JPEG is the wire's own ``rgb_encoding="jpeg"`` (:mod:`protocol.arrays`, quality 90).

>>> import numpy as np
>>> poses = np.stack([np.eye(4)] * 5)
>>> bool(np.array_equal(perturb_poses(poses, "exact", seed=0), poses))
True
>>> perturb_poses(poses, "wobble", seed=0)
Traceback (most recent call last):
...
ValueError: unknown pose error 'wobble'; choose one of ['drift', 'exact', 'noise_1cm', 'noise_3cm']
"""

from __future__ import annotations

import math

import numpy as np

POSE_ERRORS: dict[str, tuple[float, float]] = {
    "exact": (0.0, 0.0),
    "noise_1cm": (0.01, 0.5),
    "noise_3cm": (0.03, 1.5),
    "drift": (0.004, 0.08),
}
"""Pose error kind -> (translation std m, rotation std deg): per frame and independent for the
``noise_*`` kinds; the per-frame step of a random walk for ``drift`` (about 4 cm and 0.8 degrees
of drift after 100 frames)."""

BLUR_EXPOSURE = 0.5
"""Share of the frame interval the shutter is open (the blur covers this share of the motion)."""
BLUR_DEPTH_M = 2.0
"""Depth of the point whose image motion sets the blur (nearer points move more)."""
MAX_BLUR_PX = 24


def rotation_from_vector(rotvec: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the axis-angle vector ``rotvec`` (radians), Rodrigues' formula."""
    theta = float(np.linalg.norm(rotvec))
    if theta < 1e-12:
        return np.eye(3)
    k = np.asarray(rotvec, np.float64) / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * kx + (1.0 - math.cos(theta)) * (kx @ kx)


def perturb_poses(poses: np.ndarray, kind: str, seed: int) -> np.ndarray:
    """Poses (F, 4, 4) world_from_cam as odometry of error ``kind`` (:data:`POSE_ERRORS`) reports
    them: the camera centre moved and the orientation turned (about the camera centre)."""
    if kind not in POSE_ERRORS:
        raise ValueError(f"unknown pose error {kind!r}; choose one of {sorted(POSE_ERRORS)}")
    poses = np.asarray(poses, np.float64)
    if kind == "exact":
        return poses.copy()
    t_std, r_std = POSE_ERRORS[kind]
    return noisy_poses(poses, t_std, r_std, seed, drift=kind == "drift")


def noisy_poses(
    poses: np.ndarray, t_std_m: float, r_std_deg: float, seed: int, drift: bool = False
) -> np.ndarray:
    """Poses (F, 4, 4) with per-frame independent errors of ``t_std_m`` metres and ``r_std_deg``
    degrees (1 sigma per axis; the rotation about the camera centre, in the world frame), or with a
    random walk of such steps (``drift``). :func:`perturb_poses` with a level of its own."""
    poses = np.asarray(poses, np.float64)
    rng = np.random.default_rng([seed, 41])
    n = len(poses)
    dt = rng.normal(0.0, t_std_m, (n, 3))
    dr = rng.normal(0.0, math.radians(r_std_deg), (n, 3))
    if drift:  # a random walk starting at the exact first pose
        dt[0] = dr[0] = 0.0
        dt, dr = np.cumsum(dt, axis=0), np.cumsum(dr, axis=0)
    out = poses.copy()
    for k in range(n):
        out[k, :3, :3] = rotation_from_vector(dr[k]) @ poses[k, :3, :3]
        out[k, :3, 3] = poses[k, :3, 3] + dt[k]
    return out


def blur_vector_px(K: np.ndarray, prev_pose: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(2,) image motion (pixels) of the point BLUR_DEPTH_M ahead of the current camera's centre
    between the previous and the current pose, times BLUR_EXPOSURE."""
    fx, fy, cx, cy = (float(v) for v in K)
    point = pose[:3, :3] @ np.array([0.0, 0.0, BLUR_DEPTH_M]) + pose[:3, 3]
    cam = prev_pose[:3, :3].T @ (point - prev_pose[:3, 3])
    if cam[2] <= 1e-3:
        return np.zeros(2)
    uv = np.array([fx * cam[0] / cam[2] + cx, fy * cam[1] / cam[2] + cy])
    return BLUR_EXPOSURE * (np.array([cx, cy]) - uv)


def motion_blur(rgb: np.ndarray, vector_px: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 averaged over copies shifted along ``vector_px`` (2,) (centred; edges
    repeat); at most MAX_BLUR_PX long; returned unchanged below 1 pixel."""
    length = min(float(np.linalg.norm(vector_px)), float(MAX_BLUR_PX))
    if length < 1.0:
        return rgb
    direction = np.asarray(vector_px, np.float64) / float(np.linalg.norm(vector_px))
    steps = int(math.ceil(length)) + 1
    h, w = rgb.shape[:2]
    acc = np.zeros(rgb.shape, np.float64)
    rows, cols = np.arange(h), np.arange(w)
    for s in np.linspace(-length / 2, length / 2, steps):
        dx, dy = int(round(s * direction[0])), int(round(s * direction[1]))
        acc += rgb[np.clip(rows - dy, 0, h - 1)][:, np.clip(cols - dx, 0, w - 1)]
    return np.clip(np.round(acc / steps), 0, 255).astype(np.uint8)


def exposure_gains(n_frames: int, seed: int, amplitude: float = 0.35, jumps: int = 2) -> np.ndarray:
    """(n_frames,) gains around 1: exp of a slow random wave (log-amplitude ``amplitude``) plus
    ``jumps`` steps of +-0.3 in log gain at random frames."""
    rng = np.random.default_rng([seed, 43])
    k = np.arange(n_frames, dtype=np.float64)
    wave = np.zeros(n_frames)
    for _ in range(2):
        period = rng.uniform(25.0, 60.0)
        wave += np.sin(2.0 * math.pi * k / period + rng.uniform(0.0, 2.0 * math.pi))
    log_gain = amplitude * wave / 2.0
    for frame in rng.integers(0, max(n_frames, 1), jumps):
        log_gain[int(frame):] += rng.choice((-0.3, 0.3))
    return np.exp(log_gain)


def apply_exposure(rgb: np.ndarray, gain: float) -> np.ndarray:
    """(H, W, 3) uint8 times ``gain``, clipped (over-exposure saturates)."""
    return np.clip(np.round(rgb.astype(np.float32) * np.float32(gain)), 0, 255).astype(np.uint8)
