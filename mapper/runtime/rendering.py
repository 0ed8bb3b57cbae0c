"""Renders of novel views from the window: :class:`Renderer` answers ``render`` requests.

A render marches each pixel's ray through the density of the window's volume (or of a volume over
the keyframes that best overlap the view, ``render_volume_views``) with the model's one marcher
(:func:`mapper.model.render.march_rays`) and blends each sample's appearance (rgb and the OV feature)
from the source views of its view group. Steps of a request (:meth:`Renderer.render`):

1. check the request (:func:`_render_request`);
2. under the runtime's lock: the prepared window (:meth:`~mapper.runtime.volume.WindowVolume.prepare`),
   the render volume (:func:`~mapper.runtime.prepared.render_prep`), the text embeddings and the
   occupancy grid (empty-space skipping);
3. the pixels (:meth:`Renderer._render_pixels`): pixels with a known surface (``surface_depth_m``)
   get one appearance evaluation at that point (:meth:`Renderer._render_surface`), the others march
   (:meth:`Renderer._march`); with skipping, pixels whose best two texts are close are marched again
   with every sample's appearance (:meth:`Renderer._refine`);
4. the frame (:func:`_frame`): rgb, z-depth, per-text cosine and label where opacity suffices.

See ``docs/concepts/rendering.md``.
"""

from __future__ import annotations

import numbers
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.model.field import GovNeSF
from mapper.model.ops.geometry import pixel_rays
from mapper.model.ops.rendering import Rays
from mapper.model.render import AppearanceFn, march_rays, occupancy_mask
from mapper.runtime.density import density, occupancy_grid
from mapper.runtime.loading import LoadedModel
from mapper.runtime.prepared import Prepared, render_prep
from mapper.runtime.text import text_embeddings
from mapper.runtime.views import all_views, chunk_slots, group_slots, source_views, view_groups
from mapper.runtime.volume import WindowVolume
from protocol.messages import RENDER_OUTPUTS  # what render can produce: the wire's names


@dataclass
class RenderFrame:
    """What :meth:`ModelRuntime.render` returns; outputs not requested are None."""

    rgb: np.ndarray | None = None  # (H, W, 3) uint8
    depth_m: np.ndarray | None = None  # (H, W) float32 z-depth (m), 0 where nothing is rendered
    label: np.ndarray | None = None  # (H, W) int32 index into texts, -1 where nothing is rendered
    score: np.ndarray | None = None  # (H, W, T) float32 cosine similarity per text
    opacity: np.ndarray | None = None  # (H, W) float32 accumulated opacity (always filled)
    timing_ms: dict[str, float] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    """Sample counts: ``samples`` (total), ``density_evals``, ``appearance_evals``, ``view_groups``;
    ``render_volume_views``: the keyframes of the render volume the density came from (0: the window's)."""


@dataclass(frozen=True)
class _RenderRequest:
    """A checked render request."""

    outputs: list[str]
    K: Tensor  # (4,) float64 [fx, fy, cx, cy] for width x height
    world_from_cam: Tensor  # (4, 4) float64
    width: int
    height: int
    texts: Sequence[str] | None
    semantic: bool  # label or score asked for
    surface: np.ndarray | None  # (H, W) float32 known surface z-depth, 0 = none


