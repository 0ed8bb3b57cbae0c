"""Training loop for GOV-NeSF (``govnesf train``), single process or data-parallel (torchrun).

One global step = ``batch_views`` target views (each with its own N source views, volume and
``rays_per_view`` rays). Under torch.distributed (``torchrun --nproc_per_node P``; gloo on CPU,
NCCL on GPU) rank r computes items r, r + P, ... of the global batch; after backward the
gradients are all-reduced (summed and divided by P), so every rank takes the same optimiser step
and P processes reproduce a 1-process run over the same global batch (up to float summation
order). Only rank 0 validates and writes files.

Optimisation follows the official code: AdamW (lr 1e-3, weight decay 1e-4), gradient clipping
at norm 35, cosine decay (after a short linear warm-up), loss = colour MSE + alpha * (1 - cos)
with the OV term detached from the density (``govnesf_loss`` on ``render_rays`` output).

Checkpoints (``mapper.model.checkpoint``; safetensors + JSON, atomic): ``OUT/last`` every
``checkpoint_every`` steps with the optimiser state (``--resume OUT/last.json``), and the
weights-only export (``export``, e.g. ``checkpoints/cpu-small``) at every validation and at the
end. Sampling is a pure function of (seed, step, item) and the learning rate of the step, so a
resumed run is the same as an uninterrupted one.

Validation (rank 0, every ``val_every`` steps and at the end): render held-out novel views of the
validation scenes (every ``val_stride_px``-th pixel), label every pixel by the class whose text
embedding is most cosine-similar to the rendered OV feature, and report 2D mIoU over the 20
ScanNet classes present (averaged over scenes) and PSNR of the rendered colour.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist

from govnesf._compat import tomllib
from mapper.model.checkpoint import (
    config_from_dict,
    load_metadata,
    load_training_state,
    load_weights_except,
    save_checkpoint,
)
from mapper.model.config import ModelConfig, get_preset
from mapper.model.field import GovNeSF, SourceViews, render_rays
from mapper.model.losses import distortion_loss, govnesf_loss, ov_cosine_loss
from mapper.model.ops.geometry import pixel_rays
from mapper.model.ops.rendering import Rays
from mapper.model.supervision import (
    ray_depth_loss,
    surface_loss,
    surface_points,
    visibility_loss,
    visibility_targets,
)
from mapper.training.data import (
    POINT_OV_TARGETS,
    RaySampler,
    Scene,
    TrainSample,
    ValidationView,
    drop_frames,
    find_scenes,
    held_out_positions,
    load_scene,
    source_batch,
    validation_views,
)
from mapper.training.metrics import (
    NUM_SCANNET_CLASSES,
    average_over_scenes,
    predict_labels,
    scores_from_labels,
)

__all__ = ["TrainConfig", "learning_rate", "load_train_config", "train", "validate"]


@dataclass
class TrainConfig:
    """Everything a training run needs (``[train]`` table of ``launch/train_*.toml``)."""

    preset: str = "cpu-small"
    """Model preset (``mapper.model.config.PRESETS``); ``fusion.ov_dim`` follows the data."""
    mode: str = "blend"
    """``blend`` (GOV-NeSF) or ``distill`` (the Distill baseline)."""
    distill_hidden_dim: int = 0
    """Distill head width (``FusionConfig.distill_hidden_dim``; 0 = the preset's, ``2 * hidden_dim``)."""
    distill_layers: int = 0
    """Distill head hidden layers (``FusionConfig.distill_layers``; 0 = the preset's, 1)."""
    range_encoding: bool = False
    """Give the blend each view's camera-to-point distance (``FusionConfig.range_encoding``).
    With ``init_weights`` from a checkpoint without it, the new layer starts at zero (the
    checkpoint's blend) and everything else loads as usual."""
    train_dir: str = "data/train"
    val_dir: str = "data/val"
    out_dir: str = "out/train/cpu-small"
    """Training checkpoints (``last``) and the log (``log.jsonl``)."""
    export: str = ""
    """Weights-only checkpoint written at every validation and at the end (e.g. checkpoints/cpu-small)."""
    export_half: bool = True
    """Export float16 weights (the validation metrics are checked with them)."""
    init_weights: str = ""
    """Fine-tune: start from this checkpoint's weights (``NAME`` / ``NAME.json`` of an export or a
    training checkpoint, e.g. ``checkpoints/cpu-small``) with a fresh optimiser and schedule
    (step 0). Its model config and mode must be the run's (except ``range_encoding``, see there).
    Empty = random init. Ignored on resume (the training checkpoint has the weights)."""
    max_steps: int = 2000
    """Length of the run (the cosine schedule ends here)."""
    batch_views: int = 2
    """Target views per global step (split over ranks; must be a multiple of the world size)."""
    rays_per_view: int = 512
    num_sources: int = 0
    """Source views per target (0: the preset's ``num_source_views``)."""
    pool_factor: float = 1.5
    """Sources drawn from the ceil(N * pool_factor) best-overlapping frames (augmentation)."""
    volume_sources: int = 0
    """> the number of sources: each example's cost volume (and its bounds) is built over N
    frames, N drawn uniformly from [sources, volume_sources]: the blended sources plus the next
    best-overlapping frames, as the node builds one volume over its whole window (30 keyframes)
    while each point blends a few views. The model's density blurs on volumes over more views
    than it was trained on (docs/concepts/rendering.md). 0: the volume is over the blended sources."""
    frustum_bounds_prob: float = 0.0
    """Fraction of examples whose cost-volume bounds come from the source frusta (up to
    ``frustum_range_m``) instead of their depth points, as the node does for frames without depth.
    Without it the model learns that surfaces lie ~``margin_m`` inside the volume's faces and
    renders depth at the far face when the bounds are frusta (docs/how-to/train.md)."""
    frustum_range_m: float = 4.0
    """Frustum depth of that augmentation (the node's ``model.max_range_m``)."""
    n_samples: int = 0
    """Samples per ray (0: the preset's)."""
    lr: float = 1e-3
    weight_decay: float = 1e-4
    grad_clip: float = 35.0
    warmup_steps: int = 50
    min_lr_ratio: float = 0.02
    ov_weight: float = 1.0
    """alpha of the loss."""
    distortion_weight: float = 0.0
    """Weight of mip-NeRF 360's distortion loss on the rendering weights (0 = off, the paper's
    loss). Pushes the density towards sharp surfaces (an experiment; docs/how-to/train.md)."""
    depth_weight: float = 0.0
    """Geometry supervision: weight of the relative L1 between each ray's rendered distance and the
    true one from the target's depth (``mapper.model.supervision.ray_depth_loss``; 0 = off, the
    paper's depth-free loss). Inference stays RGB-only."""
    surface_weight: float = 0.0
    """Weight of the line-of-sight loss: no rendering weight in front of the true surface, the
    weight mass within ``surface_band_m`` of it (``supervision.surface_loss``; 0 = off)."""
    surface_band_m: float = 0.15
    """Half-width of the surface band (metres; widened to the sample spacing)."""
    point_ov_weight: float = 0.0
    """Weight of the point-level OV loss: ``1 - cos`` of the blended OV feature AT the true surface
    point of each target ray (the 3D task's query) against the target's OV (0 = off)."""
    point_ov_target: str = "frame"
    """What that loss compares with: "frame", the target frame's own OV feature at the ray's pixel
    (one view's 2D prediction, whose errors depend on the view); "visible_mean", the mean of the
    unit OV features of every frame of the scene whose depth says it sees the point
    (``mapper.training.data.visible_mean_features``, ``visibility_rel_tol``; training depth only)."""
    visibility_weight: float = 0.0
    """Weight of the visibility loss on the OV blending weights at those surface points: ``-log``
    of the weight mass on the source views whose depth says they see the point (blend mode only;
    ``supervision.visibility_loss``; 0 = off)."""
    visibility_rel_tol: float = 0.05
    """A source view sees a surface point when its depth there agrees within 5 cm + this x depth."""
    photometric_prob: float = 0.0
    """Fraction of examples whose colours get a random camera response (gamma, white balance,
    offset, per-view exposure; ``mapper.training.data.photometric_jitter``), so real cameras are not
    a new world (0 = off)."""
    photometric_strength: float = 0.2
    """Size of that jitter (0 <= s < 1)."""
    sensor_prob: float = 0.0
    """Fraction of examples whose SOURCE images get a robot camera's effects: motion blur, noise,
    a JPEG round trip (``mapper.training.augment.sensor_effects``; the target's colour stays clean).
    0 = off."""
    sensor_strength: float = 1.0
    """Size of those effects (0..4; 1: blur up to 8 px, noise std up to 0.03, JPEG quality 60-95)."""
    pose_noise_prob: float = 0.0
    """Fraction of examples whose source poses get odometry-like error (the target rays stay true;
    ``mapper.training.augment.perturb_poses``). 0 = off."""
    pose_noise_m: float = 0.02
    """Largest std per axis of that translation error (each example draws a scale in [0, 1])."""
    pose_noise_deg: float = 1.0
    """Largest std per axis of that rotation error (degrees)."""
    ov_noise_prob: float = 0.0
    """Fraction of examples whose SOURCE views' OV maps get a 2D model's worse days: noise and
    regions confused with others (``mapper.training.augment.ov_noise``; the target's OV supervision
    stays). 0 = off."""
    ov_noise_strength: float = 1.0
    """Size of that noise (0..4; 1: std up to half the cells' mean norm)."""
    world_scale_prob: float = 0.0
    """Fraction of examples whose world is scaled (camera centres, depths, the target's rays, the
    volume bounds; ``mapper.training.data.scale_world``) by a factor drawn log-uniformly in
    [1 / ``world_scale_max``, ``world_scale_max``]: rooms of other sizes behind the same images, so
    the depth the model renders follows the cost volume rather than the training rooms' sizes.
    0 = off."""
    world_scale_max: float = 1.5
    """Largest factor of that scaling (1..4)."""
    depth_guided_masking: bool = False
    """Depth Guided Masking in every example (the rays' samples and the surface points)."""
    depth_guided_masking_prob: float = 0.0
    """Fraction of the examples (drawn per example from its seed) that use Depth Guided Masking
    when ``depth_guided_masking`` is off, so the blend also learns the view sets a robot with depth
    gives it (the depth test has already removed the occluded views). 0 = never."""
    clip_to_volume: bool = True
    """Spend the ray samples inside the volume bounds (density is 0 outside; ``render_rays``)."""
    seed: int = 0
    threads: int = 2
    """torch threads per process (0: leave torch's default)."""
    log_every: int = 10
    checkpoint_every: int = 100
    val_every: int = 250
    val_views_per_scene: int = 3
    val_stride_px: int = 4
    max_train_scenes: int = 0
    """Use only the first N training scenes (0: all)."""
    extra_train_dirs: list[str] = field(default_factory=list)
    """Scene folders or roots of scenes without OV maps (real RGB-D sequences from ``govnesf
    import``, e.g. ``scripts/make_real_data.sh data`` -> ``data/real``) for colour and geometry:
    loaded with ``load_scene(require_ov=False)``, resized to the training scenes' image size, and
    drawn with probability ``extra_train_weight``. Every folder must exist; they are loaded only
    when ``extra_train_weight > 0``."""
    extra_train_weight: float = 0.0
    """Probability that an example comes from ``extra_train_dirs`` (0 = never: the run is
    bit-identical to one without them). Those examples train colour, depth, surface and visibility;
    their OV terms get weight 0 (and read 0 in the logged means)."""
    extra_holdout_every: int = 0
    """Drop from every ``extra_train_dirs`` scene the frames within ``extra_holdout_radius``
    positions of every ``extra_holdout_every``-th frame (0 = keep all): the held-out poses that
    ``benchmarks/studies/real_sequence.py --every N`` renders (default 10) never train."""
    extra_holdout_radius: int = 2
    """Neighbours on each side of a held-out frame that are dropped with it."""
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        checks = [
            (self.mode in ("blend", "distill"), "mode", "'blend' or 'distill'"),
            (self.distill_hidden_dim >= 0, "distill_hidden_dim", ">= 0"),
            (self.distill_layers >= 0, "distill_layers", ">= 0"),
            (self.max_steps >= 1, "max_steps", ">= 1"),
            (self.batch_views >= 1, "batch_views", ">= 1"),
            (self.rays_per_view >= 1, "rays_per_view", ">= 1"),
            (self.num_sources >= 0, "num_sources", ">= 0"),
            (self.pool_factor >= 1.0, "pool_factor", ">= 1"),
            (self.volume_sources >= 0, "volume_sources", ">= 0"),
            (0.0 <= self.frustum_bounds_prob <= 1.0, "frustum_bounds_prob", "in [0, 1]"),
            (self.frustum_range_m > 0, "frustum_range_m", "> 0"),
            (self.n_samples >= 0, "n_samples", ">= 0"),
            (self.lr > 0, "lr", "> 0"),
            (self.weight_decay >= 0, "weight_decay", ">= 0"),
            (self.grad_clip > 0, "grad_clip", "> 0"),
            (self.warmup_steps >= 0, "warmup_steps", ">= 0"),
            (0.0 <= self.min_lr_ratio <= 1.0, "min_lr_ratio", "in [0, 1]"),
            (self.ov_weight >= 0, "ov_weight", ">= 0"),
            (self.distortion_weight >= 0, "distortion_weight", ">= 0"),
            (self.depth_weight >= 0, "depth_weight", ">= 0"),
            (self.surface_weight >= 0, "surface_weight", ">= 0"),
            (self.surface_band_m > 0, "surface_band_m", "> 0"),
            (self.point_ov_weight >= 0, "point_ov_weight", ">= 0"),
            (self.visibility_weight >= 0, "visibility_weight", ">= 0"),
            (self.visibility_rel_tol >= 0, "visibility_rel_tol", ">= 0"),
            (self.point_ov_target in POINT_OV_TARGETS, "point_ov_target", f"one of {POINT_OV_TARGETS}"),
            (0.0 <= self.photometric_prob <= 1.0, "photometric_prob", "in [0, 1]"),
            (0.0 <= self.depth_guided_masking_prob <= 1.0, "depth_guided_masking_prob", "in [0, 1]"),
            (0.0 <= self.photometric_strength < 1.0, "photometric_strength", "in [0, 1)"),
            (0.0 <= self.sensor_prob <= 1.0, "sensor_prob", "in [0, 1]"),
            (0.0 <= self.sensor_strength <= 4.0, "sensor_strength", "in [0, 4]"),
            (0.0 <= self.pose_noise_prob <= 1.0, "pose_noise_prob", "in [0, 1]"),
            (0.0 <= self.ov_noise_prob <= 1.0, "ov_noise_prob", "in [0, 1]"),
            (0.0 <= self.world_scale_prob <= 1.0, "world_scale_prob", "in [0, 1]"),
            (1.0 <= self.world_scale_max <= 4.0, "world_scale_max", "in [1, 4]"),
            (0.0 <= self.ov_noise_strength <= 4.0, "ov_noise_strength", "in [0, 4]"),
            (self.pose_noise_m >= 0, "pose_noise_m", ">= 0"),
            (self.pose_noise_deg >= 0, "pose_noise_deg", ">= 0"),
            (self.log_every >= 1, "log_every", ">= 1"),
            (self.checkpoint_every >= 1, "checkpoint_every", ">= 1"),
            (self.val_every >= 1, "val_every", ">= 1"),
            (self.val_views_per_scene >= 1, "val_views_per_scene", ">= 1"),
            (self.val_stride_px >= 1, "val_stride_px", ">= 1"),
            (self.threads >= 0, "threads", ">= 0"),
            (self.max_train_scenes >= 0, "max_train_scenes", ">= 0"),
            (
                isinstance(self.extra_train_dirs, list)
                and all(isinstance(d, str) and d for d in self.extra_train_dirs),
                "extra_train_dirs",
                "a list of folder paths",
            ),
            (0.0 <= self.extra_train_weight <= 1.0, "extra_train_weight", "in [0, 1]"),
            (self.extra_holdout_every >= 0, "extra_holdout_every", ">= 0"),
            (self.extra_holdout_radius >= 0, "extra_holdout_radius", ">= 0"),
            (
                self.extra_holdout_every == 0 or 2 * self.extra_holdout_radius + 1 < self.extra_holdout_every,
                "extra_holdout_radius",
                "< (extra_holdout_every - 1) / 2, so that some frames stay",
            ),
            (
                self.extra_train_weight == 0 or bool(self.extra_train_dirs),
                "extra_train_weight",
                "0 when extra_train_dirs is empty",
            ),
        ]
        for ok, name, allowed in checks:
            if not ok:
                raise ValueError(
                    f"train config: {name} = {getattr(self, name)!r} out of range: must be {allowed}"
                )


def load_train_config(path: str | Path, **overrides: Any) -> TrainConfig:
    """Read the ``[train]`` table of a TOML file; keyword overrides win (None values are ignored)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"training config {path} not found")
    with path.open("rb") as f:
        data = tomllib.load(f)
    table = data.get("train", data)
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = set(table) - known
    if unknown:
        raise ValueError(
            f"{path}: unknown [train] keys {sorted(unknown)}; known: {sorted(known - {'extra'})}"
        )
    table = {**table, **{k: v for k, v in overrides.items() if v is not None}}
    return TrainConfig(**table)


def learning_rate(cfg: TrainConfig, step: int) -> float:
    """Learning rate of step ``step`` (0-based): linear warm-up, then cosine decay to min_lr_ratio * lr."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    span = max(1, cfg.max_steps - cfg.warmup_steps)
    progress = min(1.0, (step - cfg.warmup_steps) / span)
    return cfg.lr * (cfg.min_lr_ratio + (1.0 - cfg.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress)))


