"""The global semantic point map: voxel-hashed surface points with fused open-vocabulary features.

Every keyframe with input depth adds its surface points: a subsampled grid of its depth pixels
(``pixel_stride``) is back-projected with the protocol conventions (pixel centres at +0.5, ``K``
for the image as sent, depth is z-depth), the keyframe's OV map is sampled bilinearly at those
pixels (the OV map may be coarser than the image; it covers the whole image), each observation
gets a quality weight and the observations are fused into the voxel (``voxel_size_m``) they fall
in. One voxel holds:

- ``xyz``: weighted mean of the points that fell in it (float32, metres, world frame);
- ``feat``: the fused OV feature, served as an fp16 unit vector; ``feat_norm`` keeps the norm of
  the weighted mean so that fusion stays an exact running weighted mean (float32 while fusing);
- ``weight`` (the confidence: sum of observation weights), ``feat_weight`` (the part of it that
  carried features), ``hits`` (observations) and ``last_seen_ns`` / ``last_seen_kf``.

Quality weight of an observation (the same shape as the simulated 2D model's quality, and what a
real 2D model's reliability looks like): 1 up to ``near_m`` along the ray, ``exp(-(d - near_m) /
falloff_m)`` beyond, times ``|cos(ray, surface normal)| ** grazing_power`` (normals from the depth
image's neighbours; 0.5 where they are unknown). Observations below ``min_weight`` are skipped.

The fusion rule is the pure function :func:`weighted_mean_fusion`; the learned model can pass its
own ``fusion=`` with the same signature (:class:`FusionRule`).

Frames without depth add no points here; when the node serves the learned model,
:mod:`mapper.node.workers.depth_points` adds their points later from the model's rendered depth;
frames without ``ov`` add geometry only (points without a feature); when the node runs an
in-process OV backend (:mod:`mapper.node.workers.ov_features`) their features arrive later through
:meth:`GlobalSemanticMap.integrate_features`, which fuses features into the voxels the keyframe's
points fell in without adding geometry weight a second time. Points are kept when their
keyframe leaves the window. Memory is bounded by ``max_points``: beyond it whole tiles of the map
(``tile_m``), least recently observed first, are paged out to the map's tile store
(:mod:`mapper.map.tile_store`) until ``prune_to_fraction * max_points`` remain, and come back when
needed (:class:`_StoredMap`); with ``paging`` off the voxels with the lowest priority ``weight *
0.5 ** (keyframes since last seen / stale_half_life_keyframes)`` are dropped instead (rarely seen,
long unseen voxels go first).
With ``carve`` (default), a keyframe with input depth first lowers the confidence of the voxels it
sees through and removes those whose evidence is gone (:mod:`mapper.map.carving`), so what moved
away leaves the map.

Threads: :meth:`GlobalSemanticMap.integrate` runs under the map's own lock. Readers call
:meth:`GlobalSemanticMap.snapshot`, which returns an immutable copy per map version (cached, so
many queries of one version share it; the copy is the only time a reader holds the lock), and
compute on it without any lock, so a query never waits on an integrate beyond that copy and an
integrate never waits on a query.

Example::

    >>> import numpy as np
    >>> from mapper.map.window import Keyframe
    >>> gmap = GlobalSemanticMap(GlobalMapConfig(voxel_size_m=0.1, pixel_stride=4))
    >>> depth = np.full((24, 32), 2.0, np.float32)                     # a wall 2 m ahead
    >>> kf = Keyframe(seq=0, stamp_ns=0, camera="cam0", K=np.array([30.0, 30.0, 16.0, 12.0]),
    ...               world_from_cam=np.eye(4), rgb=np.zeros((24, 32, 3), np.uint8), depth_m=depth)
    >>> stats = gmap.integrate(kf)
    >>> snap = gmap.snapshot()
    >>> bool(np.allclose(snap.xyz[:, 2], 2.0)), snap.has_feature.any()
    (True, np.False_)
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import math
import os
import sys
import tempfile
import threading
import time
import warnings
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from mapper.checks import check_range as _check_range
from mapper.checks import check_shape
from mapper.errors import ConfigError
from mapper.map.carving import carve, changed_region
from mapper.map.evicted_views import EvictedViewStore
from mapper.map.tile_store import TileInfo, TileStore, key_indices, tile_ids, tile_summary
from mapper.map.voxels import KEY_OFFSET, pack_indices, voxel_keys

log = logging.getLogger("mapper.map.global_map")

__all__ = [
    "FusionRule",
    "GlobalMapSnapshot",
    "GlobalSemanticMap",
    "IntegrateStats",
    "KeyframeLike",
    "Observations",
    "observe_keyframe",
    "voxel_keys",
    "weighted_mean_fusion",
]

@dataclass(frozen=True)
class GlobalMapConfig:
    """The global semantic point map (see :mod:`mapper.map.global_map`): voxel-hashed surface points
    with fused OV features, kept when keyframes leave the window."""

    voxel_size_m: float = 0.05
    """Edge of a map voxel (metres); one fused point per occupied voxel. 0.005..1."""

    pixel_stride: int = 2
    """Back-project every ``pixel_stride``-th pixel of each keyframe's depth (both axes). 1..64."""

    max_observed_pixels: int = 19_200
    """Most depth pixels a keyframe fuses: a larger frame's stride grows to ``ceil(sqrt(H W /
    max_observed_pixels))`` (a 640 x 480 frame at the default: stride 4, 19 200 pixels, about 2 cm
    apart at 3 m with a 60 degree lens, finer than ``voxel_size_m``), so fusing a keyframe costs the
    same at any resolution. 160 x 120 and 320 x 240 keep ``pixel_stride`` 2. 100..1e8."""

    max_points: int = 250_000
    """Most voxels kept in memory. Beyond this, with ``paging`` (default), the least recently
    observed tiles (``tile_m``) are written to the map directory's tile store and dropped from
    memory until ``prune_to_fraction`` of it remain (they come back when needed:
    :mod:`mapper.map.tile_store`); without it the lowest-priority voxels are dropped (confidence
    halved per ``stale_half_life_keyframes`` keyframes since last seen). 1..1e8."""

    prune_to_fraction: float = 0.9
    """After a page-out or prune, keep this fraction of ``max_points`` (hysteresis: not every frame
    pages). 0.1..1."""

    stale_half_life_keyframes: float = 200.0
    """Keyframes after which an unseen voxel's pruning priority halves. > 0."""

    paging: bool = True
    """Beyond ``max_points``, page the least recently observed tiles out to the tile store (nothing
    is forgotten). Off: prune the lowest-priority voxels (the map forgets; two rooms 12 m apart with
    ``max_points`` far below both: docs/concepts/map-paging.md)."""

    tile_m: float = 4.0
    """Edge of a paging tile (metres; rounded to whole voxels): what pages out and in together.
    ``voxel_size_m``..1000."""

    tile_summary_k: int = 8
    """Feature centroids kept per paged tile (:func:`mapper.map.tile_store.tile_summary`): a
    ``query_points`` reads only the paged tiles whose summary says a voxel may match (exact: the
    skipped ones cannot). 1..256."""

    tile_skip: str = "exact"
    """Which paged tiles a ``query_points`` skips: "exact" (default): those whose summary proves no
    voxel can match (the answer is that of the whole map); "centroids": also those none of whose
    centroids would match as a point (approximate: a match among a centroid's voxels can be
    missed; measured in docs/concepts/map-paging.md)."""

    max_disk_points: int = 0
    """Most voxels in the tile store; beyond it the paged voxels with the lowest priority (as
    without ``paging``) are dropped down to ``prune_to_fraction`` of it and counted in
    ``global_points_pruned``. 0 = unlimited. 0..1e10."""

    min_depth_m: float = 0.1
    """Depths below this (metres) are ignored (sensor minimum range). >= 0."""

    max_depth_m: float = 8.0
    """Depths beyond this (metres) are ignored (noisy far returns). > min_depth_m."""

    near_m: float = 2.0
    """Observation weight is 1 up to this distance along the ray (metres) ..."""

    falloff_m: float = 3.0
    """... and decays as exp(-(distance - near_m) / falloff_m) beyond it (metres). > 0."""

    grazing_power: float = 1.0
    """Weight is also multiplied by |cos(ray, surface normal)| ** grazing_power (0 disables). 0..10."""

    min_weight: float = 0.02
    """Observations whose weight falls below this are not fused. 0..1."""

    carve: bool = False
    """Visibility carving (:mod:`mapper.map.carving`): a keyframe with input depth lowers the
    confidence of the map points it sees through (projecting into its image in front of the
    measured depth by more than the margin) and removes those whose confidence falls below
    ``carve_min_weight``, so a moved object leaves its old place. Rendered and triangulated depth
    do not carve. Off (the default): the map only adds. (A chair moved 2 m in the simulated demo
    room: 299 of its 315 points stayed at the old place without carving, 0 with it;
    docs/concepts/window-and-map.md.)"""

    carve_margin_voxels: float = 2.0
    """A point is seen through only when it is in front of the measured depth by more than
    ``max(carve_margin_voxels * voxel_size_m, carve_margin_rel * depth)``: points on the surface
    (a voxel mean lies up to half a voxel off it) are never carved. 0..100."""

    carve_margin_rel: float = 0.05
    """... the part of that margin that grows with the depth (depth noise does). 0..1."""

    carve_decay: float = 0.5
    """Each see-through multiplies a point's confidence (and feature weight) by ``1 - (1 -
    carve_decay) * q``, ``q`` the quality weight an observation at its distance would have (1 up
    to ``near_m``, less beyond). 0..1 (1: nothing is carved; 0: one near see-through removes it)."""

    carve_min_weight: float = 0.05
    """A point whose confidence falls below this by carving is removed (counted as
    ``global_points_carved`` in status). > 0..1000."""

    rendered_depth: bool = True
    """Keyframes without input depth add points from the learned model's rendered depth at their
    pose (when the node serves the model; :mod:`mapper.node.workers.depth_points`).
    Off: they add no points."""

    rendered_depth_stride: int = 4
    """The depth is rendered at the keyframe's size / this (K scaled with it), every pixel used. 1..64."""

    rendered_volume_views: int = 0
    """> 1: the keyframe's depth is rendered from a cost volume over this many window keyframes that
    best overlap it, itself first (``ModelRuntime.render``'s ``volume_views``: the network's
    training regime is 8 sources, whose density is far sharper than over a whole window), with
    bounds over what they observed. 0 (default; or 1) = the window's volume. Measured with 8
    (docs/concepts/rgb-only.md): on five simulated RGB-only streams the map points' p90 distance to the
    surface 0.226 -> 0.182, 0.337 -> 0.234, 0.412 -> 0.313 m in three, 0.213 -> 0.229 and 0.212 ->
    0.208 in two; but on the real ICL-NUIM sequence the map got worse (median 0.027 -> 0.045 m,
    p90 0.108 -> 0.150 m), hence off. 0..256."""

    rendered_min_opacity: float = 0.9
    """Rendered pixels whose accumulated opacity is below this add no point (the ray found no
    clear surface). 0..1."""

    rendered_edge_rel: float = 0.1
    """Rendered pixels whose depth differs from one of their 4 neighbours' by more than this
    fraction of the nearer of the two add no point: at an occlusion edge the rendered depth blends
    the near and the far surface ("flying pixels"). 0 = off. 0..10. (0.1 keeps smooth surfaces up
    to about 70 deg of incidence at the demo's 40 x 30 renders; docs/concepts/rgb-only.md.)"""

    rendered_weight: float = 0.5
    """Observation weights of rendered-depth points are multiplied by this times the opacity (input
    depth outranks rendered depth in the fused confidence). 0..1."""

    rendered_min_views: int = 4
    """The model needs at least this many keyframes in its window before it renders depth
    (keyframes that arrive earlier wait). 1..1000."""

    rendered_max_pending: int = 256
    """Most keyframes waiting for a rendered depth; beyond it the oldest is dropped (counted as
    ``dropped`` in status). 1..100000."""

    rendered_consistency: bool = True
    """Multi-view consistency for rendered-depth points (:func:`mapper.node.workers.depth_points.
    consistency_mask`): a rendered pixel is kept only where it agrees with the triangulated points
    projecting near it (within ``rendered_consistency_radius_px``) or, where none do, with the
    rendered depth of at least one other recent keyframe that sees it. Off: every pixel above
    ``rendered_min_opacity`` is kept."""

    rendered_consistency_sigmas: float = 1.0
    """A triangulated point agrees with a rendered depth within this many of its 1-sigma
    uncertainties (but never less than ``rendered_consistency_voxels`` voxels). 0..100. (1 and 1
    rather than 3 and 2: RGB-only map points 0.095 -> 0.073 m median from the surface,
    docs/concepts/rgb-only.md.)"""

    rendered_consistency_voxels: float = 1.0
    """Depth tolerance between two keyframes' rendered depths, and the least tolerance against a
    triangulated point, in ``voxel_size_m`` units. 0..100."""

    rendered_consistency_radius_px: int = 2
    """Triangulated points projecting within this many pixels (of the rendered depth's size) of a
    pixel are its neighbours. 0..32."""

    rendered_consistency_views: int = 8
    """Recent rendered keyframes kept to compare new ones with (besides those rendered together
    with it). 1..1000."""

    rendered_consistency_min_baseline_m: float = 0.1
    """Another keyframe counts as a second view only when its camera centre is this far away (a
    render from nearly the same pose agrees trivially). 0..100."""

    rendered_view_agreement: str = "auto"
    """Whether a rendered pixel with no triangulated or swept point near it may be kept because
    another keyframe's rendered depth agrees: "on", "off", or "auto" (default): on unless the
    node's plane-sweep stereo (``[stereo]``) is on, since two renders of the same density share its
    errors (RGB-only map points: median 0.11 -> 0.06 m off the surface in the demo room with
    stereo, 25% fewer points; docs/concepts/rgb-only.md)."""

    learned_features: bool = True
    """When the node serves the learned model: just before a keyframe leaves the window, the map
    voxels it saw take the model's blended features (:mod:`mapper.node.workers.map_features`), so the
    persistent map carries what the model knows, not only plain averages. Off: plain fusion only."""

    learned_features_once: bool = True
    """A voxel takes the model's blended feature once: when the first keyframe that saw it leaves
    the window (then the window still holds the views that first observed it). Off: again at every
    keyframe that saw it and leaves, each time an equal mix with the direction it has, so after k
    evictions the fused average keeps only about 2^-k of the say. Whole-map ``segment_points`` on
    9 recorded scenes, bounded window minus unbounded: worst scene -1.6 once against -2.7 every
    time (``govnesf``; docs/concepts/window-and-map.md). Once also spares the model the voxels already set."""

    learned_features_depth_test: bool = True
    """Those blended features use only the views whose input depth confirms the voxel (the model's
    ``use_depth`` view selection) while the window's keyframes mostly carry input depth; off: every
    view the voxel falls in, occluded or not."""

    learned_features_batch: int = 4
    """When the window's oldest keyframe is due, it and the next oldest up to this many are done
    together (one model evaluation for their voxels: the model's cached volume is recomputed once
    per window change, so one call per keyframe would cost that every keyframe). 1..1000."""

    learned_features_max_pending: int = 64
    """Most keyframes waiting for that; beyond it the oldest is dropped (``dropped`` in status). 1..100000."""

    integrate_queue: int = 16
    """Keyframes acked but not yet integrated into this map (the node's integrator thread fuses
    them shortly after the ack; a keyframe is in the window as soon as it is acked). When that many
    are waiting, the ingest thread waits for room before acking the next keyframe (backpressure,
    counted in status ``integration.backpressure_waits``): nothing acked is dropped. ``save``
    first integrates everything acked before it. 0 = integrate on the ingest thread before the
    ack (the ack then waits for it). 0..100000."""

    def validate(self, where: str) -> None:
        _check_range(where, "global_map.integrate_queue", self.integrate_queue, 0, 100_000)
        _check_range(
            where, "global_map.learned_features_max_pending", self.learned_features_max_pending, 1, 100_000
        )
        _check_range(where, "global_map.learned_features_batch", self.learned_features_batch, 1, 1000)
        _check_range(where, "global_map.rendered_depth_stride", self.rendered_depth_stride, 1, 64)
        _check_range(where, "global_map.rendered_volume_views", self.rendered_volume_views, 0, 256)
        if isinstance(self.rendered_volume_views, bool) or not isinstance(self.rendered_volume_views, int):
            raise ConfigError(f"{where}: global_map.rendered_volume_views = {self.rendered_volume_views!r} "
                              "must be an integer")
        _check_range(where, "global_map.rendered_min_opacity", self.rendered_min_opacity, 0.0, 1.0)
        _check_range(where, "global_map.rendered_weight", self.rendered_weight, 0.0, 1.0)
        _check_range(where, "global_map.rendered_edge_rel", self.rendered_edge_rel, 0.0, 10.0)
        _check_range(where, "global_map.rendered_min_views", self.rendered_min_views, 1, 1000)
        _check_range(where, "global_map.rendered_max_pending", self.rendered_max_pending, 1, 100_000)
        _check_range(where, "global_map.rendered_consistency_sigmas",
                     self.rendered_consistency_sigmas, 0.0, 100.0)
        _check_range(where, "global_map.rendered_consistency_voxels",
                     self.rendered_consistency_voxels, 0.0, 100.0)
        _check_range(where, "global_map.rendered_consistency_radius_px",
                     self.rendered_consistency_radius_px, 0, 32)
        _check_range(where, "global_map.rendered_consistency_views", self.rendered_consistency_views, 1, 1000)
        if self.rendered_view_agreement not in ("auto", "on", "off"):
            raise ConfigError(f"{where}: global_map.rendered_view_agreement = "
                              f"{self.rendered_view_agreement!r}; allowed: auto, on, off")
        _check_range(where, "global_map.rendered_consistency_min_baseline_m",
                     self.rendered_consistency_min_baseline_m, 0.0, 100.0)
        _check_range(where, "global_map.carve_margin_voxels", self.carve_margin_voxels, 0.0, 100.0)
        _check_range(where, "global_map.carve_margin_rel", self.carve_margin_rel, 0.0, 1.0)
        _check_range(where, "global_map.carve_decay", self.carve_decay, 0.0, 1.0)
        _check_range(where, "global_map.carve_min_weight", self.carve_min_weight, 1e-6, 1000.0)
        _check_range(where, "global_map.voxel_size_m", self.voxel_size_m, 0.005, 1.0)
        _check_range(where, "global_map.pixel_stride", self.pixel_stride, 1, 64)
        _check_range(where, "global_map.max_observed_pixels", self.max_observed_pixels, 100, 100_000_000)
        _check_range(where, "global_map.max_points", self.max_points, 1, 100_000_000)
        _check_range(where, "global_map.prune_to_fraction", self.prune_to_fraction, 0.1, 1.0)
        _check_range(where, "global_map.stale_half_life_keyframes", self.stale_half_life_keyframes, 1e-3, 1e9)
        _check_range(where, "global_map.tile_m", self.tile_m, self.voxel_size_m, 1000.0)
        _check_range(where, "global_map.tile_summary_k", self.tile_summary_k, 1, 256)
        _check_range(where, "global_map.max_disk_points", self.max_disk_points, 0, 10_000_000_000)
        if self.tile_skip not in ("exact", "centroids"):
            raise ConfigError(
                f"{where}: global_map.tile_skip = {self.tile_skip!r}; allowed: exact, centroids")
        if not isinstance(self.paging, bool):
            raise ConfigError(f"{where}: global_map.paging = {self.paging!r} must be true or false")
        _check_range(where, "global_map.min_depth_m", self.min_depth_m, 0.0, 1e3)
        _check_range(where, "global_map.max_depth_m", self.max_depth_m, 1e-3, 1e4)
        if self.max_depth_m <= self.min_depth_m:
            raise ConfigError(
                f"{where}: global_map.max_depth_m = {self.max_depth_m} must exceed "
                f"global_map.min_depth_m = {self.min_depth_m}"
            )
        _check_range(where, "global_map.near_m", self.near_m, 0.0, 1e3)
        _check_range(where, "global_map.falloff_m", self.falloff_m, 1e-3, 1e3)
        _check_range(where, "global_map.grazing_power", self.grazing_power, 0.0, 10.0)
        _check_range(where, "global_map.min_weight", self.min_weight, 0.0, 1.0)


