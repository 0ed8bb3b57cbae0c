"""The learned GOV-NeSF model inside the node: incremental cost volume, point segmentation, renders.

:class:`ModelRuntime` turns the node's keyframe window into the inputs of the trained network and
answers ``segment_points`` (method ``govnesf``) and ``render`` requests with it.

Streaming updates (``attach(window)``):

* The window's ``on_add`` / ``on_evict`` callbacks run under the node's state lock, on the ingest
  thread. They only RECORD the change (O(1), a dict entry), so ingest is never slowed down by the
  model. A keyframe added and evicted before anything used it cancels out, so the record holds at
  most one entry per keyframe of the window plus the evictions not yet applied.
* The next query (or :meth:`ModelRuntime.sync`) APPLIES the recorded changes incrementally: each
  new keyframe is resized to the model's working size (K scaled with it), encoded ONCE by the 2D
  encoder, its OV map resampled to the common OV grid (``ov`` may be coarser than the image, any
  size), and its features are added to the :class:`~mapper.model.ops.cost_volume.CostVolume` with
  ``add_view`` (only the voxels it sees); an evicted keyframe is removed with ``remove_view``.
* The volume's bounds follow what the window observed: every keyframe contributes extent points
  (its depth back-projected when it has depth, else its camera frustum up to ``max_range_m``, or up
  the points :meth:`ModelRuntime.set_view_extent` gave it: RGB-only keyframes get their
  triangulated points, :mod:`mapper.node.plugins.triangulation`).
  When a new keyframe's points leave the current bounds (more than ``rebuild_outside_fraction`` of
  them outside), the bounds are recomputed from the whole window (recentred / grown, or moved with
  the robot) and the volume is rebuilt from the stored views. This is the ONE non-incremental step;
  it is counted in :attr:`ModelRuntime.rebuilds`.
* Everything derived from the volume (3D U-Net output, occupancy grid, stacked view tensors) is
  computed at query time and cached per runtime version (+1 per applied change).

Queries:

* :meth:`ModelRuntime.segment`: the source-view-agnostic OV feature at given points
  (``GovNeSF.query_points``) with per-point view selection, cosine to the text embeddings.
* :meth:`ModelRuntime.render`: rgb, z-depth, label and per-text cosine score of a novel view, with
  empty-space skipping (see ``docs/RENDERING.md``).

Per-point view selection: points are bucketed into cells of ``view_cell_m``; for each cell the
``source_views`` views that see the most of its points (ties and partial visibility ranked by
distance, or by how frontally they see it with ``view_selection = "frontal"``) are its source
views, and cells with the same view set are evaluated together. Inside a set, the network masks
every view that does not see the individual point, so a point only ever uses views that see it.

Frames without ``ov`` still count for geometry (cost volume, rgb and depth renders); semantic
outputs use the views that carry ``ov`` and answer :class:`RuntimeNotReady` when none does.
"""

from __future__ import annotations

import logging
import math
import numbers
import threading
import time
from collections.abc import Callable, Hashable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from govnesf.resources import data_root
from mapper.errors import RuntimeNotReady
from mapper.model.field import GovNeSF, OVMaps, PointOutputs, PointViewSamples, SourceViews, default_device
from mapper.model.fusion import FusionNet
from mapper.model.ops.cost_volume import (
    CostVolume,
    VolumeBounds,
    bounds_from_points,
    build_cost_volume,
    cost_volume_features,
    sample_volume,
)
from mapper.model.ops.geometry import (
    DEFAULT_EPS,
    camera_centers,
    frustum_points,
    in_view,
    invert_pose,
    pixel_rays,
    project_points,
)
from mapper.model.ops.rendering import Rays
from mapper.model.render import AppearanceFn, march_rays, occupancy_mask
from mapper.ov.encoders import TextEncoder, UnknownSpaceError, get_text_encoder
from mapper.runtime.config import ModelRuntimeConfig
from protocol.messages import RENDER_OUTPUTS  # what render can produce: the wire's names

__all__ = [
    "RENDER_OUTPUTS",
    "ModelRuntime",
    "ModelRuntimeConfig",
    "RenderFrame",
    "RuntimeNotReady",
]

log = logging.getLogger("mapper.runtime.model_runtime")


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


@dataclass
class _ViewEntry:
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


@dataclass
class _Prepared:
    """Everything a query needs, cached per runtime version."""

    version: int
    bounds: VolumeBounds
    volume: Tensor  # (Dv, X, Y, Z) 3D U-Net output
    rgb: Tensor  # (M, 3, H, W)
    features: Tensor  # (M, F, h, w)
    ov: Tensor | None  # (M, D, h_ov, w_ov) float32 (zeros for views without ov) or None
    has_ov: Tensor  # (M,) bool
    depth_m: Tensor | None  # (M, H, W) (zeros for views without depth) or None
    K: Tensor  # (M, 4)
    world_from_cam: Tensor  # (M, 4, 4)
    ov_space: str | None
    support: Tensor | None = None  # (1, X, Y, Z) 1 where >= min_view_support views see the voxel
    max_density: Tensor | None = None  # (X, Y, Z) dilated max sub-voxel density (1/m), on first use
    prior_only: Tensor | None = None  # (M,) bool: the view's depth_m is a prior (no input depth)
    input_depth: Tensor | None = None  # (M,) bool: the view's depth_m is input depth
    free_space: Tensor | None = None  # (X, Y, Z) bool carved by the priors (carve_free_space), on first use
    ov_table: Tensor | None = None  # (M * h_ov * w_ov, D) ``ov`` channel-last, on first use
    extents: list[Tensor] = field(default_factory=list)
    """M x (E_m, 3): what each view observed (depth points; without depth the points
    ``set_view_extent`` gave it, without the camera centre), for the bounds of render volumes."""
    render_volumes: dict[tuple[int, ...], _Prepared] = field(default_factory=dict)
    """Render preps over keyframe subsets (``render_volume_views``), by view indices; this version's."""
    parent: _Prepared | None = None
    """A render volume's prep (``render_volume_views``): the window's, whose OV gather table it
    shares (built once) and whose volume features the blend takes at points outside this prep's
    bounds (the render volume has none there)."""
    render_views: int = 0
    """A render volume's prep: the keyframes its volume spans (0: the window's prep)."""

    def ov_maps(self, view_idx: Tensor, image_wh: tuple[int, int]) -> OVMaps:
        """The OV maps of ``view_idx`` (N,) as a gather table (built once per version)."""
        assert self.ov is not None
        if self.parent is not None:
            return self.parent.ov_maps(view_idx, image_wh)
        if self.ov_table is None:
            self.ov_table = self.ov.permute(0, 2, 3, 1).reshape(-1, self.ov.shape[1]).contiguous()
        h, w = self.ov.shape[-2:]
        return OVMaps(self.ov_table, (int(w), int(h)), view_idx, image_wh)

    def __len__(self) -> int:
        return int(self.rgb.shape[0])


def _render_extents(entries: Iterable[_ViewEntry]) -> list[Tensor]:
    """What each view observed, for the bounds of render volumes: its extent (depth points; without
    depth the frustum, or the points ``set_view_extent`` gave it plus the camera centre), except
    that a view given at least 16 such points counts them without its camera centre."""
    return [e.observed if e.observed is not None and e.observed.shape[0] >= 16 else e.extent for e in entries]


def _keyframe_key(keyframe: Any) -> tuple[str, int, int]:
    """``(camera, seq, stamp_ns)``: a keyframe's identity that survives a swap in the window."""
    return (str(getattr(keyframe, "camera", "")), int(keyframe.seq), int(keyframe.stamp_ns))


FUSED_CHUNK_POINTS = 65536
"""Points per call of the one-pass point answers (``model.fused_point_answers``): its samples stay in
per-block buffers whatever the call's size; this bounds the copies of the points' view indices
(16 views a point: 8 MB a call), not the kernel's work. A multiple of the kernel's blocks, so the
answers do not depend on it."""


def _group_slots(groups: Sequence[tuple[Tensor, Tensor]]) -> tuple[Tensor, Tensor, Tensor]:
    """View groups ``[(point_indices (p,), view_indices (k,)), ...]`` -> the points of every group
    (G,), each one's views (G, k_max) and slot mask (G, k_max) (False = padding, a masked view).
    Groups come largest view set first, so that a chunk of consecutive points can drop the padding
    columns none of its points uses (:func:`_chunk_slots`)."""
    k_max = max(int(views.numel()) for _, views in groups)
    members, view_idx, slots = [], [], []
    for idx, views in sorted(groups, key=lambda g: -int(g[1].numel())):
        n, k = int(idx.numel()), int(views.numel())
        padded = torch.zeros(k_max, dtype=torch.long, device=idx.device)
        padded[:k] = views
        mask = torch.zeros(k_max, dtype=torch.bool, device=idx.device)
        mask[:k] = True
        members.append(idx)
        view_idx.append(padded.expand(n, k_max))
        slots.append(mask.expand(n, k_max))
    return torch.cat(members), torch.cat(view_idx), torch.cat(slots)


def _chunk_slots(view_idx: Tensor, slots: Tensor, sel: slice) -> tuple[Tensor, Tensor]:
    """Rows ``sel`` of :func:`_group_slots`' (G, k_max) views and slot mask, without the trailing
    padding columns that no row of the chunk uses (padding is masked: the answers are the same)."""
    s = slots[sel]
    k = max(1, int(s.sum(dim=1).max())) if s.shape[0] else 1
    return view_idx[sel, :k], s[:, :k]


def _cell_view_sets(order: Tensor, chosen: Tensor, n_views: int) -> tuple[Tensor, list[Tensor]]:
    """Group cells by their set of chosen views: ``order`` (C, k) view indices, ``chosen`` (C, k)
    bool, views 0..n_views-1. Returns each cell's group (C,) long (-1 for a cell with no chosen
    view) and each group's views (ascending), groups in the order of their first cell. Equal to
    collecting ``tuple(sorted(chosen views))`` per cell in a dict, without a Python loop over
    cells."""
    n_cells = order.shape[0]
    rows = torch.where(chosen, order, torch.full_like(order, n_views)).sort(dim=1).values  # unused last
    if n_views <= 62:  # each set as one int64 bit mask: a 1-D unique, several times faster than by rows
        bits = torch.where(chosen, torch.bitwise_left_shift(torch.ones_like(order), order), 0).sum(dim=1)
        _, inverse = torch.unique(bits, return_inverse=True)  # a cell's views are distinct: the sum is the OR
        n_groups = int(inverse.max()) + 1 if n_cells else 0
    else:
        uniq, inverse = torch.unique(rows, dim=0, return_inverse=True)  # (G, k), (C,)
        n_groups = uniq.shape[0]
    first = torch.full((n_groups,), n_cells, dtype=torch.long, device=order.device)
    first.scatter_reduce_(0, inverse, torch.arange(n_cells, device=order.device), reduce="amin")
    uniq = rows[first]  # (G, k) each group's sorted views (and the unused marks)
    by_first = torch.argsort(first)  # groups in the order of their first cell
    non_empty = uniq[by_first, 0] < n_views
    kept = by_first[non_empty]
    new_id = torch.full((uniq.shape[0],), -1, dtype=torch.long, device=order.device)
    new_id[kept] = torch.arange(kept.numel(), device=order.device)
    keys = [row[row < n_views] for row in uniq[kept]]
    return new_id[inverse], keys