# ---- distributed helpers ---------------------------------------------------------------------------
@dataclass
class _Dist:
    rank: int
    world: int
    device: torch.device
    initialised_here: bool


def _init_distributed() -> _Dist:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", str(rank)))
    cuda = torch.cuda.is_available()
    device = torch.device(f"cuda:{local}" if cuda else "cpu")
    if cuda:
        torch.cuda.set_device(device)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if cuda else "gloo")
        return _Dist(rank, world, device, True)
    if dist.is_initialized():
        return _Dist(dist.get_rank(), dist.get_world_size(), device, False)
    return _Dist(0, 1, device, False)


def _average_gradients(model: torch.nn.Module, world: int) -> None:
    """Sum gradients over ranks and divide by the world size (missing grads count as 0)."""
    if world == 1:
        return
    grads = []
    for p in model.parameters():
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        grads.append(p.grad)
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat, op=dist.ReduceOp.SUM)
    flat /= world
    offset = 0
    for g in grads:
        n = g.numel()
        g.copy_(flat[offset : offset + n].view_as(g))
        offset += n


def _git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            cwd=Path(__file__).resolve().parent,
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


# ---- one step ------------------------------------------------------------------------------------
LOSS_TERMS = ("loss", "color", "ov", "depth", "surface", "point_ov", "visibility")
"""The per-step loss terms ``train_step`` reports (the total first; a term switched off reads 0)."""


