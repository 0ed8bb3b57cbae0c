"""Camera geometry: rigid poses, projection, pixel rays and image sampling.

Pure, batched torch functions; every function follows the dtype and device of its inputs
(float64 works end to end, which the property tests rely on).

Conventions (see docs/concepts/method.md):

* Camera frame: OpenCV optical, +x right, +y down, +z forward. World: right-handed metres.
* Poses are 4x4 rigid transforms named ``a_from_b`` (maps points in frame b to frame a);
  ``world_from_cam`` is camera-to-world, ``cam_from_world`` its inverse.
* Intrinsics ``K = [fx, fy, cx, cy]`` in pixels: ``u = fx * x / z + cx``, ``v = fy * y / z + cy``.
* Pixel (col i, row j) covers ``[i, i + 1) x [j, j + 1)``; its centre is ``(i + 0.5, j + 0.5)``.
  An image of width W spans ``u in [0, W]``. Rescaling an image to another resolution is then a
  pure scale of uv (``scale_uv``), with no half-pixel offsets.

Example:
    >>> import torch
    >>> K = torch.tensor([100.0, 100.0, 32.0, 24.0])
    >>> world_from_cam = torch.eye(4)
    >>> uv, z = project_points(torch.tensor([[0.0, 0.0, 2.0]]), K, invert_pose(world_from_cam))
    >>> uv.tolist(), z.tolist()
    ([[32.0, 24.0]], [2.0])
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.checks import check_shape

__all__ = [
    "frustum_points",
    "DEFAULT_EPS",
    "camera_centers",
    "in_view",
    "invert_pose",
    "pixel_rays",
    "project_points",
    "sample_bilinear",
    "sample_nearest",
    "scale_uv",
    "transform_points",
    "unproject_points",
]

DEFAULT_EPS = 1e-6
"""Smallest camera-frame depth (metres) that counts as in front of the camera."""

# uv of points that cannot be projected (z <= eps) or that land absurdly far away are clamped to
# this magnitude so that they stay finite (and far outside any image) in every dtype >= fp16.
_UV_LIMIT = 6.0e4


def _check_pose(pose: Tensor, name: str) -> None:
    check_shape(pose, "* 4 4", name)


def _check_points(points: Tensor, name: str) -> None:
    check_shape(points, "* N 3", name)


def _check_K(K: Tensor) -> None:
    check_shape(K, "* 4", "K must have shape [fx, fy, cx, cy]")


def invert_pose(a_from_b: Tensor) -> Tensor:
    """Inverse of a rigid transform.

    Args:
        a_from_b: (..., 4, 4) rigid transform (rotation + translation, last row [0, 0, 0, 1]).

    Returns:
        b_from_a: (..., 4, 4), computed as [R^T, -R^T t] (exact for rigid transforms).
    """
    _check_pose(a_from_b, "a_from_b")
    rot = a_from_b[..., :3, :3]
    trans = a_from_b[..., :3, 3:]
    rot_t = rot.transpose(-1, -2)
    out = torch.zeros_like(a_from_b)
    out[..., :3, :3] = rot_t
    out[..., :3, 3:] = -rot_t @ trans
    out[..., 3, 3] = 1.0
    return out


def transform_points(a_from_b: Tensor, points_b: Tensor) -> Tensor:
    """Apply a rigid transform to points.

    Args:
        a_from_b: (..., 4, 4).
        points_b: (..., N, 3) points in frame b (leading dims broadcast against the pose's).

    Returns:
        points_a: (..., N, 3).
    """
    _check_pose(a_from_b, "a_from_b")
    _check_points(points_b, "points_b")
    rot = a_from_b[..., :3, :3]
    trans = a_from_b[..., :3, 3]
    return points_b @ rot.transpose(-1, -2) + trans.unsqueeze(-2)


def camera_centers(world_from_cam: Tensor) -> Tensor:
    """Camera centres in the world frame: (..., 4, 4) -> (..., 3).

    This is the translation of ``world_from_cam`` (NOT of ``cam_from_world``, a quirk of the
    official code that we do not copy).
    """
    _check_pose(world_from_cam, "world_from_cam")
    return world_from_cam[..., :3, 3]


def project_points(
    points_world: Tensor, K: Tensor, cam_from_world: Tensor, eps: float = DEFAULT_EPS
) -> tuple[Tensor, Tensor]:
    """Project world points into a pinhole camera.

    Args:
        points_world: (..., N, 3) points in the world frame.
        K: (..., 4) intrinsics [fx, fy, cx, cy] in pixels.
        cam_from_world: (..., 4, 4) world-to-camera transform.
        eps: depth (m) at or below which a point is behind / on the camera plane.

    Returns:
        uv: (..., N, 2) pixel coordinates (pixel centres at i + 0.5). Always finite: points with
            ``z <= eps`` (and absurdly far projections) get clamped, meaningless uv; callers must
            mask them with ``z`` (see ``in_view``).
        z: (..., N) depth along the optical axis in metres (negative behind the camera).
    """
    _check_K(K)
    out_dtype = points_world.dtype
    # Half precision is computed in float32 (x / z and its gradient x / z^2 overflow fp16).
    work = torch.float32 if out_dtype in (torch.float16, torch.bfloat16) else out_dtype
    points_cam = transform_points(cam_from_world.to(work), points_world.to(work))
    z = points_cam[..., 2]
    # Divide only by a safe depth; torch.where keeps the gradient of the masked branch finite.
    z_safe = torch.where(z > eps, z, torch.full_like(z, eps))
    xy = points_cam[..., :2] / z_safe.unsqueeze(-1)
    focal = K[..., None, 0:2].to(work)
    centre = K[..., None, 2:4].to(work)
    uv = (xy * focal + centre).clamp(-_UV_LIMIT, _UV_LIMIT)
    return uv.to(out_dtype), z.to(out_dtype)


def unproject_points(uv: Tensor, z: Tensor, K: Tensor, world_from_cam: Tensor) -> Tensor:
    """Inverse of ``project_points`` for points in front of the camera.

    Args:
        uv: (..., N, 2) pixel coordinates.
        z: (..., N) depth along the optical axis (m), not the distance along the ray.
        K: (..., 4) intrinsics.
        world_from_cam: (..., 4, 4).

    Returns:
        points_world: (..., N, 3).
    """
    _check_K(K)
    focal = K[..., None, 0:2]
    centre = K[..., None, 2:4]
    xy = (uv - centre) / focal * z.unsqueeze(-1)
    points_cam = torch.cat([xy, z.unsqueeze(-1)], dim=-1)
    return transform_points(world_from_cam, points_cam)


def pixel_rays(K: Tensor, world_from_cam: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Rays through the pixel centres of a camera.

    Args:
        K: (..., 4) intrinsics for an image of ``width x height`` pixels.
        world_from_cam: (..., 4, 4).
        width, height: image size in pixels (>= 1).

    Returns:
        origins: (..., H, W, 3) camera centre, repeated.
        directions: (..., H, W, 3) unit directions in the world frame through (i + 0.5, j + 0.5).
    """
    _check_K(K)
    _check_pose(world_from_cam, "world_from_cam")
    if width < 1 or height < 1:
        raise ValueError(f"image size {width}x{height} out of range: width and height must be >= 1")
    dtype, device = K.dtype, K.device
    cols = torch.arange(width, dtype=dtype, device=device) + 0.5
    rows = torch.arange(height, dtype=dtype, device=device) + 0.5
    v, u = torch.meshgrid(rows, cols, indexing="ij")  # (H, W) each
    batch = K.shape[:-1]
    fx, fy, cx, cy = (K[..., i].reshape(*batch, 1, 1) for i in range(4))
    x = (u - cx) / fx  # (..., H, W)
    y = ((v - cy) / fy).expand_as(x)
    dirs_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)  # (..., H, W, 3)
    rot = world_from_cam[..., :3, :3]  # (..., 3, 3)
    dirs = torch.einsum("...ij,...hwj->...hwi", rot, dirs_cam)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    origins = camera_centers(world_from_cam)[..., None, None, :].expand_as(dirs)
    return origins, dirs


