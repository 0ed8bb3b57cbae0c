"""Settings of sparse triangulation, dense plane-sweep stereo and dense optical-flow points from posed
RGB (TOML tables ``[triangulation]``, ``[stereo]`` and ``[dense_flow]``; no torch).

:class:`TriangulationConfig` is one field of :class:`mapper.node.config.NodeConfig`; the pure
geometry (:mod:`mapper.geometry.triangulation`) and the node plugin
(:mod:`mapper.node.workers.triangulation`) read it.
"""

from __future__ import annotations

from dataclasses import dataclass

from mapper.errors import ConfigError

DETECTORS = ("sift", "orb")
POSE_METHODS = ("pnp", "window")


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

    detect_max_side: int = 1280
    """The image detected on is at most this many pixels on its longer side: ``detect_upscale``
    applies while the upscaled image fits, larger images are downscaled (area) to fit (a
    4096 x 4096 RGB-only frame took 80 s of SIFT at 2x; a 640 x 480 camera keeps its 2x).
    64..16384."""

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

    refine_poses: bool = False
    """Refine each RGB-only keyframe's pose (``pose_method``) before its own triangulation and
    stereo; later keyframes use the refined pose too. The window, the ack and the saved map keep the
    pose as sent. Off by default: docs/concepts/rgb-only.md has the measurements."""

    pose_prior_m: float = 0.02
    """Expected odometry error of a keyframe's camera centre, per axis (metres, 1 sigma): the
    prior's weight and, times ``pose_max_sigmas``, the largest accepted move. 1e-4..10."""

    pose_prior_deg: float = 1.0
    """Expected odometry error of a keyframe's orientation, per axis (degrees, 1 sigma). 0.01..45."""

    pose_min_inliers: int = 12
    """Fewest 2D-3D correspondences a refinement must explain (within ``pose_ransac_px``) to be
    kept; fewer leave the pose as sent. 4..100000."""

    pose_ransac_px: float = 4.0
    """Reprojection error (pixels) within which a correspondence is an inlier. 0.1..100."""

    pose_huber_px: float = 1.5
    """Reprojection errors beyond this (pixels) weigh linearly, not quadratically. 0.01..100."""

    pose_min_gain: float = 0.2
    """The inliers' median reprojection error must drop by at least this share. 0..1."""

    pose_max_sigmas: float = 3.0
    """A refinement moving the pose more than this many prior sigmas (of the 3-axis norm) is
    rejected. 0.1..100."""

    pose_method: str = "pnp"
    """How ``refine_poses`` refines: "pnp" (each keyframe against its partners' triangulated points,
    :mod:`mapper.geometry.pose_refine`) or "window" (the last ``pose_window`` RGB-only keyframes
    adjusted jointly from dense matches, :mod:`mapper.geometry.window_adjust`)."""

    pose_window: int = 12
    """"window": keyframes adjusted together (the newest and the ones before it). 2..256."""

    pose_partners: int = 3
    """"window": partners a keyframe is matched with (chosen among the adjusted keyframes by overlap
    and parallax, as triangulation's partners). 1..16."""

    pose_pair_matches: int = 120
    """"window": matches kept per pair, spread over the image (one per grid cell). 8..10000."""

    pose_flow_sigma_px: float = 0.5
    """"window": expected error of a dense match (pixels, 1 sigma per axis). 0.01..100."""

    pose_max_evaluations: int = 20
    """"window": most residual evaluations of one adjustment (SciPy's ``max_nfev``). 5..10000."""

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
        check("detect_max_side", self.detect_max_side, 64, 16384)
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
        check("pose_prior_m", self.pose_prior_m, 1e-4, 10.0)
        check("pose_prior_deg", self.pose_prior_deg, 0.01, 45.0)
        check("pose_min_inliers", self.pose_min_inliers, 4, 100_000)
        check("pose_ransac_px", self.pose_ransac_px, 0.1, 100.0)
        check("pose_huber_px", self.pose_huber_px, 0.01, 100.0)
        check("pose_min_gain", self.pose_min_gain, 0.0, 1.0)
        check("pose_max_sigmas", self.pose_max_sigmas, 0.1, 100.0)
        if self.pose_method not in POSE_METHODS:
            raise ConfigError(f"{where}: triangulation.pose_method = {self.pose_method!r}; allowed: "
                              f"{', '.join(POSE_METHODS)}")
        check("pose_window", self.pose_window, 2, 256)
        check("pose_partners", self.pose_partners, 1, 16)
        check("pose_pair_matches", self.pose_pair_matches, 8, 10_000)
        check("pose_flow_sigma_px", self.pose_flow_sigma_px, 0.01, 100.0)
        check("pose_max_evaluations", self.pose_max_evaluations, 5, 10_000)