def _render_request(
    K: np.ndarray | Sequence[float],
    world_from_cam: np.ndarray,
    width: int,
    height: int,
    outputs: Sequence[str],
    texts: Sequence[str] | None,
    surface_depth_m: np.ndarray | None,
    volume_views: int | None,
    max_render_pixels: int,
) -> _RenderRequest:
    """The request of :meth:`Renderer.render`, checked; ``ValueError`` saying what is wrong."""
    outputs = list(outputs)
    bad = [o for o in outputs if o not in RENDER_OUTPUTS]
    if bad or not outputs or len(set(outputs)) != len(outputs):
        raise ValueError(
            f"outputs {outputs} must be a non-empty subset of {list(RENDER_OUTPUTS)} without repeats"
        )
    if not (1 <= int(width) <= 4096 and 1 <= int(height) <= 4096):
        raise ValueError(f"image size {width}x{height} out of range 1..4096")
    if int(width) * int(height) > max_render_pixels:
        raise ValueError(
            f"render size {width}x{height} = {int(width) * int(height)} pixels exceeds "
            f"model.max_render_pixels = {max_render_pixels}; ask for a smaller image "
            "(scale K with it)"
        )
    semantic = "label" in outputs or "score" in outputs
    if semantic and not texts:
        raise ValueError("texts are required when outputs include 'label' or 'score'")
    K_t = torch.tensor(np.array(K, dtype=np.float64)).reshape(-1)
    pose = torch.tensor(np.array(world_from_cam, dtype=np.float64))
    if (
        K_t.shape != (4,)
        or pose.shape != (4, 4)
        or not bool(torch.isfinite(K_t).all() & torch.isfinite(pose).all())
    ):
        raise ValueError(
            "K must be 4 finite numbers and world_from_cam a finite (4, 4), got shapes "
            f"{tuple(K_t.shape)} and {tuple(pose.shape)}"
        )
    if not bool((K_t[:2] > 0).all()):
        raise ValueError(f"K: fx, fy must be > 0, got {K_t[:2].tolist()}")
    surface_np = None
    if surface_depth_m is not None:
        surface_np = np.asarray(surface_depth_m, np.float32)
        if surface_np.shape != (int(height), int(width)):
            raise ValueError(
                f"surface_depth_m must have shape (H, W) = ({int(height)}, {int(width)}), "
                f"got {surface_np.shape}"
            )
        if not (np.isfinite(surface_np).all() and (surface_np >= 0).all()):
            raise ValueError("surface_depth_m must be finite and >= 0 (0 = no surface)")
    if volume_views is not None and not (
        isinstance(volume_views, numbers.Integral) and not isinstance(volume_views, bool)
        and 0 <= int(volume_views) <= 256
    ):
        raise ValueError(f"volume_views {volume_views!r} must be an integer in 0..256")
    return _RenderRequest(outputs, K_t, pose, int(width), int(height), texts, semantic, surface_np)


@dataclass
class _RayOutputs:
    """The per-ray outputs of one render, filled in place (R rays)."""

    rgb: Tensor  # (R, 3)
    ray_depth: Tensor  # (R,) distance along the ray
    opacity: Tensor  # (R,)
    covered: Tensor  # (R,) opacity of the samples some source view sees
    ov: Tensor | None  # (R, D) blended OV feature, None when no semantic output is asked for

    def store(self, rays: Tensor, part: tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor]) -> None:
        """Write :meth:`Renderer.render_rays`' outputs for the rays ``rays`` (r,)."""
        self.rgb[rays], self.ray_depth[rays], self.opacity[rays], self.covered[rays] = (
            part[0], part[1], part[2], part[4]
        )
        if self.ov is not None and part[3] is not None:
            self.ov[rays] = part[3]


def _frame(
    config: Any,  # ModelRuntimeConfig
    req: _RenderRequest,
    out: _RayOutputs,
    dirs: Tensor,  # (R, 3) unit ray directions
    axis: Tensor,  # (3,) the camera's optical axis (world)
    emb: Tensor | None,  # (T, D) unit text embeddings (semantic outputs)
    stats: dict[str, Any],
) -> RenderFrame:
    """The requested images from the per-ray outputs (nothing drawn below ``min_opacity``)."""
    hw = (req.height, req.width)
    drawn = out.opacity >= config.min_opacity
    frame = RenderFrame(opacity=out.opacity.reshape(hw).cpu().numpy(), stats=stats)
    if "rgb" in req.outputs:
        frame.rgb = (out.rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).reshape(*hw, 3).cpu().numpy()
    if "depth" in req.outputs:
        z = out.ray_depth * (dirs @ axis)  # ray distance -> z-depth along the optical axis
        frame.depth_m = (
            torch.where(drawn, z, torch.zeros_like(z)).reshape(hw).cpu().numpy().astype(np.float32)
        )
    if req.semantic:
        assert out.ov is not None and emb is not None
        cos = F.normalize(out.ov, dim=-1) @ emb.T  # (R, T)
        # Only where the source views saw enough of what the ray hit (a cosine of a few tiny
        # background contributions would be noise).
        has_feature = (out.covered >= config.min_opacity) & (out.ov.norm(dim=-1) > 1e-8)
        cos = torch.where(has_feature[:, None], cos, torch.zeros_like(cos))
        if "score" in req.outputs:
            frame.score = cos.reshape(*hw, -1).cpu().numpy().astype(np.float32)
        if "label" in req.outputs:
            lab = torch.where(
                has_feature, cos.argmax(dim=-1), torch.full_like(has_feature, -1, dtype=torch.long)
            )
            frame.label = lab.to(torch.int32).reshape(hw).cpu().numpy()
    return frame


