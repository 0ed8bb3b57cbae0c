"""The learned GOV-NeSF model inside the node: incremental cost volume, point segmentation, renders.

:class:`ModelRuntime` turns the node's keyframe window into the inputs of the trained network and
answers ``segment_points`` (method ``govnesf``) and ``render`` requests with it. It composes the
parts of :mod:`mapper.runtime`, each of which does one thing:

* :mod:`~mapper.runtime.loading`: the checkpoint (and point head) loaded once, and the settings
  every part reads (:class:`~mapper.runtime.loading.LoadedModel`);
* :mod:`~mapper.runtime.volume`: the window's views and their incremental cost volume: recording the
  window's changes (O(1), under the node's lock), applying them at the next query, bounds that
  follow what the window observed, the per-version cache (:class:`~mapper.runtime.volume.WindowVolume`;
  :mod:`~mapper.runtime.entries` encodes the keyframes, :mod:`~mapper.runtime.prepared` stacks them
  and builds render volumes);
* :mod:`~mapper.runtime.views`: which source views answer a point or a marched sample;
* :mod:`~mapper.runtime.points`: point answers: ``segment`` (the OV feature at each point, blended by
  the network from its views, cosine to the text embeddings) and the features written into the
  global map (:class:`~mapper.runtime.points.PointAnswers`);
* :mod:`~mapper.runtime.rendering`: renders of novel views with empty-space skipping
  (:class:`~mapper.runtime.rendering.Renderer`, :mod:`~mapper.runtime.density`; see
  ``docs/concepts/rendering.md``).

Frames without ``ov`` still count for geometry (cost volume, rgb and depth renders); semantic
outputs use the views that carry ``ov`` and answer :class:`RuntimeNotReady` when none does.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from mapper.errors import RuntimeNotReady
from mapper.model.field import GovNeSF, PointViewSamples
from mapper.model.fusion import FusionNet
from mapper.model.ops.cost_volume import CostVolume, VolumeBounds
from mapper.ov.encoders import TextEncoder, get_text_encoder
from mapper.runtime.config import ModelRuntimeConfig
from mapper.runtime.density import occupancy_grid
from mapper.runtime.loading import LoadedModel
from mapper.runtime.points import PointAnswers
from mapper.runtime.rendering import Renderer, RenderFrame
from mapper.runtime.volume import WindowVolume
from protocol.messages import RENDER_OUTPUTS  # what render can produce: the wire's names

__all__ = [
    "RENDER_OUTPUTS",
    "ModelRuntime",
    "ModelRuntimeConfig",
    "RenderFrame",
    "RuntimeNotReady",
]


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
        self._loaded = LoadedModel(config or ModelRuntimeConfig(), model=model, text_encoder=text_encoder)
        self._volume = WindowVolume(self._loaded)
        self._points = PointAnswers(self._loaded, self._volume)
        self._renderer = Renderer(self._loaded, self._volume)
        self._attached: list[Any] = []

    # -- the loaded model and its settings ------------------------------------------------------

    @property
    def config(self) -> ModelRuntimeConfig:
        """Runtime settings (assign a new config to change them for every later query)."""
        return self._loaded.config

    @config.setter
    def config(self, config: ModelRuntimeConfig) -> None:
        self._loaded.config = config

    @property
    def device(self) -> torch.device:
        return self._loaded.device

    @property
    def model(self) -> GovNeSF | None:
        """The network (None when the checkpoint could not be loaded: :attr:`load_error`)."""
        return self._loaded.model

    @property
    def point_head(self) -> FusionNet | None:
        """The network weighing point answers' views in place of the model's FusionNet (None: the
        model's own); ``model.point_head`` (:mod:`mapper.model.point_head`)."""
        return self._loaded.point_head

    @point_head.setter
    def point_head(self, head: FusionNet | None) -> None:
        self._loaded.point_head = head

    @property
    def load_error(self) -> str | None:
        """Why no model is served (None when one is)."""
        return self._loaded.load_error

    @property
    def metadata(self) -> dict[str, Any]:
        """The loaded checkpoint's metadata (empty for a model given in-process)."""
        return self._loaded.metadata

    @property
    def ready(self) -> bool:
        """True when a model is loaded (queries may still need keyframes)."""
        return self._loaded.ready

    @property
    def image_wh(self) -> tuple[int, int]:
        """(W, H) working size of the keyframes."""
        return self._loaded.image_wh

    @property
    def source_views(self) -> int:
        """Source views per render sample (``source_views``, default the model's)."""
        return self._loaded.source_views

    @property
    def point_source_views(self) -> int:
        """Source views per point for point answers (``segment``, ``point_features``)."""
        return self._loaded.point_source_views

    @property
    def samples_per_ray(self) -> int:
        """Samples per marched ray (``samples_per_ray``, default the model's)."""
        return self._loaded.samples_per_ray

    # -- the window (the views and their cost volume) ------------------------------------------

    def attach(self, window: Any) -> None:
        """Follow a :class:`mapper.map.window.KeyframeWindow`: register the callbacks and record every
        keyframe already in it. Call with the node's state lock held (the window is not thread-safe)."""
        window.on_add.append(self.on_add)
        window.on_evict.append(self.on_evict)
        self._attached.append(window)
        for keyframe in window.keyframes:
            self.on_add(keyframe)

    def sibling(self) -> ModelRuntime:
        """A runtime over the same loaded model (network, point head and config shared: a changed
        ``config`` reaches both) with views and a cost volume of its own, for another window (one
        per robot, :mod:`mapper.node.backends.robot_runtimes`). Not attached to any window yet."""
        twin = ModelRuntime.__new__(ModelRuntime)
        twin._loaded = self._loaded
        twin._volume = WindowVolume(self._loaded)
        twin._points = PointAnswers(self._loaded, twin._volume)
        twin._renderer = Renderer(self._loaded, twin._volume)
        twin._attached = []
        return twin

    def on_add(self, keyframe: Any) -> None:
        """Record that ``keyframe`` entered the window (applied by the next :meth:`sync`); O(1), no
        model work (it runs under the node's state lock)."""
        self._volume.on_add(keyframe)

    def on_evict(self, keyframe: Any) -> None:
        """Record that ``keyframe`` left the window."""
        self._volume.on_evict(keyframe)

    @property
    def pending(self) -> int:
        """Window changes recorded but not applied yet."""
        return self._volume.pending

    def sync(self) -> int:
        """Apply the recorded window changes to the views and the cost volume (incrementally).

        Returns the number of changes applied. Raises :class:`RuntimeNotReady` without a model.
        """
        return self._volume.sync()

    def set_view_extent(self, key: tuple[str, int, int], points_m: np.ndarray | None) -> None:
        """Give the keyframe ``key = (camera, seq, stamp_ns)`` the world points it observed,
        ``points_m`` (N, 3) metres (None: back to its frustum up to ``max_range_m``); see
        :meth:`mapper.runtime.volume.WindowVolume.set_view_extent`."""
        self._volume.set_view_extent(key, points_m)

    def set_view_depth_prior(self, key: tuple[str, int, int], depth_m: np.ndarray | None) -> None:
        """Give the keyframe ``key = (camera, seq, stamp_ns)`` a sparse z-depth prior ``depth_m``
        (H, W) metres, 0 = none (None: remove it); see
        :meth:`mapper.runtime.volume.WindowVolume.set_view_depth_prior`."""
        self._volume.set_view_depth_prior(key, depth_m)

    @property
    def version(self) -> int:
        """+1 whenever an applied change altered the views or the volume."""
        return self._volume.version

    @property
    def rebuilds(self) -> int:
        """How often the volume was rebuilt on new bounds (the one non-incremental step)."""
        return self._volume.rebuilds

    @property
    def bounds_outliers(self) -> int:
        """Keyframes left out of the volume's bounds (``bounds_outlier_m``), each counted once."""
        return self._volume.bounds_outliers

    @property
    def views_added(self) -> int:
        return self._volume.views_added

    @property
    def views_removed(self) -> int:
        return self._volume.views_removed

    @property
    def bounds(self) -> VolumeBounds | None:
        """Current cost-volume bounds (None before the first keyframe)."""
        return self._volume.bounds

    @property
    def cost_volume(self) -> CostVolume | None:
        """The incremental cost volume (read it under no concurrent :meth:`sync`)."""
        return self._volume.cost_volume

    def __len__(self) -> int:
        return len(self._volume)

    def memory_bytes(self) -> int:
        """Bytes held: per-view caches, cost-volume sums, and the cached query tensors."""
        return self._volume.memory_bytes()

    def stats(self) -> dict[str, Any]:
        """Counters for the node's status reply."""
        b = self.bounds
        return {
            "ready": self.ready,
            "load_error": self.load_error,
            "views": len(self._volume),
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
    def occupancy(self) -> tuple[VolumeBounds, Tensor]:
        """The occupancy grid (cached per version): (X, Y, Z) bool, True where the density at the
        voxel's 2x2x2 sub-samples or at a neighbour's reaches ``occupancy_threshold``."""
        with self._volume.lock:
            prep = self._volume.prepare()
            return prep.bounds, occupancy_grid(self._loaded, prep)

    # -- point answers --------------------------------------------------------------------------

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
        label, score, _, timing = self._points.segment(points, texts, use_depth=use_depth, keep_cosines=False)
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
        label, score, cos, timing = self._points.segment(points, texts, use_depth=use_depth,
                                                         keep_cosines=True)
        assert cos is not None
        return label, score, cos, timing

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
        return self._points.point_samples(points, use_depth=use_depth)

    @torch.no_grad()
    def point_features(
        self,
        points: np.ndarray,  # (N, 3) float32 world points (m)
        *,
        use_depth: bool = False,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(features (N, D), valid (N,)): the learned blended OV feature at world points
        (:meth:`mapper.runtime.points.PointAnswers.point_features`)."""
        return self._points.point_features(points, use_depth=use_depth)

    # -- renders --------------------------------------------------------------------------------

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
        return self._renderer.render(
            K, world_from_cam, width, height, outputs, texts, empty_space_skipping=empty_space_skipping,
            surface_depth_m=surface_depth_m, volume_views=volume_views,
        )  # fmt: skip
