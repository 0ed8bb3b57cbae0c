"""The window's keyframes as the network sees them: one :class:`ViewEntry` per keyframe.

A new keyframe is resized to the model's working size (K scaled with it), encoded ONCE by the 2D
encoder (batched, :func:`encode_keyframes`), its OV map resampled to the common OV grid, and given
its extent: the world points it observed (:func:`extent_points`), which the volume's bounds follow.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.model.field import GovNeSF
from mapper.model.ops.geometry import frustum_points
from mapper.runtime.loading import LoadedModel


@dataclass
class ViewEntry:
    """One keyframe as the network sees it (all tensors on the runtime's device, float32)."""

    seq: int
    rgb: Tensor  # (3, H, W) in [0, 1], working size
    features: Tensor  # (F, H/4, W/4) 2D encoder output
    ov: Tensor | None  # (D, h_ov, w_ov) float16 on the common OV grid, or None
    ov_space: str | None
    depth_m: Tensor | None  # (H, W) z-depth (m) at the working size, 0 = none
    K: Tensor  # (4,) for the working size
    world_from_cam: Tensor  # (4, 4)
    extent: Tensor  # (M, 3) world points of what the keyframe observed
    key: tuple[str, int, int] = ("", -1, -1)  # (camera, seq, stamp_ns): matches set_view_extent
    observed: Tensor | None = None  # (N, 3) set_view_extent's points behind ``extent`` (no depth)
    depth_prior: Tensor | None = None  # (H, W) set_view_depth_prior's sparse z-depth, 0 = none

    @property
    def nbytes(self) -> int:
        tensors = [self.rgb, self.features, self.ov, self.depth_m, self.K, self.world_from_cam, self.extent,
                   self.depth_prior]
        return sum(t.numel() * t.element_size() for t in tensors if t is not None)


def keyframe_key(keyframe: Any) -> tuple[str, int, int]:
    """``(camera, seq, stamp_ns)``: a keyframe's identity that survives a swap in the window; a
    named robot's camera is ``"<robot>/<camera>"`` (two robots' frames may share seq and stamp)."""
    camera, robot = str(getattr(keyframe, "camera", "")), str(getattr(keyframe, "robot", ""))
    return (f"{robot}/{camera}" if robot else camera, int(keyframe.seq), int(keyframe.stamp_ns))


def render_extents(entries: Iterable[ViewEntry]) -> list[Tensor]:
    """What each view observed, for the bounds of render volumes: its extent (depth points; without
    depth the frustum, or the points ``set_view_extent`` gave it plus the camera centre), except
    that a view given at least 16 such points counts them without its camera centre."""
    return [e.observed if e.observed is not None and e.observed.shape[0] >= 16 else e.extent for e in entries]


def encode_keyframes(
    loaded: LoadedModel,
    model: GovNeSF,
    keyframes: Sequence[Any],
    observed: Sequence[Tensor | None],  # per keyframe: set_view_extent's (N, 3) points, or None
    priors: Sequence[Tensor | None],  # per keyframe: set_view_depth_prior's (h, w) z-depth, or None
) -> list[ViewEntry]:
    """Resize, encode (batched) and cache the new keyframes."""
    if not keyframes:
        return []
    width, height = loaded.image_wh
    device = loaded.device
    rgbs, Ks = [], []
    for kf in keyframes:
        rgb = torch.tensor(np.asarray(kf.rgb)).to(device)
        rgb = rgb.permute(2, 0, 1).float().div_(255.0)  # (3, H0, W0)
        h0, w0 = rgb.shape[-2:]
        if (w0, h0) != (width, height):
            rgb = F.interpolate(
                rgb.unsqueeze(0), size=(height, width), mode="bilinear", align_corners=False,
                antialias=w0 > width or h0 > height,
            ).squeeze(0).clamp_(0.0, 1.0)  # fmt: skip
        sx, sy = width / w0, height / h0
        K0 = torch.tensor(np.array(kf.K, dtype=np.float64), device=device)
        Ks.append(torch.stack([K0[0] * sx, K0[1] * sy, K0[2] * sx, K0[3] * sy]).float())
        rgbs.append(rgb)
    features = []
    batch = 8
    stacked = torch.stack(rgbs)
    for i in range(0, len(rgbs), batch):
        features.append(model.encode(stacked[i : i + batch]))
    feats = torch.cat(features)
    entries = []
    for i, kf in enumerate(keyframes):
        pose = torch.tensor(np.array(kf.world_from_cam, dtype=np.float64), device=device).float()
        depth = _working_depth(kf.depth_m, width, height, device)
        entries.append(
            ViewEntry(
                seq=int(kf.seq),
                rgb=rgbs[i],
                features=feats[i],
                ov=_common_grid_ov(kf.ov, loaded.ov_wh, device),
                ov_space=kf.ov_space,
                depth_m=depth,
                K=Ks[i],
                world_from_cam=pose,
                extent=extent_points(loaded, Ks[i], pose, depth, observed[i]),
                key=keyframe_key(kf),
                observed=None if depth is not None else observed[i],
                depth_prior=None if depth is not None else prior_at_working_size(loaded, priors[i]),
            )
        )
    return entries


def _common_grid_ov(ov: Any, ov_wh: tuple[int, int], device: torch.device) -> Tensor | None:
    """A keyframe's (h, w, D) OV map -> (D, h_ov, w_ov) float16 on the common OV grid (None: none)."""
    if ov is None:
        return None
    ov_t = torch.tensor(np.asarray(ov)).to(device, torch.float32)
    ov_t = ov_t.permute(2, 0, 1)  # (D, h, w)
    ow, oh = ov_wh
    if tuple(ov_t.shape[1:]) != (oh, ow):
        ov_t = F.interpolate(
            ov_t.unsqueeze(0), size=(oh, ow), mode="bilinear", align_corners=False,
            antialias=ov_t.shape[1] > oh or ov_t.shape[2] > ow,
        ).squeeze(0)  # fmt: skip
    return ov_t.to(torch.float16)


def _working_depth(depth_m: Any, width: int, height: int, device: torch.device) -> Tensor | None:
    """A keyframe's (H0, W0) z-depth -> (H, W) at the working size (nearest), 0 where not a positive
    finite depth (None: none)."""
    if depth_m is None:
        return None
    d = torch.tensor(np.asarray(depth_m)).to(device, torch.float32)
    d = torch.where(torch.isfinite(d) & (d > 0), d, torch.zeros_like(d))
    if tuple(d.shape) != (height, width):
        d = F.interpolate(d[None, None], size=(height, width), mode="nearest-exact")[0, 0]
    return d


def extent_points(
    loaded: LoadedModel,
    K: Tensor,  # (4,) for the working size
    world_from_cam: Tensor,  # (4, 4)
    depth_m: Tensor | None,  # (H, W) at the working size, 0 = none
    observed: Tensor | None = None,  # (N, 3) set_view_extent's points
) -> Tensor:
    """(M, 3) world points a keyframe observed: depth back-projected (<= max_range_m, up to
    ~1024 points) when it has enough depth, else the ``observed`` points
    ``ModelRuntime.set_view_extent`` gave it (e.g. triangulated), else its frustum sampled up to
    max_range_m."""
    width, height = loaded.image_wh
    cfg = loaded.config
    if depth_m is not None:
        valid = (depth_m > 0) & (depth_m <= cfg.max_range_m)
        rows, cols = valid.nonzero(as_tuple=True)
        if rows.numel() >= 16:
            step = max(1, rows.numel() // 1024)
            rows, cols = rows[::step], cols[::step]
            z = depth_m[rows, cols]
            u, v = cols.float() + 0.5, rows.float() + 0.5
            cam = torch.stack([(u - K[2]) / K[0] * z, (v - K[3]) / K[1] * z, z], dim=-1)
            return cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    if observed is not None:
        return torch.cat([observed, world_from_cam[:3, 3][None]])  # the camera is inside too
    near = min(max(cfg.near_m, 0.05), 0.5 * cfg.max_range_m)
    return frustum_points(K, world_from_cam, width, height, near, cfg.max_range_m)


def prior_at_working_size(loaded: LoadedModel, prior: Tensor | None) -> Tensor | None:
    """A sparse z-depth prior (h, w) resized to the working size (nearest); None stays None."""
    if prior is None:
        return None
    width, height = loaded.image_wh
    if tuple(prior.shape) != (height, width):
        prior = F.interpolate(prior[None, None], size=(height, width), mode="nearest-exact")[0, 0]
    return prior