class Renderer:
    """Renders novel views over the window (``loaded``'s model, ``volume``'s views).

    Every render takes ``volume.lock`` (the runtime's lock) for its whole computation.
    """

    def __init__(self, loaded: LoadedModel, volume: WindowVolume) -> None:
        self.loaded = loaded
        self.volume = volume

    @torch.no_grad()
    def render(
        self,
        K: np.ndarray | Sequence[float],  # (4,) [fx, fy, cx, cy] for width x height
        world_from_cam: np.ndarray,  # (4, 4) camera-to-world
        width: int,
        height: int,
        outputs: Sequence[str] = RENDER_OUTPUTS,
        texts: Sequence[str] | None = None,
        *,
        empty_space_skipping: bool | None = None,
        surface_depth_m: np.ndarray | None = None,  # (H, W) float32 z-depth (m), 0 = none
        volume_views: int | None = None,
    ) -> RenderFrame:
        """Render a novel view (:meth:`mapper.runtime.model_runtime.ModelRuntime.render`)."""
        cfg = self.loaded.config
        req = _render_request(K, world_from_cam, width, height, outputs, texts, surface_depth_m, volume_views,
                              cfg.max_render_pixels)
        skip = cfg.empty_space_skipping if empty_space_skipping is None else empty_space_skipping
        model = self.loaded.require_model()
        timing: dict[str, float] = {}
        t0 = time.perf_counter()
        with self.volume.lock:
            prep = self.volume.prepare()
            t_local = time.perf_counter()
            n_views = self.loaded.config.render_volume_views if volume_views is None else int(volume_views)
            prep = render_prep(self.loaded, model, prep, req.K.to(torch.float32),
                               req.world_from_cam.to(torch.float32), req.width, req.height, n_views)
            t1 = time.perf_counter()
            timing["prepare"] = (t_local - t0) * 1e3
            timing["render_volume"] = (t1 - t_local) * 1e3
            emb = text_embeddings(self.loaded, prep, req.texts or []) if req.semantic else None
            # the occupancy grid only serves marched rays (none when every pixel has a surface)
            marches = req.surface is None or bool((req.surface <= 0).any())
            occupancy = occupancy_grid(self.loaded, prep) if skip and marches else None
            t2 = time.perf_counter()
            timing["text_occupancy"] = (t2 - t1) * 1e3
            out, dirs, axis, stats = self._render_pixels(model, prep, req, emb, occupancy, skip, timing)
            timing["render"] = (time.perf_counter() - t2) * 1e3
        frame = _frame(self.loaded.config, req, out, dirs, axis, emb, stats)
        timing["total"] = (time.perf_counter() - t0) * 1e3
        frame.timing_ms = timing
        return frame

    def _render_pixels(
        self,
        model: GovNeSF,
        prep: Prepared,
        req: _RenderRequest,
        emb: Tensor | None,  # (T, D) unit text embeddings (semantic outputs)
        occupancy: Tensor | None,  # (X, Y, Z) bool, None = dense
        skip: bool,
        timing: dict[str, float],
    ) -> tuple[_RayOutputs, Tensor, Tensor, dict[str, Any]]:
        """Every pixel's ray: at its known surface, else marched (and refined); returns the
        outputs, the rays' directions (R, 3), the optical axis (3,) and the sample counts."""
        cfg = self.loaded.config
        device = self.loaded.device
        origins, dirs = pixel_rays(req.K, req.world_from_cam, req.width, req.height)
        origins = origins.reshape(-1, 3).to(device, torch.float32)
        dirs = dirs.reshape(-1, 3).to(device, torch.float32)
        axis = req.world_from_cam[:3, 2].to(device, torch.float32)
        allowed = prep.has_ov if req.semantic else torch.ones_like(prep.has_ov)
        appearance = req.semantic or "rgb" in req.outputs  # depth alone needs only the density
        n_rays = origins.shape[0]
        out = _RayOutputs(
            rgb=torch.zeros(n_rays, 3, device=device),
            ray_depth=torch.zeros(n_rays, device=device),
            opacity=torch.zeros(n_rays, device=device),
            covered=torch.zeros(n_rays, device=device),
            ov=(torch.zeros(n_rays, prep.ov.shape[1], device=device)
                if req.semantic and prep.ov is not None else None),
        )
        stats = {"samples": 0, "density_evals": 0, "appearance_evals": 0, "view_groups": 0,
                 "render_volume_views": prep.render_views}
        marched = torch.arange(n_rays, device=device)
        if req.surface is not None:
            z_surface = torch.from_numpy(req.surface.reshape(-1)).to(device)
            at_surface = (z_surface > 0).nonzero().squeeze(-1)
            marched = (z_surface <= 0).nonzero().squeeze(-1)
            t_surface = time.perf_counter()
            self._render_surface(
                model, prep, origins, dirs, axis, z_surface, at_surface, req.semantic, allowed, stats,
                appearance, out,
            )  # fmt: skip
            timing["surface"] = (time.perf_counter() - t_surface) * 1e3
        self._march(
            model, prep, origins, dirs, marched, occupancy, req.semantic, allowed, stats, appearance, out,
            appearance_groups=cfg.appearance_groups if skip else 0,
            stop_transmittance=cfg.stop_transmittance if skip else 0.0,
            batched=cfg.batched_view_groups and skip,
        )  # fmt: skip
        if skip and out.ov is not None and emb is not None and self._refines(emb.shape[0]):
            self._refine(model, prep, origins, dirs, marched, occupancy, req.semantic, allowed, stats,
                         appearance, out, emb)
        return out, dirs, axis, stats

    def _march(
        self,
        model: GovNeSF,
        prep: Prepared,
        origins: Tensor,  # (R, 3)
        dirs: Tensor,  # (R, 3) unit
        rays: Tensor,  # (S,) int64 the rays to march
        occupancy: Tensor | None,  # (X, Y, Z) bool, None = dense
        need_ov: bool,
        allowed: Tensor,  # (M,) bool views usable as sources
        stats: dict[str, int],
        appearance: bool,
        out: _RayOutputs,
        *,
        appearance_groups: int,
        stop_transmittance: float,
        batched: bool,
    ) -> None:
        """March ``rays`` in chunks of ``chunk_rays`` (:meth:`render_rays`) into ``out``."""
        chunk = self.loaded.config.chunk_rays
        for i in range(0, rays.numel(), chunk):
            sub = rays[i : i + chunk]
            part = self.render_rays(
                model, prep, origins[sub], dirs[sub], occupancy, need_ov, allowed, stats, appearance,
                appearance_groups=appearance_groups, stop_transmittance=stop_transmittance, batched=batched,
            )  # fmt: skip
            out.store(sub, part)

    def _refine(
        self,
        model: GovNeSF,
        prep: Prepared,
        origins: Tensor,  # (R, 3)
        dirs: Tensor,  # (R, 3) unit
        marched: Tensor,  # (S,) int64 the marched rays
        occupancy: Tensor | None,  # (X, Y, Z) bool
        need_ov: bool,
        allowed: Tensor,  # (M,) bool views usable as sources
        stats: dict[str, Any],
        appearance: bool,
        out: _RayOutputs,
        emb: Tensor,  # (T, D) unit text embeddings
    ) -> None:
        """Coarse-to-fine labels: marched pixels whose best two texts are closer than
        ``refine_margin`` are marched again with every sample's appearance (their weight groups
        could have swapped the two). Surface pixels had one exact evaluation at their point:
        nothing to refine; nor have rays below ``min_opacity``, which no refinement can label
        (covered <= opacity, and the opacity depends on the density only)."""
        cfg = self.loaded.config
        assert out.ov is not None
        top2 = (F.normalize(out.ov[marched], dim=-1) @ emb.T).topk(2, dim=-1).values
        close = top2[:, 0] - top2[:, 1] < cfg.refine_margin
        redo = marched[close & (out.opacity[marched] >= cfg.min_opacity)]
        stats["refined_rays"] = int(redo.numel())
        again = {"samples": 0, "density_evals": 0, "appearance_evals": 0, "view_groups": 0}
        self._march(
            model, prep, origins, dirs, redo, occupancy, need_ov, allowed, again, appearance, out,
            appearance_groups=0, stop_transmittance=cfg.stop_transmittance, batched=cfg.batched_view_groups,
        )  # fmt: skip
        for key in ("density_evals", "appearance_evals", "view_groups"):
            stats[key] += again[key]  # "samples" stays the image's

    def _render_surface(
        self,
        model: GovNeSF,
        prep: Prepared,
        origins: Tensor,  # (R, 3)
        dirs: Tensor,  # (R, 3) unit
        axis: Tensor,  # (3,) the camera's optical axis (world)
        z_surface: Tensor,  # (R,) known surface z-depth, 0 = none
        rays: Tensor,  # (S,) int64 the rays with a surface
        need_ov: bool,
        allowed: Tensor,  # (M,) bool views usable as sources
        stats: dict[str, int],
        appearance: bool,
        out: _RayOutputs,
    ) -> None:
        """Render ``rays`` at their known surface: the point at z-depth ``z_surface`` along each ray
        gets one appearance evaluation (the same view-grouped FusionNet blend as a marched sample);
        ray distance = z / (d . axis), opacity 1, covered = whether an allowed view sees the point.
        Writes into ``out`` in place."""
        rgb, ray_depth, opacity, covered, ov = out.rgb, out.ray_depth, out.opacity, out.covered, out.ov
        stats["surface_rays"] = int(rays.numel())
        if rays.numel() == 0:
            return
        t = z_surface[rays] / (dirs[rays] @ axis).clamp_min(1e-6)
        ray_depth[rays] = t
        opacity[rays] = 1.0
        if not appearance:
            return
        fn = self._appearance(model, prep, need_ov, allowed, stats, self.loaded.config.batched_view_groups)
        for i in range(0, rays.numel(), self.loaded.config.chunk_rays):
            sub = rays[i : i + self.loaded.config.chunk_rays]
            points = origins[sub] + t[i : i + self.loaded.config.chunk_rays, None] * dirs[sub]
            _, features = density(model, prep, points)  # the marcher's features, the same way
            stats["density_evals"] += int(sub.numel())
            rgb_k, ov_k, valid_k = fn(points, dirs[sub], features)
            rgb[sub] = rgb_k.to(rgb.dtype)
            covered[sub] = valid_k.to(covered.dtype)
            if ov is not None and ov_k.shape[-1] == ov.shape[-1]:
                ov[sub] = ov_k.to(ov.dtype)
            stats["appearance_evals"] += int(sub.numel())

    def _refines(self, n_texts: int) -> bool:
        """Whether a skipping render re-renders its ambiguous pixels (``refine_margin``)."""
        cfg = self.loaded.config
        samples = self.loaded.samples_per_ray
        return cfg.refine_margin > 0 and n_texts > 1 and 0 < cfg.appearance_groups < samples

    def render_rays(
        self,
        model: GovNeSF,
        prep: Prepared,
        origins: Tensor,  # (R, 3)
        dirs: Tensor,  # (R, 3) unit
        occupancy: Tensor | None,  # (X, Y, Z) bool, None = dense
        need_ov: bool,
        allowed: Tensor,  # (M,) bool views usable as sources
        stats: dict[str, int],
        appearance: bool = True,
        *,
        appearance_groups: int = 0,
        stop_transmittance: float = 0.0,
        batched: bool = False,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor]:
        """rgb (R, 3), ray distance (R,), opacity (R,), ov (R, D) | None and covered (R,) (the
        opacity of samples some source view sees) for one chunk of rays.

        The model's one marcher (``mapper.model.render.march_rays``) with the runtime's density
        (view-support mask), its view-grouped appearance, ``samples_per_ray`` bins on
        ``[near, far]`` clipped to the volume box (density is exactly 0 outside it; rays that miss
        the box render nothing). Dense mode evaluates every sample; skipping evaluates the density
        only in occupied voxels and the appearance only where the weight reaches ``min_weight``;
        ``stop_transmittance`` > 0 ends a ray's density evaluation once its transmittance fell below
        it, and ``appearance_groups`` > 0 evaluates the appearance once per weight group (both
        ``march_rays`` options; 0 = off, as in dense mode).
        ``appearance=False`` (a depth-only render) skips the appearance pass: rgb and covered are 0;
        depth and opacity are exactly those of a full render (they depend on the density only).
        """
        cfg = self.loaded.config
        b = prep.bounds
        out = march_rays(
            Rays(origins, dirs),
            lambda points: density(model, prep, points),
            self._appearance(model, prep, need_ov, allowed, stats, batched) if appearance else None,
            n_samples=self.loaded.samples_per_ray,
            near_m=cfg.near_m,
            far_m=cfg.far_m,
            box=(origins.new_tensor(b.origin_m), origins.new_tensor(b.max_corner_m)),
            skip_missed=True,
            sample_mask=occupancy_mask(occupancy, b) if occupancy is not None else None,
            min_weight=cfg.min_weight if occupancy is not None else 0.0,  # pruning only with skipping
            stop_transmittance=stop_transmittance,
            termination_block=cfg.termination_block,
            appearance_groups=appearance_groups,
        )
        stats["samples"] += out.t.numel()
        stats["density_evals"] += out.density_evals
        stats["appearance_evals"] += out.appearance_evals
        rgb = out.rgb if out.rgb is not None else origins.new_zeros(origins.shape[0], 3)
        ov = out.ov if (need_ov and prep.ov is not None and out.ov is not None) else None
        covered = (out.weights * out.valid.to(out.weights.dtype)).sum(dim=-1)
        return rgb, out.depth_m, out.opacity, ov, covered

    def _appearance(
        self,
        model: GovNeSF,
        prep: Prepared,
        need_ov: bool,
        allowed: Tensor,
        stats: dict[str, int],
        batched: bool = False,
    ) -> AppearanceFn:
        """The marcher's appearance: each sample with the source views of its view group
        (:func:`~mapper.runtime.views.view_groups`), in chunks of ``chunk_points``; samples no allowed
        view sees get 0.
        ``batched``: every view group in one network pass (``GovNeSF.sample_views_indexed``), else
        one pass per group (the reference)."""
        d_ov = prep.ov.shape[1] if (need_ov and prep.ov is not None) else 0
        chunk = self.loaded.config.chunk_points

        def appearance(points: Tensor, view_dirs: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
            n = points.shape[0]
            rgb = points.new_zeros(n, 3)
            ov = points.new_zeros(n, d_ov)
            valid = torch.zeros(n, dtype=torch.bool, device=points.device)
            groups = view_groups(self.loaded, prep, points, allowed)
            stats["view_groups"] += len(groups)
            if batched and groups:  # one network pass over every view group
                members, view_idx, slots = group_slots(groups)
                views = all_views(self.loaded, prep, need_ov=False, use_depth=False)
                for j in range(0, members.numel(), chunk):
                    sel = slice(j, j + chunk)
                    sub = members[sel]
                    chunk_views, chunk_mask = chunk_slots(view_idx, slots, sel)
                    samples = model.sample_views_indexed(views, chunk_views, chunk_mask, points[sub], False)
                    ov_maps = prep.ov_maps(chunk_views, self.loaded.image_wh) if d_ov else None
                    rgb_k, ov_k, valid_k = model.fuse_samples(
                        samples, v[sub], view_dirs[sub], ov_maps=ov_maps
                    )
                    rgb[sub], valid[sub] = rgb_k, valid_k
                    if d_ov:
                        ov[sub] = ov_k
                return rgb, ov, valid
            for local, view_idx in groups:
                # OV blended straight from the window's maps (never sampled or copied per group)
                views = source_views(self.loaded, prep, view_idx, need_ov=False, use_depth=False)
                ov_maps = prep.ov_maps(view_idx, self.loaded.image_wh) if d_ov else None
                for j in range(0, local.numel(), chunk):
                    sub = local[j : j + chunk]
                    rgb_k, ov_k, valid_k = model.appearance(
                        views, v[sub], points[sub], view_dirs[sub], False, ov_maps=ov_maps
                    )
                    rgb[sub], valid[sub] = rgb_k, valid_k
                    if d_ov:
                        ov[sub] = ov_k
            return rgb, ov, valid

        return appearance