def frustum_points(
    K: Tensor,  # (4,) [fx, fy, cx, cy]
    world_from_cam: Tensor,  # (4, 4)
    width: int,
    height: int,
    near_m: float,
    far_m: float,
    *,
    n_uv: int = 5,
    n_z: int = 8,
) -> Tensor:
    """(n_z * n_uv * n_uv, 3) world points filling a camera's viewing frustum: an ``n_uv`` x
    ``n_uv`` grid over the image (corners included) at ``n_z`` z-depths from ``near_m`` to ``far_m``.

    What a frame without depth "observed" (the node's volume bounds; training's bounds augmentation).
    """
    _check_K(K)
    _check_pose(world_from_cam, "world_from_cam")
    if not (0.0 <= near_m < far_m):
        raise ValueError(f"frustum depths must satisfy 0 <= near_m < far_m, got {near_m}, {far_m}")
    dev, dt = world_from_cam.device, world_from_cam.dtype
    us = torch.linspace(0.0, float(width), n_uv, device=dev, dtype=dt)
    vs = torch.linspace(0.0, float(height), n_uv, device=dev, dtype=dt)
    zs = torch.linspace(float(near_m), float(far_m), n_z, device=dev, dtype=dt)
    z, v, u = torch.meshgrid(zs, vs, us, indexing="ij")
    Kd = K.to(dt)
    cam = torch.stack([(u - Kd[2]) / Kd[0] * z, (v - Kd[3]) / Kd[1] * z, z], dim=-1).reshape(-1, 3)
    return cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]