@dataclass(frozen=True)
class StereoConfig:
    """Dense depth from posed RGB by plane sweep (:mod:`mapper.geometry.plane_sweep`; TOML table
    ``[stereo]``): for RGB-only keyframes, against the partners triangulation chose."""

    enabled: bool = True
    """Sweep every keyframe that arrives without depth (in the triangulation worker, after its
    points: they set the depth range). False = sparse points only."""

    planes: int = 48
    """Depth hypotheses of the coarse sweep, uniform in inverse depth. 3..512."""

    refine_steps: int = 9
    """Hypotheses per pixel of the refining sweep across one coarse step either side of the coarse
    winner (1 = no refinement). 1..64."""

    patch_px: int = 5
    """Side of the square ZNCC patch (odd). 3..31."""

    top_k: int = 2
    """The score of a hypothesis is the mean ZNCC of its ``top_k`` best sources (occlusion robust);
    a pixel needs at least this many sources that see it. 1..16."""

    max_sources: int = 4
    """Partner keyframes swept against (the best of triangulation's partners). 1..16."""

    min_ncc: float = 0.75
    """Lowest aggregated ZNCC a depth is kept at. -1..1."""

    min_texture: float = 0.02
    """Lowest standard deviation of the reference patch's intensity (0..1 scale): no texture, no
    depth. 0..1."""

    uniqueness_planes: int = 3
    """A depth is dropped when a coarse hypothesis more than this many steps away scores within
    ``uniqueness_margin`` of the best (repetitive texture); 0 = no check. 0..512."""

    uniqueness_margin: float = 0.02
    """See ``uniqueness_planes``. 0..2."""

    min_depth_m: float = 0.2
    """Nearest depth swept (m). 1e-3..1e3."""

    max_depth_m: float = 12.0
    """Farthest depth swept (m). 1e-2..1e4."""

    range_quantile: float = 0.02
    """The range follows the keyframe's triangulated depths: from their ``range_quantile`` to their
    ``1 - range_quantile`` quantile, each widened by ``range_margin``. 0..0.5."""

    range_margin: float = 1.5
    """See ``range_quantile`` (near / margin, far x margin). 1..10."""

    min_range_points: int = 8
    """Fewer triangulated points than this: the range is the room's (recent keyframes' points)
    or ``[min_depth_m, fallback_far_m]``. 1..100000."""

    fallback_far_m: float = 6.0
    """Farthest depth swept while no keyframe has triangulated points (m). 0.1..1e4."""

    max_backlog: int = 16
    """While more keyframes than this wait for the triangulation worker, new ones are triangulated
    without a sweep (counted in ``status`` as ``stereo.skipped_busy``): under a fast stream the
    worker keeps up with the cheaper sparse geometry instead of dropping keyframes. 0 = never
    skip. 0..100000."""

    max_deferred: int = 128
    """A sweep skipped while busy (``max_backlog``) is remembered and done later, oldest first,
    whenever no keyframe waits for the worker (``status``: ``stereo.deferred``, ``deferred_swept``,
    ``deferred_forgotten``); beyond this many remembered (or ``max_deferred_mb``), the oldest is
    forgotten. A stream sent as fast as acks come back had 22-37 of its 40-54 keyframes skipped for
    good before (the scenario matrix's RGB-only streams: docs/concepts/rgb-only.md). 0 = a skipped
    sweep is never done. 0..100000."""

    max_deferred_mb: float = 256.0
    """Most memory the remembered sweeps hold (MB): each keeps its keyframe (colour, OV map) and its
    working image until swept, about 1 MB at 160 x 120 with a 40 x 30 x 384 OV map; the oldest is
    forgotten beyond. 0..1e6."""

    max_width: int = 200
    """Keyframes wider than this are swept at this width (area-downscaled; the depth is scaled
    back up, nearest pixel): the cost grows with the pixels. 16..4096."""

    consistency_rel: float = 0.05
    """Multi-view geometric consistency: a partner *agrees* with a swept depth when its own depth
    (input depth, or its swept depth) at the point's projection is within this relative
    difference. 0..1."""

    min_agreeing: int = 1
    """Partners that must agree (``consistency_rel``) for a swept depth to be kept; 0 = no
    check. 0..16."""

    global_map_weight: float = 0.3
    """Swept depths are fused into the global map at this weight (times the score above
    ``min_ncc``, normalised); 0 = not added. 0..1."""

    depth_prior: bool = True
    """With a learned-model runtime, the swept depth (where it has one, the triangulated prior
    elsewhere), filled along the image (``prior_fill_px``), is the keyframe's depth prior for
    Depth Guided Masking. The global map only ever gets the swept depths themselves."""

    sigma_rel: float = 0.03
    """1-sigma uncertainty of a kept swept depth, relative to the depth (about its measured median
    error: benchmarks/studies/stereo_depth.py); the rendered-depth points' consistency check
    (``global_map.rendered_consistency``) uses the swept depths as it uses triangulated points,
    with this sigma. 1e-4..1."""

    max_points: int = 400_000
    """Swept points kept for that check (the oldest keyframes' go first). 0 = none kept. 0..1e8."""

    prior_geometry: bool = True
    """The holes left in a keyframe's depth prior (after ``prior_fill_px``) take the surface that
    the node's whole RGB-only geometry (every keyframe's triangulated and kept swept points, splat
    as ``render`` splats them: ``mapper.node.queries.surface_depth``) shows at the keyframe's pose.
    The priors of the latest ``window.max_keyframes`` keyframes are filled again when the number of
    geometry points moved by more than ``prior_geometry_refresh`` since they last were. Measured:
    +0.05 to +3.1 mIoU for ``govnesf`` + DGM on four RGB-only rooms (docs/concepts/rgb-only.md)."""

    prior_geometry_refresh: float = 0.1
    """See ``prior_geometry`` (relative change of the geometry's point count). 0..10."""

    prior_fill_px: int = 8
    """Holes of the prior are filled from the depths within this radius (pixels at the working
    size) of similar intensity (``plane_sweep.fill_depth``); 0 = no filling. 0..64."""

    prior_fill_sigma: float = 0.05
    """Intensity difference (0..1 scale) at which a neighbour's weight falls to exp(-1/2). 1e-3..1."""

    prior_fill_spread: float = 0.1
    """A hole stays empty where the neighbours' inverse depths spread more than this (relative
    standard deviation: a depth edge). 0..1."""

    def validate(self, where: str) -> None:
        """Raise :class:`ConfigError` naming ``where``, the key, the value and the allowed range."""

        def check(key: str, value: float, lo: float, hi: float) -> None:
            if not lo <= value <= hi:
                raise ConfigError(f"{where}: stereo.{key} = {value!r} out of range {lo}..{hi}")

        check("planes", self.planes, 3, 512)
        check("refine_steps", self.refine_steps, 1, 64)
        check("patch_px", self.patch_px, 3, 31)
        if self.patch_px % 2 == 0:
            raise ConfigError(f"{where}: stereo.patch_px = {self.patch_px} must be odd")
        check("top_k", self.top_k, 1, 16)
        check("max_sources", self.max_sources, 1, 16)
        if self.top_k > self.max_sources:
            raise ConfigError(f"{where}: stereo.top_k = {self.top_k} exceeds stereo.max_sources = "
                              f"{self.max_sources}")
        check("min_ncc", self.min_ncc, -1.0, 1.0)
        check("min_texture", self.min_texture, 0.0, 1.0)
        check("uniqueness_planes", self.uniqueness_planes, 0, 512)
        check("uniqueness_margin", self.uniqueness_margin, 0.0, 2.0)
        check("min_depth_m", self.min_depth_m, 1e-3, 1e3)
        check("max_depth_m", self.max_depth_m, 1e-2, 1e4)
        if self.max_depth_m <= self.min_depth_m:
            raise ConfigError(f"{where}: stereo.max_depth_m = {self.max_depth_m} must exceed "
                              f"stereo.min_depth_m = {self.min_depth_m}")
        check("range_quantile", self.range_quantile, 0.0, 0.5)
        check("range_margin", self.range_margin, 1.0, 10.0)
        check("min_range_points", self.min_range_points, 1, 100_000)
        check("fallback_far_m", self.fallback_far_m, 0.1, 1e4)
        check("max_width", self.max_width, 16, 4096)
        check("consistency_rel", self.consistency_rel, 0.0, 1.0)
        check("min_agreeing", self.min_agreeing, 0, 16)
        check("global_map_weight", self.global_map_weight, 0.0, 1.0)
        check("prior_fill_px", self.prior_fill_px, 0, 64)
        check("prior_geometry_refresh", self.prior_geometry_refresh, 0.0, 10.0)
        check("prior_fill_sigma", self.prior_fill_sigma, 1e-3, 1.0)
        check("prior_fill_spread", self.prior_fill_spread, 0.0, 1.0)
        check("sigma_rel", self.sigma_rel, 1e-4, 1.0)
        check("max_points", self.max_points, 0, 100_000_000)
        check("max_backlog", self.max_backlog, 0, 100_000)
        check("max_deferred", self.max_deferred, 0, 100_000)
        check("max_deferred_mb", self.max_deferred_mb, 0.0, 1e6)