def _loss_for_sample(
    model: GovNeSF, sampler: RaySampler, cfg: TrainConfig, step: int, item: int, device: torch.device
) -> tuple[torch.Tensor, dict[str, float]]:
    """The total loss of one example (to back-propagate) and its detached terms (``LOSS_TERMS``)."""
    s = sampler.sample(step, item).to(device)
    src = s.sources
    dgm = uses_depth_guided_masking(cfg, s.seed)
    views = model.make_source_views(src.rgb, src.ov, src.K, src.world_from_cam, src.depth_m)
    volume = model.build_volume(views, src.bounds)
    if s.blend_sources:  # the volume is over every source, the blend over the first ones
        views = first_views(views, s.blend_sources)
    gen = torch.Generator(device="cpu")  # the jitter is drawn on the CPU (the same samples on any device)
    gen.manual_seed(s.seed)
    out = render_rays(
        model,
        views,
        volume,
        src.bounds,
        Rays(s.origins, s.directions),
        n_samples=cfg.n_samples or None,
        stratified=True,
        generator=gen,
        depth_guided_masking=dgm,
        clip_to_volume=cfg.clip_to_volume,
    )
    # An example without OV supervision (a real RGB-D scene, s.has_ov False) keeps its OV terms in
    # the graph with weight 0 (zero gradients, not missing ones) and reports them as 0.
    ov_weight = cfg.ov_weight if s.has_ov else 0.0
    loss = govnesf_loss(out.rgb, s.target_rgb, out.ov, s.target_ov, ov_weight=ov_weight)
    total = loss.total
    terms = {"color": float(loss.color.detach()), "ov": float(loss.ov.detach()) if s.has_ov else 0.0}
    if cfg.distortion_weight > 0:
        total = total + cfg.distortion_weight * distortion_loss(out.weights, out.t)
    target_t = s.target_t if s.target_t is not None and bool((s.target_t > 0).any()) else None
    if target_t is not None and (cfg.depth_weight > 0 or cfg.surface_weight > 0):
        depth = ray_depth_loss(out.depth_m, target_t)
        surface = surface_loss(out.weights, out.t, target_t, band_m=cfg.surface_band_m)
        total = total + cfg.depth_weight * depth + cfg.surface_weight * surface
        terms.update(depth=float(depth.detach()), surface=float(surface.detach()))
    if target_t is not None and (cfg.point_ov_weight > 0 or cfg.visibility_weight > 0):
        point_terms = _surface_point_losses(model, views, volume, s, cfg, dgm)
        point_ov_weight = cfg.point_ov_weight if s.has_ov else 0.0
        for name, weight in (("point_ov", point_ov_weight), ("visibility", cfg.visibility_weight)):
            if name in point_terms:
                total = total + weight * point_terms[name]
                terms[name] = float(point_terms[name].detach()) if weight > 0 else 0.0
    terms["loss"] = float(total.detach())
    return total, terms


