"""SimLSeg: a SIMULATED onboard 2D open-vocabulary segmentation model (not a real network).

No model weights can be downloaded here, so the simulated robot stands in for an onboard LSeg /
OpenSeg / CLIP model with this simulator. From a rendered view's ground-truth label image it
produces per-pixel features in the ``minilm-l6-v2`` text-embedding space (the embedding of each
pixel's class name), corrupted the way real 2D open-vocabulary models are:

* low resolution (stride 4 by default) and blurred boundaries (area pooling + Gaussian blur);
* confusions between semantically close classes (confusers drawn from the text-embedding
  similarity of class names), chosen at random per frame and per instance, so the maps are NOT
  view-consistent: the same chair can read "sofa" in one frame and "chair" in the next;
* quality that falls with distance and at grazing viewing angles: low-quality pixels are
  confused more often and are noisier;
* per-pixel noise.

Everything is deterministic given ``(seed, frame_index)``. ``docs/concepts/simlseg.md`` has the
calibration (single-view 2D mIoU, near/far split) against the ground truth.

Example:
    >>> from clients.sim.text import get_text_encoder            # doctest: +SKIP
    >>> sim = SimLSeg(CLASS_NAMES, get_text_encoder(), seed=0)    # doctest: +SKIP
    >>> ov = sim.features(view, frame_index=7)                    # doctest: +SKIP
    >>> ov.shape, ov.dtype                                        # doctest: +SKIP
    ((30, 40, 384), dtype('float16'))
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import gaussian_filter
from scipy.special import ndtr

__all__ = ["SimLSeg", "SimLSegConfig", "TextEncoderLike", "view_quality"]


class TextEncoderLike(Protocol):
    """Anything with ``encode(texts) -> (N, D) float32`` L2-normalised rows."""

    def encode(self, texts: Sequence[str]) -> np.ndarray: ...


@dataclass(frozen=True)
class SimLSegConfig:
    """Corruption model of the simulator. Defaults are calibrated (docs/concepts/simlseg.md) so that the
    single-view 2D mIoU over the 20 ScanNet classes lies in 45-60% (LSeg on ScanNet: 55.9)."""

    stride: int = 4
    """Output resolution divisor: features are (ceil(H / stride), ceil(W / stride), D)."""
    prompt_template: str = "{}"
    """Text prompt per class name; ``"{}"`` embeds the bare name (as queries usually are)."""
    void_text: str = "background"
    """Text whose embedding fills pixels without a label (no hit)."""
    boundary_blur_cells: float = 0.6
    """Gaussian blur sigma (output cells) applied after area pooling: soft object boundaries."""
    near_m: float = 2.0
    """Distance along the ray (m) up to which distance does not lower quality."""
    falloff_m: float = 6.0
    """Quality decays as exp(-(distance - near_m) / falloff_m) beyond ``near_m``."""
    grazing_power: float = 0.7
    """Quality is multiplied by |cos(angle between ray and surface normal)| ** grazing_power."""
    min_quality: float = 0.05
    """Floor of the per-pixel quality in [0, 1] (also the quality of pixels without a hit)."""
    instance_confusion: float = 0.10
    """Probability that a whole instance is read as a confuser in a frame, at full quality
    (objects only: room structure without an instance id is confused by regions only)."""
    instance_confusion_low_quality: float = 0.3
    """Extra instance-confusion probability at zero quality (scaled by 1 - mean quality)."""
    region_confusion: float = 0.05
    """Fraction of pixels inside blob-shaped regions read as a confuser, at full quality."""
    region_confusion_low_quality: float = 0.3
    """Extra region-confusion fraction at zero quality (scaled by 1 - pixel quality)."""
    region_scale_cells: float = 1.5
    """Correlation length (output cells) of the random field that shapes the confused regions."""
    confusion_mix: tuple[float, float] = (0.55, 1.0)
    """Range of the confuser's weight in a confused pixel's feature (the rest is the true class)."""
    confuser_persistence: float = 0.8
    """Probability that a confused frame uses the instance's favourite confuser (fixed per seed
    and instance) rather than a fresh draw: real models err consistently on hard objects, so
    averaging many views does not cancel every error (it still varies from frame to frame)."""
    confuser_top_k: int = 4
    """Confusers are drawn among the k classes whose names embed closest to the true class."""
    confuser_temperature: float = 0.05
    """Softmax temperature over cosine similarity for drawing a confuser among the top k."""
    noise_std: float = 0.05
    """Per-dimension std of Gaussian feature noise (before L2 normalisation), at full quality."""
    noise_std_low_quality: float = 0.3
    """Extra per-dimension noise std at zero quality (scaled by 1 - pixel quality)."""

    def __post_init__(self) -> None:
        checks = [
            ("stride", self.stride, 1, 64),
            ("boundary_blur_cells", self.boundary_blur_cells, 0.0, 50.0),
            ("near_m", self.near_m, 0.0, 1e3),
            ("falloff_m", self.falloff_m, 1e-6, 1e3),
            ("grazing_power", self.grazing_power, 0.0, 10.0),
            ("min_quality", self.min_quality, 0.0, 1.0),
            ("instance_confusion", self.instance_confusion, 0.0, 1.0),
            ("instance_confusion_low_quality", self.instance_confusion_low_quality, 0.0, 1.0),
            ("region_confusion", self.region_confusion, 0.0, 1.0),
            ("region_confusion_low_quality", self.region_confusion_low_quality, 0.0, 1.0),
            ("region_scale_cells", self.region_scale_cells, 0.0, 100.0),
            ("confuser_persistence", self.confuser_persistence, 0.0, 1.0),
            ("confuser_top_k", self.confuser_top_k, 1, 10_000),
            ("confuser_temperature", self.confuser_temperature, 1e-6, 100.0),
            ("noise_std", self.noise_std, 0.0, 10.0),
            ("noise_std_low_quality", self.noise_std_low_quality, 0.0, 10.0),
        ]
        for name, value, lo, hi in checks:
            if not lo <= value <= hi:
                raise ValueError(f"SimLSegConfig.{name} = {value} out of range {lo}..{hi}")
        lo, hi = self.confusion_mix
        if not 0.0 <= lo <= hi <= 1.0:
            raise ValueError(f"SimLSegConfig.confusion_mix = {self.confusion_mix}: need 0 <= lo <= hi <= 1")
        if "{}" not in self.prompt_template:
            raise ValueError(f"SimLSegConfig.prompt_template {self.prompt_template!r} must contain '{{}}'")


def _ray_dirs_cam(width: int, height: int, K: np.ndarray | None, depth_m: np.ndarray,
                  ray_dist_m: np.ndarray) -> np.ndarray:
    """Unit ray directions in the camera frame through the pixel centres: (H, W, 3).

    With ``K`` they are exact. Without it the principal point is taken at the image centre with
    square pixels, and the angle off the optical axis comes from ``depth_m / ray_dist_m``.
    """
    cols = np.arange(width, dtype=np.float32) + 0.5
    rows = np.arange(height, dtype=np.float32) + 0.5
    u, v = np.meshgrid(cols, rows)  # (H, W)
    if K is not None:
        fx, fy, cx, cy = (float(k) for k in K)
        d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)
    du, dv = u - width / 2.0, v - height / 2.0
    rad = np.hypot(du, dv)
    hit = (depth_m > 0) & (ray_dist_m > 0)
    cos_off = np.where(hit, np.clip(depth_m / np.where(hit, ray_dist_m, 1.0), 0.0, 1.0), 1.0)
    sin_off = np.sqrt(1.0 - cos_off**2)
    with np.errstate(invalid="ignore", divide="ignore"):
        cu = np.where(rad > 0, du / rad, 0.0)
        cv = np.where(rad > 0, dv / rad, 0.0)
    return np.stack([sin_off * cu, sin_off * cv, cos_off], axis=-1).astype(np.float32)


def view_quality(view: Any, config: SimLSegConfig, K: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel quality in [min_quality, 1] of a rendered view: (H, W) float32.

    Falls with the distance along the ray beyond ``near_m`` and at grazing angles (from
    ``view.depth_m``, ``view.ray_dist_m`` and ``view.normal_cam``); pixels without a hit get
    ``min_quality``.
    """
    depth = np.asarray(view.depth_m, dtype=np.float32)  # (H, W)
    height, width = depth.shape
    ray_dist = getattr(view, "ray_dist_m", None)
    ray_dist = depth if ray_dist is None else np.asarray(ray_dist, dtype=np.float32)
    q = np.exp(-np.maximum(ray_dist - config.near_m, 0.0) / config.falloff_m)
    normal = getattr(view, "normal_cam", None)
    if normal is not None and config.grazing_power > 0:
        dirs = _ray_dirs_cam(width, height, K, depth, ray_dist)
        cos = np.abs(np.sum(np.asarray(normal, dtype=np.float32) * dirs, axis=-1))
        q = q * np.clip(cos, 0.0, 1.0) ** config.grazing_power
    q = np.where(depth > 0, q, 0.0)
    return np.clip(q, config.min_quality, 1.0).astype(np.float32)