FLOW_PRESETS = ("ultrafast", "fast", "medium")


@dataclass(frozen=True)
class DenseFlowConfig:
    """Dense points from posed RGB by optical flow (:mod:`mapper.geometry.dense_flow`; TOML table
    ``[dense_flow]``): each RGB-only keyframe's pixels matched into one or two partner keyframes
    with OpenCV's DIS flow, checked forward-backward, triangulated with the known poses.

    The reprojection, parallax and depth-uncertainty tests follow from the expected errors
    (``flow_sigma_px``, ``pose_sigma_m``, ``pose_sigma_deg``), not from fixed pixel thresholds."""

    enabled: bool = False
    """Run the worker on every keyframe without depth (``mapper-dense-flow``; the ack never waits
    for it). Off by default: docs/concepts/rgb-only.md has the measurement."""

    preset: str = "medium"
    """DIS flow preset: "ultrafast", "fast" or "medium" (OpenCV's; finer and slower in that order)."""

    max_partners: int = 2
    """Earlier keyframes each keyframe is matched against (best by overlap and baseline). 1..8."""

    candidate_keyframes: int = 32
    """The recent keyframes (their small grayscale images) partners are chosen from. 1..10000."""

    min_overlap: float = 0.5
    """A partner must see at least this share of the keyframe's probe grid (dense flow needs the
    same surfaces in both images). 0..1."""

    min_baseline_m: float = 0.05
    """A partner's camera centre must be at least this far away (metres). > 0."""

    target_parallax_deg: float = 8.0
    """Partners are ranked by overlap times min(1, parallax at 2.35 m / this angle). 0.1..90."""

    max_width: int = 320
    """Wider keyframes are matched downscaled to this width (flow cost grows with the pixels). 16..4096."""

    stride_px: int = 2
    """Every this many pixels (at the working size, both directions) is triangulated. 1..16."""

    flow_sigma_px: float = 0.5
    """Expected flow error (pixels, 1 sigma). 0.01..100."""

    fb_sigmas: float = 3.0
    """Forward-backward check: the round trip must come back within this many times
    sqrt(2) ``flow_sigma_px``. 0.1..100."""

    min_texture: float = 0.01
    """Pixels whose 5 x 5 patch's intensity standard deviation (0..1 scale) is below this are not
    matched (flow there is interpolated, not measured). 0..1."""

    pose_sigma_m: float = 0.005
    """Expected error of a keyframe's camera centre per axis (metres, 1 sigma); two keyframes'
    relative pose carries sqrt(2) times it. 0..10."""

    pose_sigma_deg: float = 0.2
    """Expected error of a keyframe's orientation per axis (degrees, 1 sigma). 0..45."""

    reprojection_sigmas: float = 3.0
    """A point must reproject within this many expected ray errors (``f * sigma_ray``) in both
    views. 0.1..100."""

    max_sigma_rel: float = 0.08
    """A point's 1-sigma depth uncertainty (``range * sigma_ray / sin(parallax)``) must be at most this
    share of its depth: with the expected errors above this sets the parallax a point needs. 1e-4..1."""

    min_parallax_deg: float = 1.0
    """Rays must meet at least at this angle, whatever the expected errors. 0.01..90."""

    min_depth_m: float = 0.1
    """Cheirality: at least this far in front of both cameras (metres). > 0."""

    max_depth_m: float = 12.0
    """Points farther from the keyframe (z-depth, metres) are dropped. > min_depth_m."""

    agree_sigmas: float = 3.0
    """With two partners, their estimates of a pixel must agree within this many combined sigmas
    (else the pixel is dropped); agreeing ones are fused by inverse variance. 0.1..100."""

    min_views: int = 2
    """Views a point must be triangulated in, the keyframe included (3 = both partners agree). 2..9."""

    global_map_weight: float = 0.3
    """Points join the global map with the keyframe's OV features at this weight times a certainty
    (1 - sigma / (max_sigma_rel * depth), at least 0.1); 0 = not added. 0..1."""

    max_points: int = 400_000
    """Points kept (for the rendered-depth check and renders); the oldest keyframes' go first. 0..10^8."""

    max_pending: int = 64
    """Keyframes waiting for the worker; beyond it the oldest is dropped (``dropped``). 1..100000."""

    def validate(self, where: str) -> None:
        """Raise :class:`ConfigError` naming ``where``, the key, the value and the allowed range."""

        def check(key: str, value: float, lo: float, hi: float) -> None:
            if not lo <= value <= hi:
                raise ConfigError(f"{where}: dense_flow.{key} = {value!r} out of range {lo}..{hi}")

        if self.preset not in FLOW_PRESETS:
            raise ConfigError(f"{where}: dense_flow.preset = {self.preset!r} is not one of {FLOW_PRESETS}")
        check("max_partners", self.max_partners, 1, 8)
        check("candidate_keyframes", self.candidate_keyframes, 1, 10_000)
        check("min_overlap", self.min_overlap, 0.0, 1.0)
        check("min_baseline_m", self.min_baseline_m, 1e-6, 1e3)
        check("target_parallax_deg", self.target_parallax_deg, 0.1, 90.0)
        check("max_width", self.max_width, 16, 4096)
        check("stride_px", self.stride_px, 1, 16)
        check("flow_sigma_px", self.flow_sigma_px, 0.01, 100.0)
        check("fb_sigmas", self.fb_sigmas, 0.1, 100.0)
        check("min_texture", self.min_texture, 0.0, 1.0)
        check("pose_sigma_m", self.pose_sigma_m, 0.0, 10.0)
        check("pose_sigma_deg", self.pose_sigma_deg, 0.0, 45.0)
        check("reprojection_sigmas", self.reprojection_sigmas, 0.1, 100.0)
        check("max_sigma_rel", self.max_sigma_rel, 1e-4, 1.0)
        check("min_parallax_deg", self.min_parallax_deg, 0.01, 90.0)
        check("min_depth_m", self.min_depth_m, 1e-3, 1e3)
        check("max_depth_m", self.max_depth_m, 1e-2, 1e4)
        if self.max_depth_m <= self.min_depth_m:
            raise ConfigError(f"{where}: dense_flow.max_depth_m = {self.max_depth_m} must exceed "
                              f"dense_flow.min_depth_m = {self.min_depth_m}")
        check("agree_sigmas", self.agree_sigmas, 0.1, 100.0)
        check("min_views", self.min_views, 2, 9)
        if self.min_views > self.max_partners + 1:
            raise ConfigError(f"{where}: dense_flow.min_views = {self.min_views} needs max_partners >= "
                              f"{self.min_views - 1}, got {self.max_partners}")
        check("global_map_weight", self.global_map_weight, 0.0, 1.0)
        check("max_points", self.max_points, 0, 100_000_000)
        check("max_pending", self.max_pending, 1, 100_000)