def first_views(views: SourceViews, n: int) -> SourceViews:
    """The first ``n`` of ``views`` (every map and camera sliced alike)."""
    return SourceViews(views.rgb[:n], views.features[:n], views.ov[:n], views.K[:n], views.world_from_cam[:n],
                       None if views.depth_m is None else views.depth_m[:n])


def uses_depth_guided_masking(cfg: TrainConfig, seed: int) -> bool:
    """Whether the example of this seed uses Depth Guided Masking (``depth_guided_masking`` or a
    draw of probability ``depth_guided_masking_prob``, the same on every rank and every rerun)."""
    if cfg.depth_guided_masking:
        return True
    if cfg.depth_guided_masking_prob <= 0:
        return False
    draw = np.random.default_rng([seed, 0x6D61736B]).random()  # its own stream ("mask")
    return bool(draw < cfg.depth_guided_masking_prob)


def _surface_point_losses(
    model: GovNeSF, views: SourceViews, volume: torch.Tensor, s: TrainSample, cfg: TrainConfig, dgm: bool
) -> dict[str, torch.Tensor]:
    """Point-level OV and visibility losses at the true surface points of the target rays."""
    assert s.target_t is not None
    keep = s.target_t > 0
    src = s.sources
    points = surface_points(s.origins[keep], s.directions[keep], s.target_t[keep])  # (P, 3)
    po = model.query_points(views, volume, src.bounds, points, depth_guided_masking=dgm)
    out: dict[str, torch.Tensor] = {}
    if cfg.point_ov_weight > 0:
        target = s.target_ov if s.target_ov_point is None else s.target_ov_point
        out["point_ov"] = ov_cosine_loss(po.ov, target[keep], po.valid)
    if cfg.visibility_weight > 0 and po.ov_weights is not None:
        w, h = src.rgb.shape[-1], src.rgb.shape[-2]
        n = len(views)  # the blended sources (the first ones of src)
        visible, known = visibility_targets(
            points, src.K[:n], src.world_from_cam[:n], src.depth_m[:n], (w, h), rel_tol=cfg.visibility_rel_tol
        )
        out["visibility"] = visibility_loss(po.ov_weights, visible, known)
    return out


def train_step(
    model: GovNeSF,
    optimizer: torch.optim.Optimizer,
    sampler: RaySampler,
    cfg: TrainConfig,
    step: int,
    rank: int,
    world: int,
    device: torch.device,
) -> dict[str, float]:
    """One global step; returns the global-batch mean losses and the step's lr / grad norm."""
    if cfg.batch_views % world:
        raise ValueError(f"batch_views {cfg.batch_views} must be a multiple of the world size {world}")
    model.train()
    optimizer.zero_grad(set_to_none=True)
    items = list(range(rank, cfg.batch_views, world))
    stats = torch.zeros(len(LOSS_TERMS), dtype=torch.float64)
    for item in items:
        total, terms = _loss_for_sample(model, sampler, cfg, step, item, device)
        (total / len(items)).backward()
        stats += torch.tensor([terms.get(k, 0.0) for k in LOSS_TERMS], dtype=torch.float64)
    _average_gradients(model, world)
    if world > 1:
        dist.all_reduce(stats, op=dist.ReduceOp.SUM)
    stats /= cfg.batch_views
    grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
    lr = learning_rate(cfg, step)
    for group in optimizer.param_groups:
        group["lr"] = lr
    optimizer.step()
    losses = {k: float(v) for k, v in zip(LOSS_TERMS, stats, strict=True)}
    if cfg.depth_weight == 0 and cfg.surface_weight == 0:
        del losses["depth"], losses["surface"]
    if cfg.point_ov_weight == 0 and cfg.visibility_weight == 0:
        del losses["point_ov"], losses["visibility"]
    return {**losses, "lr": lr, "grad_norm": float(grad_norm)}