class SimLSeg:
    """SIMULATED 2D open-vocabulary model: ground-truth labels -> corrupted OV feature maps.

    Args:
        class_names: names of the label ids 0..C-1 of the rendered label images.
        text_encoder: embeds the (templated) class names; defines the feature space (e.g. the
            ``minilm-l6-v2`` ``clients.sim.text.TextEncoder``).
        seed: simulator seed; outputs are a pure function of (seed, frame_index, view).
        config: corruption model (``SimLSegConfig``).
    """

    @staticmethod
    def prompt_texts(class_names: Sequence[str], config: SimLSegConfig | None = None) -> list[str]:
        """Every text SimLSeg embeds: each class's prompt, then the void text (C + 1)."""
        cfg = config or SimLSegConfig()
        return [cfg.prompt_template.format(n) for n in class_names] + [cfg.void_text]

    def __init__(self, class_names: Sequence[str], text_encoder: TextEncoderLike, *, seed: int = 0,
                 config: SimLSegConfig | None = None) -> None:
        names = list(class_names)
        if not names:
            raise ValueError("class_names is empty; SimLSeg needs at least one class")
        self.class_names = names
        self.config = config or SimLSegConfig()
        self.seed = int(seed)
        cfg = self.config
        texts = self.prompt_texts(names, cfg)
        emb = np.asarray(text_encoder.encode(texts), dtype=np.float32)  # (C + 1, D)
        if emb.ndim != 2 or emb.shape[0] != len(texts):
            raise ValueError(f"text_encoder returned shape {emb.shape}, expected ({len(texts)}, D)")
        self.embeddings = emb / np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-12)
        self.dim = int(emb.shape[1])
        n = len(names)
        sim = self.embeddings[:n] @ self.embeddings[:n].T  # (C, C)
        np.fill_diagonal(sim, -np.inf)
        k = min(cfg.confuser_top_k, max(n - 1, 1))
        self._confusers = np.argsort(-sim, axis=1)[:, :k]  # (C, k)
        if n == 1:
            self._confusers = np.zeros((1, 1), dtype=np.int64)
            self._confuser_probs = np.ones((1, 1))
        else:
            top = np.take_along_axis(sim, self._confusers, axis=1) / cfg.confuser_temperature
            top = np.exp(top - top.max(axis=1, keepdims=True))
            self._confuser_probs = top / top.sum(axis=1, keepdims=True)  # (C, k)

    def out_size(self, width: int, height: int) -> tuple[int, int]:
        """(w, h) of the feature map for a ``width x height`` image."""
        s = self.config.stride
        return -(-width // s), -(-height // s)

    def confuser_of(self, label: int, rng: np.random.Generator) -> int:
        """Draw a confuser class id for ``label`` (never ``label`` itself when C > 1)."""
        pick = rng.choice(self._confusers.shape[1], p=self._confuser_probs[label])
        return int(self._confusers[label, pick])

    def features(self, view: Any, frame_index: int, K: np.ndarray | None = None) -> np.ndarray:
        """Simulated OV feature map of one rendered view.

        Args:
            view: a ``RenderedView`` (or anything with ``label`` (H, W) int, -1 = none;
                ``depth_m`` (H, W) z-depth, 0 = no hit; optional ``instance`` (H, W) int,
                ``ray_dist_m`` (H, W), ``normal_cam`` (H, W, 3), ``K`` (4,)).
            frame_index: index of the frame; with the seed it fixes every random choice.
            K: (4,) [fx, fy, cx, cy] of the view, for exact grazing angles (else ``view.K`` if
                present, else a centred principal point is assumed).

        Returns:
            (h, w, D) float16, h = ceil(H / stride), w = ceil(W / stride), rows L2-normalised.
        """
        cfg = self.config
        label = np.asarray(view.label)
        if label.ndim != 2:
            raise ValueError(f"view.label must be (H, W), got shape {label.shape}")
        height, width = label.shape
        n_cls = len(self.class_names)
        bad = (label >= n_cls) | (label < -1)
        if bad.any():
            raise ValueError(
                f"view.label has ids {np.unique(label[bad])[:5].tolist()} outside -1..{n_cls - 1} "
                f"({n_cls} class names)"
            )
        if frame_index < 0:
            raise ValueError(f"frame_index {frame_index} must be >= 0")
        if K is None:
            K = getattr(view, "K", None)
        quality = view_quality(view, cfg, None if K is None else np.asarray(K, np.float64))  # (H, W)
        inst = getattr(view, "instance", None)
        inst = np.full_like(label, -1) if inst is None else np.asarray(inst)
        w_out, h_out = self.out_size(width, height)
        frame_rng = np.random.default_rng([self.seed, frame_index, 0])

        # Per-pixel weights over classes (+ void): start from the one-hot ground truth.
        void = n_cls
        lab = np.where(label >= 0, label, void)
        weights = np.zeros((height, width, n_cls + 1), np.float32)  # (H, W, C + 1)
        np.put_along_axis(weights, lab[..., None], 1.0, axis=-1)

        # Blob-shaped regions, one smooth uniform field a frame (its values rank pixels).
        field = frame_rng.standard_normal((h_out, w_out)).astype(np.float32)
        if cfg.region_scale_cells > 0:
            field = gaussian_filter(field, cfg.region_scale_cells, mode="reflect")
        field = (field - field.mean()) / max(float(field.std()), 1e-6)
        field_full = _upsample(ndtr(field).astype(np.float32), height, width)  # (H, W) ~ U(0, 1)
        region_p = cfg.region_confusion + cfg.region_confusion_low_quality * (1.0 - quality)

        # Units: (instance, label) pairs; pixels without an instance id group by label.
        labelled = label >= 0
        key = np.where(labelled, (inst.astype(np.int64) + 1) * (n_cls + 1) + label, -1)
        for k in np.unique(key[labelled]):
            mask = key == k
            cls = int(k % (n_cls + 1))
            inst_id = int(k // (n_cls + 1)) - 1
            rng = np.random.default_rng([self.seed, frame_index, 1, inst_id + 1, cls])
            p_inst = cfg.instance_confusion + cfg.instance_confusion_low_quality * (
                1.0 - float(quality[mask].mean()))
            # Room structure (no instance id) is one huge unit: only blob regions confuse it.
            whole = inst_id >= 0 and rng.random() < p_inst
            # Each instance has a favourite confuser (fixed by the seed, not the frame); a frame
            # uses it with probability ``confuser_persistence``, else draws a fresh one.
            favourite = self.confuser_of(cls, np.random.default_rng([self.seed, 2, inst_id + 1, cls]))
            whole_cls, region_cls = (
                favourite if rng.random() < cfg.confuser_persistence else self.confuser_of(cls, rng)
                for _ in range(2)
            )
            whole_mix, region_mix = rng.uniform(*cfg.confusion_mix), rng.uniform(*cfg.confusion_mix)
            if n_cls == 1:
                continue
            if whole:
                weights[mask, cls] -= whole_mix
                weights[mask, whole_cls] += whole_mix
            region = mask & (field_full < region_p)
            if region.any():
                w = weights[region]
                w *= 1.0 - region_mix
                w[:, region_cls] += region_mix
                weights[region] = w

        # Low resolution with soft boundaries: area pooling, then a Gaussian blur.
        low = _area_pool(weights, h_out, w_out)  # (h, w, C + 1)
        if cfg.boundary_blur_cells > 0:
            low = gaussian_filter(low, (cfg.boundary_blur_cells, cfg.boundary_blur_cells, 0), mode="nearest")
        feats = low @ self.embeddings  # (h, w, D)
        q_low = _area_pool(quality[..., None], h_out, w_out)[..., 0]  # (h, w)
        std = cfg.noise_std + cfg.noise_std_low_quality * (1.0 - q_low)
        feats += frame_rng.standard_normal(feats.shape, dtype=np.float32) * std[..., None]
        feats /= np.maximum(np.linalg.norm(feats, axis=-1, keepdims=True), 1e-6)
        return feats.astype(np.float16)


def _area_pool(image: np.ndarray, h_out: int, w_out: int) -> np.ndarray:
    """(H, W, C) -> (h_out, w_out, C) by area averaging (exact box filter when sizes divide)."""
    t = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    return F.adaptive_avg_pool2d(t, (h_out, w_out))[0].permute(1, 2, 0).numpy()


def _upsample(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """(h, w) -> (height, width) bilinear (pixel centres aligned, no half-pixel shift)."""
    t = torch.from_numpy(np.ascontiguousarray(image))[None, None]
    return F.interpolate(t, size=(height, width), mode="bilinear", align_corners=False)[0, 0].numpy()
