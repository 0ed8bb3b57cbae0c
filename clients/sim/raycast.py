"""Ray-cast renderer for procedural scenes (Open3D `RaycastingScene`, or a pure-torch fallback).

Two ray-casting backends give the same hits up to float32 ties (`SceneRenderer`, docs/how-to/simulator.md):
Open3D's `RaycastingScene` (CPU, the default where it is installed) and `TorchRaycaster`
(Moller-Trumbore in float32 on CUDA when available, else on the CPU), which lets the simulator
run where open3d has no wheel. `GOVNESF_SIM_RAYCAST` = `open3d` | `torch` picks one (unset: auto).

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

import os
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from clients.sim.scenes import Scene, Texture
from govnesf._extras import MissingExtraError, require

if TYPE_CHECKING:
    import torch

RAYCAST_ENV = "GOVNESF_SIM_RAYCAST"
"""Environment variable choosing the ray-casting backend: `open3d`, `torch`, or unset / `auto`
(open3d when it can be imported, else torch). `SceneRenderer(backend=...)` overrides it."""
RAYCAST_DEVICE_ENV = "GOVNESF_SIM_RAYCAST_DEVICE"
"""Environment variable choosing the torch backend's device (`cpu`, `cuda`, `cuda:1`, ...; unset /
`auto`: CUDA when `torch.cuda.is_available()`, else the CPU). `SceneRenderer(device=...)` overrides it."""
RAYCAST_BACKENDS = ("open3d", "torch")


def _open3d() -> ModuleType:
    """The open3d module (imported on first use: only the open3d backend needs it)."""
    return require("open3d", "sim", f"the simulator's Open3D ray casting (or set {RAYCAST_ENV}=torch)")


def raycast_backend(backend: str | None = None) -> str:
    """The ray-casting backend to use: `backend` if given, else $GOVNESF_SIM_RAYCAST; unset, empty
    or `auto` -> "open3d" when open3d can be imported, else "torch" (with a RuntimeWarning when
    open3d is installed but fails to import). Raises ValueError for any other name,
    MissingExtraError when "open3d" is asked for and not installed."""
    source = "backend" if backend is not None else RAYCAST_ENV
    raw = backend if backend is not None else os.environ.get(RAYCAST_ENV, "")
    choice = raw.strip().lower()
    if choice in ("", "auto"):
        try:
            _open3d()
        except MissingExtraError:
            return "torch"
        except (ImportError, OSError) as exc:  # installed but broken (e.g. libusb-1.0 missing)
            warnings.warn(f"open3d is installed but does not import ({exc}); the simulator ray casts "
                          f"with torch (set {RAYCAST_ENV}=open3d to see the error)", RuntimeWarning,
                          stacklevel=2)
            return "torch"
        return "open3d"
    if choice not in RAYCAST_BACKENDS:
        raise ValueError(f"{source}={raw!r} is not a ray-casting backend; choose one of "
                         f"{', '.join(RAYCAST_BACKENDS)} (or leave {RAYCAST_ENV} unset / 'auto' for "
                         "open3d when installed, else torch)")
    if choice == "open3d":
        _open3d()  # a missing open3d names the [sim] extra here, not at the first cast
    return choice


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


def torch_device(device: str | None = None) -> torch.device:
    """The torch backend's device: `device` if given, else $GOVNESF_SIM_RAYCAST_DEVICE; unset, empty
    or `auto` -> CUDA when available, else the CPU. ValueError for a name torch does not know or a
    device this machine does not have."""
    import torch

    source = "device" if device is not None else RAYCAST_DEVICE_ENV
    raw = device if device is not None else os.environ.get(RAYCAST_DEVICE_ENV, "")
    name = raw.strip().lower()
    if name in ("", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
        torch.zeros(1, device=dev)
    except (RuntimeError, AssertionError, ValueError) as exc:  # unknown name, no CUDA build, no such GPU
        raise ValueError(f"{source}={raw!r}: not a usable torch device on this machine "
                         f"(cpu, cuda, cuda:N, or auto): {exc}") from None
    return dev


@contextmanager
def _torch_settings(cpu_threads: int | None) -> Iterator[None]:
    """While casting: float32 matmuls in full float32 (no TF32 / bfloat16 shortcut set elsewhere
    in the process) and, when `cpu_threads` is given, at most that many intra-op CPU threads;
    both are put back afterwards."""
    import torch

    precision, threads = torch.get_float32_matmul_precision(), torch.get_num_threads()
    if precision != "highest":
        torch.set_float32_matmul_precision("highest")
    if cpu_threads is not None and threads > cpu_threads:
        torch.set_num_threads(cpu_threads)
    try:
        yield
    finally:
        if torch.get_float32_matmul_precision() != precision:
            torch.set_float32_matmul_precision(precision)
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


def _spread_table(stride: int) -> np.ndarray:
    """(1024,) int64: bit k of the index moved to bit stride * k."""
    x = np.arange(1024, dtype=np.int64)
    out = np.zeros_like(x)
    for k in range(10):
        out |= ((x >> k) & 1) << (stride * k)
    return out


_SPREAD = {2: _spread_table(2), 3: _spread_table(3)}


def _spread_bits(x: np.ndarray, stride: int) -> np.ndarray:
    """Bit k of x (int64 in 0..1023) moved to bit stride * k (Morton interleaving)."""
    return _SPREAD[stride][x]


def coherent_ray_order(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """A permutation of N rays that puts rays with nearby origins and directions next to each other
    (Morton order of the quantised origin, then cube-map face and Morton order of the direction on
    it), so that a run of consecutive rays is a compact bundle (a tile of a camera image, a patch
    of a grid of parallel rays). origins, dirs: (N, 3) -> (N,) int64, stable for equal keys."""
    o = np.asarray(origins, np.float64)
    d = np.asarray(dirs, np.float64)
    ax = np.argmax(np.abs(d), axis=1)
    rows = np.arange(len(d))
    major = d[rows, ax]
    face = 2 * ax + (major < 0)
    other = np.stack([d[rows, (ax + 1) % 3], d[rows, (ax + 2) % 3]], 1)
    other /= np.maximum(np.abs(major), 1e-12)[:, None]                        # on the cube face, [-1, 1]
    qd = np.zeros((len(d), 2), np.int64)
    for f in np.unique(face):  # the rays' own extent on each face, so that an image splits into tiles
        on = face == f
        lo_d = other[on].min(0)
        span = max(float((other[on].max(0) - lo_d).max()), 1e-9)
        qd[on] = np.floor((other[on] - lo_d) / span * 1023.999).astype(np.int64).clip(0, 1023)  # 10 bits
    key = face << 20 | _spread_bits(qd[:, 0], 2) | _spread_bits(qd[:, 1], 2) << 1
    lo = o.min(0)
    extent = float((o.max(0) - lo).max())
    if extent > 0.0:   # rays from more than one origin: their places come first (7 bits a coordinate)
        qo = np.floor((o - lo) / extent * 127.999).astype(np.int64).clip(0, 127)
        morton = _spread_bits(qo[:, 0], 3) | _spread_bits(qo[:, 1], 3) << 1 | _spread_bits(qo[:, 2], 3) << 2
        key |= morton << 23
    return np.argsort(key, kind="stable")


class TorchRaycaster:
    """Nearest ray/triangle hits in torch (Moller-Trumbore), double-sided, deterministic.

    The test: Moller-Trumbore's scalars for a ray x triangle pair (det, and u, v, 1 - u - v and t
    times det) are bilinear in the ray's features (d, o x d, o, 1) and the triangle's (built once
    here from v0 and the edges e1 = v1 - v0, e2 = v2 - v0), so two matmuls give them for a block
    of pairs; the rest is elementwise, without branches (a pair that fails a test gets its t
    pushed beyond `_MISS`; every value stays finite, never NaN). Float32 on the device, like
    Open3D, in coordinates centred on the mesh's bounding box (smaller numbers, smaller rounding).
    A hit needs u, v >= -tol, u + v <= 1 + tol (`bary_tol`: a ray through an edge shared by two
    triangles never slips between them), t > `t_min`, and the ray not within `det_min` (cosine)
    of parallel to the plane; either side of a triangle counts, as in Open3D. The nearest hit
    wins; hits within `tie_tol_m` (+ 1e-6 t) of it are ties, which go to the lowest face id.

    Which pairs are tested: with `cull` False (the default on a GPU) every ray against every
    triangle, a chunk of rays at a time (at most `max_pairs` pairs in flight, so memory stays
    bounded). With `cull` True (the default on the CPU) the rays are sorted into bundles of
    `bundle_rays` (`coherent_ray_order`: a camera image falls into tiles) and each bundle is
    tested only against the triangles whose bounding sphere its cone of rays can reach (a
    conservative test, its margins far above float32 rounding): in a room about 10% of them,
    with the same answers as testing all.
    """

    max_pairs = 8_000_000   # ray x triangle pairs per block (about 12 float32 tensors of that size)
    bundle_rays = 256       # rays per bundle when culling (fastest on a 160x120 image on the CPU)
    cpu_threads = 1         # torch threads while casting on the CPU: the blocks are small, more threads
    #                         spin (16 threads: the same wall time for 12x the CPU time of one)
    t_min = 1e-6            # metres: hits at t <= t_min (at or behind the origin) do not count
    det_min = 1e-7          # |cos| of the angle between a ray and a plane below which they are parallel
    bary_tol = 1e-6         # barycentric slack at edges (float32 rounding between neighbours)
    tie_tol_m = 4e-6        # metres: hits this close to the nearest are ties (lowest face id)
    _MISS = 1e29            # a missing pair's t (|t| < 1e16 before) plus 1e30 is above this

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, device: str | None = None,
                 cull: bool | None = None) -> None:
        import torch

        self.device = torch_device(device)
        self.cull = self.device.type == "cpu" if cull is None else bool(cull)
        v = np.asarray(vertices, np.float64).reshape(-1, 3)
        tri = np.asarray(triangles, np.int64).reshape(-1, 3)
        self.n_faces = len(tri)
        self._centre = 0.5 * (v.min(0) + v.max(0)) if len(v) else np.zeros(3)
        v0, v1, v2 = (v[tri[:, k]] - self._centre for k in range(3))
        e1, e2 = v1 - v0, v2 - v0
        n = np.cross(e1, e2)                                   # |n| = twice the area
        norm = np.linalg.norm(n, axis=1)
        good = norm > 1e-20                                    # degenerate triangles never hit
        scale = np.where(good, 1.0 / np.where(good, norm, 1.0), 0.0)[:, None]
        n_hat = n * scale
        # per triangle, the coefficients of a ray's features [d (3), m = o x d (3), o (3), 1] in
        w = np.zeros((5, self.n_faces, 10))
        w[0, :, 0:3] = -n_hat                                  # det = e1 . (d x e2) = -d . n
        w[1, :, 0:3] = np.cross(v0, e2) * scale                # u det = (o - v0) . (d x e2)
        w[1, :, 3:6] = e2 * scale
        w[2, :, 0:3] = np.cross(e1, v0) * scale                # v det = d . ((o - v0) x e1)
        w[2, :, 3:6] = -e1 * scale
        w[4, :, 6:9] = n_hat                                   # t det = e2 . ((o - v0) x e1) = (o - v0) . n
        w[4, :, 9] = -np.sum(v0 * n_hat, axis=1)
        tol = self.bary_tol
        w[3] = (1.0 + tol) * w[0] - w[1] - w[2]               # (1 + tol - u - v) det
        w[1] += tol * w[0]                                     # (u + tol) det
        w[2] += tol * w[0]                                     # (v + tol) det
        w[4] -= self.t_min * w[0]                              # (t - t_min) det
        self._w_uvr = torch.from_numpy(w[1:4, :, 0:6].astype(np.float32)).to(self.device)  # (3, T, 6)
        self._w_dt = torch.from_numpy(w[[0, 4]][:, :, [0, 1, 2, 6, 7, 8, 9]].astype(np.float32)).to(
            self.device)                                                                  # (2, T, 7)
        # bounding spheres for the culling, float64 on the host
        self._sphere_c = (v0 + v1 + v2) / 3.0
        self._sphere_r = np.sqrt(np.max([np.sum((p - self._sphere_c) ** 2, axis=1) for p in (v0, v1, v2)],
                                        axis=0, initial=0.0))

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """origins, dirs: (N, 3) world rays (dirs unit) -> t_hit (N,) float64 metres (inf: miss),
        face id (N,) int64 (-1: miss)."""
        import torch

        o = np.asarray(origins, np.float64).reshape(-1, 3) - self._centre
        d = np.asarray(dirs, np.float64).reshape(-1, 3)
        n_rays = len(o)
        t_out = np.full(n_rays, np.inf)
        f_out = np.full(n_rays, -1, np.int64)
        if n_rays == 0 or self.n_faces == 0:
            return t_out, f_out
        order = coherent_ray_order(o, d) if self.cull else np.arange(n_rays)
        o, d = o[order], d[order]
        m = np.cross(o, d)
        ones = np.ones((n_rays, 1))
        f_dm = torch.from_numpy(np.concatenate([d, m], 1).astype(np.float32)).to(self.device)
        f_do1 = torch.from_numpy(np.concatenate([d, o, ones], 1).astype(np.float32)).to(self.device)
        t_dev = torch.empty(n_rays, dtype=torch.float32, device=self.device)
        f_dev = torch.empty(n_rays, dtype=torch.int64, device=self.device)
        cpu_threads = self.cpu_threads if self.device.type == "cpu" else None
        with torch.no_grad(), _torch_settings(cpu_threads):
            for a, b, faces in self._blocks(o, d):
                if faces is not None and len(faces) == 0:   # no triangle within reach: all miss
                    t_dev[a:b] = torch.inf
                    f_dev[a:b] = -1
                    continue
                if faces is None:
                    w_uvr, w_dt = self._w_uvr, self._w_dt
                else:
                    ids = torch.from_numpy(faces).to(self.device)
                    w_uvr, w_dt = self._w_uvr[:, ids], self._w_dt[:, ids]
                t, local = self._nearest(f_dm[a:b], f_do1[a:b], w_uvr, w_dt)
                t_dev[a:b] = t
                f_dev[a:b] = local if faces is None else torch.where(local >= 0, ids[local.clamp(min=0)], -1)
        t_out[order] = t_dev.cpu().numpy()
        f_out[order] = f_dev.cpu().numpy()
        return t_out, f_out

    def _blocks(self, o: np.ndarray, d: np.ndarray) -> Iterator[tuple[int, int, np.ndarray | None]]:
        """(first ray, end ray, ascending ids of the triangles to test them against; None: all) for
        rays o, d (N, 3) (in `coherent_ray_order` when culling), at most `max_pairs` pairs a block."""
        n_rays, n_faces = len(o), self.n_faces
        if not self.cull:
            step = max(1, self.max_pairs // n_faces)
            for a in range(0, n_rays, step):
                yield a, min(a + step, n_rays), None
            return
        size = self.bundle_rays
        per_block = max(1, self.max_pairs // (8 * n_faces))   # bundles culled at once (~100 MB at most)
        for first in range(0, n_rays, size * per_block):
            end = min(first + size * per_block, n_rays)
            keep = self._reachable(o[first:end], d[first:end])
            for g, row in enumerate(keep):
                faces = np.flatnonzero(row)
                a, b = first + g * size, min(first + (g + 1) * size, end)
                step = max(1, self.max_pairs // max(len(faces), 1))
                for c in range(a, b, step):
                    yield c, min(c + step, b), faces

    def _reachable(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(G, T) bool: which triangles each bundle of `bundle_rays` consecutive rays of o, d (n, 3)
        can hit (the last bundle may be short): those whose bounding sphere meets the bundle's cone
        (its mean direction, its widest angle to it) from the sphere around its origins."""
        size = self.bundle_rays
        n_bundles = -(-len(o) // size)
        pad = n_bundles * size - len(o)
        o_b = np.concatenate([o, np.repeat(o[-1:], pad, 0)]).reshape(n_bundles, size, 3)
        d_b = np.concatenate([d, np.repeat(d[-1:], pad, 0)]).reshape(n_bundles, size, 3)
        oc = o_b.mean(1)                                                       # (G, 3)
        r_o = np.sqrt(((o_b - oc[:, None]) ** 2).sum(2).max(1))                # (G,)
        axis = d_b.mean(1)
        length = np.maximum(np.linalg.norm(axis, axis=1), 1e-12)
        axis /= length[:, None]
        cos_spread = np.einsum("gnk,gk->gn", d_b, axis).min(1)
        theta = np.arccos(np.clip(cos_spread, -1.0, 1.0)) + 1e-6               # (G,) half-angle of the cone
        c = self._sphere_c                                                     # (T, 3)
        dist2 = (c**2).sum(1)[None] - 2.0 * (oc @ c.T) + (oc**2).sum(1)[:, None]  # (G, T) |c - oc|^2
        dist = np.sqrt(np.maximum(dist2, 0.0))
        along = axis @ c.T - (axis * oc).sum(1)[:, None]                       # (c - oc) . axis
        reach = self._sphere_r[None] * (1.0 + 1e-5) + r_o[:, None] + 1e-4      # margins >> float32 rounding
        sin_a = np.minimum(reach / np.maximum(dist, 1e-12), 1.0)
        cos_bound = np.cos(theta)[:, None] * np.sqrt(1.0 - sin_a**2) - np.sin(theta)[:, None] * sin_a
        keep = (dist <= reach) | (along >= cos_bound * dist)
        keep[cos_spread < 0.05] = True    # a cone wider than ~87 degrees: theta + alpha could pass pi
        return keep

    def _nearest(self, f_dm: torch.Tensor, f_do1: torch.Tensor, w_uvr: torch.Tensor,
                 w_dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays as features f_dm (n, 6) = [d, o x d], f_do1 (n, 7) = [d, o, 1]; triangles as
        coefficients w_uvr (3, k, 6) of (u + tol, v + tol, 1 + tol - u - v) det, w_dt (2, k, 7)
        of det and (t - t_min) det -> t (n,) float32 (inf: miss), the nearest triangle's index
        in the k (n,) int64 (-1: miss)."""
        import torch

        k = w_uvr.shape[1]
        det, t = torch.matmul(w_dt.reshape(2 * k, 7), f_do1.T).view(2, k, -1)       # (k, n) each
        u, v, rest = torch.matmul(w_uvr.reshape(3 * k, 6), f_dm.T).view(3, k, -1)
        slack = det.abs().sub_(self.det_min)                    # > 0 unless the ray is parallel
        inv = det / det.square().add_(1e-30)                   # 1 / det, finite even where det = 0
        for x in (u, v, rest, t):
            x.mul_(inv)
        worst = torch.minimum(torch.minimum(u, v), torch.minimum(rest, t))
        miss = torch.minimum(worst, slack).sub_(1e-20).clamp_(max=0.0).sign_()   # -1: a miss, 0: a hit
        t_key = t.sub_(miss, alpha=1e30)                        # t - t_min, and misses beyond _MISS
        t_best = t_key.amin(dim=0)
        hit = t_best < self._MISS
        # the lowest index among the ties (t_key < limit), as an exact float: index + k for the others
        limit = t_best * (1.0 + 1e-6) + self.tie_tol_m
        index = torch.arange(k, dtype=torch.float32, device=t_key.device).unsqueeze(1)
        key = torch.sub(t_key, limit).clamp_(max=0.0).sign_().add_(1.0).mul_(float(k)).add_(index)
        first = key.amin(dim=0).nan_to_num_(0.0).long().clamp_(0, k - 1)
        t_first = torch.gather(t_key, 0, first.unsqueeze(0)).squeeze(0) + self.t_min
        return torch.where(hit, t_first, torch.inf), torch.where(hit, first, -1)


class SceneRenderer:
    """Ray casts a `Scene` into colour, depth, label, instance and normal images.

    backend: "open3d" or "torch" (None: $GOVNESF_SIM_RAYCAST, else auto: open3d when installed,
    else torch); device: the torch backend's device (None: $GOVNESF_SIM_RAYCAST_DEVICE, else
    CUDA when available, else the CPU). See `raycast_backend`, `torch_device`.
    """

    def __init__(self, scene: Scene, backend: str | None = None, device: str | None = None) -> None:
        self.backend = raycast_backend(backend)
        self.scene = scene
        self._rc: Any
        if self.backend == "open3d":
            self._o3d = o3d = _open3d()
            self._rc = o3d.t.geometry.RaycastingScene()
            self._rc.add_triangles(
                o3d.core.Tensor(scene.vertices.astype(np.float32)),
                o3d.core.Tensor(scene.triangles.astype(np.uint32)))
        else:
            self._rc = TorchRaycaster(scene.vertices, scene.triangles, device)
        self._emissive = scene.face_texture == int(Texture.SKY)
        lights = scene.light_map.lights if scene.light_map is not None else [scene.light]
        self._light_table = {
            "position": np.stack([lt.position for lt in lights]).astype(np.float64),
            "colour": np.stack([lt.colour for lt in lights]).astype(np.float64),
            "ambient": np.array([lt.ambient for lt in lights]),
            "diffuse": np.array([lt.diffuse for lt in lights]),
            "falloff": np.array([lt.falloff_m for lt in lights])}

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cast world rays. origins, dirs: (N, 3) (dirs unit) -> t_hit (N,) metres (inf: miss),
        face id (N,) int64 (-1: miss)."""
        if isinstance(self._rc, TorchRaycaster):
            return self._rc.cast(origins, dirs)
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        ans = self._rc.cast_rays(self._o3d.core.Tensor(rays))
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
        """(N, 3) light multiplier at points p (N, 3) with camera-facing normals n (N, 3). A floor's
        points each take the light of the part of the floor they face (`Scene.light_map`, looked up
        5 cm off the surface towards the camera, so the two faces of a wall take their own sides')."""
        light_map = self.scene.light_map
        if light_map is None:
            light = self.scene.light
            position, colour = light.position[None, :], light.colour[None, :]
            ambient, diffuse, falloff = light.ambient, light.diffuse, light.falloff_m
        else:
            ids = light_map.lookup(p + 0.05 * n)
            table = self._light_table
            position, colour = table["position"][ids], table["colour"][ids]
            ambient, diffuse, falloff = table["ambient"][ids], table["diffuse"][ids], table["falloff"][ids]
        to_l = position - p
        d = np.linalg.norm(to_l, axis=1)
        lam = np.clip(np.sum(n * to_l, axis=1) / np.maximum(d, 1e-9), 0.0, 1.0)
        atten = 1.0 / (1.0 + (d / falloff) ** 2) * 2.0
        s = (ambient + diffuse * lam * atten)[:, None] * colour
        s[emissive] = 1.0
        return s
