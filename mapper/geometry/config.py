"""Settings of sparse triangulation from posed RGB (TOML table ``[triangulation]``; no torch).

:class:`TriangulationConfig` is one field of :class:`mapper.node.config.NodeConfig`; the pure
geometry (:mod:`mapper.geometry.triangulation`) and the node plugin
(:mod:`mapper.node.plugins.triangulation`) read it.
"""

from __future__ import annotations

from dataclasses import dataclass

from mapper.errors import ConfigError

DETECTORS = ("sift", "orb")


@dataclass(frozen=True)
class TriangulationConfig:
    """Feature matching and triangulation against overlapping keyframes with known poses."""

    enabled: bool = True
    """Triangulate every keyframe that arrives without depth (a background worker; the ack never
    waits for it). False = no sparse geometry."""

    detector: str = "sift"
    """Feature detector: "sift" (float descriptors, sub-pixel keypoints) or "orb" (binary)."""

    max_features: int = 1500
    """Most keypoints detected per keyframe. 16..100000."""

    sift_contrast_threshold: float = 0.01
    """SIFT's contrast threshold (OpenCV's default is 0.04); lower finds more, weaker keypoints on
    low-contrast surfaces. 0.001..1."""

    detect_upscale: int = 2
    """Detect on the image upscaled by this integer factor (more and finer keypoints on small
    images); keypoints are mapped back to the image as sent. 1..4."""

    ratio: float = 0.8
    """Lowe's ratio test: a match is kept when its descriptor distance is below ``ratio`` times the
    second best (and the match is mutual). 0.1..1."""

    max_partners: int = 6
    """Most earlier keyframes a new keyframe is matched against. 1..64."""

    candidate_keyframes: int = 64
    """The recent keyframes (features kept in memory) partners are chosen from. 1..100000."""

    min_baseline_m: float = 0.08
    """A partner's camera centre must be at least this far from the new one's (metres): shorter
    baselines (e.g. a pure rotation) give no usable parallax. > 0."""

    target_parallax_deg: float = 12.0
    """Partners are ranked by frustum overlap times min(1, parallax at the mid probe depth / this
    angle): wider baselines are preferred up to it. 0.1..90."""

    min_overlap: float = 0.25
    """Fraction of the new view's probe points (a pixel grid at the probe depths) a partner must
    see. 0..1."""

    probe_near_m: float = 0.7
    """Nearest probe depth along the new view's rays for the overlap test (metres). > 0."""

    probe_far_m: float = 4.0
    """Farthest probe depth (metres); three depths from near to far, evenly spaced. > probe_near_m."""

    max_epipolar_px: float = 1.5
    """A match is kept when both points lie within this distance (pixels) of the epipolar lines the
    known poses predict. 0.01..100."""

    max_reprojection_px: float = 1.5
    """A triangulated point is kept when it reprojects within this distance (pixels) in both views.
    0.01..100."""

    min_parallax_deg: float = 2.0
    """A point is kept when the rays from the two camera centres meet at least at this angle
    (near-parallel rays give unbounded depth error). 0.01..90."""

    min_depth_m: float = 0.1
    """Cheirality: a point must lie at least this far in front of both cameras (z-depth, metres). > 0."""

    max_depth_m: float = 20.0
    """Points farther than this from the new camera (z-depth, metres) are dropped. > min_depth_m."""

    pixel_sigma_px: float = 0.5
    """Assumed keypoint noise (pixels, 1 sigma) for the uncertainty; the reprojection error is used
    when larger. 0.01..100."""

    max_sigma_m: float = 0.08
    """Points whose 1-sigma position uncertainty exceeds this (metres) are dropped. > 0."""

    agree_sigmas: float = 3.0
    """Estimates of one keypoint from several partners are fused (inverse-variance mean) when they
    lie within this many combined sigmas of the most certain one. 0.1..100."""

    min_views: int = 3
    """Views a point must be consistent in, the keyframe included: a partner counts when its match
    triangulates to the point or when the point's patch looks the same there (``min_ncc``). 2 = one
    pair suffices; 3 = one more view must confirm (multi-view consistency). 2..64."""

    ncc_patch_px: int = 7
    """Side of the square patch (pixels, odd) compared across views for the photometric check. 3..31."""

    min_ncc: float = 0.8
    """A partner confirms a point when the patch around it (a fronto-parallel plane at the point's
    depth) has at least this normalised cross-correlation there. 1 = no photometric check. -1..1."""

    max_points: int = 200_000
    """Point budget of the sparse map: beyond it the oldest keyframes' points are dropped. 1..10^8."""

    max_pending: int = 64
    """Keyframes waiting for triangulation; beyond it the oldest is dropped (``dropped`` in status).
    1..100000."""

    global_map_weight: float = 0.5
    """Triangulated points are fused into the global semantic map with their keyframe's OV features
    at this weight (times a confidence that falls with the uncertainty); 0 = not added. 0..1."""

    bounds: bool = True
    """Feed the learned model's volume bounds: an RGB-only keyframe's extent becomes its
    triangulated points (and its camera centre) instead of its frustum up to the fixed
    ``model.max_range_m``, as a keyframe with depth contributes its back-projected depth."""

    bounds_min_points: int = 12
    """A keyframe with fewer triangulated points than this (a textureless view, the first keyframes)
    gets its frustum up to the room's depth instead: the median over recent keyframes of their
    points' ``bounds_depth_quantile`` z-depth (until any is known, ``model.max_range_m``). 1..100000."""

    bounds_depth_quantile: float = 0.9
    """See ``bounds_min_points``. 0.5..1."""

    depth_prior_radius_px: int = 2
    """With a learned-model runtime, each RGB-only keyframe gets a sparse depth prior for Depth
    Guided Masking: its points' z-depths splatted over discs of this radius (pixels; the farther
    depth where discs overlap); pixels without a point stay 0 (no masking there). 0 = no prior.
    0..16."""

    def validate(self, where: str) -> None:
        """Raise :class:`ConfigError` naming ``where``, the key, the value and the allowed range."""

        def check(key: str, value: float, lo: float, hi: float) -> None:
            if not lo <= value <= hi:
                raise ConfigError(f"{where}: triangulation.{key} = {value!r} out of range {lo}..{hi}")

        def exceeds(hi_key: str, lo_key: str) -> None:
            hi, lo = getattr(self, hi_key), getattr(self, lo_key)
            if hi <= lo:
                raise ConfigError(f"{where}: triangulation.{hi_key} = {hi} must exceed "
                                  f"triangulation.{lo_key} = {lo}")

        if self.detector not in DETECTORS:
            raise ConfigError(
                f"{where}: triangulation.detector = {self.detector!r}; allowed: {', '.join(DETECTORS)}"
            )
        check("max_features", self.max_features, 16, 100_000)
        check("detect_upscale", self.detect_upscale, 1, 4)
        check("sift_contrast_threshold", self.sift_contrast_threshold, 0.001, 1.0)
        check("ratio", self.ratio, 0.1, 1.0)
        check("max_partners", self.max_partners, 1, 64)
        check("candidate_keyframes", self.candidate_keyframes, 1, 100_000)
        check("min_baseline_m", self.min_baseline_m, 1e-4, 1e3)
        check("target_parallax_deg", self.target_parallax_deg, 0.1, 90.0)
        check("min_overlap", self.min_overlap, 0.0, 1.0)
        check("probe_near_m", self.probe_near_m, 1e-3, 1e3)
        check("probe_far_m", self.probe_far_m, 1e-3, 1e3)
        exceeds("probe_far_m", "probe_near_m")
        check("max_epipolar_px", self.max_epipolar_px, 0.01, 100.0)
        check("max_reprojection_px", self.max_reprojection_px, 0.01, 100.0)
        check("min_parallax_deg", self.min_parallax_deg, 0.01, 90.0)
        check("min_depth_m", self.min_depth_m, 1e-4, 1e3)
        check("max_depth_m", self.max_depth_m, 1e-3, 1e4)
        exceeds("max_depth_m", "min_depth_m")
        check("pixel_sigma_px", self.pixel_sigma_px, 0.01, 100.0)
        check("max_sigma_m", self.max_sigma_m, 1e-4, 1e3)
        check("agree_sigmas", self.agree_sigmas, 0.1, 100.0)
        check("min_views", self.min_views, 2, 64)
        check("ncc_patch_px", self.ncc_patch_px, 3, 31)
        if self.ncc_patch_px % 2 == 0:
            raise ConfigError(f"{where}: triangulation.ncc_patch_px = {self.ncc_patch_px} must be odd")
        check("min_ncc", self.min_ncc, -1.0, 1.0)
        check("max_points", self.max_points, 1, 100_000_000)
        check("max_pending", self.max_pending, 1, 100_000)
        check("global_map_weight", self.global_map_weight, 0.0, 1.0)
        check("bounds_min_points", self.bounds_min_points, 1, 100_000)
        check("bounds_depth_quantile", self.bounds_depth_quantile, 0.5, 1.0)
        check("depth_prior_radius_px", self.depth_prior_radius_px, 0, 16)