_UNKNOWN_NORMAL_COS = 0.5
_NORMAL_REL_JUMP = 0.1
"""Depth neighbours differing by more than this fraction of the depth are across an edge: no normal."""
_FORMAT = "global-map-v1"
_RECENT_INTEGRATES = 1000
"""``stats`` reports the integrate time percentiles over this many latest keyframes."""

_SIMILARITY_SETS = 4
"""Text sets whose cosines with every row a snapshot keeps (:meth:`GlobalMapSnapshot.similarities_cached`)."""

UNIT_BLOCK_ROWS = 16384
"""Rows per block of a snapshot's normalised fp32 features: a new snapshot reuses the blocks of the
previous one whose fp16 rows did not change (:meth:`GlobalMapSnapshot.unit_feature_blocks`)."""


def _unit_rows(feat: np.ndarray) -> np.ndarray:
    """(n, D) float32 L2-normalised rows of ``feat`` (n, D) (zero rows stay zero). Where torch is
    loaded already (the learned model's node) the fp16 -> fp32 conversion and the normalisation run
    in torch: about 7x faster than numpy's scalar fp16 conversion (100k x 384 rows: 15 vs 105 ms on
    the 2-core machine); elsewhere numpy (this module never imports torch). Both equal a float64
    reference within 2e-7."""
    out = np.empty(feat.shape, np.float32)
    if out.size == 0:
        return out
    torch = sys.modules.get("torch")
    if torch is None:
        out[...] = feat
        out /= np.maximum(np.sqrt(np.einsum("ij,ij->i", out, out))[:, None], np.float32(1e-12))
        return out
    t = torch.from_numpy(out)
    t.copy_(torch.from_numpy(np.ascontiguousarray(feat)))  # only reads the (read-only) rows
    t.div_(torch.linalg.vector_norm(t, dim=1, keepdim=True).clamp_min_(1e-12))
    return out


# torch warns (once) that snapshot rows are read-only; _unit_rows only reads them. A filter set
# once at import, for this module's calls only (catch_warnings per call is not thread-safe).
warnings.filterwarnings(
    "ignore", message="The given NumPy array is not writable", category=UserWarning, module=__name__
)


def _row_words(a: np.ndarray) -> np.ndarray:
    """The bytes of each row of ``a`` (n, D) as (n, k) unsigned words (8-byte words when a row's
    size allows), for an exact row-by-row comparison."""
    a = np.ascontiguousarray(a)
    row_bytes = a.dtype.itemsize * (a.shape[1] if a.ndim > 1 else 1)
    word = np.uint64 if row_bytes % 8 == 0 else np.uint8
    return a.view(np.uint8).reshape(a.shape[0], row_bytes).view(word)


_BLOCK_TOKENS = itertools.count(1)
"""Tokens of unit-feature blocks (:meth:`GlobalMapSnapshot.unit_block_tokens`), unique in the process."""

_GENERATIONS = itertools.count(1)
"""Map generations, unique in the process: a new map, a ``restore`` and a ``clear`` each take the
next, so an answer computed on one map is never taken for another's (``GlobalMapSnapshot.generation``)."""


