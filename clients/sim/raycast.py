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
import open3d as o3d

from clients.sim.scenes import Scene, Texture


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


def fbm(p: np.ndarray, octaves: int = 3) -> np.ndarray:
    """Fractal sum of value noise, roughly in [0, 1]. p: (N, 3) -> (N,)."""
    acc, amp, norm = np.zeros(p.shape[0]), 1.0, 0.0
    for o in range(octaves):
        acc += amp * value_noise(p * (2.0**o) + 17.0 * o)
        norm += amp
        amp *= 0.5
    return acc / norm


def _plane_uv(p: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points onto the two axes spanning the face's dominant plane. (N, 3) -> 2x (N,)."""
    ax = np.argmax(np.abs(n), axis=1)
    u = np.where(ax == 0, p[:, 1], p[:, 0])
    v = np.where(ax == 2, p[:, 1], p[:, 2])
    return u, v


def procedural_albedo(
    p: np.ndarray, n: np.ndarray, colour: np.ndarray, colour2: np.ndarray, kind: np.ndarray,
    scale_m: np.ndarray,
) -> np.ndarray:
    """Albedo at world points.

    Args:
        p: (N, 3) world hit points, metres.
        n: (N, 3) world face normals.
        colour, colour2: (N, 3) the face's two colours.
        kind: (N,) Texture ids.
        scale_m: (N,) texture period.
    Returns:
        (N, 3) float64 albedo in [0, 1].
    """
    s = np.maximum(scale_m.astype(np.float64), 1e-3)[:, None]
    q = p / s                                   # lattice units
    u, v = _plane_uv(p, n)
    us, vs = u / s[:, 0], v / s[:, 0]
    fine = fbm(p / 0.015, 2)                    # grain every surface has (helps stereo matching)
    mix = np.zeros(p.shape[0])                  # 0 -> colour, 1 -> colour2

    def sel(k: Texture) -> np.ndarray:
        return kind == int(k)

    m = sel(Texture.PLAIN)
    mix[m] = 0.35 * fbm(q[m], 3)
    m = sel(Texture.CHECKER)
    mix[m] = ((np.floor(us[m]) + np.floor(vs[m])) % 2 == 1) * 0.9 + 0.1 * fbm(q[m] * 3, 2)
    m = sel(Texture.STRIPES)
    mix[m] = 0.5 + 0.5 * np.sign(np.sin(2 * np.pi * us[m])) * 0.8 + 0.1 * fbm(q[m] * 4, 2)
    m = sel(Texture.WOOD)
    warp = fbm(q[m] * np.array([0.3, 0.3, 0.3]), 3) * 3.0
    mix[m] = 0.5 + 0.5 * np.sin(2 * np.pi * (vs[m] * 0.2 + us[m] + warp))
    m = sel(Texture.FABRIC)
    mix[m] = 0.6 * fbm(q[m] * 2.0, 3) + 0.4 * (0.5 + 0.5 * np.sin(2 * np.pi * us[m] * 3) * np.sin(
        2 * np.pi * vs[m] * 3))
    m = sel(Texture.TILES)
    fu, fv = us[m] - np.floor(us[m]), vs[m] - np.floor(vs[m])
    grout = (np.minimum(fu, 1 - fu) < 0.03) | (np.minimum(fv, 1 - fv) < 0.03)
    mix[m] = np.where(grout, 1.0, 0.3 * fbm(q[m] * 0.5 + np.floor(q[m]), 2))
    m = sel(Texture.MARBLE)
    mix[m] = np.abs(np.sin(2 * np.pi * (us[m] * 0.3 + 2.5 * fbm(q[m], 4)))) ** 0.4
    albedo = colour * (1.0 - mix[:, None]) + colour2 * mix[:, None]

    m = sel(Texture.PATCHES)  # each cell a random colour
    if m.any():
        cell_u, cell_v = np.floor(us[m]), np.floor(vs[m] * 0.35)
        cell_w = np.floor(q[m].sum(1) * 0.0)
        rnd = np.stack([_hash3(cell_u, cell_v, cell_w + k) for k in range(3)], 1)
        albedo[m] = 0.55 * rnd + 0.45 * colour[m] * (0.6 + 0.4 * fbm(q[m] * 3, 2))[:, None]
    m = sel(Texture.SKY)
    if m.any():
        t = np.clip((p[m, 2] - 0.8) / 1.6, 0.0, 1.0)[:, None]
        albedo[m] = colour[m] * (1 - t) + colour2[m] * t + 0.08 * (fbm(p[m] * 2.0, 2)[:, None] - 0.5)
    albedo *= (0.85 + 0.3 * fine)[:, None]
    return np.clip(albedo, 0.0, 1.0)


# ----------------------------------------------------------------------------------------------
# Renderer
# ----------------------------------------------------------------------------------------------


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
            albedo = procedural_albedo(p, scene.face_normal[f].astype(np.float64), scene.face_colour[f],
                                       scene.face_colour2[f], scene.face_texture[f],
                                       scene.face_texture_scale[f])
            rgb[hit] = albedo * self._shade(p, n_w, self._emissive[f])
        return RenderedView(
            rgb=(np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).reshape(height, width, 3),
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