def scale_uv(uv: Tensor, from_wh: tuple[int, int], to_wh: tuple[int, int]) -> Tensor:
    """Rescale pixel coordinates from an image of size ``from_wh`` to one of size ``to_wh``.

    With pixel edges at integers this is exact: (..., 2) -> (..., 2).
    """
    if min(from_wh) <= 0 or min(to_wh) <= 0:
        raise ValueError(f"image sizes must be positive, got from {from_wh} to {to_wh}")
    scale = uv.new_tensor([to_wh[0] / from_wh[0], to_wh[1] / from_wh[1]])
    return uv * scale


def in_view(
    uv: Tensor, z: Tensor, width: int, height: int, border_px: float = 0.0, eps: float = DEFAULT_EPS
) -> Tensor:
    """Whether projected points are visible: in front of the camera and inside the image.

    Args:
        uv: (..., N, 2) pixel coordinates; z: (..., N) depth (m).
        width, height: image size (pixels) the uv refer to.
        border_px: points closer than this to the image edge count as outside.

    Returns:
        (..., N) bool: ``z > eps`` and ``border <= u <= W - border`` and ``border <= v <= H - border``.
    """
    u, v = uv[..., 0], uv[..., 1]
    return (
        (z > eps) & (u >= border_px) & (u <= width - border_px) & (v >= border_px) & (v <= height - border_px)
    )


def _flatten_for_sampling(image: Tensor, uv: Tensor) -> tuple[Tensor, Tensor, tuple[int, ...]]:
    check_shape(image, "* C H W", "image")
    check_shape(uv, "* N 2", "uv must have shape [u, v] per point")
    batch = torch.broadcast_shapes(image.shape[:-3], uv.shape[:-2])
    n_batch = math.prod(batch)
    img = image.expand(*batch, *image.shape[-3:]).reshape(n_batch, *image.shape[-3:])
    pts = uv.expand(*batch, *uv.shape[-2:]).reshape(n_batch, uv.shape[-2], 2)
    return img, pts, tuple(batch)