# ---- validation ----------------------------------------------------------------------------------
def class_text_embeddings(val_dir: str | Path, class_names: list[str]) -> np.ndarray:
    """(20, D) text embeddings of the ScanNet-20 class names, cached in ``val_dir``.

    Computed once with ``mapper.ov.encoders`` (the ``minilm-l6-v2`` space SimLSeg uses, bare class
    names) and stored as ``VAL_DIR/text_embeddings_minilm-l6-v2.npz`` next to the scenes.
    """
    names = list(class_names[:NUM_SCANNET_CLASSES])
    cache = Path(val_dir) / "text_embeddings_minilm-l6-v2.npz"
    if cache.is_file():
        with np.load(cache, allow_pickle=False) as d:
            if d["names"].tolist() == names:
                return d["embeddings"].astype(np.float32)
    from mapper.ov.encoders import get_text_encoder

    emb = get_text_encoder("minilm-l6-v2").encode(names)
    try:
        np.savez(cache, names=np.array(names), embeddings=emb)
    except OSError:
        pass
    return emb


@torch.no_grad()
def validate(
    model: GovNeSF,
    views: list[ValidationView],
    text_emb: np.ndarray,
    *,
    stride_px: int = 4,
    n_samples: int | None = None,
    depth_guided_masking: bool = False,
    clip_to_volume: bool = False,
    chunk_rays: int = 2048,
    device: torch.device | str = "cpu",
) -> dict[str, Any]:
    """2D novel-view mIoU (ScanNet-20, per scene then averaged) and PSNR of rendered views.

    Renders every ``stride_px``-th pixel (pixel centres) of each view.
    """
    model.eval()
    per_scene_gt: dict[str, list[np.ndarray]] = {}
    per_scene_pred: dict[str, list[np.ndarray]] = {}
    psnrs = []
    text = torch.as_tensor(text_emb, dtype=torch.float32, device=device)
    for v in views:
        src = source_batch(v.scene, v.source_indices, model.cfg).to(device)
        sv = model.make_source_views(src.rgb, src.ov, src.K, src.world_from_cam, src.depth_m)
        volume = model.build_volume(sv, src.bounds)
        w, h = v.scene.image_wh
        origins, dirs = pixel_rays(v.K.to(device), v.world_from_cam.to(device), w, h)  # (H, W, 3)
        off = stride_px // 2
        origins = origins[off::stride_px, off::stride_px].reshape(-1, 3)
        dirs = dirs[off::stride_px, off::stride_px].reshape(-1, 3)
        rgb_parts, ov_parts = [], []
        for i in range(0, origins.shape[0], chunk_rays):
            out = render_rays(
                model,
                sv,
                volume,
                src.bounds,
                Rays(origins[i : i + chunk_rays], dirs[i : i + chunk_rays]),
                n_samples=n_samples,
                depth_guided_masking=depth_guided_masking,
                clip_to_volume=clip_to_volume,
            )
            rgb_parts.append(out.rgb)
            ov_parts.append(out.ov)
        rgb = torch.cat(rgb_parts).clamp(0, 1).cpu().numpy()
        pred_t = predict_labels(torch.cat(ov_parts), text)
        assert isinstance(pred_t, torch.Tensor)
        pred = pred_t.cpu().numpy()
        gt_rgb = v.rgb[off::stride_px, off::stride_px].reshape(-1, 3).astype(np.float64) / 255.0
        mse = float(np.mean((rgb - gt_rgb) ** 2))
        psnrs.append(10.0 * math.log10(1.0 / max(mse, 1e-10)))
        gt = v.label[off::stride_px, off::stride_px].reshape(-1)
        per_scene_gt.setdefault(v.scene.name, []).append(gt)
        per_scene_pred.setdefault(v.scene.name, []).append(pred)
    scores = {
        name: scores_from_labels(np.concatenate(per_scene_gt[name]), np.concatenate(per_scene_pred[name]))
        for name in per_scene_gt
    }
    avg = average_over_scenes(scores.values())
    return {
        "miou_2d": avg.miou,
        "macc_2d": avg.macc,
        "oacc_2d": avg.oacc,
        "psnr": float(np.mean(psnrs)),
        "num_views": len(views),
        "stride_px": stride_px,
        "per_scene_miou": {k: s.miou for k, s in scores.items()},
    }


# ---- the run -------------------------------------------------------------------------------------
def budget_probe_steps(cfg: TrainConfig) -> int:
    """Steps timed before a wall budget fixes max_steps: 20, or the warm-up if shorter (at least 2)."""
    return max(2, min(20, cfg.warmup_steps))