class _UnitSource:
    """The fp16 features and fp32 unit blocks of the latest snapshot that computed its blocks,
    shared by the snapshots of one map (so a new snapshot normalises only the changed blocks)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.version = -1
        self.feat: np.ndarray | None = None  # (M, D) float16, read-only
        self.blocks: list[np.ndarray] = []  # (<= UNIT_BLOCK_ROWS, D) float32 each, read-only
        self.tokens: list[int] = []  # each block's token (:meth:`GlobalMapSnapshot.unit_block_tokens`)


class KeyframeLike(Protocol):
    """What :meth:`GlobalSemanticMap.integrate` reads from a keyframe (``mapper.map.window.Keyframe``)."""

    @property
    def stamp_ns(self) -> int: ...
    @property
    def K(self) -> np.ndarray: ...  # noqa: N802 - (4,) [fx, fy, cx, cy] for the image as sent
    @property
    def world_from_cam(self) -> np.ndarray: ...  # (4, 4)
    @property
    def rgb(self) -> np.ndarray: ...  # (H, W, 3)
    @property
    def depth_m(self) -> np.ndarray | None: ...  # (H, W) z-depth, metres, 0 = none
    @property
    def ov(self) -> np.ndarray | None: ...  # (h, w, D)


class FusionRule(Protocol):
    """Fuses new observations into voxels (the learned model may supply its own).

    Args:
        old_unit: (U, D) float16 current fused unit features (zeros where none yet).
        old_norm: (U,) float32 norm of the current weighted-mean feature.
        old_weight: (U,) float32 current feature weight (0 = no feature yet).
        add_sum: (U, D) float32 weighted sum of the new observations' features.
        add_weight: (U,) float32 sum of the new observations' weights (> 0).

    Returns:
        (unit (U, D) float16, norm (U,) float32, weight (U,) float32).
    """

    def __call__(
        self,
        old_unit: np.ndarray,
        old_norm: np.ndarray,
        old_weight: np.ndarray,
        add_sum: np.ndarray,
        add_weight: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


def weighted_mean_fusion(
    old_unit: np.ndarray,  # (U, D) float16
    old_norm: np.ndarray,  # (U,) float32
    old_weight: np.ndarray,  # (U,) float32
    add_sum: np.ndarray,  # (U, D) float32
    add_weight: np.ndarray,  # (U,) float32
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Running weighted mean of features (float32 while fusing), returned as an fp16 unit vector,
    the mean's norm and the new total weight. Exact up to the fp16 rounding of the direction:
    ``unit * norm * weight`` is the weighted sum of everything fused so far."""
    # numpy, not torch: for these small arrays torch's thread pool costs more than the arithmetic
    mean = old_unit.astype(np.float32)
    mean *= (old_norm * old_weight).astype(np.float32)[:, None]
    mean += add_sum
    weight = (old_weight + add_weight).astype(np.float32)
    mean /= np.maximum(weight, 1e-12)[:, None]
    norm = np.sqrt(np.einsum("ud,ud->u", mean, mean)).astype(np.float32)
    mean /= np.maximum(norm, 1e-12)[:, None]
    return mean.astype(np.float16), norm, weight


def _percentiles_ms(prefix: str, seconds: deque[float]) -> dict[str, float | None]:
    """``{prefix_p50, prefix_p95}`` in ms of ``seconds`` (None when empty)."""
    if not seconds:
        return {f"{prefix}_p50": None, f"{prefix}_p95": None}
    p50, p95 = np.percentile(np.fromiter(seconds, np.float64), [50, 95])
    return {f"{prefix}_p50": round(1e3 * float(p50), 3), f"{prefix}_p95": round(1e3 * float(p95), 3)}


def _check_depth(keyframe: KeyframeLike) -> None:
    """A keyframe's depth, when it has one, covers its image pixel for pixel."""
    if keyframe.depth_m is not None:
        height, width = keyframe.rgb.shape[:2]
        check_shape(keyframe.depth_m, "H W", "depth_m (the image's H, W)", {"H": height, "W": width})


@dataclass(frozen=True)
class Observations:
    """One keyframe's observations, ready to fuse (from :meth:`GlobalSemanticMap.observe`)."""

    xyz: np.ndarray  # (M, 3) float64 world points, metres
    weight: np.ndarray  # (M,) float32 quality weights
    cells: np.ndarray | None  # (M, 4) int64 bilinear taps: flat indices into ov_flat
    bilinear: np.ndarray | None  # (M, 4) float64 bilinear weights of those taps (sum 1)
    ov_flat: np.ndarray | None  # (h * w, D) float32 the keyframe's OV map, None without ov


@dataclass(frozen=True)
class IntegrateStats:
    """What one :meth:`GlobalSemanticMap.integrate` did."""

    points: int
    """Observations fused (valid depth pixels at the stride, above ``min_weight``)."""
    voxels_touched: int
    voxels_new: int
    voxels_pruned: int
    with_features: bool
    seconds: float
    skipped: str | None = None
    """Why no points were added (e.g. no depth), else None."""
    carved: int = 0
    """Voxels removed because the keyframe saw through them (``global_map.carve``)."""


@dataclass(frozen=True, eq=False)
class GlobalMapSnapshot:
    """An immutable copy of the map at one version; safe to read from any thread without a lock.
    Arrays are read-only. Derived matrices (normalised fp32 features) are computed once and cached."""

    version: int
    """Internal version of the global map (changes with every integrate, prune, restore)."""
    map_version: int
    """The node's map version this snapshot includes (as given to ``integrate`` / ``restore``)."""
    voxel_size_m: float
    xyz: np.ndarray  # (N, 3) float32
    feat: np.ndarray | None  # (N, D) float16 unit rows (zero rows where no feature), None if D unknown
    weight: np.ndarray  # (N,) float32 confidence
    feat_weight: np.ndarray  # (N,) float32
    hits: np.ndarray  # (N,) int32
    last_seen_ns: np.ndarray  # (N,) int64
    feat_stamp: np.ndarray | None = None  # (N,) int64: the version that last wrote each row's feature
    feat_reset: int = 0
    """Rows moved or were replaced at this version (prune, restore, clear): ``feat_stamp`` says
    nothing about blocks computed before it."""
    keys: np.ndarray | None = None  # (N,) int64 each row's voxel key
    generation: int = 0
    """The map's :attr:`GlobalSemanticMap.generation` (unique in the process; a new map,
    ``restore`` and ``clear`` change it, growing and fusing do not): answers of another generation
    describe another map."""
    _cache: dict[Any, Any] = field(default_factory=dict, repr=False)
    _cache_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _unit_source: _UnitSource | None = field(default=None, repr=False)
    """Set by the map: earlier snapshots' unit blocks, reused where the fp16 rows are equal."""

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def has_feature(self) -> np.ndarray:
        """(N,) bool: the voxel has a fused OV feature."""
        return self.feat_weight > 0

    @property
    def n_with_features(self) -> int:
        return int(np.count_nonzero(self.feat_weight > 0))

    def unit_feature_blocks(self) -> list[np.ndarray]:
        """The (N, D) float32 L2-normalised features (zero rows where none) as consecutive
        read-only blocks of ``UNIT_BLOCK_ROWS`` rows, computed once per snapshot (per map version).
        A block whose fp16 rows equal those of the map's previous computed snapshot (same rows,
        same bytes) is shared with it instead of normalised again; in a block with a few changed
        rows only those are normalised (into a copy), so after an integrate only the touched rows
        cost time. No rows: an empty list."""
        with self._cache_lock:
            blocks = self._cache.get("unit_blocks")
            if blocks is not None:
                return blocks
            n = len(self)
            tokens: list[int]
            patches: list[tuple[int, np.ndarray] | None]
            if self.feat is None:
                blocks = [np.zeros((min(UNIT_BLOCK_ROWS, n - lo), 0), np.float32)
                          for lo in range(0, n, UNIT_BLOCK_ROWS)]
                tokens = [next(_BLOCK_TOKENS) for _ in blocks]
                patches = [None] * len(blocks)
            else:
                prev_feat, prev_blocks, prev_tokens, prev_version = None, [], [], -1
                if self._unit_source is not None:
                    with self._unit_source.lock:
                        prev_feat, prev_blocks = self._unit_source.feat, self._unit_source.blocks
                        prev_tokens = self._unit_source.tokens
                        prev_version = self._unit_source.version
                # the rows written since the previous blocks, from the stamps (no row compare) when
                # those blocks are of an older version of this snapshot's rows
                stamps = (self.feat_stamp if self.feat_stamp is not None
                          and self.feat_reset <= prev_version <= self.version else None)
                same_dim = (prev_feat is not None and prev_feat.shape[1] == self.feat.shape[1]
                            and prev_feat.dtype == self.feat.dtype)
                blocks, tokens, patches = [], [], []
                for b, lo in enumerate(range(0, n, UNIT_BLOCK_ROWS)):
                    patch = None  # (parent token, rows normalised again) for a patched copy
                    hi = min(lo + UNIT_BLOCK_ROWS, n)
                    cur = self.feat[lo:hi]
                    if (same_dim and prev_feat is not None and b < min(len(prev_blocks), len(prev_tokens))
                            and prev_blocks[b].shape[0] == hi - lo and prev_feat.shape[0] >= hi):
                        # rows written (stamps) or whose bytes changed since the previous blocks
                        if stamps is not None:
                            changed = stamps[lo:hi] > prev_version
                        else:
                            changed = (_row_words(prev_feat[lo:hi]) != _row_words(cur)).any(axis=1)
                        if not changed.any():  # shared, with its token
                            blocks.append(prev_blocks[b])
                            tokens.append(prev_tokens[b])
                            patches.append(None)
                            continue
                        if np.count_nonzero(changed) * 4 < hi - lo:  # few rows: copy and patch them
                            block = prev_blocks[b].copy()
                            block[changed] = _unit_rows(cur[changed])
                            patch = (prev_tokens[b], np.flatnonzero(changed))
                    if patch is None:
                        block = _unit_rows(cur)
                    block.setflags(write=False)
                    blocks.append(block)
                    tokens.append(next(_BLOCK_TOKENS))
                    patches.append(patch)
                if self._unit_source is not None:
                    with self._unit_source.lock:
                        if self.version >= self._unit_source.version:
                            self._unit_source.version = self.version
                            self._unit_source.feat, self._unit_source.blocks = self.feat, blocks
                            self._unit_source.tokens = tokens
            self._cache["unit_tokens"] = tokens
            self._cache["unit_patches"] = patches
            self._cache["unit_blocks"] = blocks
            return blocks

    def unit_block_tokens(self) -> list[int]:
        """A token per block of :meth:`unit_feature_blocks`, unique in the process for the block's
        contents: a block shared with an earlier snapshot keeps its token, a new or changed block
        takes a new one. Results kept per block (the label cache) are keyed by it."""
        self.unit_feature_blocks()
        with self._cache_lock:
            return list(self._cache["unit_tokens"])

    def unit_block_patches(self) -> list[tuple[int, np.ndarray] | None]:
        """For each block of :meth:`unit_feature_blocks`: ``(parent token, rows)`` when the block is
        a copy of an earlier snapshot's block (that token, :meth:`unit_block_tokens`) with only
        ``rows`` (int64 indices into the block) normalised again, else None. Lets a per-block result
        (the label cache's scores) be patched instead of recomputed."""
        self.unit_feature_blocks()
        with self._cache_lock:
            return list(self._cache["unit_patches"])

    def unit_features_f32(self) -> np.ndarray:
        """(N, D) float32 L2-normalised features (zero rows where none) in one read-only array,
        computed once per snapshot (the blocks of :meth:`unit_feature_blocks`, joined; queries use
        :meth:`similarities`, which needs no joined copy)."""
        blocks = self.unit_feature_blocks()
        with self._cache_lock:
            cached = self._cache.get("unit_f32")
            if cached is None:
                if len(blocks) == 1:
                    cached = blocks[0]
                elif blocks:
                    cached = np.concatenate(blocks)
                else:
                    cached = np.zeros((0, 0 if self.feat is None else self.feat.shape[1]), np.float32)
                cached.setflags(write=False)
                self._cache["unit_f32"] = cached
            return cached

    def similarities(self, emb: np.ndarray) -> np.ndarray:
        """(N, K) float32 cosines of the unit features with ``emb`` (K, D) float32 rows, per block
        of :meth:`unit_feature_blocks` (:func:`mapper.map.query_kernels.row_cosines`: each row's
        bits independent of the other rows, so a patched block's scores can be patched)."""
        from mapper.map.query_kernels import row_cosines  # numba: compiled or loaded when first used

        blocks = self.unit_feature_blocks()
        out = np.empty((len(self), emb.shape[0]), np.float32)
        lo = 0
        for block in blocks:
            if block.shape[1] == 0:
                out[lo:lo + block.shape[0]] = 0.0
            else:
                out[lo:lo + block.shape[0]] = row_cosines(block, emb)
            lo += block.shape[0]
        return out

    def similarities_cached(self, emb: np.ndarray, *, compute: bool = True) -> np.ndarray | None:
        """:meth:`similarities` kept per snapshot for the last few ``emb`` (the same texts asked
        again on the same map version cost a lookup): (N, K) float32, read-only. ``compute=False``:
        the kept array or None, nothing computed."""
        emb = np.ascontiguousarray(emb, np.float32)
        key = ("similarities", emb.shape, hashlib.blake2b(emb.tobytes(), digest_size=16).digest())
        with self._cache_lock:
            cached = self._cache.get(key)
        if cached is not None or not compute:
            return cached
        sims = self.similarities(emb)
        sims.setflags(write=False)
        with self._cache_lock:
            keys = [k for k in self._cache if isinstance(k, tuple) and k[:1] == ("similarities",)]
            for old in keys[: max(0, len(keys) - _SIMILARITY_SETS + 1)]:
                del self._cache[old]
            self._cache[key] = sims
        return sims

    def row_similarities(self, rows: np.ndarray, emb: np.ndarray) -> np.ndarray:
        """(n, K) float32 cosines of the unit features of ``rows`` (n,) int64 with ``emb`` (K, D):
        the same values as ``similarities(emb)[rows]``, reading only those rows."""
        from mapper.map.query_kernels import row_cosines  # numba: compiled or loaded when first used

        blocks = self.unit_feature_blocks()
        out = np.zeros((rows.shape[0], emb.shape[0]), np.float32)
        order = np.argsort(rows, kind="stable")
        block_of = rows[order] // UNIT_BLOCK_ROWS
        bounds = np.searchsorted(block_of, np.arange(len(blocks) + 1))
        for b, block in enumerate(blocks):
            lo, hi = bounds[b], bounds[b + 1]
            if hi > lo and block.shape[1]:
                sel = order[lo:hi]
                out[sel] = row_cosines(block, emb, rows[sel] - b * UNIT_BLOCK_ROWS)
        return out

    def nearest_with_feature(
        self,
        xyz: np.ndarray,  # (N, 3) float32 world metres
        radius_m: float,
    ) -> np.ndarray:
        """(N,) int64 row of the nearest map point that carries a feature within ``radius_m`` of
        each point, -1 where there is none. The index over those points is built once per snapshot
        (per map version) and shared by later calls: a grid of voxel-sized cells
        (:class:`mapper.map.query_kernels.NearestGrid`) for radii up to its
        ``MAX_REACH_CELLS`` voxels, else (and where the grid would be too large: a sparse map over a
        large extent) a k-d tree. The same rows either way, except that of equidistant map points
        the grid takes the lowest row (the tree any)."""
        pts = np.asarray(xyz, np.float64).reshape(-1, 3)
        out = np.full(pts.shape[0], -1, np.int64)
        if pts.shape[0] == 0 or radius_m <= 0:
            return out
        from mapper.map.query_kernels import NearestGrid  # numba: compiled or loaded when first used

        grid = radius_m <= NearestGrid.MAX_REACH_CELLS * self.voxel_size_m
        with self._cache_lock:
            rows = self._cache.get("feature_rows")
            if rows is None:
                rows = self._cache["feature_rows"] = np.flatnonzero(self.feat_weight > 0)
            index = self._cache.get("feature_grid" if grid else "feature_tree", False)
            if index is False:
                at = self.xyz[rows].astype(np.float64)
                index = NearestGrid.build(at, self.voxel_size_m) if grid and rows.size else None
                if index is None and rows.size:  # a large radius, or a grid too large for the map
                    index = cKDTree(at)
                self._cache["feature_grid" if grid else "feature_tree"] = index
        if index is None:
            return out
        if isinstance(index, NearestGrid):
            idx = index.nearest(pts, radius_m, threads=_query_workers())
            hit = idx >= 0
        else:
            dist, idx = index.query(pts, distance_upper_bound=radius_m, workers=_query_workers())
            hit = np.isfinite(dist)
        out[hit] = rows[idx[hit]]
        return out


