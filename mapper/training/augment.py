"""Sensor and pose augmentation of training examples: what a real robot's camera and odometry do.

The simulated training frames are clean: sharp, noise-free, losslessly stored, at exact poses. A
robot's are not (motion blur, sensor noise, JPEG on the wire, poses from odometry with centimetres
and a degree of error), and the scenario matrix (docs/how-to/scenario-matrix.md) streams exactly
those. :func:`sensor_effects` degrades the SOURCE images of an example (the target's colour stays
the clean supervision, as a denoising target); :func:`perturb_poses` moves the sources' poses by
a random rigid error while the target rays stay true, so the blend learns to weigh views whose
projection is off. Both draw from the generator they are given (``RaySampler`` gives each its own
stream, so examples without them are unchanged).

OpenCV does the blur and the JPEG round trip (the same codec a robot's ``rgb_encoding="jpeg"``
uses), rather than code of our own.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from torch import Tensor

__all__ = ["SENSOR_EFFECTS", "motion_blur_kernel", "ov_noise", "perturb_poses", "sensor_effects"]

SENSOR_EFFECTS = ("blur", "noise", "jpeg")
"""The effects :func:`sensor_effects` draws from (one or more per example)."""


def motion_blur_kernel(length_px: float, angle_rad: float) -> np.ndarray:  # (k, k) float32, sums to 1
    """A linear motion-blur kernel: a line of ``length_px`` pixels at ``angle_rad`` (odd size).

    >>> k = motion_blur_kernel(1.0, 0.0)
    >>> k.shape, float(k.sum())
    ((1, 1), 1.0)
    """
    if not (math.isfinite(length_px) and length_px >= 0):
        raise ValueError(f"length_px {length_px} must be finite and >= 0")
    size = max(1, int(math.ceil(length_px)) | 1)
    if size == 1:
        return np.ones((1, 1), np.float32)
    kernel = np.zeros((size, size), np.float32)
    c = size // 2
    dx, dy = math.cos(angle_rad), math.sin(angle_rad)
    for t in np.linspace(-0.5 * length_px, 0.5 * length_px, 4 * size):
        x, y = int(round(c + t * dx)), int(round(c + t * dy))
        if 0 <= x < size and 0 <= y < size:
            kernel[y, x] += 1.0
    return kernel / kernel.sum()


def sensor_effects(
    rgb: Tensor,  # (N, 3, H, W) float in [0, 1]
    rng: np.random.Generator,
    strength: float = 1.0,
) -> Tensor:  # (N, 3, H, W) float in [0, 1]
    """Each view, independently: with probability 1/2 each, motion blur (a line of up to
    ``8 * strength`` px at a random angle), Gaussian noise (std up to ``0.03 * strength``) and a
    JPEG round trip (quality 60-95). ``strength`` 0 returns the input unchanged.

    >>> x = torch.rand(2, 3, 8, 8)
    >>> bool(torch.equal(sensor_effects(x, np.random.default_rng(0), 0.0), x))
    True
    """
    if rgb.ndim != 4 or rgb.shape[1] != 3:
        raise ValueError(f"rgb must have shape (N, 3, H, W), got {tuple(rgb.shape)}")
    if not 0.0 <= strength <= 4.0:
        raise ValueError(f"strength {strength} out of range 0..4")
    if strength == 0.0:
        return rgb
    out = []
    for view in rgb:
        img = view.permute(1, 2, 0).clamp(0, 1).numpy().astype(np.float32)  # (H, W, 3)
        blur, noise, jpeg = rng.random(3) < 0.5
        if blur:
            length, angle = float(rng.uniform(1.0, 8.0 * strength)), float(rng.uniform(0, math.pi))
            kernel = motion_blur_kernel(length, angle)
            img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REFLECT)
        if noise:
            std = float(rng.uniform(0.0, 0.03 * strength))
            img = img + rng.normal(0.0, std, img.shape).astype(np.float32)
        if jpeg:
            q = int(rng.integers(60, 96))
            u8 = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
            ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, q])
            if ok:
                img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).astype(np.float32) / 255.0
        out.append(torch.from_numpy(np.clip(img, 0.0, 1.0)).permute(2, 0, 1))
    return torch.stack(out).to(rgb.dtype)


def ov_noise(
    ov: Tensor,  # (N, D, h, w) float: the source views' OV maps
    rng: np.random.Generator,
    strength: float = 1.0,
) -> Tensor:  # (N, D, h, w)
    """A 2D model's worse days on each source view's OV map, independently: Gaussian noise of std up
    to ``0.5 * strength`` times the map's mean cell norm, and with probability 1/2 one to three
    regions (each side 15-40% of the map's) confused with another region of the same map (its
    features copied in: a wall read as the sofa next to it), as SimLSeg's ``harsh`` level doubles
    the calibrated level's noise and confusions (``clients.matrix.driver.HARSH_OV``). The target's
    OV supervision stays as it was, so the blend learns to weigh down views that disagree.
    ``strength`` 0 returns the input unchanged.

    >>> x = torch.rand(2, 4, 6, 8)
    >>> bool(torch.equal(ov_noise(x, np.random.default_rng(0), 0.0), x))
    True
    """
    if ov.ndim != 4:
        raise ValueError(f"ov must have shape (N, D, h, w), got {tuple(ov.shape)}")
    if not 0.0 <= strength <= 4.0:
        raise ValueError(f"strength {strength} out of range 0..4")
    if strength == 0.0:
        return ov
    out = ov.clone()
    n, d, h, w = ov.shape
    for i in range(n):
        scale = float(out[i].norm(dim=0).mean())
        std = float(rng.uniform(0.0, 0.5 * strength)) * scale / math.sqrt(max(d, 1))
        out[i] += torch.from_numpy(rng.normal(0.0, std, (d, h, w)).astype(np.float32)).to(ov.dtype)
        if rng.random() < 0.5:
            for _ in range(int(rng.integers(1, 4))):
                rh, rw = max(1, int(h * rng.uniform(0.15, 0.4))), max(1, int(w * rng.uniform(0.15, 0.4)))
                y0, x0 = int(rng.integers(0, h - rh + 1)), int(rng.integers(0, w - rw + 1))
                y1, x1 = int(rng.integers(0, h - rh + 1)), int(rng.integers(0, w - rw + 1))
                out[i, :, y0: y0 + rh, x0: x0 + rw] = ov[i, :, y1: y1 + rh, x1: x1 + rw]
    return out


def perturb_poses(
    world_from_cam: Tensor,  # (N, 4, 4) float
    rng: np.random.Generator,
    sigma_m: float,
    sigma_deg: float,
) -> Tensor:  # (N, 4, 4) float, rigid
    """Each pose moved by an independent rigid error: a translation of std ``sigma_m`` per axis
    and a rotation about a random axis of std ``sigma_deg`` per axis (composed on the camera side,
    as odometry error), the matrix kept rigid.

    >>> T = torch.eye(4).expand(3, 4, 4).clone()
    >>> bool(torch.equal(perturb_poses(T, np.random.default_rng(0), 0.0, 0.0), T))
    True
    """
    if world_from_cam.ndim != 3 or world_from_cam.shape[1:] != (4, 4):
        raise ValueError(f"world_from_cam must have shape (N, 4, 4), got {tuple(world_from_cam.shape)}")
    if not (sigma_m >= 0 and sigma_deg >= 0):
        raise ValueError(f"sigma_m {sigma_m} and sigma_deg {sigma_deg} must be >= 0")
    if sigma_m == 0 and sigma_deg == 0:
        return world_from_cam
    n = world_from_cam.shape[0]
    rotvec = rng.normal(0.0, math.radians(sigma_deg), (n, 3))
    shift = rng.normal(0.0, sigma_m, (n, 3))
    delta = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        delta[i, :3, :3] = cv2.Rodrigues(rotvec[i])[0]
        delta[i, :3, 3] = shift[i]
    out = world_from_cam.double() @ torch.from_numpy(delta)
    return out.to(world_from_cam.dtype)
