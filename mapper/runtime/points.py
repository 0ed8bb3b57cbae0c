"""Point answers of the learned model: ``segment_points`` (method ``govnesf``) and the features
the node writes into the global map before a keyframe leaves the window.

Each point is answered with its own source views (:func:`~mapper.runtime.views.view_groups`, up to
``point_source_views``): the source-view-agnostic OV feature at the point (``GovNeSF.query_points``:
the FusionNet's (or the point head's) learned blend of the views' OV maps), and for ``segment`` its
cosine to each text. Three ways compute the same answers (up to float rounding), chosen by config:
one compiled pass over every point (``fused_point_answers``, :data:`FUSED_CHUNK_POINTS` a call), one
network pass over every view group (``batched_view_groups``), or one pass per view group (the
reference). With ``use_depth`` a view is masked for a point its depth (input depth, the sparse prior,
or the request's own points splatted, ``point_occlusion``) says is hidden: Depth Guided Masking.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.errors import RuntimeNotReady
from mapper.model.field import GovNeSF, OVMaps, PointOutputs, PointViewSamples
from mapper.model.ops.cost_volume import sample_volume
from mapper.runtime.loading import LoadedModel
from mapper.runtime.prepared import Prepared
from mapper.runtime.text import text_embeddings
from mapper.runtime.views import all_views, chunk_slots, group_slots, source_views, view_groups
from mapper.runtime.volume import WindowVolume

FUSED_CHUNK_POINTS = 65536
"""Points per call of the one-pass point answers (``model.fused_point_answers``): its samples stay in
per-block buffers whatever the call's size; this bounds the copies of the points' view indices
(16 views a point: 8 MB a call), not the kernel's work. A multiple of the kernel's blocks, so the
answers do not depend on it."""


class PointAnswers:
    """Answers at world points over the window's views (``loaded``'s model, ``volume``'s views).

    Every query takes ``volume.lock`` (the runtime's lock) for its whole computation.
    """

    def __init__(self, loaded: LoadedModel, volume: WindowVolume) -> None:
        self.loaded = loaded
        self.volume = volume

    def segment(
        self,
        points: np.ndarray | Tensor,  # (N, 3) float32 world points (m)
        texts: Sequence[str],
        *,
        use_depth: bool,
        keep_cosines: bool,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict[str, float]]:
        """label (N,) int32 (-1 where no keyframe with OV sees the point), score (N,) float32 (0
        there), every text's cosine (N, T) float32 when ``keep_cosines`` (else None), timing_ms.
        Raises ``ValueError`` on a bad request, :class:`RuntimeNotReady` when it cannot be answered."""
        pts = self._segment_points(points, texts)
        cfg = self.loaded.config
        device = self.loaded.device
        model = self.loaded.require_model()
        timing: dict[str, float] = {}
        t0 = time.perf_counter()
        with self.volume.lock:
            prep = self.volume.prepare()
            t1 = time.perf_counter()
            timing["prepare"] = (t1 - t0) * 1e3
            emb = text_embeddings(self.loaded, prep, texts)  # (T, D)
            t2 = time.perf_counter()
            timing["text"] = (t2 - t1) * 1e3
            n = pts.shape[0]
            label = torch.full((n,), -1, dtype=torch.int32, device=device)
            score = torch.zeros(n, dtype=torch.float32, device=device)
            cosines = None  # (N, T) every text's cosine, only when asked for
            if keep_cosines:
                cosines = torch.zeros(n, emb.shape[0], dtype=torch.float32, device=device)
            occluders = self.occluder_depth(prep, pts) if use_depth else None
            t_occ = time.perf_counter()
            if occluders is not None:
                timing["occluders"] = (t_occ - t2) * 1e3
            dgm_depth = occluders if occluders is not None else prep.depth_m
            select_by = dgm_depth if (use_depth and cfg.dgm_view_selection) else None
            groups = view_groups(self.loaded, prep, pts, prep.has_ov, self.loaded.point_source_views,
                                 depth_m=select_by)
            t3 = time.perf_counter()
            timing["view_selection"] = (t3 - t_occ) * 1e3
            for sub, cos, valid in self._group_cosines(model, prep, pts, groups, use_depth, emb, occluders):
                # cos (p, T), valid (p,); each point is in one view group, so in one chunk: its rows
                # are written once
                best, arg = cos.max(dim=-1)
                label[sub] = torch.where(valid, arg.to(torch.int32), -1)
                score[sub] = torch.where(valid, best, 0.0)
                if cosines is not None:
                    cosines[sub] = cos.float() * valid[:, None]
            timing["network"] = (time.perf_counter() - t3) * 1e3
        timing["total"] = (time.perf_counter() - t0) * 1e3
        cos_np = None if cosines is None else cosines.cpu().numpy()
        return label.cpu().numpy(), score.cpu().numpy(), cos_np, timing

    def _segment_points(self, points: np.ndarray | Tensor, texts: Sequence[str]) -> Tensor:
        """A segment request's (N, 3) points as float32 on the runtime's device; ``ValueError``
        unless they are finite, within ``max_segment_points``, and there is at least one text."""
        limit = self.loaded.config.max_segment_points
        pts = points if isinstance(points, Tensor) else torch.tensor(np.array(points, dtype=np.float32))
        if pts.ndim != 2 or pts.shape[-1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {tuple(pts.shape)}")
        if not bool(torch.isfinite(pts).all()):
            raise ValueError("points must be finite (got NaN or Inf)")
        if not texts:
            raise ValueError("texts must hold at least one prompt, got none")
        if pts.shape[0] > limit:
            raise ValueError(
                f"{pts.shape[0]} points exceed model.max_segment_points = {limit}; split the request"
            )
        return pts.to(self.loaded.device, torch.float32)

    def _group_cosines(
        self,
        model: GovNeSF,
        prep: Prepared,
        pts: Tensor,  # (P, 3)
        groups: list[tuple[Tensor, Tensor]],
        use_depth: bool,
        emb: Tensor,  # (T, D) unit text embeddings
        occluders: Tensor | None,  # (M, H, W) the depth DGM tests against (occluder_depth), or None
    ) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
        """Every view group's points: yields (point indices (p,), cosines (p, T), valid (p,)), in one
        compiled pass, one network pass over every group, or one pass per group (the config's
        ``fused_point_answers`` / ``batched_view_groups``)."""
        batched = self.loaded.config.batched_view_groups
        if batched and groups and self._answer_in_one_pass(model, prep, pts):
            yield from self._one_pass_answers(model, prep, pts, groups, use_depth, emb, depth_m=occluders)
        elif batched and groups:
            # one network pass over every view group (each point with its own views)
            for sub, samples, v, ov_maps in self._point_batches(model, prep, pts, groups, use_depth,
                                                                depth_m=occluders):
                cos, valid, _ = model.point_cosines(samples, v, emb, ov_maps=ov_maps,
                                                    fusion=self.loaded.point_head)
                yield sub, cos, valid
        for idx, views_idx in groups if not batched else []:
            for sub, out in self._point_outputs(model, prep, pts, idx, views_idx, use_depth,
                                                depth_m=occluders):
                yield sub, F.normalize(out.ov, dim=-1) @ emb.T, out.valid

    def occluder_depth(self, prep: Prepared, pts: Tensor) -> Tensor | None:  # pts (P, 3)
        """(M, H, W) float32 at the working size: the depth DGM tests the request's points against
        (``point_occlusion``): each view without input depth gets its z-buffer of the request's
        points (:func:`mapper.geometry.splat.request_occluder_depths`), each view with input depth keeps
        it. None (the window's depth and priors) when ``point_occlusion`` is off, every view has
        input depth, or there are no points. Call with the runtime's lock held."""
        if not self.loaded.config.point_occlusion or pts.shape[0] == 0 or prep.input_depth is None:
            return None
        need = (~prep.input_depth).nonzero().squeeze(-1)
        if need.numel() == 0:
            return None
        from mapper.geometry.splat import request_occluder_depths

        width, height = self.loaded.image_wh
        z = request_occluder_depths(pts.detach().cpu().numpy(), prep.K[need].cpu().numpy(),
                                    prep.world_from_cam[need].cpu().numpy(), width, height,
                                    self.loaded.config.point_occlusion_footprint,
                                    threads=torch.get_num_threads())  # (m, H, W)
        out = (prep.depth_m.clone() if prep.depth_m is not None
               else torch.zeros(len(prep), height, width, device=self.loaded.device))
        occ = torch.from_numpy(z).to(out)
        if self.loaded.config.point_occlusion_prior_veto and prep.depth_m is not None:
            # an occluder that the keyframe's own depth prior sees through (the prior's surface is
            # farther by more than the DGM tolerance) is dropped: likely a point off its surface
            prior = prep.depth_m[need]
            ratio = self.loaded.require_model().cfg.render.depth_mask_ratio
            occ = torch.where((prior > 0) & (prior > (1.0 + ratio) * occ), torch.zeros_like(occ), occ)
        out[need] = occ
        return out

    def _answer_in_one_pass(self, model: GovNeSF, prep: Prepared, pts: Tensor) -> bool:
        """``segment`` answers every point in one compiled pass (``model.fused_point_answers`` and
        :meth:`GovNeSF.answer_kernel_applies`) instead of chunk by chunk."""
        if not self.loaded.config.fused_point_answers or prep.ov is None:
            return False
        views = all_views(self.loaded, prep, need_ov=False, use_depth=False)
        return model.answer_kernel_applies(views, pts, prep.ov, self.loaded.point_head)

    def _one_pass_answers(
        self,
        model: GovNeSF,
        prep: Prepared,
        pts: Tensor,  # (P, 3)
        groups: list[tuple[Tensor, Tensor]],
        use_depth: bool,
        emb: Tensor | None,  # (T, D) unit text embeddings; None: the features themselves
        depth_m: Tensor | None = None,
    ) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
        """Every view group's points in calls of :data:`FUSED_CHUNK_POINTS` to
        :meth:`GovNeSF.point_cosines_indexed` (``emb=None``: :meth:`GovNeSF.point_features_indexed`):
        yields (point indices (p,), cosines (p, T) or features (p, D), valid (p,)). ``depth_m``: see
        :func:`~mapper.runtime.views.all_views`. Call with the runtime's lock held."""
        members, view_idx, slots = group_slots(groups)
        views = all_views(self.loaded, prep, need_ov=False, use_depth=use_depth, depth_m=depth_m)
        head = self.loaded.point_head
        for i in range(0, members.numel(), FUSED_CHUNK_POINTS):
            sel = slice(i, i + FUSED_CHUNK_POINTS)
            sub = members[sel]
            chunk_views, chunk_mask = chunk_slots(view_idx, slots, sel)
            v, _ = sample_volume(prep.volume, prep.bounds, pts[sub].to(prep.volume.dtype))
            ov_maps = prep.ov_maps(chunk_views, self.loaded.image_wh)
            args = (views, chunk_views, chunk_mask, pts[sub], use_depth, v)
            if emb is None:
                out, valid, _ = model.point_features_indexed(*args, ov_maps, fusion=head)
            else:
                out, valid, _ = model.point_cosines_indexed(*args, emb, ov_maps, fusion=head)
            yield sub, out, valid

    def _point_batches(
        self,
        model: GovNeSF,
        prep: Prepared,
        pts: Tensor,
        groups: list[tuple[Tensor, Tensor]],
        use_depth: bool,
        depth_m: Tensor | None = None,
    ) -> Iterator[tuple[Tensor, PointViewSamples, Tensor, OVMaps]]:
        """Every view group's points in chunks of ``chunk_points``, each point with its own views:
        yields (point indices (p,), samples (``sample_views_indexed``), volume features (p, Dv),
        the chunk's OV maps). ``depth_m``: see :func:`~mapper.runtime.views.all_views`. Call with the
        runtime's lock held."""
        members, view_idx, slots = group_slots(groups)
        views = all_views(self.loaded, prep, need_ov=False, use_depth=use_depth, depth_m=depth_m)
        for i in range(0, members.numel(), self.loaded.config.chunk_points):
            sel = slice(i, i + self.loaded.config.chunk_points)
            sub = members[sel]
            chunk_views, chunk_mask = chunk_slots(view_idx, slots, sel)
            samples = model.sample_views_indexed(views, chunk_views, chunk_mask, pts[sub], use_depth,
                                                 sample_ov=False)  # blended from the maps (OVMaps)
            v, _ = sample_volume(prep.volume, prep.bounds, pts[sub].to(prep.volume.dtype))
            yield sub, samples, v, prep.ov_maps(chunk_views, self.loaded.image_wh)

    def _world_points(self, points: np.ndarray) -> Tensor:
        """(N, 3) float32 points on the runtime's device; ``ValueError`` unless every one is finite."""
        pts = torch.tensor(np.array(points, dtype=np.float32)).reshape(-1, 3).to(self.loaded.device)
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
        model = self.loaded.require_model()
        with self.volume.lock:
            prep = self.volume.prepare()
            groups = view_groups(self.loaded, prep, pts, prep.has_ov, self.loaded.point_source_views)
            if not groups:
                return []
            return [(sub, s, v) for sub, s, v, _ in self._point_batches(model, prep, pts, groups, use_depth)]

    def _point_outputs(
        self, model: GovNeSF, prep: Prepared, pts: Tensor, idx: Tensor, views_idx: Tensor, use_depth: bool,
        depth_m: Tensor | None = None,
    ) -> Iterator[tuple[Tensor, PointOutputs]]:
        """``model.query_points`` for the points ``pts[idx]`` over the views ``views_idx``, in
        chunks of ``chunk_points``: yields (point indices, outputs). The OV features are blended
        straight from the window's maps (``OVMaps``), never sampled per view (nor copied per
        view group); the same answers as sampling them first, up to float rounding. ``depth_m``:
        see :func:`~mapper.runtime.views.all_views`."""
        views = source_views(self.loaded, prep, views_idx, need_ov=False, use_depth=use_depth,
                             depth_m=depth_m)
        ov_maps = prep.ov_maps(views_idx, self.loaded.image_wh)
        for i in range(0, idx.numel(), self.loaded.config.chunk_points):
            sub = idx[i : i + self.loaded.config.chunk_points]
            yield sub, model.query_points(
                views, prep.volume, prep.bounds, pts[sub], depth_guided_masking=use_depth, ov_maps=ov_maps,
                fusion=self.loaded.point_head,
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
        model = self.loaded.require_model()
        with self.volume.lock:
            prep = self.volume.prepare()
            if prep.ov is None or not bool(prep.has_ov.any()):
                raise RuntimeNotReady("no keyframe in the window carries 'ov'")
            n = pts.shape[0]
            feats = torch.zeros(n, prep.ov.shape[1], dtype=torch.float32, device=self.loaded.device)
            valid = torch.zeros(n, dtype=torch.bool, device=self.loaded.device)
            groups = view_groups(self.loaded, prep, pts, prep.has_ov, self.loaded.point_source_views)
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

