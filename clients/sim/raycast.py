"""CPU ray-cast renderer for procedural scenes (Open3D `RaycastingScene`).

Rays go through pixel centres `(i + 0.5, j + 0.5)` in the OpenCV optical convention (+x right,
+y down, +z forward); we build them ourselves rather than relying on Open3D's pinhole helper.
Colour is the procedural albedo of the hit face evaluated at the world hit point, shaded with
Lambert's law under the scene's point light plus an ambient term (two-sided surfaces: the normal
is flipped towards the camera). Window panes (`Texture.SKY`) are emissive.

>>> from clients.sim.scenes import generate_scene
>>> from clients.sim.robot import default_intrinsics, look_at
>>> scene = generate_scene(0)
>>> world_from_cam = look_at(eye=[0.5, 0.5, 1.3], target=0.5 * (scene.room_min + scene.room_max))
>>> view = SceneRenderer(scene).render(default_intrinsics(64, 48), world_from_cam, 64, 48)
>>> view.rgb.shape, view.depth_m.dtype, bool((view.label >= 0).all())
((48, 64, 3), dtype('float32'), True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clients.sim.scenes import Scene, Texture
from govnesf._extras import require

o3d = require("open3d", "sim", "the simulator's ray casting (Open3D)")


@dataclass
class RenderedView:
    """Everything a simulated camera sees from one pose."""

    rgb: np.ndarray         # (H, W, 3) uint8, procedural albedo under simple lighting
    depth_m: np.ndarray     # (H, W) float32 z-depth (OpenCV camera z), 0 where nothing is hit
    label: np.ndarray       # (H, W) int32 index into CLASS_NAMES, -1 where nothing is hit
    instance: np.ndarray    # (H, W) int32 instance id, -1 for room structure or nothing
    normal_cam: np.ndarray  # (H, W, 3) float32 unit normal in the camera frame, facing the camera
    ray_dist_m: np.ndarray  # (H, W) float32 distance along the ray, 0 where nothing is hit


def _check_camera(K: np.ndarray, world_from_cam: np.ndarray, width: int, height: int) -> None:
    if not (1 <= int(width) <= 4096) or not (1 <= int(height) <= 4096):
        raise ValueError(f"image size {width}x{height} out of range 1..4096")
    K = np.asarray(K)
    if K.shape != (4,) or not np.isfinite(K).all() or K[0] <= 0 or K[1] <= 0:
        raise ValueError(f"K must be 4 finite numbers [fx, fy, cx, cy] with fx, fy > 0, got {K!r}")
    T = np.asarray(world_from_cam)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"world_from_cam must be a finite (4, 4) matrix, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
        raise ValueError("world_from_cam rotation is not a proper rotation (R^T R != I or det < 0)")


def camera_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 3) float64 unit ray directions in the camera frame through pixel centres."""
    fx, fy, cx, cy = (float(x) for x in K)
    u = (np.arange(width) + 0.5 - cx) / fx
    v = (np.arange(height) + 0.5 - cy) / fy
    uu, vv = np.meshgrid(u, v)
    d = np.stack([uu, vv, np.ones_like(uu)], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------------------------
# Procedural textures (pure functions of world position and per-face parameters)
# ----------------------------------------------------------------------------------------------


def _hash3(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray) -> np.ndarray:
    """Deterministic hash of integer lattice points -> float in [0, 1)."""
    h = (ix.astype(np.int64) * 73856093) ^ (iy.astype(np.int64) * 19349663) ^ (iz.astype(np.int64) * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float64) / float(0x1000000)


def value_noise(p: np.ndarray) -> np.ndarray:
    """Smooth 3D value noise in [0, 1]. p: (N, 3) in lattice units -> (N,)."""
    f = np.floor(p)
    t = p - f
    t = t * t * (3.0 - 2.0 * t)
    i = f.astype(np.int64)
    out = np.zeros(p.shape[0])
    for dx in (0, 1):
        wx = t[:, 0] if dx else 1.0 - t[:, 0]
        for dy in (0, 1):
            wy = t[:, 1] if dy else 1.0 - t[:, 1]
            for dz in (0, 1):
                wz = t[:, 2] if dz else 1.0 - t[:, 2]
                out += wx * wy * wz * _hash3(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz)
    return out


def _fade(period: np.ndarray | float, footprint: np.ndarray | None) -> np.ndarray | float:
    """Weight of a pattern detail of `period` seen through a pixel of `footprint` (same units):
    1 while the pixel is at most half the period, falling to 0 when it covers a whole period
    (the detail then averages out inside the pixel, as it does in a real camera)."""
    if footprint is None:
        return 1.0
    return np.clip(2.0 - 2.0 * footprint / period, 0.0, 1.0)


def fbm(p: np.ndarray, octaves: int = 3, footprint: np.ndarray | None = None) -> np.ndarray:
    """Fractal sum of value noise, roughly in [0, 1], mean 0.5. p: (N, 3) -> (N,).

    footprint: (N,) pixel size on the surface in the units of p; octaves finer than it fade to
    their mean (a cheap pre-filter against aliasing).
    """
    acc, amp, norm = np.zeros(p.shape[0]), 1.0, 0.0
    for o in range(octaves):
        spacing = 0.5**o
        acc += amp * (value_noise(p / spacing + 17.0 * o) - 0.5) * _fade(spacing, footprint)
        norm += amp
        amp *= 0.5
    return 0.5 + acc / norm


def _soft_square(phase: np.ndarray, period_m: np.ndarray, footprint_m: np.ndarray | None) -> np.ndarray:
    """Square wave sign(sin(2 pi phase)) box-filtered over the pixel footprint (approximately)."""
    if footprint_m is None:
        return np.sign(np.sin(2 * np.pi * phase))
    gain = period_m / (np.pi * np.maximum(footprint_m, 1e-6))
    return np.clip(np.sin(2 * np.pi * phase) * gain, -1.0, 1.0)


def _plane_uv(p: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points onto the two axes spanning the face's dominant plane. (N, 3) -> 2x (N,)."""
    ax = np.argmax(np.abs(n), axis=1)
    u = np.where(ax == 0, p[:, 1], p[:, 0])
    v = np.where(ax == 2, p[:, 1], p[:, 2])
    return u, v


_GRAIN_M = 0.015  # lattice spacing of the fine grain every surface carries


def procedural_albedo(
    p: np.ndarray, n: np.ndarray, colour: np.ndarray, colour2: np.ndarray, kind: np.ndarray,
    scale_m: np.ndarray, footprint_m: np.ndarray | None = None,
) -> np.ndarray:
    """Albedo at world points.

    Args:
        p: (N, 3) world hit points, metres.
        n: (N, 3) world face normals.
        colour, colour2: (N, 3) the face's two colours.
        kind: (N,) Texture ids.
        scale_m: (N,) texture period.
        footprint_m: (N,) size of the pixel on the surface, metres; details smaller than it are
            averaged out (None: no filtering, the pattern at the exact point).
    Returns:
        (N, 3) float64 albedo in [0, 1].
    """
    s1 = np.maximum(scale_m.astype(np.float64), 1e-3)
    s = s1[:, None]
    q = p / s                                   # lattice units
    u, v = _plane_uv(p, n)
    us, vs = u / s1, v / s1
    fp = None if footprint_m is None else np.asarray(footprint_m, dtype=np.float64)
    fq = None if fp is None else fp / s1        # footprint in lattice units
    fine = fbm(p / _GRAIN_M, 2, None if fp is None else fp / _GRAIN_M)  # stereo-matchable grain
    mix = np.zeros(p.shape[0])                  # 0 -> colour, 1 -> colour2

    def sel(k: Texture) -> np.ndarray:
        return kind == int(k)

    def sub(x: np.ndarray | None, m: np.ndarray, factor: float = 1.0) -> np.ndarray | None:
        return None if x is None else x[m] * factor

    m = sel(Texture.PLAIN)
    mix[m] = 0.35 * fbm(q[m], 3, sub(fq, m))
    m = sel(Texture.CHECKER)
    sq = _soft_square(us[m] * 0.5, 2 * s1[m], sub(fp, m)) * _soft_square(vs[m] * 0.5, 2 * s1[m], sub(fp, m))
    mix[m] = 0.45 - 0.45 * sq + 0.1 * fbm(q[m] * 3, 2, sub(fq, m, 3.0))
    m = sel(Texture.STRIPES)
    grain = fbm(q[m] * 4, 2, sub(fq, m, 4.0)) - 0.5
    mix[m] = 0.5 + 0.4 * _soft_square(us[m], s1[m], sub(fp, m)) + 0.1 * grain
    m = sel(Texture.WOOD)
    warp = fbm(q[m] * 0.3, 3, sub(fq, m, 0.3)) * 3.0
    mix[m] = 0.5 + 0.5 * np.sin(2 * np.pi * (vs[m] * 0.2 + us[m] + warp)) * _fade(s1[m], sub(fp, m))
    m = sel(Texture.FABRIC)
    weave = np.sin(2 * np.pi * us[m] * 3) * np.sin(2 * np.pi * vs[m] * 3) * _fade(s1[m] / 3, sub(fp, m))
    mix[m] = 0.6 * fbm(q[m] * 2.0, 3, sub(fq, m, 2.0)) + 0.4 * (0.5 + 0.5 * weave)
    m = sel(Texture.TILES)
    fu, fv = us[m] - np.floor(us[m]), vs[m] - np.floor(vs[m])
    d_line = np.minimum(np.minimum(fu, 1 - fu), np.minimum(fv, 1 - fv)) * s1[m]   # metres to a grout line
    half_w = 0.03 * s1[m]
    if fp is None:
        grout = (d_line < half_w).astype(np.float64)
    else:  # fraction of the pixel covered by the line, roughly
        f = np.maximum(fp[m], 1e-6)
        grout = np.clip((half_w - d_line) / f + 0.5, 0.0, 1.0) * np.minimum(1.0, 2 * half_w / f)
        grout = np.maximum(grout, np.minimum(1.0, 4 * half_w / f) * 0.5 * (1 - _fade(s1[m], f)))
    tile = 0.3 * fbm(q[m] * 0.5 + np.floor(q[m]), 2, sub(fq, m, 0.5))
    mix[m] = grout + (1.0 - grout) * tile
    m = sel(Texture.MARBLE)
    veins = np.abs(np.sin(2 * np.pi * (us[m] * 0.3 + 2.5 * fbm(q[m], 4, sub(fq, m))))) ** 0.4
    mix[m] = 0.8 + (veins - 0.8) * _fade(s1[m] * 0.25, sub(fp, m))
    albedo = colour * (1.0 - mix[:, None]) + colour2 * mix[:, None]

    m = sel(Texture.PATCHES)  # each cell a random colour
    if m.any():
        cell_u, cell_v = np.floor(us[m]), np.floor(vs[m] * 0.35)
        cell_w = np.zeros_like(cell_u)
        rnd = np.stack([_hash3(cell_u, cell_v, cell_w + k) for k in range(3)], 1)
        rnd = 0.5 + (rnd - 0.5) * np.asarray(_fade(s1[m], sub(fp, m)))[..., None] if fp is not None else rnd
        albedo[m] = 0.55 * rnd + 0.45 * colour[m] * (0.6 + 0.4 * fbm(q[m] * 3, 2, sub(fq, m, 3.0)))[:, None]
    m = sel(Texture.SKY)
    if m.any():
        t = np.clip((p[m, 2] - 0.8) / 1.6, 0.0, 1.0)[:, None]
        albedo[m] = colour[m] * (1 - t) + colour2[m] * t + 0.08 * (fbm(p[m] * 2.0, 2)[:, None] - 0.5)
    albedo *= (0.85 + 0.3 * fine)[:, None]
    return np.clip(albedo, 0.0, 1.0)


# ----------------------------------------------------------------------------------------------
# Renderer
# ----------------------------------------------------------------------------------------------


def tone_map(x: np.ndarray, knee: float = 0.75) -> np.ndarray:
    """Linear up to `knee`, then a smooth exponential shoulder towards 1 (slope continuous), so
    brightly lit surfaces keep their texture instead of clipping to white. Any shape -> same."""
    x = np.maximum(x, 0.0)
    head = 1.0 - knee
    return np.where(x <= knee, x, knee + head * (1.0 - np.exp(-(x - knee) / head)))


class SceneRenderer:
    """Ray casts a `Scene` into colour, depth, label, instance and normal images."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self._rc = o3d.t.geometry.RaycastingScene()
        self._rc.add_triangles(
            o3d.core.Tensor(scene.vertices.astype(np.float32)),
            o3d.core.Tensor(scene.triangles.astype(np.uint32)))
        self._emissive = scene.face_texture == int(Texture.SKY)

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cast world rays. origins, dirs: (N, 3) (dirs unit) -> t_hit (N,) metres (inf: miss),
        face id (N,) int64 (-1: miss)."""
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        ans = self._rc.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        prim = np.where(hit, prim, -1)
        return t, prim

    def render(self, K: np.ndarray, world_from_cam: np.ndarray, width: int, height: int) -> RenderedView:
        """Render one view.

        Args:
            K: (4,) [fx, fy, cx, cy] pixels.
            world_from_cam: (4, 4) camera-to-world pose (OpenCV optical camera frame).
            width, height: image size in pixels.
        """
        _check_camera(K, world_from_cam, width, height)
        scene = self.scene
        T = np.asarray(world_from_cam, dtype=np.float64)
        R, c = T[:3, :3], T[:3, 3]
        d_cam = camera_rays(K, width, height).reshape(-1, 3)    # (N, 3)
        d_world = np.einsum("pk,jk->pj", d_cam, R)            # R @ d, per pixel
        origins = np.broadcast_to(c, d_world.shape)
        t, face = self.cast(origins, d_world)
        hit = face >= 0
        n_px = d_cam.shape[0]

        depth = np.zeros(n_px, np.float32)
        dist = np.zeros(n_px, np.float32)
        label = np.full(n_px, -1, np.int32)
        inst = np.full(n_px, -1, np.int32)
        normal_cam = np.zeros((n_px, 3), np.float32)
        rgb = np.zeros((n_px, 3), np.float32)
        if hit.any():
            f = face[hit]
            th = t[hit]
            dist[hit] = th
            depth[hit] = th * d_cam[hit, 2]
            label[hit] = scene.face_label[f]
            inst[hit] = scene.face_instance[f]
            n_w = scene.face_normal[f].astype(np.float64)
            facing = np.sum(n_w * d_world[hit], axis=1) > 0
            n_w[facing] *= -1.0                                     # towards the camera
            normal_cam[hit] = np.einsum("pk,kj->pj", n_w, R)   # R^T @ n
            p = c + th[:, None] * d_world[hit]
            # pixel size on the surface (metres): distance x angular pixel size / obliquity
            cos_inc = np.abs(np.sum(n_w * d_world[hit], axis=1))
            pixel_rad = (d_cam[hit, 2] ** 2) / min(float(K[0]), float(K[1]))
            footprint = th * pixel_rad / np.maximum(cos_inc, 0.2)
            albedo = procedural_albedo(p, scene.face_normal[f].astype(np.float64), scene.face_colour[f],
                                       scene.face_colour2[f], scene.face_texture[f],
                                       scene.face_texture_scale[f], footprint)
            rgb[hit] = albedo * self._shade(p, n_w, self._emissive[f])
        return RenderedView(
            rgb=(tone_map(rgb) * 255.0 + 0.5).astype(np.uint8).reshape(height, width, 3),
            depth_m=depth.reshape(height, width), label=label.reshape(height, width),
            instance=inst.reshape(height, width), normal_cam=normal_cam.reshape(height, width, 3),
            ray_dist_m=dist.reshape(height, width))

    def _shade(self, p: np.ndarray, n: np.ndarray, emissive: np.ndarray) -> np.ndarray:
        """(N, 3) light multiplier at points p (N, 3) with camera-facing normals n (N, 3)."""
        light = self.scene.light
        to_l = light.position - p
        d = np.linalg.norm(to_l, axis=1)
        lam = np.clip(np.sum(n * to_l, axis=1) / np.maximum(d, 1e-9), 0.0, 1.0)
        atten = 1.0 / (1.0 + (d / light.falloff_m) ** 2) * 2.0
        s = (light.ambient + light.diffuse * lam * atten)[:, None] * light.colour[None, :]
        s[emissive] = 1.0
        return s