def steps_for_budget(budget_s: float, elapsed_s: float, done: int, per_step_s: float, max_steps: int) -> int:
    """The max_steps that a wall budget allows: the ``done`` steps taken in ``elapsed_s`` plus as many
    more of ``per_step_s`` as fit in what is left (5% kept for checkpoints and the export), within
    ``done .. max_steps``."""
    if per_step_s <= 0 or not math.isfinite(per_step_s):
        raise ValueError(f"per_step_s {per_step_s} out of range: must be > 0")
    more = int(max(0.0, 0.95 * budget_s - elapsed_s) // per_step_s)
    return int(min(max_steps, max(done, done + more)))


def _load_scenes(root: str, *, limit: int = 0, with_novel_views: bool = False) -> list[Scene]:
    paths = find_scenes(root)
    if limit:
        paths = paths[:limit]
    return [load_scene(p, with_novel_views=with_novel_views) for p in paths]


def _load_extra_scenes(cfg: TrainConfig, like: Scene, ov_dim: int) -> list[Scene]:
    """The ``extra_train_dirs`` scenes (ov-less allowed), at the image size and ov grid of ``like``
    with the model's ``ov_dim``; none when ``extra_train_weight`` is 0 (the folders must exist)."""
    for d in cfg.extra_train_dirs:
        if not Path(d).exists():
            raise FileNotFoundError(
                f"train config: extra_train_dirs: folder {d} does not exist "
                "(real sequences: scripts/make_real_data.sh DATA_DIR writes DATA_DIR/real)"
            )
    if cfg.extra_train_weight == 0:
        return []
    paths: list[Path] = []
    for d in cfg.extra_train_dirs:
        try:
            paths += find_scenes(d)
        except FileNotFoundError:
            raise FileNotFoundError(
                f"train config: extra_train_dirs: no scene (frames.govrec, or */frames.govrec) in {d}"
            ) from None
    ov_h, ov_w = like.ov.shape[1:3]
    scenes = [
        load_scene(p, require_ov=False, image_wh=like.image_wh, ov_shape=(ov_h, ov_w, ov_dim)) for p in paths
    ]
    if cfg.extra_holdout_every:
        every, radius = cfg.extra_holdout_every, cfg.extra_holdout_radius
        scenes = [drop_frames(s, held_out_positions(s.num_frames, every, radius)) for s in scenes]
    return scenes


def train(
    cfg: TrainConfig,
    *,
    resume: str | Path | None = None,
    until_step: int | None = None,
    model_cfg: ModelConfig | None = None,
    command: str | None = None,
    progress: bool = True,
    wall_budget_s: float | None = None,
) -> dict[str, Any]:
    """Run (or continue) training; returns the last step's stats and validation metrics.

    Args:
        resume: a training checkpoint (``OUT/last.json``) to continue from.
        until_step: stop after this many completed steps (the schedule still ends at max_steps).
        model_cfg: a model config to use instead of the preset (tests use a tiny one).
        command: the command line recorded in the checkpoints.
        progress: show a tqdm bar on rank 0.
        wall_budget_s: seconds for the training steps (data loading not counted): the first
            ``budget_probe_steps(cfg)`` steps are timed, then max_steps becomes the most steps that
            fit (``steps_for_budget``, never more than the config's max_steps) and the schedule
            follows it. The probe lies inside the warm-up, whose learning rates do not depend on
            max_steps, so the run is the one its final max_steps would have given.
    """
    if wall_budget_s is not None and not (math.isfinite(wall_budget_s) and wall_budget_s > 0):
        raise ValueError(f"wall_budget_s {wall_budget_s} out of range: must be > 0 seconds")
    if wall_budget_s is not None and (resume is not None or until_step is not None):
        raise ValueError("wall_budget_s does not combine with resume or until_step")
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    if cfg.init_weights and resume is None:
        load_metadata(cfg.init_weights)  # a missing checkpoint fails now, not after loading the data
    dd = _init_distributed()
    try:
        return _train(
            cfg,
            dd,
            resume=resume,
            until_step=until_step,
            model_cfg=model_cfg,
            command=command,
            progress=progress,
            wall_budget_s=wall_budget_s,
        )
    finally:
        if dd.initialised_here:
            dist.destroy_process_group()


@dataclass
class _Data:
    """What a run trains and validates on (validation only on rank 0)."""

    train_scenes: list[Scene]
    mcfg: ModelConfig
    sampler: RaySampler
    val_views: list[ValidationView]
    text_emb: np.ndarray
    load_s: float
    extra_scenes: list[Scene] = field(default_factory=list)
    """The ``extra_train_dirs`` scenes (empty when ``extra_train_weight`` is 0)."""


def _with_fusion_options(mcfg: ModelConfig, cfg: TrainConfig) -> ModelConfig:
    """The preset with the run's Distill head sizes (0 keeps the preset's) and range encoding."""
    pairs = (("distill_hidden_dim", cfg.distill_hidden_dim), ("distill_layers", cfg.distill_layers))
    options: dict[str, Any] = {k: v for k, v in pairs if v}
    if cfg.range_encoding:
        options["range_encoding"] = True
    return replace(mcfg, fusion=replace(mcfg.fusion, **options)) if options else mcfg


def _load_data(cfg: TrainConfig, dd: _Dist, model_cfg: ModelConfig | None) -> _Data:
    """Training scenes, the model config (its ``ov_dim`` follows the data), the ray sampler and, on
    rank 0, the validation views and class text embeddings."""
    t_load = time.perf_counter()
    train_scenes = _load_scenes(cfg.train_dir, limit=cfg.max_train_scenes)
    ov_dim = train_scenes[0].ov_dim
    mcfg = _with_fusion_options(model_cfg or get_preset(cfg.preset, ov_dim=ov_dim), cfg)
    extra_scenes = _load_extra_scenes(cfg, train_scenes[0], mcfg.fusion.ov_dim)
    sampler = RaySampler(
        train_scenes,
        mcfg,
        rays_per_view=cfg.rays_per_view,
        num_sources=cfg.num_sources or None,
        pool_factor=cfg.pool_factor,
        seed=cfg.seed,
        frustum_bounds_prob=cfg.frustum_bounds_prob,
        frustum_range_m=cfg.frustum_range_m,
        photometric_prob=cfg.photometric_prob,
        photometric_strength=cfg.photometric_strength,
        sensor_prob=cfg.sensor_prob,
        sensor_strength=cfg.sensor_strength,
        pose_noise_prob=cfg.pose_noise_prob,
        pose_noise_m=cfg.pose_noise_m,
        pose_noise_deg=cfg.pose_noise_deg,
        ov_noise_prob=cfg.ov_noise_prob,
        ov_noise_strength=cfg.ov_noise_strength,
        world_scale_prob=cfg.world_scale_prob,
        world_scale_max=cfg.world_scale_max,
        extra_scenes=extra_scenes,
        extra_weight=cfg.extra_train_weight,
        volume_sources=cfg.volume_sources,
        point_ov_target=cfg.point_ov_target,
        point_ov_rel_tol=cfg.visibility_rel_tol,
    )
    val_views: list[ValidationView] = []
    text_emb = np.zeros((0, ov_dim), np.float32)
    if dd.rank == 0 and cfg.val_dir:
        val_scenes = _load_scenes(cfg.val_dir, with_novel_views=True)
        val_views = validation_views(
            val_scenes, cfg.num_sources or mcfg.num_source_views, views_per_scene=cfg.val_views_per_scene
        )
        text_emb = class_text_embeddings(cfg.val_dir, val_scenes[0].class_names)
    load_s = time.perf_counter() - t_load
    return _Data(train_scenes, mcfg, sampler, val_views, text_emb, load_s, extra_scenes)


@dataclass
class _Model:
    """The model and optimiser, and where the run starts (after ``--resume``)."""

    model: GovNeSF
    optimizer: torch.optim.Optimizer
    start: int = 0
    wall_before: float = 0.0
    history: list[dict[str, Any]] = field(default_factory=list)
    wall_budget: dict[str, Any] | None = None
    """The resumed run's wall-budget choice (``max_steps``), when it had one."""


def _build_model(cfg: TrainConfig, mcfg: ModelConfig, dd: _Dist, resume: str | Path | None) -> _Model:
    """Seeded model + AdamW, restored from ``resume`` if given; every rank gets rank 0's weights."""
    torch.manual_seed(cfg.seed)
    model = GovNeSF(mcfg, mode=cfg.mode).to(dd.device)  # type: ignore[arg-type]
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    built = _Model(model, optimizer)
    if resume is None and cfg.init_weights:
        _init_from(model, cfg.init_weights, mcfg, cfg.mode)
    if resume is not None:
        meta, extra = load_training_state(resume, model, optimizer)
        built.start = int(meta["step"])
        built.wall_before = float(meta.get("train_wall_s", 0.0))
        built.history = list(meta.get("validation_history", []))
        built.wall_budget = meta.get("wall_budget")
        if "rng.torch" in extra:
            torch.set_rng_state(extra["rng.torch"])
    if dd.world > 1:  # every rank starts from rank 0's weights
        for t in list(model.state_dict().values()):
            dist.broadcast(t, src=0)
    return built


def _config_diff(ours: dict[str, Any], theirs: dict[str, Any], prefix: str = "") -> list[str]:
    """Dotted names of the (nested) config fields that differ."""
    out: list[str] = []
    for key, value in ours.items():
        other = theirs.get(key)
        if isinstance(value, dict) and isinstance(other, dict):
            out += _config_diff(value, other, f"{prefix}{key}.")
        elif value != other:
            out.append(f"{prefix}{key}")
    return sorted(out)


def _init_from(model: GovNeSF, path: str, mcfg: ModelConfig, mode: str) -> None:
    """Load ``path``'s weights into ``model`` in place (float32), refusing another config or mode."""
    meta = load_metadata(path)
    theirs = config_from_dict(meta["config"])
    # a checkpoint without the range encoding fine-tunes into a run with it: the new layer starts
    # at zero, so the run starts as the checkpoint's blend
    adds_range = mcfg.fusion.range_encoding and not theirs.fusion.range_encoding
    if adds_range:
        theirs = replace(theirs, fusion=replace(theirs.fusion, range_encoding=True))
    if theirs != mcfg:
        diff = _config_diff(dataclasses.asdict(mcfg), dataclasses.asdict(theirs))
        raise ValueError(
            f"init_weights {path}: its model config differs from the run's in {diff}; "
            "fine-tuning needs the same preset, OV size and Distill head (a checkpoint without "
            "range_encoding may fine-tune into a run with it, not the other way round)"
        )
    if meta.get("mode", "blend") != mode:
        raise ValueError(f"init_weights {path}: mode {meta.get('mode', 'blend')!r}, the run's is {mode!r}")
    if adds_range:
        load_weights_except(path, model, prefix="fusion.range_encoding.")
    else:
        load_training_state(path, model)  # the weights only, in place (no optimiser state)


class _Run:
    """One run's bookkeeping on rank 0: the log, the progress bar, validation and checkpoints."""

    def __init__(
        self,
        cfg: TrainConfig,
        dd: _Dist,
        data: _Data,
        built: _Model,
        *,
        stop: int,
        command: str,
        preset: str,
    ) -> None:
        self.cfg, self.data, self.built, self.stop = cfg, data, built, stop
        self.out_dir = Path(cfg.out_dir)
        self.log_path = self.out_dir / "log.jsonl"
        self.base_meta = {
            "preset": preset,
            "train_config": dataclasses.asdict(cfg),
            "command": command,
            "git_commit": _git_commit(),
            "world_size": dd.world,
            "device": str(dd.device),
            "torch": torch.__version__,
            "ov_space": "minilm-l6-v2",
        }
        self.device = dd.device
        self.t0 = time.perf_counter()
        self.last_stats: dict[str, float] = {}
        self.last_val: dict[str, Any] = built.history[-1] if built.history else {}
        self.bar: Any = None

    def wall(self) -> float:
        return self.built.wall_before + time.perf_counter() - self.t0

    def meta_for(self, step: int) -> dict[str, Any]:
        return {
            **self.base_meta,
            "step": step,
            "train_wall_s": round(self.wall(), 1),
            "last_train_stats": self.last_stats,
            "metrics": self.last_val,
            "validation_history": self.built.history,
        }

    def save_training(self, step: int) -> None:
        save_checkpoint(
            self.out_dir / "last",
            self.built.model,
            metadata=self.meta_for(step),
            optimizer=self.built.optimizer,
            extra_tensors={"rng.torch": torch.get_rng_state()},
        )

    def run_validation(self, step: int) -> None:
        cfg = self.cfg
        if not self.data.val_views:
            return
        t_val = time.perf_counter()
        res = validate(
            self.built.model,
            self.data.val_views,
            self.data.text_emb,
            stride_px=cfg.val_stride_px,
            depth_guided_masking=cfg.depth_guided_masking,
            clip_to_volume=cfg.clip_to_volume,
            device=self.device,
        )
        res = {"step": step, **res, "val_s": round(time.perf_counter() - t_val, 1)}
        self.last_val = res
        self.built.history.append({k: v for k, v in res.items() if k != "per_scene_miou"})
        _log(self.log_path, {"event": "validation", **res})
        if self.bar is not None:
            self.bar.write(
                f"step {step}: val 2D mIoU {res['miou_2d']:.3f}  PSNR {res['psnr']:.2f} dB "
                f"({res['val_s']:.0f} s)"
            )
        if cfg.export:
            save_checkpoint(cfg.export, self.built.model, metadata=self.meta_for(step), half=cfg.export_half)

    def set_budget(self, cfg: TrainConfig, stop: int, record: dict[str, Any]) -> None:
        """A wall budget fixed max_steps (``record``): the run, its checkpoints and its bar follow."""
        self.cfg, self.stop = cfg, stop
        self.base_meta["train_config"] = dataclasses.asdict(cfg)
        self.base_meta["wall_budget"] = record
        _log(self.log_path, {"event": "budget", **record})
        if self.bar is not None:
            self.bar.total = stop
            self.bar.refresh()

    def begin(self, *, progress: bool) -> None:
        """The ``start`` log record and the progress bar."""
        cfg, start = self.cfg, self.built.start
        _log(
            self.log_path,
            {
                "event": "start",
                "from_step": start,
                "until": self.stop,
                "max_steps": cfg.max_steps,
                "world_size": self.base_meta["world_size"],
                "load_s": round(self.data.load_s, 1),
                "command": self.base_meta["command"],
                "train_scenes": len(self.data.train_scenes),
                "extra_train_scenes": len(self.data.extra_scenes),
                "extra_train_frames": [s.num_frames for s in self.data.extra_scenes],
                "val_views": len(self.data.val_views),
            },
        )
        if progress:
            from tqdm import tqdm

            self.bar = tqdm(
                total=self.stop,
                initial=start,
                desc=f"train {self.data.mcfg.name}/{cfg.mode}",
                dynamic_ncols=True,
                file=sys.stderr,
            )

    def after_step(self, done: int, stats: dict[str, float]) -> None:
        """Progress, log, validation and checkpoint after ``done`` completed steps."""
        cfg = self.cfg
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(
                loss=f"{stats['loss']:.4f}",
                rgb=f"{stats['color']:.4f}",
                ov=f"{stats['ov']:.3f}",
                lr=f"{stats['lr']:.1e}",
            )
        if done % cfg.log_every == 0 or done == self.stop:
            _log(self.log_path, {"event": "step", "step": done, **stats, "wall_s": round(self.wall(), 1)})
        if done % cfg.val_every == 0 and done != self.stop:
            self.run_validation(done)
        if done % cfg.checkpoint_every == 0 or done == self.stop:
            self.save_training(done)

    def end(self, done: int, *, validate_last: bool) -> None:
        """Final validation (when the run is complete), checkpoint and ``end`` record; a complete
        run without validation scenes (``val_dir = ""``) still writes its export."""
        if validate_last:
            self.run_validation(done)
            if not self.data.val_views and self.cfg.export:
                save_checkpoint(
                    self.cfg.export, self.built.model, metadata=self.meta_for(done), half=self.cfg.export_half
                )
        self.save_training(done)
        if self.bar is not None:
            self.bar.close()
        _log(self.log_path, {"event": "end", "step": done, "wall_s": round(self.wall(), 1)})


def _train(
    cfg: TrainConfig,
    dd: _Dist,
    *,
    resume: str | Path | None,
    until_step: int | None,
    model_cfg: ModelConfig | None,
    command: str | None,
    progress: bool,
    wall_budget_s: float | None = None,
) -> dict[str, Any]:
    is_main = dd.rank == 0
    data = _load_data(cfg, dd, model_cfg)
    built = _build_model(cfg, data.mcfg, dd, resume)
    model, start = built.model, built.start
    if built.wall_budget:  # a resumed budget run keeps the length (and schedule) its budget chose
        cfg = dataclasses.replace(cfg, max_steps=int(built.wall_budget["max_steps"]))
    if is_main:
        Path(cfg.out_dir).mkdir(parents=True, exist_ok=True)
    stop = cfg.max_steps if until_step is None else min(cfg.max_steps, until_step)
    command = command or " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])
    preset = cfg.preset if model_cfg is None else data.mcfg.name
    run = _Run(cfg, dd, data, built, stop=stop, command=command, preset=preset)
    if is_main:
        run.begin(progress=progress)
    budget = _WallBudget(wall_budget_s, cfg, dd) if wall_budget_s is not None else None
    step = start
    while step < stop:
        stats = train_step(model, built.optimizer, data.sampler, cfg, step, dd.rank, dd.world, dd.device)
        if not all(math.isfinite(v) for v in stats.values()):
            raise FloatingPointError(f"step {step}: non-finite training statistics {stats}")
        run.last_stats = stats
        done = step + 1
        change = budget.after_step(done, cfg.max_steps) if budget is not None else None
        if change is not None:  # the budget fixed the run's length (and so its schedule)
            length, record = change
            cfg = dataclasses.replace(cfg, max_steps=length)
            stop = length
            if is_main:  # the log and the checkpoints' metadata are rank 0's
                run.set_budget(cfg, stop, {"wall_budget_s": wall_budget_s, **record, "max_steps": length})
        if is_main:
            run.after_step(done, stats)
        if dd.world > 1 and done % cfg.val_every == 0:
            dist.barrier()
        step = done
    done = max(start, stop)
    if is_main:
        run.end(done, validate_last=done >= cfg.max_steps or until_step is None)
    if dd.world > 1:
        dist.barrier()
    return {
        "step": done,
        "train": run.last_stats,
        "validation": run.last_val,
        "train_wall_s": run.wall(),
        "max_steps": cfg.max_steps,
        "model": model,
    }


class _WallBudget:
    """``train(wall_budget_s=...)``: times the first ``budget_probe_steps`` steps, then fixes the
    run's length to what fits (:func:`steps_for_budget`, rank 0's choice on every rank); stops at
    once when the budget is spent before the probe ends, or when the steps turn out slower than the
    probe said and 1.1 x the budget has passed (both on one process only: ranks would not agree
    on when)."""

    def __init__(self, budget_s: float, cfg: TrainConfig, dd: _Dist) -> None:
        self.budget_s, self.dd = budget_s, dd
        self.probe = budget_probe_steps(cfg)
        self.fixed = False
        self.t_begin = self.t_first = time.perf_counter()

    def after_step(self, done: int, max_steps: int) -> tuple[int, dict[str, Any]] | None:
        """After ``done`` completed steps: (the new max_steps, what to log) or None (no change)."""
        now = time.perf_counter()
        if done == 1:
            self.t_first = now  # the first step carries one-off costs (CUDA start-up)
        elapsed = now - self.t_begin
        alone = self.dd.world == 1
        if self.fixed:
            if alone and elapsed > 1.1 * self.budget_s and done < max_steps:  # slower than probed
                return done, {"probe_steps": self.probe, "overrun_at_s": round(elapsed, 1)}
            return None
        if done < min(self.probe, max_steps) and not (alone and elapsed >= 0.95 * self.budget_s):
            return None
        per_step = (now - self.t_first) / (done - 1) if done > 1 else elapsed
        fitted = _agreed(steps_for_budget(self.budget_s, elapsed, done, per_step, max_steps), self.dd)
        self.fixed, self.probe = True, done
        return fitted, {"probe_steps": done, "probe_s_per_step": round(per_step, 4)}


def _agreed(value: int, dd: _Dist) -> int:
    """Rank 0's value on every rank."""
    if dd.world == 1:
        return value
    t = torch.tensor([value], dtype=torch.int64, device=dd.device)
    dist.broadcast(t, src=0)
    return int(t.item())


def _log(path: Path, record: dict[str, Any]) -> None:
    record = {"time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **record}
    with path.open("a") as f:
        f.write(json.dumps(record, default=float) + "\n")