def _cell_inverse(cell: Tensor) -> Tensor:
    """``torch.unique(cell, dim=0, return_inverse=True)[1]`` for (P, 3) int64 cells: the same
    indices (cells in lexicographic order), from a 1-D unique of one int64 key per cell (the
    row-wise unique is several times slower on the CPU)."""
    lo = cell.amin(dim=0)
    span = cell.amax(dim=0) - lo + 1  # (3,)
    if bool((span.double().prod() >= 2**62).item()):  # keys would overflow: the row-wise unique
        return torch.unique(cell, dim=0, return_inverse=True)[1]
    c = cell - lo
    key = (c[:, 0] * span[1] + c[:, 1]) * span[2] + c[:, 2]
    return torch.unique(key, return_inverse=True)[1]


def _resolve_checkpoint(path: str) -> Path:
    p = Path(path).expanduser()
    if p.is_absolute() or p.exists() or p.with_suffix(".json").exists():
        return p
    in_repo = data_root() / p  # the checkout, or the installed wheel's packaged data
    if in_repo.exists() or in_repo.with_suffix(".json").exists():
        return in_repo
    return p


class ModelRuntime:
    """The learned GOV-NeSF model serving a keyframe window.

    Args:
        config: runtime settings.
        model: an already built model (tests, benchmarks); when None the checkpoint is loaded.
            A missing or unreadable checkpoint does not raise: :attr:`load_error` says why and
            every query raises :class:`RuntimeNotReady` with that message.
        text_encoder: ``space -> TextEncoder`` (default ``mapper.ov.encoders.get_text_encoder``).

    Thread safety: the window callbacks may run on any thread (they take a short private lock);
    queries are serialised by the runtime's own lock, never the node's.
    """

    def __init__(
        self,
        config: ModelRuntimeConfig | None = None,
        *,
        model: GovNeSF | None = None,
        text_encoder: Callable[[str], TextEncoder] = get_text_encoder,
    ) -> None:
        self.config = config or ModelRuntimeConfig()
        self.device = default_device() if self.config.device == "auto" else torch.device(self.config.device)
        self.load_error: str | None = None
        self.metadata: dict[str, Any] = {}
        self.model: GovNeSF | None = None
        self.point_head: FusionNet | None = None
        """The network weighing point answers' views in place of the model's FusionNet (None: the
        model's own); ``model.point_head`` (:mod:`mapper.model.point_head`)."""
        if model is not None:
            self.model = model.to(self.device).eval()
        else:
            self._load_checkpoint()
        self._text_encoder = text_encoder
        self._pending_lock = threading.Lock()
        self._pending: dict[Hashable, tuple[str, Any]] = {}  # key -> ("add", keyframe) | ("evict", None)
        self._lock = threading.RLock()
        self._entries: dict[Hashable, _ViewEntry] = {}
        self._volume: CostVolume | None = None
        self._prepared: _Prepared | None = None
        self.version = 0
        """+1 whenever an applied change altered the views or the volume."""
        self.rebuilds = 0
        """How often the volume was rebuilt on new bounds (the one non-incremental step)."""
        self.bounds_outliers = 0
        """Keyframes left out of the volume's bounds (``bounds_outlier_m``), each counted once."""
        self._bounds_outliers_logged: set[tuple[str, int, int]] = set()
        self.views_added = 0
        self.views_removed = 0
        self._attached: list[Any] = []
        self._view_extents: dict[tuple[str, int, int], Tensor] = {}  # set_view_extent; _pending_lock
        self._extents_changed: set[tuple[str, int, int]] = set()
        self._depth_priors: dict[tuple[str, int, int], Tensor] = {}  # set_view_depth_prior; _pending_lock
        self._priors_changed: set[tuple[str, int, int]] = set()

    # -- set-up -------------------------------------------------------------------------------

    def _load_checkpoint(self) -> None:
        path = _resolve_checkpoint(self.config.checkpoint)
        try:
            from mapper.model.checkpoint import load_model

            self.model, self.metadata = load_model(path, device=self.device)
        except FileNotFoundError as exc:
            self.load_error = (
                f"the GOV-NeSF checkpoint {str(path)!r} was not found ({exc}); train one "
                "(govnesf train) or set model.checkpoint to an existing file"
            )
        except Exception as exc:  # corrupt file, wrong format, ...: serve the rest, say why
            self.load_error = f"the GOV-NeSF checkpoint {str(path)!r} could not be loaded: {exc}"
        if not self.load_error and self.config.point_head:
            self._load_point_head(path)
        if self.load_error:
            log.error("%s", self.load_error)
        else:
            log.info("loaded GOV-NeSF checkpoint %s on %s", path, self.device)

    def _load_point_head(self, checkpoint: Path) -> None:
        """``model.point_head`` beside the loaded checkpoint. ``"auto"``: ``NAME-point-head`` next to
        the checkpoint ``NAME`` when it exists and was distilled from these weights, else the
        model's own FusionNet (logged, never an error). A named head that is missing, unreadable or
        distilled from other weights leaves the model unserved (``load_error`` says why)."""
        from mapper.model.checkpoint import checkpoint_paths
        from mapper.model.point_head import head_paths, load_point_head

        auto = self.config.point_head == "auto"
        if auto:
            meta_path = checkpoint_paths(checkpoint)[1]
            path = meta_path.with_name(meta_path.stem + "-point-head")
            if not head_paths(path)[1].exists():
                log.info("point answers use the checkpoint's FusionNet (no %s.json)", path)
                return
        else:
            path = _resolve_checkpoint(self.config.point_head)
        try:
            self.point_head, meta = load_point_head(
                path, teacher_sha256=self.metadata.get("weights_sha256"), device=self.device
            )
        except (ValueError, OSError) as exc:
            if auto:
                log.warning("point answers use the checkpoint's FusionNet: %s", exc)
                return
            missing = isinstance(exc, FileNotFoundError)
            self.load_error = (f"the point head {str(path)!r} was not found ({exc}); set model.point_head"
                               if missing else f"the point head {str(path)!r} could not be loaded: {exc}")
            self.model = None
            return
        log.info("point answers use the point head %s (%s)", path, meta["fusion"])

    @property
    def ready(self) -> bool:
        """True when a model is loaded (queries may still need keyframes)."""
        return self.model is not None

    def _require_model(self) -> GovNeSF:
        if self.model is None:
            raise RuntimeNotReady(self.load_error or "no GOV-NeSF model is loaded")
        return self.model

    @property
    def image_wh(self) -> tuple[int, int]:
        """(W, H) working size of the keyframes."""
        model = self._require_model()
        w = self.config.image_width or model.cfg.image_wh[0]
        h = self.config.image_height or model.cfg.image_wh[1]
        return int(w), int(h)

    @property
    def ov_wh(self) -> tuple[int, int]:
        """(w, h) of the common OV grid: the working size / 4 (the 2D feature resolution)."""
        w, h = self.image_wh
        return max(1, math.ceil(w / 4)), max(1, math.ceil(h / 4))

    @property
    def source_views(self) -> int:
        return self.config.source_views or self._require_model().cfg.num_source_views

    @property
    def point_source_views(self) -> int:
        """Source views per point for point answers (``segment``, ``point_features``)."""
        return max(self.config.point_source_views, self.source_views)

    @property
    def samples_per_ray(self) -> int:
        return self.config.samples_per_ray or self._require_model().cfg.render.n_samples

    def attach(self, window: Any) -> None:
        """Follow a :class:`mapper.map.window.KeyframeWindow`: register the callbacks and record every
        keyframe already in it. Call with the node's state lock held (the window is not thread-safe)."""
        window.on_add.append(self.on_add)
        window.on_evict.append(self.on_evict)
        self._attached.append(window)
        for keyframe in window.keyframes:
            self.on_add(keyframe)

    # -- window callbacks (under the node's state lock: O(1), no model work) ---------------------

    def on_add(self, keyframe: Any) -> None:
        """Record that ``keyframe`` entered the window (applied by the next :meth:`sync`)."""
        with self._pending_lock:
            previous = self._pending.get(keyframe)
            if previous is not None and previous[0] == "evict":
                del self._pending[keyframe]  # evicted and re-added before anything was applied
            else:
                self._pending[keyframe] = ("add", keyframe)

    def on_evict(self, keyframe: Any) -> None:
        """Record that ``keyframe`` left the window."""
        with self._pending_lock:
            previous = self._pending.get(keyframe)
            if previous is not None and previous[0] == "add":
                del self._pending[keyframe]  # never applied: nothing to undo
            else:
                self._pending[keyframe] = ("evict", None)

    @property
    def pending(self) -> int:
        """Window changes recorded but not applied yet."""
        with self._pending_lock:
            return len(self._pending)

    # -- applying changes ---------------------------------------------------------------------

    @torch.no_grad()
    def sync(self) -> int:
        """Apply the recorded window changes to the views and the cost volume (incrementally).

        Returns the number of changes applied. Raises :class:`RuntimeNotReady` without a model.
        """
        model = self._require_model()
        with self._pending_lock:
            pending, self._pending = self._pending, {}
            extents_changed, self._extents_changed = self._extents_changed, set()
            priors_changed, self._priors_changed = self._priors_changed, set()
        if not pending:
            if not extents_changed and not priors_changed:
                return 0
            return self._apply_view_extents(extents_changed) + self._apply_depth_priors(priors_changed)
        with self._lock:
            removed = [key for key, (op, _) in pending.items() if op == "evict"]
            added = [(key, kf) for key, (op, kf) in pending.items() if op == "add"]
            for key in removed:
                if key in self._entries:
                    del self._entries[key]
                    if self._volume is not None:
                        self._volume.remove_view(key)
                    self.views_removed += 1
            if not self._entries:
                self._volume = None  # window emptied (e.g. a map load): start from fresh bounds
            new_entries = self._prepare_entries(model, [kf for _, kf in added])
            for (key, _), entry in zip(added, new_entries, strict=True):
                self._entries[key] = entry
            changed = self._refresh_extents(extents_changed)
            self._refresh_depth_priors(priors_changed)
            self._update_bounds([*new_entries, *changed], evicted=bool(removed) or bool(changed))
            assert self._volume is not None or not self._entries
            if self._volume is not None:
                for (key, _), entry in zip(added, new_entries, strict=True):
                    if key not in self._volume.view_ids:
                        self._volume.add_view(
                            key, entry.features, entry.K, entry.world_from_cam, self.image_wh
                        )
            self.views_added += len(added)
            self.version += 1
            self._prepared = None
            return len(pending)

    def _prepare_entries(self, model: GovNeSF, keyframes: Sequence[Any]) -> list[_ViewEntry]:
        """Resize, encode (batched) and cache the new keyframes."""
        if not keyframes:
            return []
        width, height = self.image_wh
        rgbs, Ks = [], []
        for kf in keyframes:
            rgb = torch.tensor(np.asarray(kf.rgb)).to(self.device)
            rgb = rgb.permute(2, 0, 1).float().div_(255.0)  # (3, H0, W0)
            h0, w0 = rgb.shape[-2:]
            if (w0, h0) != (width, height):
                rgb = F.interpolate(
                    rgb.unsqueeze(0), size=(height, width), mode="bilinear", align_corners=False,
                    antialias=w0 > width or h0 > height,
                ).squeeze(0).clamp_(0.0, 1.0)  # fmt: skip
            sx, sy = width / w0, height / h0
            K0 = torch.tensor(np.array(kf.K, dtype=np.float64), device=self.device)
            Ks.append(torch.stack([K0[0] * sx, K0[1] * sy, K0[2] * sx, K0[3] * sy]).float())
            rgbs.append(rgb)
        features = []
        batch = 8
        stacked = torch.stack(rgbs)
        for i in range(0, len(rgbs), batch):
            features.append(model.encode(stacked[i : i + batch]))
        feats = torch.cat(features)
        observed = [self._view_extent(kf) for kf in keyframes]  # set_view_extent (RGB-only keyframes)
        with self._pending_lock:
            priors = [self._depth_priors.get(_keyframe_key(kf)) for kf in keyframes]
        entries = []
        for i, kf in enumerate(keyframes):
            pose = torch.tensor(np.array(kf.world_from_cam, dtype=np.float64), device=self.device).float()
            ov = None
            if kf.ov is not None:
                ov_t = torch.tensor(np.asarray(kf.ov)).to(self.device, torch.float32)
                ov_t = ov_t.permute(2, 0, 1)  # (D, h, w)
                ow, oh = self.ov_wh
                if tuple(ov_t.shape[1:]) != (oh, ow):
                    ov_t = F.interpolate(
                        ov_t.unsqueeze(0), size=(oh, ow), mode="bilinear", align_corners=False,
                        antialias=ov_t.shape[1] > oh or ov_t.shape[2] > ow,
                    ).squeeze(0)  # fmt: skip
                ov = ov_t.to(torch.float16)
            depth = None
            if kf.depth_m is not None:
                d = torch.tensor(np.asarray(kf.depth_m)).to(self.device, torch.float32)
                d = torch.where(torch.isfinite(d) & (d > 0), d, torch.zeros_like(d))
                if tuple(d.shape) != (height, width):
                    d = F.interpolate(d[None, None], size=(height, width), mode="nearest-exact")[0, 0]
                depth = d
            entries.append(
                _ViewEntry(
                    seq=int(kf.seq),
                    rgb=rgbs[i],
                    features=feats[i],
                    ov=ov,
                    ov_space=kf.ov_space,
                    depth_m=depth,
                    K=Ks[i],
                    world_from_cam=pose,
                    extent=self._extent_points(Ks[i], pose, depth, observed[i]),
                    key=_keyframe_key(kf),
                    observed=None if depth is not None else observed[i],
                    depth_prior=None if depth is not None else self._prior_at_working_size(priors[i]),
                )
            )
        return entries

    def _extent_points(
        self, K: Tensor, world_from_cam: Tensor, depth_m: Tensor | None, observed: Tensor | None = None
    ) -> Tensor:
        """(M, 3) world points a keyframe observed: depth back-projected (<= max_range_m, up to
        ~1024 points) when it has enough depth, else the ``observed`` points
        :meth:`set_view_extent` gave it (e.g. triangulated), else its frustum sampled up to
        max_range_m."""
        width, height = self.image_wh
        cfg = self.config
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

    # -- view extents (bounds that follow the room without depth) --------------------------------

    def set_view_extent(self, key: tuple[str, int, int], points_m: np.ndarray | None) -> None:
        """Give the keyframe ``key = (camera, seq, stamp_ns)`` the world points it observed,
        ``points_m`` (N, 3) metres, N >= 1 (None: back to its frustum up to ``max_range_m``).

        For keyframes without depth only: the volume's bounds then cover these points (and the
        camera) instead of the frustum up to the fixed ``max_range_m``, so the volume follows what
        the sparse geometry (:mod:`mapper.node.plugins.triangulation`) found, growing with the
        room within the voxel budget. Thread-safe; applied by the next :meth:`sync`, which re-checks
        the bounds and rebuilds the volume when they moved. Extents of keyframes that left the
        window are dropped at the next change. Raises ``ValueError`` (nothing changed) on a bad array."""
        pts = None
        if points_m is not None:
            arr = np.asarray(points_m, np.float64)
            if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 1 or not np.isfinite(arr).all():
                raise ValueError(f"points_m must be a finite (N >= 1, 3) array, got shape {arr.shape}")
            pts = torch.tensor(arr, dtype=torch.float32, device=self.device)
        self._set_pending(self._view_extents, self._extents_changed, key, pts)

    def _view_extent(self, keyframe: Any) -> Tensor | None:
        with self._pending_lock:
            return self._view_extents.get(_keyframe_key(keyframe))

    def _refresh_extents(self, keys: set[tuple[str, int, int]]) -> list[_ViewEntry]:
        """Recompute the extent of the depth-less entries whose observed points changed."""
        if not keys:
            return []
        observed = self._take_pending(self._view_extents, keys)
        changed = []
        for entry in self._entries.values():
            if entry.key in observed and entry.depth_m is None and observed[entry.key] is not entry.observed:
                entry.observed = observed[entry.key]
                entry.extent = self._extent_points(entry.K, entry.world_from_cam, None, entry.observed)
                changed.append(entry)
        return changed

    def set_view_depth_prior(self, key: tuple[str, int, int], depth_m: np.ndarray | None) -> None:
        """Give the keyframe ``key = (camera, seq, stamp_ns)`` a sparse z-depth prior ``depth_m``
        (H, W) metres, 0 = none, any size covering the image (None: remove it).

        For keyframes without depth only, and only for Depth Guided Masking (``segment_points``
        with ``use_depth``): a view is masked for a point where the prior exists and disagrees
        with the point's depth, and kept where it has no prior, as DGM treats a depth map's holes.
        Resized to the working size with nearest lookup. Thread-safe; applied by the next
        :meth:`sync`. Raises ``ValueError`` (nothing changed) on a bad array."""
        prior = None
        if depth_m is not None:
            arr = np.asarray(depth_m, np.float32)
            if arr.ndim != 2 or arr.size == 0 or not np.isfinite(arr).all() or (arr < 0).any():
                raise ValueError(f"depth_m must be a finite, non-negative (H, W) array, got {arr.shape}")
            prior = torch.tensor(arr, device=self.device)
        self._set_pending(self._depth_priors, self._priors_changed, key, prior)

    def _set_pending(self, store: dict[tuple[str, int, int], Tensor], changed: set[tuple[str, int, int]],
                     key: tuple[str, int, int], value: Tensor | None) -> None:
        """Set (or with None remove) ``store[key]`` and mark ``key`` changed for the next sync."""
        with self._pending_lock:
            if value is None:
                store.pop(key, None)
            else:
                store[key] = value
            changed.add(key)

    def _take_pending(self, store: dict[tuple[str, int, int], Any], keys: set[tuple[str, int, int]]
                      ) -> dict[tuple[str, int, int], Any]:
        """``{key: store.get(key)}`` for the changed ``keys``, under the pending lock; entries of
        keyframes that left the window (and did not just change) are dropped from ``store``."""
        live = {e.key for e in self._entries.values()}
        with self._pending_lock:
            taken = {k: store.get(k) for k in keys}
            for k in list(store):
                if k not in live and k not in keys:
                    del store[k]
        return taken

    def _prior_at_working_size(self, prior: Tensor | None) -> Tensor | None:
        if prior is None:
            return None
        width, height = self.image_wh
        if tuple(prior.shape) != (height, width):
            prior = F.interpolate(prior[None, None], size=(height, width), mode="nearest-exact")[0, 0]
        return prior

    def _refresh_depth_priors(self, keys: set[tuple[str, int, int]]) -> int:
        """Set the depth prior of the depth-less entries whose prior changed; returns how many."""
        if not keys:
            return 0
        priors = self._take_pending(self._depth_priors, keys)
        changed = 0
        for entry in self._entries.values():
            if entry.key in priors and entry.depth_m is None:
                entry.depth_prior = self._prior_at_working_size(priors[entry.key])
                changed += 1
        return changed

    def _apply_depth_priors(self, keys: set[tuple[str, int, int]]) -> int:
        """:meth:`sync` without window changes: new depth priors change the cached views."""
        with self._lock:
            changed = self._refresh_depth_priors(keys)
            if changed:
                self.version += 1
                self._prepared = None
            return changed

    @torch.no_grad()
    def _apply_view_extents(self, keys: set[tuple[str, int, int]]) -> int:
        """:meth:`sync` without window changes: new view extents may move the bounds."""
        with self._lock:
            changed = self._refresh_extents(keys)
            if not changed or self._volume is None:
                return len(changed)
            rebuilds = self.rebuilds
            self._update_bounds(changed, evicted=True)
            if self.rebuilds != rebuilds:
                self.version += 1
                self._prepared = None
            elif self._prepared is not None:  # same views and volume: only the render volumes' bounds move
                self._prepared.extents = _render_extents(self._entries.values())
                self._prepared.render_volumes.clear()
            return len(changed)

    def _target_bounds(self) -> VolumeBounds:
        model = self._require_model()
        points = torch.cat([e.extent for e in self._bounds_entries()])
        vcfg = model.cfg.volume
        return bounds_from_points(
            points.cpu(),
            max_voxels=self.config.max_voxels or vcfg.max_voxels,
            min_voxel_size_m=self.config.voxel_size_m or vcfg.min_voxel_size_m,
            margin_m=self.config.bounds_margin_m,
        )

    def _bounds_entries(self) -> list[_ViewEntry]:
        """The window's keyframes whose extent is within ``config.bounds_outlier_m`` of the others'
        (the median of their median points); all of them when that would leave none."""
        entries = [e for e in self._entries.values() if e.extent.shape[0]]
        if len(entries) < 3:
            return entries or list(self._entries.values())
        centres = torch.stack([e.extent.median(dim=0).values for e in entries]).to(torch.float64)  # (E, 3)
        centre = centres.median(dim=0).values
        far = torch.linalg.vector_norm(centres - centre, dim=1) > self.config.bounds_outlier_m
        if not bool(far.any()) or bool(far.all()):
            return entries
        outliers = far.tolist()
        for e, out in zip(entries, outliers, strict=True):
            if out and e.key not in self._bounds_outliers_logged:
                self._bounds_outliers_logged.add(e.key)
                self.bounds_outliers += 1
                log.warning("keyframe %s (seq %d): what it observed lies more than %.0f m from the window's "
                            "other keyframes; left out of the model's volume bounds (a wrong pose?)",
                            e.key[0] or "-", e.seq, self.config.bounds_outlier_m)
        return [e for e, out in zip(entries, outliers, strict=True) if not out]

    def _update_bounds(self, new_entries: Sequence[_ViewEntry], evicted: bool) -> None:
        """Create the volume, or move it (recentre / grow / shrink) + rebuild when the window's
        observations no longer fit it.

        Grow: a new view has more than ``rebuild_outside_fraction`` of its extent points outside
        the current box. Shrink (only checked after evictions): the box the window needs now has at
        most half the current box's volume (the robot left an area). Either way the new bounds are
        ``bounds_from_points`` over the whole window and the volume is rebuilt from the stored views.
        """
        model = self._require_model()
        if not self._entries:
            return
        if self._volume is None:
            self._volume = CostVolume(self._target_bounds(), model.cfg.encoder.feature_dim, self.device)
            return
        bounds = self._volume.bounds
        lo = torch.tensor(bounds.origin_m, device=self.device)
        hi = torch.tensor(bounds.max_corner_m, device=self.device)
        grow = any(
            float(((e.extent < lo) | (e.extent > hi)).any(dim=-1).float().mean())
            > self.config.rebuild_outside_fraction
            for e in new_entries
        )
        if not grow and not evicted:
            return
        target = self._target_bounds()
        if target == bounds:
            return

        def box_volume(b: VolumeBounds) -> float:
            return float(np.prod([n * b.voxel_size_m for n in b.dims]))

        if grow or box_volume(target) <= 0.5 * box_volume(bounds):
            log.info(
                "cost volume moves: origin %s dims %s voxel %.3f m -> origin %s dims %s voxel %.3f m",
                tuple(round(o, 2) for o in bounds.origin_m), bounds.dims, bounds.voxel_size_m,
                tuple(round(o, 2) for o in target.origin_m), target.dims, target.voxel_size_m,
            )  # fmt: skip
            self._volume.rebuild(target)
            self.rebuilds += 1

    # -- cached per version -------------------------------------------------------------------

    @property
    def bounds(self) -> VolumeBounds | None:
        """Current cost-volume bounds (None before the first keyframe)."""
        return None if self._volume is None else self._volume.bounds

    @property
    def cost_volume(self) -> CostVolume | None:
        """The incremental cost volume (read it under no concurrent :meth:`sync`)."""
        return self._volume

    def __len__(self) -> int:
        return len(self._entries)

    def memory_bytes(self) -> int:
        """Bytes held: per-view caches, cost-volume sums, and the cached query tensors."""
        total = sum(e.nbytes for e in list(self._entries.values()))  # may race with sync()
        if self._volume is not None:
            total += self._volume.bounds.num_voxels * (1 + 2 * self._volume.feature_dim) * 8
        prep = self._prepared
        if prep is not None:
            for t in (prep.volume, prep.rgb, prep.features, prep.ov, prep.depth_m):
                if t is not None:
                    total += t.numel() * t.element_size()
        return total

    def stats(self) -> dict[str, Any]:
        """Counters for the node's status reply."""
        b = self.bounds
        return {
            "ready": self.ready,
            "load_error": self.load_error,
            "views": len(self._entries),
            "pending": self.pending,
            "version": self.version,
            "rebuilds": self.rebuilds,
            "bounds_outliers": self.bounds_outliers,
            "views_added": self.views_added,
            "views_removed": self.views_removed,
            "bounds": None
            if b is None
            else {"origin_m": list(b.origin_m), "voxel_size_m": b.voxel_size_m, "dims": list(b.dims)},
            "memory_bytes": self.memory_bytes(),
        }

    @torch.no_grad()
    def _prepare(self) -> _Prepared:
        """Sync, then the per-version cache (stacked views, 3D U-Net output). Holds ``_lock``."""
        model = self._require_model()
        self.sync()
        if self._prepared is not None and self._prepared.version == self.version:
            return self._prepared
        if not self._entries or self._volume is None:
            raise RuntimeNotReady("no keyframes in the window yet: stream frames to the node first")
        entries = list(self._entries.values())
        has_ov = torch.tensor([e.ov is not None for e in entries], device=self.device)
        ov = None
        if bool(has_ov.any()):
            dims = {int(e.ov.shape[0]) for e in entries if e.ov is not None}
            if len(dims) != 1:
                raise RuntimeNotReady(f"keyframes carry OV features of different dimensions {sorted(dims)}")
            d = dims.pop()
            ow, oh = self.ov_wh
            ov = torch.stack(
                [
                    e.ov.float() if e.ov is not None else torch.zeros(d, oh, ow, device=self.device)
                    for e in entries
                ]
            )
        has_depth = any(e.depth_m is not None or e.depth_prior is not None for e in entries)
        depth = None
        if has_depth:  # input depth, else the sparse prior (set_view_depth_prior), else none (0)
            w, h = self.image_wh
            depth = torch.stack(
                [
                    e.depth_m if e.depth_m is not None
                    else e.depth_prior if e.depth_prior is not None
                    else torch.zeros(h, w, device=self.device)
                    for e in entries
                ]
            )
        spaces = {e.ov_space for e in entries if e.ov is not None}
        volume, support = self._volume_and_support(model, *self._volume.statistics())
        prior_only = torch.tensor([e.depth_m is None and e.depth_prior is not None for e in entries],
                                  device=self.device)
        input_depth = torch.tensor([e.depth_m is not None for e in entries], device=self.device)
        self._prepared = _Prepared(
            version=self.version,
            prior_only=prior_only,
            input_depth=input_depth,
            bounds=self._volume.bounds,
            volume=volume,
            rgb=torch.stack([e.rgb for e in entries]),
            features=torch.stack([e.features for e in entries]),
            ov=ov,
            has_ov=has_ov,
            depth_m=depth,
            K=torch.stack([e.K for e in entries]),
            world_from_cam=torch.stack([e.world_from_cam for e in entries]),
            ov_space=spaces.pop() if len(spaces) == 1 else None,
            support=support,
            extents=_render_extents(entries),
        )
        return self._prepared

    def _volume_and_support(self, model: GovNeSF, mean: Tensor, var: Tensor, count: Tensor
                            ) -> tuple[Tensor, Tensor | None]:
        """Cost-volume statistics (C, X, Y, Z) x 2 and (X, Y, Z) -> the 3D U-Net's volume (Dv, X, Y, Z)
        and the ``min_view_support`` mask (1, X, Y, Z) (None when that is off)."""
        volume = model.volume_features(cost_volume_features(mean, var, count).to(self.device))
        support = None
        if self.config.min_view_support > 1:
            support = (count >= self.config.min_view_support).to(self.device, torch.float32)[None]
        return volume, support

    # Most render volumes kept per version, the oldest dropped first (a client rendering a few poses
    # over and over reuses them).
    _RENDER_VOLUMES_KEPT = 8

    @torch.no_grad()
    def _render_prep(self, model: GovNeSF, prep: _Prepared, K: Tensor, world_from_cam: Tensor,
                     width: int, height: int, n: int) -> _Prepared:
        """``prep`` with the volume of the ``n`` keyframes that best overlap the view (K (4,) for
        width x height, world_from_cam (4, 4)) and its bounds, or ``prep`` itself: n = 0, a
        window of at most n keyframes, or fewer than 2 of them overlapping the view
        (``ModelRuntimeConfig.render_volume_views``)."""
        if n <= 0 or len(prep) <= n:
            return prep
        chosen = self._overlapping_views(prep, K, world_from_cam, width, height, n)
        if chosen.numel() < 2:
            return prep
        key = tuple(sorted(chosen.tolist()))  # the volume does not depend on the order
        local = prep.render_volumes.get(key)
        if local is not None:
            return local
        idx = torch.tensor(key, device=prep.K.device)
        vcfg = model.cfg.volume
        observed = torch.cat([prep.extents[i] for i in key]).cpu()
        lo, hi = torch.tensor(prep.bounds.origin_m), torch.tensor(prep.bounds.max_corner_m)
        # inside the window's box: a keyframe left out of its bounds (a wild pose) is no reason to
        # stretch this one
        observed = observed[((observed >= lo) & (observed <= hi)).all(dim=-1)]
        if observed.shape[0] < 2:
            return prep
        bounds = bounds_from_points(
            observed,
            max_voxels=self.config.max_voxels or vcfg.max_voxels,
            min_voxel_size_m=self.config.voxel_size_m or vcfg.min_voxel_size_m,
            margin_m=self.config.bounds_margin_m,
        )
        features, K_views, poses = prep.features[idx], prep.K[idx], prep.world_from_cam[idx]
        volume, support = self._volume_and_support(
            model, *build_cost_volume(bounds, features, K_views, poses, self.image_wh)
        )
        local = _Prepared(
            version=prep.version, bounds=bounds, volume=volume, rgb=prep.rgb, features=prep.features,
            ov=prep.ov, has_ov=prep.has_ov, depth_m=prep.depth_m, K=prep.K,
            world_from_cam=prep.world_from_cam, ov_space=prep.ov_space, support=support,
            prior_only=prep.prior_only, extents=prep.extents, parent=prep, render_views=len(key),
        )
        if len(prep.render_volumes) >= self._RENDER_VOLUMES_KEPT:
            prep.render_volumes.pop(next(iter(prep.render_volumes)))
        prep.render_volumes[key] = local
        return local

    def _overlapping_views(self, prep: _Prepared, K: Tensor, world_from_cam: Tensor, width: int, height: int,
                           n: int) -> Tensor:
        """(k,) long, k <= n: the views whose observed points fall most inside the view (share of
        each view's extent points in front of the camera, at most ``far_m`` away, inside the
        image; the training's ``overlap_scores``), best first; views with no point inside are
        left out. Ties go to the camera nearest the view's, then to the older keyframe."""
        counts = torch.tensor([e.shape[0] for e in prep.extents])
        points = torch.cat(prep.extents).to(torch.float32)
        cam_from_world = invert_pose(world_from_cam.to(points))
        uv, z = project_points(points[None], K.to(points)[None], cam_from_world[None])
        seen = in_view(uv, z, width, height)[0] & (z[0] <= self.config.far_m)
        view_of = torch.repeat_interleave(torch.arange(len(counts)), counts).to(seen.device)
        inside = torch.zeros(len(counts), device=seen.device).index_add_(0, view_of, seen.to(torch.float32))
        share = (inside.cpu() / counts.clamp_min(1)).to(torch.float64)
        centre = world_from_cam[:3, 3].to(prep.world_from_cam)
        distance = (prep.world_from_cam[:, :3, 3] - centre).norm(dim=-1).cpu()
        by_distance = torch.argsort(distance, stable=True)
        order = by_distance[torch.argsort(-share[by_distance], stable=True)][:n]
        return order[share[order] > 0]

    def _density(self, model: GovNeSF, prep: _Prepared, points: Tensor) -> tuple[Tensor, Tensor]:
        """sigma (P,) and volume feature (P, Dv) at (P, 3) points; sigma is 0 where fewer than
        ``min_view_support`` views see the volume (trilinear in the support mask). A render
        volume's prep (``parent``) has no density outside its bounds; v there is the window's."""
        sigma, v = model.density_at(prep.volume, prep.bounds, points)
        if prep.support is not None:
            support, _ = sample_volume(prep.support, prep.bounds, points)
            sigma = sigma * support[..., 0]
        if prep.parent is not None:  # a render volume: the window's features outside it
            lo, hi = points.new_tensor(prep.bounds.origin_m), points.new_tensor(prep.bounds.max_corner_m)
            outside = ~((points >= lo) & (points <= hi)).all(dim=-1)
            if bool(outside.any()):
                window = prep.parent
                v = v.clone()
                v[outside] = sample_volume(window.volume, window.bounds,
                                           points[outside].to(window.volume.dtype))[0].to(v.dtype)
        return sigma, v

    @torch.no_grad()
    def occupancy(self) -> tuple[VolumeBounds, Tensor]:
        """The occupancy grid (cached per version): (X, Y, Z) bool, True where the density at the
        voxel's 2x2x2 sub-samples or at a neighbour's reaches ``occupancy_threshold``."""
        with self._lock:
            prep = self._prepare()
            return prep.bounds, self._occupancy(prep)

    def _occupancy(self, prep: _Prepared) -> Tensor:
        """The occupancy grid: the density's (``_density_occupancy``) less the free space the
        depth priors carve (``carve_free_space``)."""
        occupied = self._density_occupancy(prep)
        if not self.config.carve_free_space:
            return occupied
        if prep.free_space is None:
            prep.free_space = self._free_space(prep)
        return occupied & ~prep.free_space

    def _free_space(self, prep: _Prepared) -> Tensor:
        """(X, Y, Z) bool: voxels the prior rays of at least ``carve_min_views`` keyframes without
        input depth cross short of their surface, away from every prior surface point."""
        cfg = self.config
        b = prep.bounds
        dims = torch.tensor(b.dims, device=self.device)
        n_vox = int(np.prod(b.dims))
        empty = torch.zeros(b.dims, dtype=torch.bool, device=self.device)
        if prep.depth_m is None or prep.prior_only is None or not bool(prep.prior_only.any()):
            return empty
        origin = torch.tensor(b.origin_m, dtype=torch.float32, device=self.device)
        step = 0.5 * b.voxel_size_m
        crossed = torch.zeros(n_vox, dtype=torch.int32, device=self.device)
        surface = torch.zeros(n_vox, dtype=torch.bool, device=self.device)

        def linear(world: Tensor) -> tuple[Tensor, Tensor]:  # (..., 3) -> voxel index, inside
            vox = torch.floor((world - origin) / b.voxel_size_m).long()
            inside = ((vox >= 0) & (vox < dims)).all(dim=-1)
            idx = (vox[..., 0] * b.dims[1] + vox[..., 1]) * b.dims[2] + vox[..., 2]
            return idx, inside

        for v in prep.prior_only.nonzero().squeeze(-1).tolist():
            depth = prep.depth_m[v]
            rows, cols = (depth > 0).nonzero(as_tuple=True)
            if rows.numel() == 0:
                continue
            keep = torch.linspace(0, rows.numel() - 1, min(cfg.carve_rays, rows.numel()), device=self.device)
            keep = keep.round().long()
            rows, cols = rows[keep], cols[keep]
            z = depth[rows, cols]
            K, pose = prep.K[v], prep.world_from_cam[v]
            ray = torch.stack([(cols.float() + 0.5 - K[2]) / K[0], (rows.float() + 0.5 - K[3]) / K[1],
                               torch.ones_like(z)], dim=-1)  # (R, 3), z = 1
            ray_w = ray @ pose[:3, :3].T
            end, inside = linear(z[:, None] * ray_w + pose[:3, 3])
            surface[end[inside]] = True
            t = torch.arange(1, int(float(z.max()) / step) + 1, device=self.device) * step  # (S,)
            before = t[None, :] <= (1.0 - cfg.carve_margin) * z[:, None]  # (R, S)
            pts = pose[:3, 3] + t[None, :, None] * ray_w[:, None, :]  # (R, S, 3)
            idx, inside = linear(pts)
            seen = torch.unique(idx[before & inside])
            crossed[seen] += 1
        near_surface = F.max_pool3d(surface.view(1, 1, *b.dims).float(), 3, 1, 1)[0, 0] > 0
        empty = (crossed.view(b.dims) >= cfg.carve_min_views) & ~near_surface
        return empty

    def _density_occupancy(self, prep: _Prepared) -> Tensor:
        if prep.max_density is not None:
            return prep.max_density >= self.config.occupancy_threshold
        model = self._require_model()
        b = prep.bounds
        axes = [
            (torch.arange(2 * n, dtype=torch.float32, device=self.device) + 0.5) * (b.voxel_size_m / 2) + o
            for n, o in zip(b.dims, b.origin_m, strict=True)
        ]
        grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
        sigma = torch.cat(
            [self._density(model, prep, grid[i : i + 65536])[0] for i in range(0, grid.shape[0], 65536)]
        )
        fine = sigma.reshape(1, 1, 2 * b.dims[0], 2 * b.dims[1], 2 * b.dims[2])
        coarse = F.max_pool3d(fine, kernel_size=2, stride=2)
        dilated = F.max_pool3d(coarse, kernel_size=3, stride=1, padding=1)[0, 0]
        prep.max_density = dilated  # cached; the threshold is applied per call (config may change)
        return prep.max_density >= self.config.occupancy_threshold

    # -- view selection -----------------------------------------------------------------------

    def _view_groups(
        self, prep: _Prepared, points: Tensor, allowed: Tensor, k: int | None = None,
        depth_m: Tensor | None = None,
    ) -> list[tuple[Tensor, Tensor]]:
        """Split (P, 3) points into groups sharing a source-view set.

        Returns ``[(point_indices (p,), view_indices (k,)), ...]``; points no allowed view sees
        are in no group. With at most ``source_views`` allowed views there is one group (views
        that do not see a point are masked per point by the network). ``k``: views per group
        (default ``source_views``). ``depth_m`` (M, H, W): a view sees a point only where this
        depth agrees with it (or has none), the DGM test (``dgm_view_selection``), so the views
        chosen are the ones DGM keeps.
        """
        candidates = allowed.nonzero().squeeze(-1)
        k = self.source_views if k is None else k
        n_points = points.shape[0]
        if n_points == 0 or candidates.numel() == 0:
            return []
        width, height = self.image_wh
        cam_from_world = invert_pose(prep.world_from_cam[candidates])  # (M, 4, 4)
        Ks = prep.K[candidates]
        cpu_kernels = (points.device.type == "cpu"
                       and points.dtype == cam_from_world.dtype == Ks.dtype == torch.float32)
        if cpu_kernels and depth_m is not None:  # in view and passing the depth test, one compiled pass
            from mapper.model.ops.occlusion_kernel import depth_test_matrix

            ratio = self._require_model().cfg.render.depth_mask_ratio
            vis = torch.from_numpy(depth_test_matrix(points.numpy(), cam_from_world.numpy(), Ks.numpy(),
                                                     (width, height), DEFAULT_EPS,
                                                     depth_m[candidates].float().numpy(), ratio,
                                                     threads=torch.get_num_threads()))  # (P, M)
        elif cpu_kernels:
            from mapper.kernels.average_kernel import in_view_matrix

            vis = torch.from_numpy(in_view_matrix(points.numpy(), cam_from_world.numpy(), Ks.numpy(),
                                                  (width, height), DEFAULT_EPS,
                                                  threads=torch.get_num_threads()))  # (P, M)
        else:  # off the CPU kernels (CUDA): in view and, with depth_m, the DGM test of one projection
            view_depth = None if depth_m is None else depth_m[candidates]
            vis_parts = []
            for i in range(0, n_points, 65536):
                chunk = points[i : i + 65536]
                uv, z = project_points(chunk.unsqueeze(0).expand(len(candidates), -1, -1), Ks, cam_from_world)
                ok = in_view(uv, z, width, height)  # (M, p)
                if view_depth is not None:
                    ok = ok & self._depth_agrees(uv, z, view_depth)
                vis_parts.append(ok.T)  # (p, M)
            vis = torch.cat(vis_parts)  # (P, M)
        seen = vis.any(dim=1)
        if candidates.numel() <= k:
            idx = seen.nonzero().squeeze(-1)
            return [(idx, candidates)] if idx.numel() else []
        inverse = _cell_inverse(torch.floor(points / self.config.view_cell_m).long())
        n_cells = int(inverse.max()) + 1
        counts = torch.zeros(n_cells, len(candidates), device=self.device).index_add_(0, inverse, vis.float())
        n_in = torch.zeros(n_cells, device=self.device).index_add_(0, inverse, torch.ones_like(points[:, 0]))
        centre = torch.zeros(n_cells, 3, device=self.device).index_add_(0, inverse, points) / n_in[:, None]
        cams = camera_centers(prep.world_from_cam[candidates])  # (M, 3)
        offset = centre[:, None, :] - cams[None, :, :]  # (C, M, 3)
        if self.config.view_selection == "frontal":
            axis = prep.world_from_cam[candidates][:, :3, 2]  # (M, 3) optical axes
            key = -(F.normalize(offset, dim=-1) * axis[None]).sum(-1)  # in [-1, 1]
        else:
            key = offset.norm(dim=-1).clamp_max(1e5)
        frac = counts / n_in[:, None]
        tier = torch.where(frac >= 0.5, 0.0, torch.where(frac > 0, 1.0, 2.0))
        order = torch.argsort(tier * 1e6 + key, dim=1)[:, :k]  # (C, k)
        chosen_ok = torch.gather(tier, 1, order) < 2
        cell_group, keys = _cell_view_sets(order, chosen_ok, len(candidates))
        point_group = torch.where(seen, cell_group[inverse], torch.full_like(inverse, -1))
        # each group's points in ascending order, from one stable sort (was a scan per group)
        by_group = torch.argsort(point_group, stable=True)
        sizes = torch.bincount(point_group + 1, minlength=len(keys) + 1).tolist()  # [unseen, g0, g1, ...]
        parts = torch.split(by_group, sizes)
        out = []
        for g, views in enumerate(keys):
            idx = parts[g + 1]
            if idx.numel():
                out.append((idx, candidates[views]))
        return out

    def _all_views(
        self, prep: _Prepared, need_ov: bool, use_depth: bool, depth_m: Tensor | None = None
    ) -> SourceViews:
        """Every view of the window as one SourceViews (no copies), for ``sample_views_indexed``.
        ``depth_m`` (M, H, W): the depth DGM tests against instead of the window's (``_occluder_depth``)."""
        if need_ov:
            assert prep.ov is not None
            ov = prep.ov
        else:  # the OV branch is not needed: a 1-channel dummy keeps sampling cheap
            ov = torch.zeros(len(prep), 1, 1, 1, device=self.device)
        depth = (prep.depth_m if depth_m is None else depth_m) if use_depth else None
        return SourceViews(prep.rgb, prep.features, ov, prep.K, prep.world_from_cam, depth)

    def _source_views(
        self, prep: _Prepared, view_idx: Tensor, need_ov: bool, use_depth: bool, depth_m: Tensor | None = None
    ) -> SourceViews:
        if need_ov:
            assert prep.ov is not None
            ov = prep.ov[view_idx]
        else:  # the OV branch is not needed: a 1-channel dummy keeps sampling cheap
            ov = torch.zeros(len(view_idx), 1, 1, 1, device=self.device)
        window_depth = prep.depth_m if depth_m is None else depth_m
        depth = window_depth[view_idx] if (use_depth and window_depth is not None) else None
        return SourceViews(
            rgb=prep.rgb[view_idx],
            features=prep.features[view_idx],
            ov=ov,
            K=prep.K[view_idx],
            world_from_cam=prep.world_from_cam[view_idx],
            depth_m=depth,
        )

    # -- text ---------------------------------------------------------------------------------

    def _text_embeddings(self, prep: _Prepared, texts: Sequence[str]) -> Tensor:
        if prep.ov is None or not bool(prep.has_ov.any()):
            raise RuntimeNotReady(
                "semantic outputs need OV features, and no keyframe in the window carries 'ov'; "
                "send frames with ov (e.g. govnesf sim stream) or configure an in-process OV encoder"
            )
        if prep.ov_space is None:
            raise RuntimeNotReady("the window's keyframes carry OV features from several spaces")
        try:
            encoder = self._text_encoder(prep.ov_space)
        except UnknownSpaceError as exc:
            raise RuntimeNotReady(str(exc)) from None
        emb = torch.as_tensor(np.asarray(encoder.encode(list(texts)), dtype=np.float32), device=self.device)
        if emb.shape[-1] != prep.ov.shape[1]:
            raise RuntimeNotReady(
                f"text encoder for {prep.ov_space!r} gives {emb.shape[-1]}-d embeddings, the keyframes' "
                f"OV features are {prep.ov.shape[1]}-d"
            )
        return F.normalize(emb, dim=-1)

    # -- queries ------------------------------------------------------------------------------

    @torch.no_grad()
    def segment(
        self,
        points: np.ndarray | Tensor,  # (N, 3) float32 world points (m)
        texts: Sequence[str],
        *,
        use_depth: bool = False,
    ) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
        """Label world points with the best-matching text (3D segmentation, method ``govnesf``).

        Returns:
            label: (N,) int32 index into ``texts``, -1 where no keyframe (with OV) sees the point;
            score: (N,) float32 cosine similarity of that label (0 where label is -1);
            timing_ms: stage timings.
        """
        label, score, _, timing = self._segment(points, texts, use_depth=use_depth, keep_cosines=False)
        return label, score, timing

    @torch.no_grad()
    def segment_cosines(
        self,
        points: np.ndarray | Tensor,  # (N, 3) float32 world points (m)
        texts: Sequence[str],
        *,
        use_depth: bool = False,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, float]]:
        """:meth:`segment` with every text's cosine: (label (N,) int32, score (N,) float32, cosines
        (N, T) float32 of the blended feature with each text, zero rows where label is -1,
        timing_ms). The node blends them with the global map's (``queries.map_blend``)."""
        label, score, cos, timing = self._segment(points, texts, use_depth=use_depth, keep_cosines=True)
        assert cos is not None
        return label, score, cos, timing

    def _segment(
        self,
        points: np.ndarray | Tensor,  # (N, 3) float32 world points (m)
        texts: Sequence[str],
        *,
        use_depth: bool,
        keep_cosines: bool,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict[str, float]]:
        pts = points if isinstance(points, Tensor) else torch.tensor(np.array(points, dtype=np.float32))
        if pts.ndim != 2 or pts.shape[-1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {tuple(pts.shape)}")
        if not bool(torch.isfinite(pts).all()):
            raise ValueError("points must be finite (got NaN or Inf)")
        if not texts:
            raise ValueError("texts must hold at least one prompt, got none")
        if pts.shape[0] > self.config.max_segment_points:
            raise ValueError(
                f"{pts.shape[0]} points exceed model.max_segment_points = {self.config.max_segment_points}; "
                "split the request"
            )
        pts = pts.to(self.device, torch.float32)
        model = self._require_model()
        timing: dict[str, float] = {}
        t0 = time.perf_counter()
        with self._lock:
            prep = self._prepare()
            t1 = time.perf_counter()
            timing["prepare"] = (t1 - t0) * 1e3
            emb = self._text_embeddings(prep, texts)  # (T, D)
            t2 = time.perf_counter()
            timing["text"] = (t2 - t1) * 1e3
            n = pts.shape[0]
            label = torch.full((n,), -1, dtype=torch.int32, device=self.device)
            score = torch.zeros(n, dtype=torch.float32, device=self.device)
            cosines = None  # (N, T) every text's cosine, only when asked for
            if keep_cosines:
                cosines = torch.zeros(n, emb.shape[0], dtype=torch.float32, device=self.device)
            occluders = self._occluder_depth(prep, pts) if use_depth else None
            t_occ = time.perf_counter()
            if occluders is not None:
                timing["occluders"] = (t_occ - t2) * 1e3
            dgm_depth = occluders if occluders is not None else prep.depth_m
            select_by = dgm_depth if (use_depth and self.config.dgm_view_selection) else None
            groups = self._view_groups(prep, pts, prep.has_ov, self.point_source_views, depth_m=select_by)
            t3 = time.perf_counter()
            timing["view_selection"] = (t3 - t_occ) * 1e3

            def answer(sub: Tensor, cos: Tensor, valid: Tensor) -> None:  # cos (p, T), valid (p,)
                # each point is in one view group, so in one chunk: its rows are written once
                best, arg = cos.max(dim=-1)
                label[sub] = torch.where(valid, arg.to(torch.int32), -1)
                score[sub] = torch.where(valid, best, 0.0)
                if cosines is not None:
                    cosines[sub] = cos.float() * valid[:, None]

            if self.config.batched_view_groups and groups and self._answer_in_one_pass(model, prep, pts):
                for sub, cos, valid in self._one_pass_answers(model, prep, pts, groups, use_depth, emb,
                                                              depth_m=occluders):
                    answer(sub, cos, valid)
            elif self.config.batched_view_groups and groups:
                # one network pass over every view group (each point with its own views)
                for sub, samples, v, ov_maps in self._point_batches(model, prep, pts, groups, use_depth,
                                                                    depth_m=occluders):
                    cos, valid, _ = model.point_cosines(samples, v, emb, ov_maps=ov_maps,
                                                        fusion=self.point_head)
                    answer(sub, cos, valid)
            for idx, views_idx in groups if not self.config.batched_view_groups else []:
                for sub, out in self._point_outputs(model, prep, pts, idx, views_idx, use_depth,
                                                    depth_m=occluders):
                    answer(sub, F.normalize(out.ov, dim=-1) @ emb.T, out.valid)
            timing["network"] = (time.perf_counter() - t3) * 1e3
        timing["total"] = (time.perf_counter() - t0) * 1e3
        cos_np = None if cosines is None else cosines.cpu().numpy()
        return label.cpu().numpy(), score.cpu().numpy(), cos_np, timing

    def _depth_agrees(
        self,
        uv: Tensor,  # (M, p, 2) pixel coordinates at the working size
        z: Tensor,  # (M, p) z-depth
        depth_m: Tensor,  # (M, H, W) at the working size, 0 = none
    ) -> Tensor:  # (M, p) bool
        """The DGM test of ``GovNeSF.sample_views`` for every (view, point): the view's depth at
        the point's pixel (nearest) agrees with the point's z within ``depth_mask_ratio``, or the
        view has no depth there (points outside the image: its clamped edge pixel)."""
        ratio = self._require_model().cfg.render.depth_mask_ratio
        m, height, width = depth_m.shape
        col = uv[..., 0].nan_to_num(0.0).floor().clamp(0, width - 1).long()
        row = uv[..., 1].nan_to_num(0.0).floor().clamp(0, height - 1).long()
        measured = depth_m.reshape(m, -1).gather(1, row * width + col)  # (M, p)
        has = torch.isfinite(measured) & (measured > 0)
        return ((z - measured).abs() <= ratio * measured) | ~has

    def _occluder_depth(self, prep: _Prepared, pts: Tensor) -> Tensor | None:  # pts (P, 3)
        """(M, H, W) float32 at the working size: the depth DGM tests the request's points against
        (``point_occlusion``): each view without input depth gets its z-buffer of the request's
        points (:func:`mapper.geometry.splat.request_occluder_depths`), each view with input depth keeps
        it. None (the window's depth and priors) when ``point_occlusion`` is off, every view has
        input depth, or there are no points. Call with the runtime's lock held."""
        if not self.config.point_occlusion or pts.shape[0] == 0 or prep.input_depth is None:
            return None
        need = (~prep.input_depth).nonzero().squeeze(-1)
        if need.numel() == 0:
            return None
        from mapper.geometry.splat import request_occluder_depths

        width, height = self.image_wh
        z = request_occluder_depths(pts.detach().cpu().numpy(), prep.K[need].cpu().numpy(),
                                    prep.world_from_cam[need].cpu().numpy(), width, height,
                                    self.config.point_occlusion_footprint,
                                    threads=torch.get_num_threads())  # (m, H, W)
        out = (prep.depth_m.clone() if prep.depth_m is not None
               else torch.zeros(len(prep), height, width, device=self.device))
        occ = torch.from_numpy(z).to(out)
        if self.config.point_occlusion_prior_veto and prep.depth_m is not None:
            # an occluder that the keyframe's own depth prior sees through (the prior's surface is
            # farther by more than the DGM tolerance) is dropped: likely a point off its surface
            prior = prep.depth_m[need]
            ratio = self._require_model().cfg.render.depth_mask_ratio
            occ = torch.where((prior > 0) & (prior > (1.0 + ratio) * occ), torch.zeros_like(occ), occ)
        out[need] = occ
        return out

    def _answer_in_one_pass(self, model: GovNeSF, prep: _Prepared, pts: Tensor) -> bool:
        """``segment`` answers every point in one compiled pass (``model.fused_point_answers`` and
        :meth:`GovNeSF.answer_kernel_applies`) instead of chunk by chunk."""
        if not self.config.fused_point_answers or prep.ov is None:
            return False
        views = self._all_views(prep, need_ov=False, use_depth=False)
        return model.answer_kernel_applies(views, pts, prep.ov, self.point_head)

    def _one_pass_answers(
        self,
        model: GovNeSF,
        prep: _Prepared,
        pts: Tensor,  # (P, 3)
        groups: list[tuple[Tensor, Tensor]],
        use_depth: bool,
        emb: Tensor | None,  # (T, D) unit text embeddings; None: the features themselves
        depth_m: Tensor | None = None,
    ) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
        """Every view group's points in calls of :data:`FUSED_CHUNK_POINTS` to
        :meth:`GovNeSF.point_cosines_indexed` (``emb=None``: :meth:`GovNeSF.point_features_indexed`):
        yields (point indices (p,), cosines (p, T) or features (p, D), valid (p,)). ``depth_m``: see
        ``_all_views``. Call with the runtime's lock held."""
        members, view_idx, slots = _group_slots(groups)
        views = self._all_views(prep, need_ov=False, use_depth=use_depth, depth_m=depth_m)
        for i in range(0, members.numel(), FUSED_CHUNK_POINTS):
            sel = slice(i, i + FUSED_CHUNK_POINTS)
            sub = members[sel]
            chunk_views, chunk_slots = _chunk_slots(view_idx, slots, sel)
            v, _ = sample_volume(prep.volume, prep.bounds, pts[sub].to(prep.volume.dtype))
            ov_maps = prep.ov_maps(chunk_views, self.image_wh)
            args = (views, chunk_views, chunk_slots, pts[sub], use_depth, v)
            if emb is None:
                out, valid, _ = model.point_features_indexed(*args, ov_maps, fusion=self.point_head)
            else:
                out, valid, _ = model.point_cosines_indexed(*args, emb, ov_maps, fusion=self.point_head)
            yield sub, out, valid

    def _point_batches(
        self,
        model: GovNeSF,
        prep: _Prepared,
        pts: Tensor,
        groups: list[tuple[Tensor, Tensor]],
        use_depth: bool,
        depth_m: Tensor | None = None,
    ) -> Iterator[tuple[Tensor, PointViewSamples, Tensor, OVMaps]]:
        """Every view group's points in chunks of ``chunk_points``, each point with its own views:
        yields (point indices (p,), samples (``sample_views_indexed``), volume features (p, Dv),
        the chunk's OV maps). ``depth_m``: see ``_all_views``. Call with the runtime's lock held."""
        members, view_idx, slots = _group_slots(groups)
        views = self._all_views(prep, need_ov=False, use_depth=use_depth, depth_m=depth_m)
        for i in range(0, members.numel(), self.config.chunk_points):
            sel = slice(i, i + self.config.chunk_points)
            sub = members[sel]
            chunk_views, chunk_slots = _chunk_slots(view_idx, slots, sel)
            samples = model.sample_views_indexed(views, chunk_views, chunk_slots, pts[sub], use_depth,
                                                 sample_ov=False)  # blended from the maps (OVMaps)
            v, _ = sample_volume(prep.volume, prep.bounds, pts[sub].to(prep.volume.dtype))
            yield sub, samples, v, prep.ov_maps(chunk_views, self.image_wh)

    def _world_points(self, points: np.ndarray) -> Tensor:
        """(N, 3) float32 points on the runtime's device; ``ValueError`` unless every one is finite."""
        pts = torch.tensor(np.array(points, dtype=np.float32)).reshape(-1, 3).to(self.device)
        if not bool(torch.isfinite(pts).all()):
            raise ValueError("points must be finite (got NaN or Inf)")
        return pts

    @torch.no_grad()
    def point_samples(
        self,
        points: np.ndarray,  # (N, 3) float32 world points (m)
        *,
        use_depth: bool = False,
    ) -> list[tuple[Tensor, PointViewSamples, Tensor]]:
        """What the point answers' network sees, with :meth:`segment`'s view selection: per chunk,
        (point indices (p,), samples (``sample_views_indexed``, each point's own views), volume
        features (p, Dv)). Points no keyframe sees are in no chunk. Used to distill a point head
        (``mapper.training.point_head``)."""
        pts = self._world_points(points)
        model = self._require_model()
        with self._lock:
            prep = self._prepare()
            groups = self._view_groups(prep, pts, prep.has_ov, self.point_source_views)
            if not groups:
                return []
            return [(sub, s, v) for sub, s, v, _ in self._point_batches(model, prep, pts, groups, use_depth)]

    def _point_outputs(
        self, model: GovNeSF, prep: _Prepared, pts: Tensor, idx: Tensor, views_idx: Tensor, use_depth: bool,
        depth_m: Tensor | None = None,
    ) -> Iterator[tuple[Tensor, PointOutputs]]:
        """``model.query_points`` for the points ``pts[idx]`` over the views ``views_idx``, in
        chunks of ``chunk_points``: yields (point indices, outputs). The OV features are blended
        straight from the window's maps (``OVMaps``), never sampled per view (nor copied per
        view group); the same answers as sampling them first, up to float rounding. ``depth_m``:
        see ``_all_views``."""
        views = self._source_views(prep, views_idx, need_ov=False, use_depth=use_depth, depth_m=depth_m)
        ov_maps = prep.ov_maps(views_idx, self.image_wh)
        for i in range(0, idx.numel(), self.config.chunk_points):
            sub = idx[i : i + self.config.chunk_points]
            yield sub, model.query_points(
                views, prep.volume, prep.bounds, pts[sub], depth_guided_masking=use_depth, ov_maps=ov_maps,
                fusion=self.point_head,
            )

    @torch.no_grad()
    def point_features(
        self,
        points: np.ndarray,  # (N, 3) float32 world points (m)
        *,
        use_depth: bool = False,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The learned blended OV feature at world points, with the same per-point view selection
        as :meth:`segment` (used to write the model's features into the global map before a
        keyframe leaves the window).

        Returns:
            features: (N, D) float32 (zero rows where not valid);
            valid: (N,) bool, False where no keyframe with OV sees the point.
        Raises :class:`RuntimeNotReady` without a model or without OV features in the window.
        """
        pts = self._world_points(points)
        model = self._require_model()
        with self._lock:
            prep = self._prepare()
            if prep.ov is None or not bool(prep.has_ov.any()):
                raise RuntimeNotReady("no keyframe in the window carries 'ov'")
            n = pts.shape[0]
            feats = torch.zeros(n, prep.ov.shape[1], dtype=torch.float32, device=self.device)
            valid = torch.zeros(n, dtype=torch.bool, device=self.device)
            groups = self._view_groups(prep, pts, prep.has_ov, self.point_source_views)
            if groups and self._answer_in_one_pass(model, prep, pts):
                for sub, out_ov, ok in self._one_pass_answers(model, prep, pts, groups, use_depth, None):
                    feats[sub] = out_ov * ok[:, None]  # each point is in one group: written once
                    valid[sub] = ok
            else:
                for idx, views_idx in groups:
                    for sub, out in self._point_outputs(model, prep, pts, idx, views_idx, use_depth):
                        feats[sub] = torch.where(out.valid[:, None], out.ov.float(), feats[sub])
                        valid[sub] = out.valid | valid[sub]
        return feats.cpu().numpy(), valid.cpu().numpy()

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
        """Render a novel view.

        Args:
            K, world_from_cam, width, height: the camera (OpenCV optical frame).
            outputs: subset of ``("rgb", "depth", "label", "score")``.
            texts: label set (required for ``label`` / ``score``).
            empty_space_skipping: override the config (dense sampling with False).
            surface_depth_m: a known surface per pixel (from the node's measured points,
                ``mapper.node.queries.surface_depth``): where > 0 the pixel is rendered AT that
                surface point (one appearance evaluation there; depth = this z, opacity 1) instead
                of marching its ray; the other pixels march as usual. None = march every pixel.
            volume_views: the density (and the blend's volume features) from a cost volume over
                this many keyframes that best overlap the view (``render_volume_views``, whose
                value None takes; 0 or 1 = the window's volume).

        Returns:
            :class:`RenderFrame`: rgb (H, W, 3) uint8 (black where nothing is rendered), depth_m
            (H, W) float32 z-depth along the optical axis (0 where opacity < ``min_opacity``),
            label (H, W) int32 (-1 there), score (H, W, T) float32 cosines, opacity (H, W).
        """
        outputs = list(outputs)
        bad = [o for o in outputs if o not in RENDER_OUTPUTS]
        if bad or not outputs or len(set(outputs)) != len(outputs):
            raise ValueError(
                f"outputs {outputs} must be a non-empty subset of {list(RENDER_OUTPUTS)} without repeats"
            )
        if not (1 <= int(width) <= 4096 and 1 <= int(height) <= 4096):
            raise ValueError(f"image size {width}x{height} out of range 1..4096")
        if int(width) * int(height) > self.config.max_render_pixels:
            raise ValueError(
                f"render size {width}x{height} = {int(width) * int(height)} pixels exceeds "
                f"model.max_render_pixels = {self.config.max_render_pixels}; ask for a smaller image "
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
        skip = self.config.empty_space_skipping if empty_space_skipping is None else empty_space_skipping
        model = self._require_model()
        timing: dict[str, float] = {}
        t0 = time.perf_counter()
        with self._lock:
            prep = self._prepare()
            t_local = time.perf_counter()
            n_views = self.config.render_volume_views if volume_views is None else int(volume_views)
            prep = self._render_prep(model, prep, K_t.to(torch.float32), pose.to(torch.float32), int(width),
                                     int(height), n_views)
            t1 = time.perf_counter()
            timing["prepare"] = (t_local - t0) * 1e3
            timing["render_volume"] = (t1 - t_local) * 1e3
            emb = self._text_embeddings(prep, texts or []) if semantic else None
            # the occupancy grid only serves marched rays (none when every pixel has a surface)
            marches = surface_np is None or bool((surface_np <= 0).any())
            occupancy = self._occupancy(prep) if skip and marches else None
            t2 = time.perf_counter()
            timing["text_occupancy"] = (t2 - t1) * 1e3
            origins, dirs = pixel_rays(K_t, pose, int(width), int(height))
            origins = origins.reshape(-1, 3).to(self.device, torch.float32)
            dirs = dirs.reshape(-1, 3).to(self.device, torch.float32)
            axis = pose[:3, 2].to(self.device, torch.float32)
            allowed = prep.has_ov if semantic else torch.ones_like(prep.has_ov)
            appearance = semantic or "rgb" in outputs  # depth alone needs only the density
            n_rays = origins.shape[0]
            rgb = torch.zeros(n_rays, 3, device=self.device)
            ray_depth = torch.zeros(n_rays, device=self.device)
            opacity = torch.zeros(n_rays, device=self.device)
            covered = torch.zeros(n_rays, device=self.device)
            ov = (
                torch.zeros(n_rays, prep.ov.shape[1], device=self.device)
                if semantic and prep.ov is not None
                else None
            )
            stats = {"samples": 0, "density_evals": 0, "appearance_evals": 0, "view_groups": 0,
                     "render_volume_views": prep.render_views}
            marched = torch.arange(n_rays, device=self.device)
            if surface_np is not None:
                z_surface = torch.from_numpy(surface_np.reshape(-1)).to(self.device)
                at_surface = (z_surface > 0).nonzero().squeeze(-1)
                marched = (z_surface <= 0).nonzero().squeeze(-1)
                t_surface = time.perf_counter()
                self._render_surface(
                    model, prep, origins, dirs, axis, z_surface, at_surface, semantic, allowed, stats,
                    appearance, (rgb, ray_depth, opacity, covered, ov),
                )  # fmt: skip
                timing["surface"] = (time.perf_counter() - t_surface) * 1e3
            for i in range(0, marched.numel(), self.config.chunk_rays):
                sl = marched[i : i + self.config.chunk_rays]
                part = self._render_rays(
                    model, prep, origins[sl], dirs[sl], occupancy, semantic, allowed, stats, appearance,
                    appearance_groups=self.config.appearance_groups if skip else 0,
                    stop_transmittance=self.config.stop_transmittance if skip else 0.0,
                    batched=self.config.batched_view_groups and skip,
                )  # fmt: skip
                rgb[sl], ray_depth[sl], opacity[sl], covered[sl] = part[0], part[1], part[2], part[4]
                if ov is not None and part[3] is not None:
                    ov[sl] = part[3]
            if skip and ov is not None and emb is not None and self._refines(emb.shape[0]):
                # coarse-to-fine labels: pixels whose best two texts are close get every sample's
                # appearance (their weight groups could have swapped the two)
                # (surface pixels had one exact evaluation at their point: nothing to refine; nor
                # have rays below min_opacity, which no refinement can label: covered <= opacity,
                # and the opacity depends on the density only)
                top2 = (F.normalize(ov[marched], dim=-1) @ emb.T).topk(2, dim=-1).values
                close = top2[:, 0] - top2[:, 1] < self.config.refine_margin
                redo = marched[close & (opacity[marched] >= self.config.min_opacity)]
                stats["refined_rays"] = int(redo.numel())
                again = {"samples": 0, "density_evals": 0, "appearance_evals": 0, "view_groups": 0}
                for i in range(0, redo.numel(), self.config.chunk_rays):
                    sub = redo[i : i + self.config.chunk_rays]
                    part = self._render_rays(
                        model, prep, origins[sub], dirs[sub], occupancy, semantic, allowed, again, appearance,
                        appearance_groups=0, stop_transmittance=self.config.stop_transmittance,
                        batched=self.config.batched_view_groups,
                    )  # fmt: skip
                    rgb[sub], ray_depth[sub], opacity[sub], covered[sub] = part[0], part[1], part[2], part[4]
                    if part[3] is not None:
                        ov[sub] = part[3]
                for key in ("density_evals", "appearance_evals", "view_groups"):
                    stats[key] += again[key]  # "samples" stays the image's
            timing["render"] = (time.perf_counter() - t2) * 1e3
        hw = (int(height), int(width))
        drawn = opacity >= self.config.min_opacity
        frame = RenderFrame(opacity=opacity.reshape(hw).cpu().numpy(), stats=stats)
        if "rgb" in outputs:
            frame.rgb = (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).reshape(*hw, 3).cpu().numpy()
        if "depth" in outputs:
            z = ray_depth * (dirs @ axis)  # ray distance -> z-depth along the optical axis
            frame.depth_m = (
                torch.where(drawn, z, torch.zeros_like(z)).reshape(hw).cpu().numpy().astype(np.float32)
            )
        if semantic:
            assert ov is not None and emb is not None
            cos = F.normalize(ov, dim=-1) @ emb.T  # (R, T)
            # Only where the source views saw enough of what the ray hit (a cosine of a few tiny
            # background contributions would be noise).
            has_feature = (covered >= self.config.min_opacity) & (ov.norm(dim=-1) > 1e-8)
            cos = torch.where(has_feature[:, None], cos, torch.zeros_like(cos))
            if "score" in outputs:
                frame.score = cos.reshape(*hw, -1).cpu().numpy().astype(np.float32)
            if "label" in outputs:
                lab = torch.where(
                    has_feature, cos.argmax(dim=-1), torch.full_like(has_feature, -1, dtype=torch.long)
                )
                frame.label = lab.to(torch.int32).reshape(hw).cpu().numpy()
        timing["total"] = (time.perf_counter() - t0) * 1e3
        frame.timing_ms = timing
        return frame

    def _render_surface(
        self,
        model: GovNeSF,
        prep: _Prepared,
        origins: Tensor,  # (R, 3)
        dirs: Tensor,  # (R, 3) unit
        axis: Tensor,  # (3,) the camera's optical axis (world)
        z_surface: Tensor,  # (R,) known surface z-depth, 0 = none
        rays: Tensor,  # (S,) int64 the rays with a surface
        need_ov: bool,
        allowed: Tensor,  # (M,) bool views usable as sources
        stats: dict[str, int],
        appearance: bool,
        out: tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None],  # rgb, ray distance, opacity, covered, ov
    ) -> None:
        """Render ``rays`` at their known surface: the point at z-depth ``z_surface`` along each ray
        gets one appearance evaluation (the same view-grouped FusionNet blend as a marched sample);
        ray distance = z / (d . axis), opacity 1, covered = whether an allowed view sees the point.
        Writes into ``out`` in place."""
        rgb, ray_depth, opacity, covered, ov = out
        stats["surface_rays"] = int(rays.numel())
        if rays.numel() == 0:
            return
        t = z_surface[rays] / (dirs[rays] @ axis).clamp_min(1e-6)
        ray_depth[rays] = t
        opacity[rays] = 1.0
        if not appearance:
            return
        fn = self._appearance(model, prep, need_ov, allowed, stats, self.config.batched_view_groups)
        for i in range(0, rays.numel(), self.config.chunk_rays):
            sub = rays[i : i + self.config.chunk_rays]
            points = origins[sub] + t[i : i + self.config.chunk_rays, None] * dirs[sub]
            _, features = self._density(model, prep, points)  # the marcher's features, the same way
            stats["density_evals"] += int(sub.numel())
            rgb_k, ov_k, valid_k = fn(points, dirs[sub], features)
            rgb[sub] = rgb_k.to(rgb.dtype)
            covered[sub] = valid_k.to(covered.dtype)
            if ov is not None and ov_k.shape[-1] == ov.shape[-1]:
                ov[sub] = ov_k.to(ov.dtype)
            stats["appearance_evals"] += int(sub.numel())

    def _refines(self, n_texts: int) -> bool:
        """Whether a skipping render re-renders its ambiguous pixels (``refine_margin``)."""
        cfg = self.config
        return cfg.refine_margin > 0 and n_texts > 1 and 0 < cfg.appearance_groups < self.samples_per_ray

    def _render_rays(
        self,
        model: GovNeSF,
        prep: _Prepared,
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
        cfg = self.config
        b = prep.bounds
        out = march_rays(
            Rays(origins, dirs),
            lambda points: self._density(model, prep, points),
            self._appearance(model, prep, need_ov, allowed, stats, batched) if appearance else None,
            n_samples=self.samples_per_ray,
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
        prep: _Prepared,
        need_ov: bool,
        allowed: Tensor,
        stats: dict[str, int],
        batched: bool = False,
    ) -> AppearanceFn:
        """The marcher's appearance: each sample with the source views of its view group
        (``_view_groups``), in chunks of ``chunk_points``; samples no allowed view sees get 0.
        ``batched``: every view group in one network pass (``GovNeSF.sample_views_indexed``), else
        one pass per group (the reference)."""
        d_ov = prep.ov.shape[1] if (need_ov and prep.ov is not None) else 0
        chunk = self.config.chunk_points

        def appearance(points: Tensor, view_dirs: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
            n = points.shape[0]
            rgb = points.new_zeros(n, 3)
            ov = points.new_zeros(n, d_ov)
            valid = torch.zeros(n, dtype=torch.bool, device=points.device)
            groups = self._view_groups(prep, points, allowed)
            stats["view_groups"] += len(groups)
            if batched and groups:  # one network pass over every view group
                members, view_idx, slots = _group_slots(groups)
                views = self._all_views(prep, need_ov=False, use_depth=False)
                for j in range(0, members.numel(), chunk):
                    sel = slice(j, j + chunk)
                    sub = members[sel]
                    chunk_views, chunk_slots = _chunk_slots(view_idx, slots, sel)
                    samples = model.sample_views_indexed(views, chunk_views, chunk_slots, points[sub], False)
                    ov_maps = prep.ov_maps(chunk_views, self.image_wh) if d_ov else None
                    rgb_k, ov_k, valid_k = model.fuse_samples(
                        samples, v[sub], view_dirs[sub], ov_maps=ov_maps
                    )
                    rgb[sub], valid[sub] = rgb_k, valid_k
                    if d_ov:
                        ov[sub] = ov_k
                return rgb, ov, valid
            for local, view_idx in groups:
                # OV blended straight from the window's maps (never sampled or copied per group)
                views = self._source_views(prep, view_idx, need_ov=False, use_depth=False)
                ov_maps = prep.ov_maps(view_idx, self.image_wh) if d_ov else None
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