def observe_keyframe(
    config: GlobalMapConfig,
    keyframe: KeyframeLike,
    *,
    pixel_stride: int | None = None,
    confidence: np.ndarray | None = None,  # (H, W) in [0, 1], same size as the depth
) -> Observations | str:
    """A keyframe's weighted observations under ``config`` (pure), or the reason there are none:
    the depth pixels on the stride grid in ``[min_depth_m, max_depth_m]``, back-projected to the
    world, with the quality weight of the module docstring (times ``confidence``) at least
    ``min_weight``, and the bilinear taps of the OV map at those pixels."""
    cfg = config
    depth = keyframe.depth_m
    if depth is None:
        return "no depth"
    dims = check_shape(depth, "H W", "depth_m")
    height, width = depth.shape
    if confidence is not None:
        check_shape(confidence, "H W", "confidence (the depth's H, W)", dims)
    if pixel_stride is None:  # the config's stride, coarser for large frames (max_observed_pixels)
        stride = max(cfg.pixel_stride, math.ceil(math.sqrt(height * width / cfg.max_observed_pixels)))
    else:
        stride = int(pixel_stride)
    if stride < 1:
        raise ValueError(f"pixel_stride {stride} out of range: must be >= 1")
    rows = np.arange(stride // 2, height, stride)
    cols = np.arange(stride // 2, width, stride)
    grid_j, grid_i = np.meshgrid(rows, cols, indexing="ij")  # (h', w')
    jj: np.ndarray = grid_j.ravel()
    ii: np.ndarray = grid_i.ravel()
    z = depth[jj, ii].astype(np.float64)
    ok = np.isfinite(z) & (z >= cfg.min_depth_m) & (z <= cfg.max_depth_m)
    if not ok.any():
        return "no valid depth in range"
    jj, ii, z = jj[ok], ii[ok], z[ok]
    fx, fy, cx, cy = (float(v) for v in keyframe.K)

    def cam_points(j: np.ndarray, i: np.ndarray, zz: np.ndarray) -> np.ndarray:
        # pixel centres at (i + 0.5, j + 0.5); depth is z along the optical axis
        return np.stack([(i + 0.5 - cx) / fx * zz, (j + 0.5 - cy) / fy * zz, zz], axis=1)

    p_cam = cam_points(jj, ii, z)  # (M, 3)
    dist = np.linalg.norm(p_cam, axis=1)
    weight = np.exp(-np.maximum(dist - cfg.near_m, 0.0) / cfg.falloff_m)
    if cfg.grazing_power > 0:
        weight = weight * _grazing_cos(depth, jj, ii, z, p_cam, dist, cam_points) ** cfg.grazing_power
    if confidence is not None:
        weight = weight * np.clip(np.nan_to_num(confidence[jj, ii].astype(np.float64), nan=0.0), 0.0, 1.0)
    keep = weight >= cfg.min_weight
    if not keep.any():
        return "every observation below min_weight"
    jj, ii, p_cam, weight = jj[keep], ii[keep], p_cam[keep], weight[keep]
    rot = np.asarray(keyframe.world_from_cam[:3, :3], np.float64)
    trans = np.asarray(keyframe.world_from_cam[:3, 3], np.float64)
    p_world = p_cam @ rot.T + trans
    cells = bilinear = ov_flat = None
    if keyframe.ov is not None:
        cells, bilinear, ov_flat = _ov_taps(keyframe.ov, jj, ii, height, width)
    return Observations(p_world, weight.astype(np.float32), cells, bilinear, ov_flat)


def _grazing_cos(
    depth: np.ndarray,  # (H, W) z-depth
    jj: np.ndarray,  # (M,) pixel rows
    ii: np.ndarray,  # (M,) pixel columns
    z: np.ndarray,  # (M,) float64 their depths
    p_cam: np.ndarray,  # (M, 3) their camera points
    dist: np.ndarray,  # (M,) their distances along the ray
    cam_points: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
) -> np.ndarray:
    """(M,) |cos(ray, surface normal)| with the normal from the depth image's four neighbours,
    ``_UNKNOWN_NORMAL_COS`` where a neighbour is missing or across a depth edge."""
    height, width = depth.shape
    il, ir = np.maximum(ii - 1, 0), np.minimum(ii + 1, width - 1)
    ju, jd = np.maximum(jj - 1, 0), np.minimum(jj + 1, height - 1)
    zl, zr = depth[jj, il].astype(np.float64), depth[jj, ir].astype(np.float64)
    zu, zd = depth[ju, ii].astype(np.float64), depth[jd, ii].astype(np.float64)
    neigh = np.nan_to_num(np.stack([zl, zr, zu, zd], axis=1), nan=0.0, posinf=0.0, neginf=0.0)
    good = (
        np.all(neigh > 0, axis=1)
        & np.all(np.abs(neigh - z[:, None]) <= _NORMAL_REL_JUMP * z[:, None], axis=1)
        & (il != ir) & (ju != jd)
    )  # fmt: skip
    normal = np.cross(cam_points(jj, ir, zr) - cam_points(jj, il, zl),
                      cam_points(jd, ii, zd) - cam_points(ju, ii, zu))  # fmt: skip
    n_norm = np.linalg.norm(normal, axis=1)
    cos = np.abs(np.einsum("md,md->m", normal, p_cam)) / np.maximum(n_norm * dist, 1e-12)
    return np.where(good & (n_norm > 0), np.clip(cos, 0.0, 1.0), _UNKNOWN_NORMAL_COS)


def _ov_taps(
    ov: np.ndarray, jj: np.ndarray, ii: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear taps of the (h, w, D) OV map at image pixels (jj, ii) of an (height, width) image:
    cells (M, 4) int64 flat indices, their weights (M, 4) and the map as (h * w, D) float32."""
    h_ov, w_ov, dim = ov.shape
    # pixel centre (i + 0.5) in image pixels -> ov cells, cell centres at +0.5, edge cells
    # replicated (as mapper.model.ops.geometry.sample_bilinear)
    x = (ii + 0.5) * (w_ov / width) - 0.5
    y = (jj + 0.5) * (h_ov / height) - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    ax, ay = x - x0, y - y0
    x0i = np.clip(x0, 0, w_ov - 1).astype(np.int64)
    x1i = np.clip(x0 + 1, 0, w_ov - 1).astype(np.int64)
    y0i = np.clip(y0, 0, h_ov - 1).astype(np.int64)
    y1i = np.clip(y0 + 1, 0, h_ov - 1).astype(np.int64)
    cells = np.stack([y0i * w_ov + x0i, y0i * w_ov + x1i, y1i * w_ov + x0i, y1i * w_ov + x1i], axis=1)
    bilinear = np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], axis=1)
    return cells, bilinear, np.asarray(ov, np.float32).reshape(h_ov * w_ov, dim)


_SAVED_AS_IS = ("keys", "xyz", "weight", "feat_norm", "feat_weight", "hits", "last_seen_ns")
"""The per-voxel arrays a saved section holds as the map holds them (``_<name>``, first ``n`` rows);
it holds ``age_kf`` (keyframes since last seen), ``learned`` and, with features, ``feat`` too."""


@dataclass(frozen=True)
class _SavedMap:
    """A checked global-map section (:func:`_read_saved`)."""

    fields: dict[str, np.ndarray]  # name -> the saved (n, ...) array (``learned`` filled in when absent)
    keys: np.ndarray  # (n,) int64 voxel keys at the map's voxel size (re-keyed when it differs)
    rows: np.ndarray  # ascending rows kept: one per key, the most confident where keys coincide
    dim: int | None
    evicted: EvictedViewStore  # the saved evicted views (empty when absent or re-keyed)
    points_pruned: int


def _read_saved(
    arrays: dict[str, np.ndarray], manifest: object, voxel_size_m: float, prefix: str
) -> _SavedMap:
    """Check a saved section (``GlobalSemanticMap.to_arrays``) for a map of ``voxel_size_m``;
    raises ``ValueError`` naming the field."""
    if not isinstance(manifest, dict) or manifest.get("format") != _FORMAT:
        raise ValueError(f"global map section: unknown format {manifest!r:.80}")
    n = manifest.get("points")
    dim = manifest.get("dim")
    if not isinstance(n, int) or n < 0 or not (dim is None or (isinstance(dim, int) and dim > 0)):
        raise ValueError("global map section: 'points' must be an int >= 0 and 'dim' an int > 0 or null")
    spec: dict[str, tuple[str, tuple[int, ...]]] = {
        "keys": ("int64", (n,)),
        "xyz": ("float32", (n, 3)),
        "weight": ("float32", (n,)),
        "feat_norm": ("float32", (n,)),
        "feat_weight": ("float32", (n,)),
        "hits": ("int32", (n,)),
        "last_seen_ns": ("int64", (n,)),
        "age_kf": ("int64", (n,)),
    }
    if dim is not None:
        spec["feat"] = ("float16", (n, dim))
    got: dict[str, np.ndarray] = {}
    for name, (dtype, shape) in spec.items():
        arr = arrays.get(f"{prefix}.{name}")
        if arr is None or arr.dtype != np.dtype(dtype) or arr.shape != shape:
            desc = "missing" if arr is None else f"{arr.dtype} {arr.shape}"
            raise ValueError(f"global map section: {name} must be {dtype} {shape}, got {desc}")
    for name in spec:
        got[name] = arrays[f"{prefix}.{name}"]
    learned = arrays.get(f"{prefix}.learned")  # optional: maps saved before 2026-12-05 lack it
    if learned is not None and (learned.dtype != np.uint8 or learned.shape != (n,)):
        raise ValueError(
            f"global map section: learned must be uint8 ({n},), got {learned.dtype} {learned.shape}"
        )
    got["learned"] = learned if learned is not None else np.zeros(n, np.uint8)
    if not np.isfinite(got["xyz"]).all() or not (got["weight"] >= 0).all():
        raise ValueError("global map section: xyz must be finite and weights >= 0")
    if manifest.get("voxel_size_m") == voxel_size_m:
        keys = got["keys"]  # the voxel a mean lies in can differ by float32 rounding at its faces
        if np.unique(keys).size != n:
            raise ValueError("global map section: keys are not unique")
    else:
        keys, ok = voxel_keys(got["xyz"], voxel_size_m)
        if not ok.all():
            raise ValueError("global map section: points outside the voxel key range")
    evicted = EvictedViewStore()
    ev_manifest = manifest.get("evicted_views")
    if ev_manifest is not None and manifest.get("voxel_size_m") == voxel_size_m:
        evicted.restore(arrays, ev_manifest, f"{prefix}.evicted")  # raises before anything changed
        if evicted.dim is not None and dim is not None and evicted.dim != dim:
            raise ValueError(f"evicted views section: dimension {evicted.dim}, the map's {dim}")
    # one row per key (re-keying can merge voxels): the most confident wins
    order = np.lexsort((-got["weight"], keys))
    first = np.ones(n, bool)
    first[1:] = keys[order][1:] != keys[order][:-1]
    rows = np.sort(order[first])
    pruned = manifest.get("points_pruned")
    return _SavedMap(got, keys, rows, dim, evicted, pruned if isinstance(pruned, int) else 0)


def _sorted_index(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sorted index of (n,) row keys: (keys ascending, their rows) (stable for equal keys)."""
    order = np.argsort(keys, kind="stable")
    return keys[order].copy(), order.astype(np.int64)


def _lookup(
    sorted_keys: np.ndarray, sorted_rows: np.ndarray, keys: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Look (U,) voxel keys up in a sorted index: (their insertion positions in ``sorted_keys``,
    their rows (0 where absent), a (U,) bool mask of those present)."""
    pos = np.searchsorted(sorted_keys, keys)
    inside = pos < sorted_keys.shape[0]
    found = np.zeros(keys.shape[0], bool)
    found[inside] = sorted_keys[pos[inside]] == keys[inside]
    rows = np.zeros(keys.shape[0], np.int64)
    rows[found] = sorted_rows[pos[found]]
    return pos, rows, found


def _geometry_sums(
    keys: np.ndarray, p_world: np.ndarray, weight: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per voxel of (M,) observations with keys ``keys``: (its key (U,) ascending, each
    observation's voxel (M,), sum of weights (U,), weighted sum of positions (U, 3), observations
    (U,) int32); sums in float64."""
    ukeys, inverse = np.unique(keys, return_inverse=True)  # sorted unique keys
    inverse = inverse.ravel()
    n_u = ukeys.shape[0]
    w64 = weight.astype(np.float64)
    sum_w = np.bincount(inverse, weights=w64, minlength=n_u)
    sum_wxyz = np.stack(
        [np.bincount(inverse, weights=w64 * p_world[:, axis], minlength=n_u) for axis in range(3)], axis=1
    )
    count = np.bincount(inverse, minlength=n_u).astype(np.int32)
    return ukeys, inverse, sum_w, sum_wxyz, count


def _feature_sums(
    weight: np.ndarray,  # (M,) float32
    cells: np.ndarray,  # (M, 4) bilinear taps into ov_flat
    bilinear: np.ndarray,  # (M, 4) their weights
    ov_flat: np.ndarray,  # (h * w, D) float32
    inverse: np.ndarray,  # (M,) each observation's voxel in [0, n_u)
    n_u: int,
) -> np.ndarray:
    """(U, D) float32: per voxel, the sum over its observations of weight * bilinear(ov), as a
    (U x cells) sparse matrix times the OV cells."""
    taps = csr_matrix(
        ((weight[:, None] * bilinear).ravel().astype(np.float32), (np.repeat(inverse, 4), cells.ravel())),
        shape=(n_u, ov_flat.shape[0]),
    )
    return np.asarray(taps @ ov_flat, np.float32)


def _mixed_features(unit: np.ndarray, fused: np.ndarray, fresh: np.ndarray) -> np.ndarray:
    """(U, D) float16 learned features for voxels: ``unit`` (U, D) float32 unit rows where ``fresh``
    (no fused feature), else ``normalise(unit + fused)`` with the (U, D) fused unit features."""
    mixed = unit
    mixed[~fresh] += fused[~fresh].astype(np.float32)
    mixed /= np.maximum(np.sqrt(np.einsum("ud,ud->u", mixed, mixed)), 1e-12)[:, None]
    return mixed.astype(np.float16)


def _learn_rows(arrays: dict[str, np.ndarray], rows: np.ndarray, unit: np.ndarray) -> None:
    """Give ``rows`` of the per-voxel ``arrays`` (``feat``, ``feat_norm``, ``feat_weight``,
    ``weight``, ``learned``) the learned unit features ``unit`` (n, D) float32 by the rule of
    :meth:`GlobalSemanticMap.set_features`, in place (``unit`` is overwritten)."""
    fresh = arrays["feat_weight"][rows] <= 0
    arrays["feat"][rows] = _mixed_features(unit, arrays["feat"][rows], fresh)
    arrays["feat_norm"][rows[fresh]] = 1.0
    arrays["feat_weight"][rows[fresh]] = np.maximum(arrays["weight"][rows[fresh]], 1e-6)
    arrays["learned"][rows] = 1


def _prune_keep(
    weight: np.ndarray, last_seen_kf: np.ndarray, kf_counter: int, config: GlobalMapConfig, limit: int = 0
) -> np.ndarray:
    """The rows (ascending) a prune keeps: the ``prune_to_fraction * limit`` (``limit`` 0:
    ``max_points``; at least 1) with the highest priority ``weight * 0.5 ** (keyframes since last
    seen / stale_half_life_keyframes)``."""
    keep_n = max(1, int((limit or config.max_points) * config.prune_to_fraction))
    age = (kf_counter - last_seen_kf).astype(np.float64)
    priority = weight * np.exp2(-age / config.stale_half_life_keyframes)
    return np.sort(np.argpartition(-priority, keep_n - 1)[:keep_n])


def _grown(arrays: dict[str, np.ndarray | None], n: int, need: int) -> dict[str, np.ndarray]:
    """Larger copies of the per-row ``arrays`` (None: skipped) when ``need`` rows exceed their
    capacity (1.5x growth, at least ``need``), with their first ``n`` rows; {} while they have room."""
    cap = next(a for a in arrays.values() if a is not None).shape[0]
    if need <= cap:
        return {}
    new_cap = max(need, int(cap * 1.5) + 1024)
    out = {}
    for name, old in arrays.items():
        if old is not None:
            out[name] = np.zeros((new_cap, *old.shape[1:]), old.dtype)
            out[name][:n] = old[:n]
    return out


def _bytes_held(arrays: dict[str, np.ndarray | None], n: int | None, *index: np.ndarray) -> int:
    """Bytes of the first ``n`` rows of the per-row ``arrays`` (None: skipped; ``n`` None: all
    allocated rows) plus the ``index`` arrays."""
    held = [a if n is None else a[:n] for a in arrays.values() if a is not None]
    return int(sum(a.nbytes for a in held) + sum(a.nbytes for a in index))


def _keep_rows(arrays: dict[str, np.ndarray | None], keep: np.ndarray) -> None:
    """Move rows ``keep`` (ascending) of every per-row array (None: skipped) to its front, in
    place, and zero the rest."""
    for arr in arrays.values():
        if arr is not None:
            kept = arr[keep]
            arr[: kept.shape[0]] = kept
            arr[kept.shape[0]:] = 0


def _frozen(rows: np.ndarray, n: int) -> np.ndarray:
    """A read-only copy of the first ``n`` rows."""
    out = rows[:n].copy()
    out.setflags(write=False)
    return out


def _query_workers() -> int:
    """Threads of a k-d tree query: torch's (the node's compute threads, OMP_NUM_THREADS) where
    torch is loaded (this module stays torch-free), else 1."""
    torch = sys.modules.get("torch")
    return max(1, int(torch.get_num_threads())) if torch is not None else 1


_PAGED_FIELDS = ("keys", "xyz", "weight", "feat_norm", "feat_weight", "hits", "last_seen_ns", "last_seen_kf",
                 "learned")
"""The per-voxel arrays a paged tile holds (:mod:`mapper.map.tile_store`), besides ``feat``."""

_STORES = itertools.count(1)
"""Tile store files of this process (one per map object)."""


class _StoredMap:
    """Saving, loading and paging of :class:`GlobalSemanticMap` (its persistence half; the rows it
    moves are the map's). Beyond ``max_points`` resident voxels the least recently observed tiles
    go to the map's :class:`mapper.map.tile_store.TileStore` and come back when an observation
    touches them (:meth:`_page_in_keys`), when ``segment_points`` asks about points in them
    (:meth:`page_in_near`); ``query_points`` reads those that may match (:meth:`query_snapshot`),
    the evicted-view worker their positions (:meth:`paged_geometry`), and the learned features of a
    keyframe leaving the window are read and written in the store (:meth:`_paged_voxels`,
    :meth:`_set_paged_features`).
    Paging out is a prune whose rows can come back: it moves rows (``feat_reset``), keeps the voxel
    keys, so the evicted views kept per key (:mod:`mapper.map.evicted_views`) re-attach on page-in."""

    config: GlobalMapConfig
    evicted: EvictedViewStore
    points_pruned: int
    points_learned: int
    keyframes_integrated: int
    points_paged_out: int
    points_paged_in: int
    _lock: threading.Lock
    _store: TileStore
    _n: int
    _dim: int | None
    _version: int
    _generation: int
    _map_version: int
    _kf_counter: int
    _keys: np.ndarray
    _feat: np.ndarray | None
    _weight: np.ndarray
    _last_seen_kf: np.ndarray
    _learned: np.ndarray
    _feat_stamp: np.ndarray
    _sorted_keys: np.ndarray
    _sorted_rows: np.ndarray
    _joined: tuple[tuple[int, int, tuple[int, ...]], GlobalMapSnapshot] | None = None
    """The latest :meth:`query_snapshot` with paged tiles: ((version, generation, tiles), snapshot)."""
    if TYPE_CHECKING:
        def _reset(self, dim: int | None) -> None: ...
        def _grow(self, need: int) -> None: ...
        def _compact(self, keep: np.ndarray) -> None: ...
        def _set_dim(self, dim: int) -> None: ...
        def _snapshot_locked(self) -> GlobalMapSnapshot: ...

    # -- persistence -------------------------------------------------------------------------

    def to_arrays(self, prefix: str = "global") -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """``({"global.<field>": array}, manifest section)`` for :class:`mapper.node.store.MapStore`
        (plain numeric arrays, no pickle): every voxel, resident and paged. Taken under the lock: a
        consistent copy."""
        with self._lock:
            rows = self._all_rows()
            arrays = {f"{prefix}.{name}": rows[name] for name in _SAVED_AS_IS}
            arrays[f"{prefix}.age_kf"] = (self._kf_counter - rows["last_seen_kf"]).astype(np.int64)
            arrays[f"{prefix}.learned"] = rows["learned"]
            if self._feat is not None:
                arrays[f"{prefix}.feat"] = rows["feat"]
            ev_arrays, ev_manifest = self.evicted.to_arrays(f"{prefix}.evicted")
            arrays.update(ev_arrays)
            manifest: dict[str, Any] = {
                "evicted_views": ev_manifest,
                "format": _FORMAT,
                "points": int(rows["keys"].shape[0]),
                "dim": self._dim,
                "voxel_size_m": self.config.voxel_size_m,
                "map_version": self._map_version,
                "points_pruned": self.points_pruned,
                "keyframes_integrated": self.keyframes_integrated,
            }
        return arrays, manifest

    def _all_rows(self) -> dict[str, np.ndarray]:
        """Copies of every voxel's arrays, the resident rows then the paged ones (lock held)."""
        n = self._n
        paged = self._store.read(list(self._store.info), self._dim)
        names = _PAGED_FIELDS + (("feat",) if self._feat is not None else ())
        return {name: np.concatenate([getattr(self, f"_{name}")[:n], paged[name]]) for name in names}

    def restore(
        self, arrays: dict[str, np.ndarray], manifest: object, map_version: int, prefix: str = "global"
    ) -> None:
        """Replace the content with a saved one (inverse of :meth:`to_arrays`). Checks every array
        and raises ``ValueError`` naming the field; the map is unchanged on error. A map saved with
        another voxel size is re-keyed (voxels that now coincide keep the most confident one).
        Beyond ``max_points``, tiles page out as they would while mapping."""
        saved = _read_saved(arrays, manifest, self.config.voxel_size_m, prefix)  # nothing changed yet
        got, keys, rows, dim = saved.fields, saved.keys, saved.rows, saved.dim
        with self._lock:
            self._store.clear()
            self._joined = None
            self._reset(dim)
            m = rows.shape[0]
            self._grow(m)
            self._n = m
            self._keys[:m] = keys[rows]  # re-keyed for another voxel size
            for name in _SAVED_AS_IS[1:]:
                getattr(self, f"_{name}")[:m] = got[name][rows]
            self._last_seen_kf[:m] = -got["age_kf"][rows]
            self._learned[:m] = got["learned"][rows] != 0
            if self._feat is not None:
                self._feat[:m] = got["feat"][rows]
            self._sorted_keys, self._sorted_rows = _sorted_index(self._keys[:m])
            self.points_pruned = saved.points_pruned
            self._map_version = map_version
            self._version += 1
            self._generation = next(_GENERATIONS)
            self.evicted = saved.evicted
            self._apply_bound()

    def retag(self, map_version: int) -> None:
        """Set the node map version that the current content corresponds to (e.g. after a load)."""
        with self._lock:
            self._map_version = map_version
            self._version += 1

    def clear(self, map_version: int | None = None) -> None:
        """Drop every point, paged ones too (the feature dimension is forgotten too)."""
        with self._lock:
            self._store.clear()
            self._joined = None
            self._reset(None)
            self.evicted = EvictedViewStore()
            if map_version is not None:
                self._map_version = map_version
            self._version += 1
            self._generation = next(_GENERATIONS)

    # -- paging ------------------------------------------------------------------------------

    @property
    def tile_voxels(self) -> int:
        """Edge of a paging tile in voxels (``tile_m`` rounded to whole voxels)."""
        return max(1, int(round(self.config.tile_m / self.config.voxel_size_m)))

    @property
    def paged_points(self) -> int:
        """Voxels in the tile store (not in memory)."""
        return self._store.points

    @property
    def total_points(self) -> int:
        """Every voxel of the map: resident and paged."""
        return self._n + self._store.points

    def all_keys(self) -> np.ndarray:
        """(N,) int64 voxel keys of every voxel, resident and paged (e.g. to drop the evicted views
        of voxels no longer in the map)."""
        with self._lock:
            return np.concatenate([self._keys[: self._n], self._store.keys()])

    def _apply_bound(self) -> int:
        """The ``max_points`` bound (lock held; the caller bumped the version): page tiles out
        (``paging``) or prune. Returns the voxels pruned (forgotten)."""
        if self._n <= self.config.max_points:
            return 0
        if not self.config.paging:
            return self._prune_rows()
        self._page_out()
        return self._prune_store()

    def _prune_rows(self) -> int:
        """Drop the lowest-priority resident voxels (``paging`` off; lock held). Returns how many."""
        n = self._n
        keep = _prune_keep(self._weight[:n], self._last_seen_kf[:n], self._kf_counter, self.config)
        self._compact(keep)
        self.points_pruned += n - keep.shape[0]
        log.debug("global map: dropped %d voxels (max_points %d)", n - keep.shape[0], self.config.max_points)
        return n - int(keep.shape[0])

    def _page_out(self) -> None:
        """Move the least recently observed whole tiles to the store until ``prune_to_fraction *
        max_points`` voxels remain; the tiles the latest keyframe observed stay (lock held)."""
        cfg, n = self.config, self._n
        self._joined = None  # memory is short: the kept query snapshot goes first
        tiles = tile_ids(self._keys[:n], self.tile_voxels)
        uniq, inverse = np.unique(tiles, return_inverse=True)
        inverse = inverse.ravel()
        counts = np.bincount(inverse, minlength=uniq.shape[0])
        recent = np.full(uniq.shape[0], np.iinfo(np.int64).min, np.int64)
        np.maximum.at(recent, inverse, self._last_seen_kf[:n])
        order = np.lexsort((uniq, recent))
        order = order[recent[order] < self._kf_counter]
        excess = n - max(1, int(cfg.max_points * cfg.prune_to_fraction))
        pick = order[: int(np.searchsorted(np.cumsum(counts[order]), excess)) + 1]
        if pick.size == 0:
            return
        out = np.zeros(uniq.shape[0], bool)
        out[pick] = True
        rows = np.flatnonzero(out[inverse])
        names = _PAGED_FIELDS + (("feat",) if self._feat is not None else ())
        self._put_tiles({name: getattr(self, f"_{name}")[rows] for name in names})
        self._compact(np.flatnonzero(~out[inverse]))
        self.points_paged_out += int(rows.shape[0])

    def _put_tiles(self, fields: dict[str, np.ndarray]) -> None:
        """Write voxels (``_PAGED_FIELDS`` and ``feat``) to the store, one row per tile, each with
        its feature summary (lock held)."""
        tiles = tile_ids(fields["keys"], self.tile_voxels)
        order = np.argsort(tiles, kind="stable")
        groups = np.split(order, np.flatnonzero(np.diff(tiles[order])) + 1)
        feat, k = fields.get("feat"), self.config.tile_summary_k
        ids, parts, cents, least, index, last = [], [], [], [], [], []
        for rows in groups:
            part = {name: arr[rows] for name, arr in fields.items()}
            unit = _unit_rows(part["feat"][part["feat_weight"] > 0]) if feat is not None else np.zeros((0, 0))
            c, lc = tile_summary(unit, k)
            ids.append(int(tiles[rows[0]]))
            parts.append(part)
            cents.append(c)
            least.append(lc)
            idx = np.floor_divide(key_indices(part["keys"][:1]), self.tile_voxels)[0]
            index.append((int(idx[0]), int(idx[1]), int(idx[2])))
            last.append(int(part["last_seen_kf"].max()))
        self._store.put(ids, parts, cents, least, index, last)

    def _prune_store(self) -> int:
        """``max_disk_points``: beyond it drop the lowest-priority paged voxels (lock held). Returns
        how many were dropped."""
        cfg = self.config
        if cfg.max_disk_points <= 0 or self._store.points <= cfg.max_disk_points:
            return 0
        got = self._store.take(list(self._store.info), self._dim)
        total = int(got["keys"].shape[0])
        keep = _prune_keep(got["weight"], got["last_seen_kf"], self._kf_counter, cfg, cfg.max_disk_points)
        self._put_tiles({name: arr[keep] for name, arr in got.items()})
        self.points_pruned += total - int(keep.shape[0])
        return total - int(keep.shape[0])

    def _page_in(self, tiles: list[int]) -> int:
        """Bring paged ``tiles`` back into memory (lock held): appended rows, a new version.
        Returns the voxels brought back."""
        got = self._store.take(tiles, self._dim)
        m = int(got["keys"].shape[0])
        if m == 0:
            return 0
        self._version += 1
        start = self._n
        self._grow(start + m)
        for name in _PAGED_FIELDS:
            getattr(self, f"_{name}")[start: start + m] = got[name]
        if self._feat is not None:
            self._feat[start: start + m] = got["feat"]
        self._feat_stamp[start: start + m] = self._version
        self._n = start + m
        self._sorted_keys, self._sorted_rows = _sorted_index(self._keys[: self._n])
        self.points_paged_in += m
        return m

    def _page_in_keys(self, keys: np.ndarray) -> int:
        """Page in the paged tiles that voxel ``keys`` fall in (lock held). Returns the voxels."""
        if not self._store.info or keys.size == 0:
            return 0
        paged = [t for t in np.unique(tile_ids(keys, self.tile_voxels)).tolist() if t in self._store.info]
        return self._page_in(paged) if paged else 0

    def _page_in_observed(self, keyframe: KeyframeLike, obs: Observations, carving: bool) -> None:
        """Page in the paged tiles a keyframe's observations fall in and, when it carves, those in
        the box it can clear (camera to depth: :func:`mapper.map.carving.changed_region`) (lock held)."""
        if not self._store.info:
            return
        if carving:
            cfg, (height, width) = self.config, keyframe.rgb.shape[:2]
            box = changed_region(keyframe.K, keyframe.world_from_cam, width, height, keyframe.depth_m,
                                 cfg.min_depth_m, cfg.max_depth_m, include_camera=True)
            self._page_in(sorted(self._store.select(self.tile_voxels * cfg.voxel_size_m, box)))
        self._page_in_keys(voxel_keys(obs.xyz, self.config.voxel_size_m)[0])

    def paged_geometry(
        self, region: tuple[np.ndarray, np.ndarray] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(xyz (n, 3) float32, keys (n,) int64) of the paged voxels (those in the tiles that
        intersect ``region``, a world box, when given), read without paging them in: with
        :meth:`geometry`, what a worker that projects the whole map into a view needs (the evicted
        views record paged voxels too)."""
        with self._lock:
            if not self._store.info:
                return np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
            tiles = self._store.select(self.tile_voxels * self.config.voxel_size_m, region)
            return self._store.read_geometry(tiles)

    def _paged_lookup(
        self, keys: np.ndarray
    ) -> tuple[dict[str, np.ndarray], list[int], np.ndarray, np.ndarray]:
        """The paged tiles voxel ``keys`` (U,) fall in, read: (their arrays, the tiles, each key's
        row in those arrays, a (U,) bool mask of the keys found) (lock held)."""
        tiles = [t for t in np.unique(tile_ids(keys, self.tile_voxels)).tolist() if t in self._store.info]
        got = self._store.read(tiles, self._dim)
        order = np.argsort(got["keys"], kind="stable")
        _, rows, found = _lookup(got["keys"][order], order.astype(np.int64), keys)
        return got, tiles, rows, found

    def _paged_voxels(self, keys: np.ndarray, unlearned: bool) -> tuple[np.ndarray, np.ndarray]:
        """Of voxel ``keys`` (U,) not resident: (keys, xyz (n, 3) float32) of those paged (with
        ``unlearned``, only those without a learned feature) (lock held)."""
        got, _, rows, found = self._paged_lookup(keys)
        if unlearned:
            found &= got["learned"][rows] == 0
        return keys[found], got["xyz"][rows[found]].copy()

    def _set_paged_features(self, keys: np.ndarray, unit: np.ndarray) -> int:
        """:meth:`set_features` for voxel ``keys`` (U,) not resident, with unit features (U, D):
        those paged take them in the store (their tiles rewritten), without paging them in (lock
        held). Returns how many were set."""
        got, _, rows, found = self._paged_lookup(keys)
        if self.config.learned_features_once:
            found[found] = got["learned"][rows[found]] == 0
        if not found.any():
            return 0
        self._set_dim(int(unit.shape[1]))
        if "feat" not in got:  # the map had no features when these tiles were read: none had any
            got["feat"] = np.zeros((got["keys"].shape[0], unit.shape[1]), np.float16)
        _learn_rows(got, rows[found], unit[found])
        self._put_tiles(got)  # the same tiles, replaced
        self.points_learned += int(np.count_nonzero(found))
        return int(np.count_nonzero(found))

    def page_in_near(self, xyz: np.ndarray, radius_m: float) -> int:
        """Page in the paged tiles within ``radius_m`` of the points ``xyz`` (N, 3) (what a
        ``segment_points`` at those points reads from the map). Resident voxels may exceed
        ``max_points`` until the next keyframe pages the least recently observed tiles out again.
        Returns the voxels brought back."""
        pts = np.asarray(xyz, np.float64).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(axis=1)]
        voxel, tile = self.config.voxel_size_m, self.tile_voxels
        reach = max(float(radius_m), 0.0)
        with self._lock:
            if not self._store.info or pts.shape[0] == 0:
                return 0
            lo = np.floor_divide(np.floor((pts - reach) / voxel).astype(np.int64), tile)
            hi = np.floor_divide(np.floor((pts + reach) / voxel).astype(np.int64), tile)
            span = int((hi - lo).max())
            if span > 2:  # a radius of several tiles: the paged tiles in the points' box
                box = (pts.min(axis=0) - reach, pts.max(axis=0) + reach)
                return self._page_in(sorted(self._store.select(tile * voxel, box)))
            wanted: set[int] = set()
            for step in itertools.product(range(span + 1), repeat=3):
                idx = np.minimum(lo + np.asarray(step, np.int64), hi)
                idx = idx[np.all(np.abs(idx) < KEY_OFFSET - 1, axis=1)]
                wanted.update(pack_indices(idx).tolist())
            paged = [t for t in wanted if t in self._store.info]
            return self._page_in(sorted(paged)) if paged else 0

    def query_snapshot(
        self,
        region: tuple[np.ndarray, np.ndarray] | None = None,
        may_match: Callable[[TileInfo], bool] | None = None,
    ) -> GlobalMapSnapshot:
        """A snapshot for a ``query_points`` over the whole map: the resident voxels (the cached
        :meth:`snapshot`) followed by the voxels of the paged tiles that intersect ``region`` and
        for which ``may_match`` holds on their summary (read, not made resident). Nothing paged
        selected: the snapshot itself. The latest such snapshot is kept until the map's version
        changes: further queries of that version selecting the same tiles share it (and its
        normalised features)."""
        with self._lock:
            snap = self._snapshot_locked()
            if not self._store.info:
                return snap
            tiles = tuple(sorted(self._store.select(self.tile_voxels * self.config.voxel_size_m, region,
                                                    may_match)))
            if not tiles:
                return snap
            kept = self._joined
            if kept is not None and kept[0] == (snap.version, snap.generation, tiles):
                return kept[1]
            got = self._store.read(tiles, self._dim)
        joined = _joined_snapshot(snap, got)
        with self._lock:
            self._joined = ((snap.version, snap.generation, tiles), joined)
        return joined


def _joined_snapshot(snap: GlobalMapSnapshot, paged: dict[str, np.ndarray]) -> GlobalMapSnapshot:
    """``snap`` with the ``paged`` voxels appended (same version: the store changes only with one);
    its unit features are computed on their own (no rows shared with the map's snapshots)."""

    def joined(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
        if a is None or b is None:
            return None
        out = np.concatenate([a, b])
        out.setflags(write=False)
        return out

    feat = joined(snap.feat, paged.get("feat"))
    weight, feat_weight = joined(snap.weight, paged["weight"]), joined(snap.feat_weight, paged["feat_weight"])
    hits, seen = joined(snap.hits, paged["hits"]), joined(snap.last_seen_ns, paged["last_seen_ns"])
    xyz = joined(snap.xyz, paged["xyz"])
    assert xyz is not None and weight is not None and feat_weight is not None and hits is not None
    assert seen is not None
    return GlobalMapSnapshot(
        version=snap.version, map_version=snap.map_version, voxel_size_m=snap.voxel_size_m, xyz=xyz,
        feat=feat, weight=weight, feat_weight=feat_weight, hits=hits, last_seen_ns=seen,
        keys=joined(snap.keys, paged["keys"]), generation=snap.generation)


class GlobalSemanticMap(_StoredMap):
    """Voxel-hashed surface points with fused OV features; see the module docstring."""

    def __init__(
        self,
        config: GlobalMapConfig,
        fusion: FusionRule = weighted_mean_fusion,
        tile_dir: str | Path | None = None,
    ) -> None:
        self.config = config
        self.tile_dir = Path(tempfile.gettempdir(), "govnesf-tiles") if tile_dir is None else Path(tile_dir)
        """Where the tile store's file is made when the first tile pages out (the node:
        ``<map_dir>/.tiles``; default: the system's temporary directory)."""
        self._store = TileStore(self.tile_dir / f"tiles-{os.getpid()}-{next(_STORES)}.sqlite3")
        weakref.finalize(self, self._store.destroy)  # the file goes with the map
        self.fusion: FusionRule = fusion
        """The feature fusion rule (replaceable by the learned model)."""
        self._lock = threading.Lock()
        self._snapshot: GlobalMapSnapshot | None = None
        self._unit_source = _UnitSource()
        self._version = 0
        self._generation = next(_GENERATIONS)
        self.evicted = EvictedViewStore()
        """What keyframes that left the window saw, per voxel (:mod:`mapper.map.evicted_views`;
        saved and loaded with the map, cleared with it)."""
        self._reset(dim=None)

    # -- state -------------------------------------------------------------------------------

    def _reset(self, dim: int | None) -> None:
        cap = 1024
        self._n = 0
        self._dim = dim
        self._keys = np.zeros(cap, np.int64)
        self._xyz = np.zeros((cap, 3), np.float32)
        self._weight = np.zeros(cap, np.float32)
        self._feat = np.zeros((cap, dim), np.float16) if dim else None
        self._feat_norm = np.zeros(cap, np.float32)
        self._feat_weight = np.zeros(cap, np.float32)
        self._hits = np.zeros(cap, np.int32)
        self._last_seen_ns = np.zeros(cap, np.int64)
        self._last_seen_kf = np.zeros(cap, np.int64)
        self._feat_stamp = np.zeros(cap, np.int64)
        """The version whose snapshots first include each row's current feature bytes."""
        self._learned = np.zeros(cap, np.uint8)
        """1 where :meth:`set_features` gave the voxel a learned feature (saved with the map)."""
        self._feat_reset = self._version + 1
        """Rows moved or were replaced (prune, restore, clear) in this version: snapshots'
        ``feat_reset``."""
        self._sorted_keys = np.zeros(0, np.int64)
        self._sorted_rows = np.zeros(0, np.int64)
        self._kf_counter = 0
        self._map_version = 0
        self.points_pruned = 0
        """Voxels dropped by the ``max_points`` bound (``paging`` off) or ``max_disk_points`` since
        start (or the last restore)."""
        self.points_paged_out = 0
        self.points_paged_in = 0
        self.points_carved = 0
        """Voxels removed by visibility carving since start (or the last restore)."""
        self.keyframes_integrated = 0
        self.integrate_seconds_total = 0.0
        self.points_learned = 0
        """Voxel feature updates by :meth:`set_features` (a voxel counts once with
        ``learned_features_once``, else once per keyframe that saw it)."""
        self.integrate_recent_s: deque[float] = deque(maxlen=_RECENT_INTEGRATES)
        """Seconds of the latest integrates (for the p50 / p95 in :meth:`stats`)."""

    _ROW_FIELDS = ("_keys", "_xyz", "_weight", "_feat", "_feat_norm", "_feat_weight", "_hits",
                   "_last_seen_ns", "_last_seen_kf", "_feat_stamp", "_learned")  # fmt: skip

    def _grow(self, need: int) -> None:
        for name, grown in _grown(self._rows(), self._n, need).items():
            setattr(self, name, grown)

    def _rows(self) -> dict[str, np.ndarray | None]:
        """The per-row arrays by attribute name (``_ROW_FIELDS``; ``_feat`` None before a feature)."""
        return {name: getattr(self, name) for name in self._ROW_FIELDS}

    def _set_dim(self, dim: int) -> None:
        if self._dim is None:
            self._dim = dim
            self._feat = np.zeros((self._keys.shape[0], dim), np.float16)
        elif dim != self._dim:
            raise ValueError(f"ov feature dimension {dim} differs from the global map's {self._dim}")

    @property
    def dim(self) -> int | None:
        """OV feature dimension (None until a keyframe with ``ov`` arrived)."""
        return self._dim

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Bytes of map data held: the used rows of every per-voxel array plus the sorted index
        (the arrays grow by 1.5x, so up to a third more may be allocated: :attr:`allocated_bytes`)."""
        return _bytes_held(self._rows(), self._n, self._sorted_keys, self._sorted_rows)

    @property
    def allocated_bytes(self) -> int:
        """Bytes allocated by the map's arrays (capacity, not only the used rows)."""
        return _bytes_held(self._rows(), None, self._sorted_keys, self._sorted_rows)

    def stats(self) -> dict[str, Any]:
        """Counters for the node's status reply."""
        with self._lock:
            n = self._n
            with_feat = int(np.count_nonzero(self._feat_weight[:n] > 0))
            return {
                "global_points": n,
                "global_points_total": n + self._store.points,
                "global_points_with_features": with_feat,
                "global_max_points": self.config.max_points,
                "global_points_pruned": self.points_pruned,
                "global_points_paged": self._store.points,
                "global_tiles_paged": len(self._store),
                "global_points_paged_out": self.points_paged_out,
                "global_points_paged_in": self.points_paged_in,
                "global_tile_store_bytes": self._store.disk_bytes,
                "global_max_disk_points": self.config.max_disk_points,
                "global_points_carved": self.points_carved,
                "global_map_bytes": self.nbytes,
                "global_map_allocated_bytes": self.allocated_bytes,
                "global_voxel_size_m": self.config.voxel_size_m,
                "global_keyframes_integrated": self.keyframes_integrated,
                "global_points_learned": self.points_learned,
                **_percentiles_ms("global_integrate_ms", self.integrate_recent_s),
                "global_integrate_ms_mean": round(
                    1e3 * self.integrate_seconds_total / max(self.keyframes_integrated, 1), 3
                ),
            }

    # -- integration -------------------------------------------------------------------------

    def observe(
        self,
        keyframe: KeyframeLike,
        *,
        pixel_stride: int | None = None,
        confidence: np.ndarray | None = None,  # (H, W) in [0, 1], same size as the depth
    ) -> Observations | str:
        """The keyframe's weighted observations (pure; no lock), or the reason there are none
        (:func:`observe_keyframe` with this map's config).

        ``pixel_stride`` overrides ``config.pixel_stride``; ``confidence`` multiplies each pixel's
        quality weight (e.g. the opacity of a rendered depth, see :mod:`mapper.node.workers.depth_points`).
        """
        return observe_keyframe(self.config, keyframe, pixel_stride=pixel_stride, confidence=confidence)

    def integrate(
        self,
        keyframe: KeyframeLike,
        map_version: int | None = None,
        *,
        pixel_stride: int | None = None,
        confidence: np.ndarray | None = None,  # (H, W) weight multiplier in [0, 1]
        count_keyframe: bool = True,
        carve: bool = True,
    ) -> IntegrateStats:
        """Fuse one keyframe (see the module docstring); ``map_version`` is the node's version that
        includes it (reported by snapshots). Touches only the voxels the keyframe sees.

        ``pixel_stride`` and ``confidence``: see :meth:`observe`. ``count_keyframe=False`` adds
        points to a keyframe already counted (rendered depth for a keyframe integrated earlier
        without depth), so the staleness clock does not tick twice. ``carve``: the depth is input
        depth, it carves what it sees through first (with ``global_map.carve``; :meth:`_carve`)."""
        started = time.perf_counter()
        if keyframe.ov is not None:
            check_shape(keyframe.ov, "h w D", "ov")
        _check_depth(keyframe)
        obs = self.observe(keyframe, pixel_stride=pixel_stride, confidence=confidence)  # outside the lock
        with self._lock:
            if keyframe.ov is not None:
                self._set_dim(int(keyframe.ov.shape[2]))
            if count_keyframe:
                self._kf_counter += 1
            self._version += 1
            if map_version is not None:
                self._map_version = map_version
            if isinstance(obs, str):
                return IntegrateStats(0, 0, 0, 0, keyframe.ov is not None, time.perf_counter() - started, obs)
            self._page_in_observed(keyframe, obs, carve and self.config.carve)
            carved = self._carve(keyframe) if carve and self.config.carve else 0
            touched, new, pruned = self._fuse(obs, int(keyframe.stamp_ns))
            seconds = time.perf_counter() - started
            self.keyframes_integrated += 1
            self.integrate_seconds_total += seconds
            self.integrate_recent_s.append(seconds)
        return IntegrateStats(len(obs.weight), touched, new, pruned, obs.ov_flat is not None, seconds,
                              carved=carved)

    def integrate_features(
        self,
        keyframe: KeyframeLike,
        map_version: int | None = None,
        *,
        pixel_stride: int | None = None,
        confidence: np.ndarray | None = None,  # (H, W) weight multiplier in [0, 1]
    ) -> IntegrateStats:
        """Fuse only the OV features of a keyframe whose geometry was integrated before without
        ``ov`` (the in-process OV backend, :mod:`mapper.node.workers.ov_features`, computes them later).

        The observations are those :meth:`integrate` made for the keyframe (same depth, stride,
        confidence, quality weights), so each voxel they fall in receives exactly the feature sum and
        weight a combined integrate would have fused. Geometry is untouched: positions, confidence,
        hits and last-seen stamps stay as they are, and no voxel is created (observations whose
        voxel was pruned since are dropped). ``stats.points`` counts the observations fused,
        ``voxels_touched`` their voxels. Raises ``ValueError`` (nothing changed) without ``ov``, on a
        bad ``ov`` shape or a feature dimension other than the map's."""
        started = time.perf_counter()
        if keyframe.ov is None:
            raise ValueError("integrate_features needs ov of shape (h, w, D), got None")
        check_shape(keyframe.ov, "h w D", "ov")
        _check_depth(keyframe)
        obs = self.observe(keyframe, pixel_stride=pixel_stride, confidence=confidence)  # outside the lock
        with self._lock:
            self._set_dim(int(keyframe.ov.shape[2]))
            if isinstance(obs, str):
                return IntegrateStats(0, 0, 0, 0, True, time.perf_counter() - started, obs)
            points, touched = self._fuse_features(obs)
            self._version += 1
            if map_version is not None:
                self._map_version = map_version
        if points == 0:
            return IntegrateStats(0, 0, 0, 0, True, time.perf_counter() - started,
                                  "none of its voxels is in the map any more")
        return IntegrateStats(points, touched, 0, 0, True, time.perf_counter() - started)

    def seen_voxels(
        self, keyframe: KeyframeLike, *, unlearned: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:  # (U,) int64 keys, (U, 3) float32 positions
        """The map voxels a keyframe's observations fall in (those still in the map): (keys (U,)
        int64, fused positions (U, 3) float32). Empty without depth. No lock held while observing.
        ``unlearned``: only voxels :meth:`set_features` has not given a learned feature yet."""
        obs = self.observe(keyframe)
        if isinstance(obs, str):
            return np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
        keys, ok = voxel_keys(obs.xyz, self.config.voxel_size_m)
        ukeys = np.unique(keys[ok])
        with self._lock:
            rows, found = self._rows_of(ukeys)
            keep = found & (self._learned[rows] == 0) if unlearned else found
            out_keys, out_xyz = ukeys[keep], self._xyz[rows[keep]].copy()
            if self._store.info and not found.all():  # paged ones too, read without paging them in
                more_keys, more_xyz = self._paged_voxels(ukeys[~found], unlearned)
                order = np.argsort(np.concatenate([out_keys, more_keys]), kind="stable")
                out_keys = np.concatenate([out_keys, more_keys])[order]
                out_xyz = np.concatenate([out_xyz, more_xyz])[order]
            return out_keys, out_xyz

    def _rows_of(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of ``keys`` (U,) and a (U,) bool mask of those in the map (lock held)."""
        _, rows, found = _lookup(self._sorted_keys, self._sorted_rows, keys)
        return rows, found

    def set_features(
        self,
        keys: np.ndarray,  # (U,) int64 voxel keys (from seen_voxels)
        features: np.ndarray,  # (U, D) float features (any norm; zero rows are skipped)
    ) -> int:
        """Give voxels the learned model's blended feature of the points a keyframe saw, just
        before it leaves the window. A voxel with a fused feature takes the equal mix of the two
        directions, ``normalise(unit(feature) + fused unit)`` (measured better than replacing
        the fused average: docs/concepts/window-and-map.md), and keeps its norm and feature weight, so later
        observations still fuse as a running weighted mean; a voxel without one takes the
        feature's direction with norm 1 and its geometric confidence as feature weight. Voxels
        paged out since are set in the tile store; voxels pruned since are skipped, and with
        ``global_map.learned_features_once`` (default) voxels given a learned feature before.
        Returns the number of voxels set. Raises ``ValueError`` (nothing changed) on a shape or
        dimension mismatch."""
        keys = np.asarray(keys, np.int64).reshape(-1)
        feats = np.asarray(features, np.float32)
        if feats.ndim != 2 or feats.shape[0] != keys.shape[0] or feats.shape[1] < 1:
            raise ValueError(f"features must be (U={keys.shape[0]}, D), got {feats.shape}")
        dims = {"D": int(feats.shape[1])}
        norm = np.sqrt(np.einsum("ud,ud->u", feats, feats))
        good = np.isfinite(norm) & (norm > 1e-8)
        with self._lock:
            if self._dim is not None and dims["D"] != self._dim:
                raise ValueError(f"features have dimension {dims['D']}, the global map's {self._dim}")
            rows, found = self._rows_of(keys)
            away = good & ~found  # paged ones are set in the store, without paging them in
            paged = self._set_paged_features(keys[away], feats[away] / norm[away, None]) if away.any() else 0
            keep = found & good
            if self.config.learned_features_once:
                keep[keep] = self._learned[rows[keep]] == 0
            if not keep.any():
                self._version += paged > 0
                return paged
            self._set_dim(int(dims["D"]))
            assert self._feat is not None
            rows = rows[keep]
            mine = {"feat": self._feat, "feat_norm": self._feat_norm, "feat_weight": self._feat_weight,
                    "weight": self._weight, "learned": self._learned}
            _learn_rows(mine, rows, feats[keep] / norm[keep, None])
            self._feat_stamp[rows] = self._version + 1
            self.points_learned += int(rows.shape[0])
            self._version += 1
            return int(rows.shape[0]) + paged

    def _fuse_features(self, obs: Observations) -> tuple[int, int]:
        """Fuse the features of ``obs`` into the voxels that exist (lock held); the same sums as
        :meth:`_fuse`. Returns (observations fused, voxels touched)."""
        assert obs.cells is not None and obs.bilinear is not None and obs.ov_flat is not None
        keys, ok = voxel_keys(obs.xyz, self.config.voxel_size_m)
        self._page_in_keys(keys[ok])
        _, _, found = _lookup(self._sorted_keys, self._sorted_rows, keys)
        keep = ok & found
        if not keep.any():
            return 0, 0
        keys, weight = keys[keep], obs.weight[keep]
        cells, bilinear = obs.cells[keep], obs.bilinear[keep]
        ukeys, inverse = np.unique(keys, return_inverse=True)
        inverse = inverse.ravel()
        n_u = ukeys.shape[0]
        sum_w = np.bincount(inverse, weights=weight.astype(np.float64), minlength=n_u)
        sum_wfeat = _feature_sums(weight, cells, bilinear, obs.ov_flat, inverse, n_u)
        rows = self._sorted_rows[np.searchsorted(self._sorted_keys, ukeys)]
        # integrate_features bumps the version after this
        self._fuse_into(rows, sum_wfeat, sum_w, self._version + 1)
        return int(keys.shape[0]), n_u

    def _fuse_into(self, rows: np.ndarray, sum_wfeat: np.ndarray, sum_w: np.ndarray, stamp: int) -> None:
        """Fuse per-row feature sums (U, D) of weight ``sum_w`` (U,) into ``rows`` with
        :attr:`fusion`; their features are new as of version ``stamp`` (lock held)."""
        assert self._feat is not None
        unit, norm, fw = self.fusion(
            self._feat[rows], self._feat_norm[rows], self._feat_weight[rows], sum_wfeat,
            sum_w.astype(np.float32),
        )
        self._feat[rows], self._feat_norm[rows], self._feat_weight[rows] = unit, norm, fw
        self._feat_stamp[rows] = stamp

    def _fuse(self, obs: Observations, stamp_ns: int) -> tuple[int, int, int]:
        """Fuse observations (called with the lock held). Returns (touched, new, pruned)."""
        keys, ok = voxel_keys(obs.xyz, self.config.voxel_size_m)
        p_world, weight, cells, bilinear = obs.xyz, obs.weight, obs.cells, obs.bilinear
        if not ok.all():
            keys, p_world, weight = keys[ok], p_world[ok], weight[ok]
            if cells is not None and bilinear is not None:
                cells, bilinear = cells[ok], bilinear[ok]
        if keys.size == 0:
            return 0, 0, 0
        ukeys, inverse, sum_w, sum_wxyz, count = _geometry_sums(keys, p_world, weight)
        n_u = ukeys.shape[0]
        sum_wfeat = None
        if cells is not None and bilinear is not None and obs.ov_flat is not None:
            sum_wfeat = _feature_sums(weight, cells, bilinear, obs.ov_flat, inverse, n_u)

        # look the voxels up; append the new ones and insert them into the sorted index
        pos, rows, found = _lookup(self._sorted_keys, self._sorted_rows, ukeys)
        n_new = int(np.count_nonzero(~found))
        if n_new:
            start = self._n
            self._grow(start + n_new)
            new_rows = np.arange(start, start + n_new, dtype=np.int64)
            rows[~found] = new_rows
            self._keys[new_rows] = ukeys[~found]
            self._n = start + n_new
            self._sorted_keys = np.insert(self._sorted_keys, pos[~found], ukeys[~found])
            self._sorted_rows = np.insert(self._sorted_rows, pos[~found], new_rows)

        old_w = self._weight[rows].astype(np.float64)
        new_w = old_w + sum_w
        self._xyz[rows] = ((self._xyz[rows] * old_w[:, None] + sum_wxyz) / new_w[:, None]).astype(np.float32)
        self._weight[rows] = new_w
        self._hits[rows] += count
        self._last_seen_ns[rows] = stamp_ns
        self._last_seen_kf[rows] = self._kf_counter
        if sum_wfeat is not None:  # integrate bumped the version before this
            self._fuse_into(rows, sum_wfeat, sum_w, self._version)
        pruned = self._apply_bound()
        return n_u, n_new, pruned

    def _carve(self, keyframe: KeyframeLike) -> int:
        """Visibility carving (:func:`mapper.map.carving.carve`; lock held). Returns the voxels removed."""
        self._n, self._sorted_keys, self._sorted_rows, gone = carve(
            self.config, keyframe, self._rows(), self._n, self._sorted_keys, self._sorted_rows, self._version)
        self.points_carved += gone
        return gone

    def _compact(self, keep: np.ndarray) -> None:
        """Keep only rows ``keep`` (ascending), rebuild the sorted index (lock held)."""
        _keep_rows(self._rows(), keep)
        self._n = int(keep.shape[0])
        self._feat_reset = max(self._feat_reset, self._version)  # rows moved (callers bumped first)
        self._sorted_keys, self._sorted_rows = _sorted_index(self._keys[: self._n])

    # -- readers -----------------------------------------------------------------------------

    @property
    def version(self) -> int:
        return self._version

    @property
    def generation(self) -> int:
        """Unique in the process to this map's content lineage: a new map, ``restore`` and ``clear``
        take a new one; integration and pruning keep it."""
        return self._generation

    def geometry(self) -> tuple[np.ndarray, np.ndarray]:  # (N, 3) float32 xyz, (N,) int64 voxel keys
        """The map's points and their voxel keys, read-only copies of the current version: what a
        worker that only projects the map needs, without :meth:`snapshot`'s copy of every feature
        (56 MB per 72k voxels at 384-d), which a map changing between calls would take each time."""
        with self._lock:
            snap = self._snapshot
            if snap is not None and snap.version == self._version and snap.keys is not None:
                return snap.xyz, snap.keys
            n = self._n
            xyz, keys = self._xyz[:n].copy(), self._keys[:n].copy()
        xyz.setflags(write=False)
        keys.setflags(write=False)
        return xyz, keys

    def snapshot(self) -> GlobalMapSnapshot:
        """The immutable snapshot of the current version (copied once per version, then cached):
        the resident voxels (:meth:`query_snapshot` adds paged ones)."""
        with self._lock:
            return self._snapshot_locked()

    def _snapshot_locked(self) -> GlobalMapSnapshot:
        """The snapshot of the current version (lock held)."""
        snap = self._snapshot
        if snap is not None and snap.version == self._version:
            return snap
        n = self._n
        snap = GlobalMapSnapshot(
            version=self._version,
            map_version=self._map_version,
            voxel_size_m=self.config.voxel_size_m,
            xyz=_frozen(self._xyz, n),
            feat=_frozen(self._feat, n) if self._feat is not None else None,
            weight=_frozen(self._weight, n),
            feat_weight=_frozen(self._feat_weight, n),
            hits=_frozen(self._hits, n),
            last_seen_ns=_frozen(self._last_seen_ns, n),
            feat_stamp=_frozen(self._feat_stamp, n),
            feat_reset=self._feat_reset,
            keys=_frozen(self._keys, n),
            generation=self._generation,
            _unit_source=self._unit_source,
        )
        self._snapshot = snap
        return snap