def sample_bilinear(image: Tensor, uv: Tensor, *, border_px: float = 0.0) -> tuple[Tensor, Tensor]:
    """Bilinearly sample an image (or a feature map) at pixel coordinates.

    Args:
        image: (..., C, H, W). Any resolution; pass uv in that resolution's pixels (``scale_uv``).
        uv: (..., N, 2) pixel coordinates, centre of pixel (i, j) at (i + 0.5, j + 0.5); leading
            dims broadcast against the image's.
        border_px: points closer than this to the edge are flagged as not inside.

    Returns:
        values: (..., N, C). Between the outermost pixel centres and the image edge the edge value
            is replicated; outside the image the values are meaningless (but finite): mask them.
        inside: (..., N) bool, uv within ``[border, W - border] x [border, H - border]``.
    """
    img, pts, batch = _flatten_for_sampling(image, uv)
    height, width = image.shape[-2:]
    size = pts.new_tensor([width, height])
    # align_corners=False: -1 and +1 are the outer image edges, matching our pixel convention.
    grid = (2.0 * pts / size - 1.0).clamp(-2.0, 2.0).to(img.dtype)
    out = F.grid_sample(img, grid.unsqueeze(1), mode="bilinear", padding_mode="border", align_corners=False)
    values = out.squeeze(2).transpose(1, 2).reshape(*batch, uv.shape[-2], image.shape[-3])
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= border_px) & (u <= width - border_px) & (v >= border_px) & (v <= height - border_px)
    return values, inside.expand(*batch, uv.shape[-2])


def bilinear_corners(uv: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """The four taps of :func:`sample_bilinear` (``grid_sample`` bilinear, border padding,
    ``align_corners=False``) at pixel coordinates ``uv`` (..., 2) of a (height, width) map.

    Returns:
        index: (..., 4) int64 row-major pixel indices ``row * width + col`` (always in range);
        weight: (..., 4) bilinear weights (sum 1), ``uv``'s dtype. Non-finite ``uv`` (a point
            behind a camera, masked anyway) reads the map's first pixel.

    ``sum_k weight[..., k] * map.flatten()[index[..., k]]`` equals ``sample_bilinear`` up to
    float rounding (tested).
    """
    uv = torch.nan_to_num(uv, nan=0.0, posinf=0.0, neginf=0.0)
    size = uv.new_tensor([width, height])
    grid = (2.0 * uv / size - 1.0).clamp(-2.0, 2.0)
    # grid_sample's unnormalisation (align_corners=False) and border padding (clip the coordinate)
    ix = (((grid[..., 0] + 1.0) * width - 1.0) / 2.0).clamp(0.0, width - 1.0)
    iy = (((grid[..., 1] + 1.0) * height - 1.0) / 2.0).clamp(0.0, height - 1.0)
    x0f, y0f = ix.floor(), iy.floor()
    tx, ty = ix - x0f, iy - y0f
    x0, y0 = x0f.long(), y0f.long()
    x1, y1 = (x0 + 1).clamp_max(width - 1), (y0 + 1).clamp_max(height - 1)
    index = torch.stack([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1], dim=-1)
    weight = torch.stack([(1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty], dim=-1)
    return index, weight


def sample_nearest(image: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
    """Nearest-pixel lookup (for depth maps, where bilinear blending across edges is wrong).

    Args:
        image: (..., C, H, W); uv: (..., N, 2) pixel coordinates.

    Returns:
        values: (..., N, C) the value of the pixel containing uv (clamped to the image),
        inside: (..., N) bool, uv within [0, W] x [0, H].
    """
    img, pts, batch = _flatten_for_sampling(image, uv)
    height, width = image.shape[-2:]
    col = pts[..., 0].floor().clamp(0, width - 1).long()  # (B, N)
    row = pts[..., 1].floor().clamp(0, height - 1).long()
    flat = img.reshape(img.shape[0], img.shape[1], -1)  # (B, C, H*W)
    index = (row * width + col).unsqueeze(1).expand(-1, img.shape[1], -1)
    values = torch.gather(flat, 2, index).transpose(1, 2)  # (B, N, C)
    values = values.reshape(*batch, uv.shape[-2], image.shape[-3])
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    return values, inside.expand(*batch, uv.shape[-2])
