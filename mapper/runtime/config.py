"""Settings of the learned model inside the node (TOML table ``[model]``). Imports no torch."""

from __future__ import annotations

from dataclasses import dataclass

from mapper.errors import ConfigError

__all__ = ["ModelRuntimeConfig"]


@dataclass(frozen=True)
class ModelRuntimeConfig:
    """Settings of the learned-model runtime (TOML table ``[model]`` once the node has it).

    Fields set to 0 take the value the checkpoint's model was trained with.
    """

    checkpoint: str = "checkpoints/cpu-small.safetensors"
    """Checkpoint to load (``NAME``, ``NAME.json`` or ``NAME.safetensors``). A relative path is
    looked up in the working directory, then under ``govnesf.resources.data_root()`` (the repository
    root in a checkout, the packaged data of an installed wheel). Missing -> the node answers
    ``not_ready`` naming this path for ``segment_points`` (govnesf) and ``render``."""

    point_head: str = "auto"
    """A point head (``mapper.model.point_head``: a smaller FusionNet distilled from this
    checkpoint's, ``govnesf distill-point-head``) that weighs the views of point answers
    (``segment_points`` with the learned model, the model's features written into the global map)
    in place of the checkpoint's FusionNet; renders keep the checkpoint's. ``"auto"``: the head
    ``NAME-point-head`` next to the checkpoint ``NAME`` when there is one distilled from these
    weights (cpu-small ships one: labels 99.2-99.8% equal to its own network's, docs/how-to/train.md),
    else the checkpoint's own network. ``""``: always the checkpoint's own. A path (looked up as
    ``checkpoint`` is): that head; one distilled from other weights, or one that cannot be read,
    leaves the model unserved with the reason (as a bad checkpoint does)."""

    device: str = "auto"
    """Torch device: ``"auto"`` (CUDA when available, else CPU), ``"cpu"``, ``"cuda"``, ``"cuda:1"``."""

    image_width: int = 0
    """Working width (pixels) every keyframe is resized to before encoding (K scaled with it);
    0 = the model's training width. 0..4096."""

    image_height: int = 0
    """Working height (pixels); 0 = the model's training height. 0..4096."""

    voxel_size_m: float = 0.0
    """Finest voxel edge of the cost volume (metres); the volume uses the smallest size on the ladder
    ``voxel_size_m * 2^(k/4)`` that fits ``max_voxels`` over the observed extent. 0 = the model's
    ``min_voxel_size_m``. 0..10."""

    max_voxels: int = 0
    """Voxel budget of the cost volume; 0 = the model's (cpu-small: 32 x 32 x 16). 0..10^7."""

    bounds_margin_m: float = 0.3
    """Margin added around the observed extent when the bounds are chosen (metres). 0..10."""

    bounds_outlier_m: float = 50.0
    """A keyframe whose observed extent (its median point) lies farther than this from the median
    of the window's keyframes is left out of the volume's bounds (logged): one frame with a wild
    pose (a translation of 1e6 m is a valid pose) would otherwise stretch the volume over it and
    its voxels to kilometres. The keyframe stays in the window. 1..1e6 (metres)."""

    max_range_m: float = 4.0
    """Frames without depth contribute their camera frustum up to this range to the observed
    extent; depth beyond it is ignored for the extent (metres). 0.1..100."""

    rebuild_outside_fraction: float = 0.05
    """A new keyframe whose extent points fall outside the current bounds by more than this fraction
    triggers a recentre/grow + rebuild of the volume. 0..1."""

    source_views: int = 0
    """Source views per point (top-k); 0 = the model's ``num_source_views``. 0..256."""

    point_source_views: int = 16
    """Source views per point for point answers (``segment_points``, the model's features written
    into the global map), never fewer than ``source_views``; 0 = ``source_views``. Renders keep
    ``source_views`` (more views cost per pixel). 16: the cpu-small model (trained with 8) blends
    more views better, as averaging does (docs/how-to/evaluate.md). 0..256."""

    view_selection: str = "nearest"
    """How the top-k views of a cell are ranked after visibility: ``"nearest"`` (camera centre
    closest to the cell) or ``"frontal"`` (optical axis most aligned with the direction to it)."""

    view_cell_m: float = 0.5
    """Cell size (metres) of the per-point view selection (points of a cell share a view set). 0.01..100."""

    point_occlusion: bool = True
    """Depth Guided Masking without input depth: ``segment_points`` with ``use_depth`` (method
    ``govnesf``) tests each point, in every keyframe that has no input depth, against that
    keyframe's z-buffer of the request's own points (:func:`mapper.geometry.splat.occluder_depths`):
    a view in which another requested point lies in front of it by more than the DGM tolerance is
    masked, as a depth map would mask it. The points a robot asks about are surfaces; asked about
    densely (a map, a scan, a room's points) they hide one another as the scene does. Off: those
    keyframes use their depth prior (plane-sweep stereo and triangulation, ``[stereo]``) as before.
    Measured on the six held-out scenes (docs/concepts/rgb-only.md, "The request's points as occluders"):
    RGB-only ``govnesf`` + DGM 55.6 / 55.1 -> 59.3 / 56.0 3D mIoU (apartment / studio; 59.5 / 56.8
    with ``dgm_view_selection`` and ``point_occlusion_prior_veto``). At the node's own RGB-only map
    points, which lie off their surfaces more often, the test is worth less. Keyframes with input
    depth always use it."""

    point_occlusion_prior_veto: bool = True
    """``point_occlusion``: drop a keyframe's occluder pixel where that keyframe's own depth prior
    (plane-sweep and triangulated depths, ``[stereo]``) sees through it, i.e. the prior's surface
    lies farther than the occluding point by more than the DGM tolerance (the point is likely off
    its surface). Off: every requested point occludes. Measured (docs/concepts/rgb-only.md): at the node's
    own RGB-only map points ``govnesf`` + DGM 48.0 / 49.1 / 48.2 / 33.0 -> 50.1 / 52.6 / 49.7 / 34.7
    (four rooms), at ground-truth points 60.6 / 65.5 / 48.2 / 51.7 -> 59.9 / 65.8 / 47.1 / 51.4 and
    held out 59.7 / 56.7 -> 59.5 / 56.8."""

    dgm_view_selection: bool = True
    """``segment_points`` with ``use_depth``: choose each cell's views among those that pass the
    depth test (input depth, else the request's points as occluders or the depth prior), so that
    DGM does not mask views that were chosen in place of visible ones. Off: views are chosen by
    whether the point projects into them, then DGM masks. Measured (docs/concepts/rgb-only.md, "The
    request's points as occluders"): ``govnesf`` + DGM with depth 62.0 / 47.7 / 51.1 -> 61.8 / 47.8
    / 52.6 3D mIoU (demo room, studio seeds 9 and 11), without depth 60.6 / 47.7 / 50.5 -> 60.6 /
    48.2 / 51.7, held out without depth 59.3 / 56.0 -> 59.7 / 56.7 (apartment / studio)."""

    point_occlusion_footprint: float = 3.0
    """Each requested point covers this many times the request's median nearest-neighbour spacing
    (:func:`mapper.geometry.splat.point_spacing`) in the z-buffers of ``point_occlusion``; 1.5 and
    3 measured equal. 0.1..100."""

    render_volume_views: int = 0
    """Client renders take their density (none outside its box), and the blend's volume features
    inside its box, from a cost volume built over this many keyframes of the window that best
    overlap the rendered view (the share
    of each keyframe's observed points inside its frustum: the training's choice of sources),
    with bounds over what those keyframes observed, instead of the window's volume over every
    keyframe. The network was trained on volumes of its ``num_source_views`` (8) sources; over a
    whole window its density blurs (the depth of apartment_s1000's frames, median relative error
    0.049 from their 8 best sources against 0.15 from 30 and 0.19 from all 80). 0 (default) =
    the window's volume: measured on three RGB-only streams (docs/concepts/rendering.md, "Render volumes
    from the overlapping keyframes"), 8 made the model's own march far better (depth 0.265 ->
    0.175, 0.565 -> 0.406, 0.328 -> 0.208) but the node's renders, which take most pixels from
    the measured geometry, lost 0.3-0.8 dB. The rendered-depth map points have their own setting,
    ``global_map.rendered_volume_views`` (also 0 by default). Volumes are cached per window
    version and keyframe set. The window's volume is used anyway when this is 0 or 1, the window
    holds no more keyframes than this, or fewer than 2 overlap the view. 0..256."""

    samples_per_ray: int = 0
    """Samples per ray for renders; 0 = the model's. 0..1024."""

    near_m: float = 0.2
    """Near bound of rendered rays (metres along the ray). >= 0."""

    far_m: float = 8.0
    """Far bound of rendered rays (metres along the ray). > near_m."""

    chunk_rays: int = 2048
    """Rays rendered at a time (memory bound). 1..10^6."""

    chunk_points: int = 4096
    """Points evaluated by the appearance/OV network at a time (memory: about chunk x views x
    (D + F + 6) floats). 1..10^7."""

    empty_space_skipping: bool = True
    """Renders leave out what the scene does not need: samples in empty cells of the occupancy
    grid, the appearance pass for samples whose weight is below ``min_weight``, early ray
    termination (``stop_transmittance``) and one appearance evaluation per weight group
    (``appearance_groups``); each of those has its own switch below. Off = the dense path (every
    sample evaluated, every lever off; ``render(empty_space_skipping=False)`` asks for it per call)."""

    occupancy_threshold: float = 0.05
    """A voxel of the occupancy grid is empty when the density (1/m) at its 2x2x2 sub-samples and in
    its 26 neighbours stays below this. >= 0."""

    carve_free_space: bool = False
    """Off by default (measured in docs/concepts/rgb-only.md: RGB-only rendered depth 0.273 -> 0.264 and
    0.332 -> 0.321 median relative error, but the studio's RGB-only chair 0.20 -> 1.21 m). On: with
    skipping, the occupancy grid also leaves out the space that depth priors of keyframes
    WITHOUT input depth (``set_view_depth_prior``: plane-sweep stereo and triangulated points) see
    through: a voxel crossed by the rays of at least ``carve_min_views`` such keyframes on their
    way to a prior depth (stopping ``carve_margin`` short of it), and not within one voxel of any
    prior surface point, gets no density. Keyframes with input depth never carve (their density is
    trained with it). RGB-only renders then stop at the surfaces the priors found instead of in
    the density's haze in front of them."""

    carve_min_views: int = 2
    """Keyframes whose prior rays must cross a voxel before it is carved. 1..1000."""

    carve_margin: float = 0.15
    """Carving stops this fraction of the prior depth short of it (priors are not exact). 0..0.9."""

    carve_rays: int = 600
    """Prior pixels per keyframe cast for carving (evenly subsampled). 1..100000."""

    min_weight: float = 1.0e-4
    """With skipping, samples whose rendering weight is below this skip the appearance pass. 0..1."""

    stop_transmittance: float = 0.0
    """Early ray termination (with skipping): a ray whose transmittance fell below this is not
    evaluated further (opacity, colour and OV change by at most this much). 0 = off. 0..0.5."""

    termination_block: int = 8
    """Samples evaluated per early-termination step (the density runs in steps of this many
    samples; the transmittance is checked after each). 1..1024."""

    appearance_groups: int = 4
    """Coarse-to-fine appearance (with skipping): each ray's samples are cut into at most this many
    runs of about equal rendering weight, and the appearance network runs once per run, at its
    weighted mean position (``mapper.model.render.weight_groups``). 0 (or >= the samples per ray) =
    every sample. 0..1024."""

    refine_margin: float = 0.02
    """Coarse-to-fine labels (with ``appearance_groups``): pixels whose two best text scores differ by
    less than this are rendered again with every sample's appearance, so the weight groups do not
    swap near-tied labels. 0 = off. 0..2."""

    batched_view_groups: bool = True
    """Renders (with skipping) and ``segment_points`` evaluate every point's view group in ONE network
    pass (each point sampled in its own source views, ``GovNeSF.sample_views_indexed``) instead of
    one pass per view group; same values up to float rounding. False = one pass per group (the
    reference path; the dense render always uses it)."""

    fused_point_answers: bool = True
    """The learned ``segment_points`` (with ``batched_view_groups``) and the learned features
    written into the global map (``point_features``), on the CPU in float32, sample, weigh and
    blend every point in ONE compiled pass (:mod:`mapper.model.ops.answer_kernel`), each block of
    points' samples kept in small buffers; the same answers as the three kernels run chunk by chunk
    (False, the reference path), without writing the pairs' samples to memory."""

    surface_from_map: str = "auto"
    """``render`` on a node: pixels where a measured surface is known are rendered AT it: one
    appearance evaluation (FusionNet's blend of the source views) at the surface point, depth =
    the surface's; only the other pixels march through the volume. The surface of a pixel: the
    nearest point splatted over its footprint (:func:`mapper.node.queries.surface_depth`).
    ``"auto"`` (default): the global map's points while at least half of the window's keyframes
    carry input depth, else the node's measured RGB-only geometry (triangulated points and kept
    plane-sweep depths, ``MapperNode.surface_points``; an RGB-only global map also holds the
    model's own rendered depth, too far off to render at); ``"on"``: the global map's points
    always; ``"off"``: march every pixel. Sharper, with far better depth, and several times
    faster than marching the model's diffuse density (docs/concepts/rendering.md, "Surfaces from the
    map"). ``ModelRuntime.render`` used in-process without a node marches."""

    surface_geometry_footprint: float = 0.5
    """Footprint of each RGB-only geometry point (triangulated, plane-sweep) in the splat, in map
    voxels (``global_map.voxel_size_m``); the global map's points cover one voxel. Half a voxel
    with ``surface_fill_px = 4`` measured best on three of four rooms (docs/concepts/rendering.md).
    0.01..10."""

    surface_see_through_px: int = 3
    """A map-surface pixel with a nearer map surface (by more than ``surface_see_through_rel``) on
    both sides within this many pixels (left and right, or above and below) sees through a hole
    of that surface; it is marched instead (or filled, ``surface_fill_px``). 0 = no test. 0..32."""

    surface_see_through_rel: float = 0.1
    """See ``surface_see_through_px``. 0..10."""

    surface_speckle_px: int = 0
    """Islands of the splat of at most this many pixels (4-connected, neighbours' depths within
    ``surface_fill_rel``) are dropped before filling (an isolated point floating off the surfaces
    around it covers up to 25 pixels) and marched instead. 0 = keep them (default: at 40, measured
    in docs/concepts/rendering.md, RGB-only renders were no better overall). 0..100000."""

    surface_fill_px: int = 4
    """Holes of the map's splat (between point footprints, or left by the see-through test) up to
    this many pixels on each side are filled where the surface on both sides agrees within
    ``surface_fill_rel`` (linear interpolation), so they are rendered at the surface too. 0 = no
    filling. 0..32."""

    surface_fill_rel: float = 0.05
    """See ``surface_fill_px``. 0..10."""

    surface_planes: bool = True
    """RGB-only renders (``surface_from_map`` taking the node's measured RGB-only geometry): pixels
    that no geometry point covers take the nearest supported plane fitted to those points, where
    one is hit (:mod:`mapper.geometry.planes`: sequential RANSAC with normal agreement; each plane
    only over the region its points cover), instead of marching. Walls and floors of a room are
    flat-shaded and carry few measured points; their planes do. False = march those pixels."""

    surface_map_fill: bool = True
    """RGB-only renders: pixels that neither the geometry nor its planes cover take the global
    map's splatted surface where it has one (the map's triangulated, swept and agreed
    rendered-depth points, one voxel each), instead of marching the model's density. Measured on
    five rooms with run K (docs/concepts/rgb-only.md): depth error lower in three, equal in one, higher in
    the demo room (0.057 -> 0.069). False = march those pixels."""

    surface_nearest_fill_px: float = 10_000.0
    """Without depth (``surface_from_map`` from the RGB-only geometry): pixels that neither the
    geometry, its planes nor the map's splat cover, within this many pixels of a pixel they do
    cover, take that nearest pixel's surface instead of the model's march
    (:func:`mapper.geometry.splat.fill_nearest`); the default reaches every pixel of any image up
    to 10 000 px across. 0 = off (marched). Measured:
    rendered depth at held-out poses 0.069 / 0.082 / 0.048 / 0.134 / 0.083 -> 0.070 / 0.068 / 0.045
    / 0.099 / 0.066 median relative error in five rooms, PSNR +0.3 to +0.7 dB in four (-0.08 in
    one), and on the real ICL-NUIM sequence 5.7% -> 4.6% at 19.01 -> 19.14 dB. 0..10000."""

    surface_plane_inlier_m: float = 0.03
    """A geometry point belongs to a plane within this distance (m). 0.001..1."""

    surface_plane_normal_deg: float = 25.0
    """...and when its local normal (``surface_plane_neighbours`` nearest points) is within this
    angle of the plane's, so that no plane cuts across several surfaces. 1..90."""

    surface_plane_neighbours: int = 30
    """Points of a geometry point's neighbourhood for its local normal. 3..1000."""

    surface_plane_min_points: int = 200
    """Smallest plane kept, in geometry points (of at most ``surface_plane_max_points``). 3..10^7."""

    surface_plane_cell_m: float = 0.25
    """Side (m) of the cells of a plane's supported region (a cell with 2 of its points counts;
    gaps of up to 2 cells are closed). 0.01..10."""

    surface_plane_max: int = 16
    """Most planes fitted. 0..256."""

    surface_plane_max_points: int = 20_000
    """The planes are fitted to at most this many geometry points (a fixed random subset beyond
    it). 100..10^7."""

    surface_plane_refit: float = 0.1
    """The planes are refitted when the number of geometry points moved by more than this share
    since the last fit (the first render after that pays for the fit); in between, renders reuse
    them. 0 = refit on every change of the count. 0..10."""

    min_view_support: int = 1
    """Density is forced to 0 where fewer than this many keyframes see the cost-volume voxel (a
    voxel seen by one view has zero feature variance, which reads as a surface). 1 = off. 1..1000."""

    min_opacity: float = 0.05
    """Pixels whose accumulated opacity is below this render no depth (0) and label -1. 0..1."""

    max_render_pixels: int = 640 * 480
    """Largest render (width x height) served; bigger requests are refused with a clear error (a
    render occupies the query thread). 1..16777216."""

    max_segment_points: int = 2_000_000
    """Most points one ``segment_points`` (govnesf) request may carry. 1..10^8."""

    def validate(self, where: str = "model") -> None:
        """Raise ``mapper.node.config.ConfigError`` naming ``where``, the key, the value and the range."""
        def check(key: str, value: float, lo: float, hi: float) -> None:
            if not (isinstance(value, int | float) and lo <= value <= hi):
                raise ConfigError(f"{where}: model.{key} = {value!r} out of range {lo}..{hi}")

        if not self.checkpoint:
            raise ConfigError(f"{where}: model.checkpoint must name a checkpoint file, got ''")
        if not (self.device == "auto" or self.device == "cpu" or self.device.startswith("cuda")):
            raise ConfigError(f"{where}: model.device = {self.device!r}; allowed: auto, cpu, cuda, cuda:N")
        check("image_width", self.image_width, 0, 4096)
        check("image_height", self.image_height, 0, 4096)
        check("voxel_size_m", self.voxel_size_m, 0.0, 10.0)
        check("max_voxels", self.max_voxels, 0, 10_000_000)
        if 0 < self.max_voxels < 64:
            raise ConfigError(f"{where}: model.max_voxels = {self.max_voxels} out of range: 0 or >= 64")
        check("bounds_margin_m", self.bounds_margin_m, 0.0, 10.0)
        check("bounds_outlier_m", self.bounds_outlier_m, 1.0, 1e6)
        check("max_range_m", self.max_range_m, 0.1, 100.0)
        check("rebuild_outside_fraction", self.rebuild_outside_fraction, 0.0, 1.0)
        check("source_views", self.source_views, 0, 256)
        check("point_source_views", self.point_source_views, 0, 256)
        if self.view_selection not in ("nearest", "frontal"):
            raise ConfigError(
                f"{where}: model.view_selection = {self.view_selection!r}; allowed: nearest, frontal"
            )
        check("view_cell_m", self.view_cell_m, 0.01, 100.0)
        check("point_occlusion_footprint", self.point_occlusion_footprint, 0.1, 100.0)
        check("samples_per_ray", self.samples_per_ray, 0, 1024)
        check("render_volume_views", self.render_volume_views, 0, 256)
        if isinstance(self.render_volume_views, bool) or not isinstance(self.render_volume_views, int):
            raise ConfigError(
                f"{where}: model.render_volume_views = {self.render_volume_views!r} must be an integer"
            )
        check("near_m", self.near_m, 0.0, 1e4)
        check("far_m", self.far_m, 0.0, 1e4)
        if self.far_m <= self.near_m:
            raise ConfigError(f"{where}: model.far_m = {self.far_m} must exceed model.near_m = {self.near_m}")
        check("chunk_rays", self.chunk_rays, 1, 1_000_000)
        check("chunk_points", self.chunk_points, 1, 10_000_000)
        check("occupancy_threshold", self.occupancy_threshold, 0.0, 1e6)
        check("min_weight", self.min_weight, 0.0, 1.0)
        check("stop_transmittance", self.stop_transmittance, 0.0, 0.5)
        check("carve_min_views", self.carve_min_views, 1, 1000)
        check("carve_margin", self.carve_margin, 0.0, 0.9)
        check("carve_rays", self.carve_rays, 1, 100_000)
        check("termination_block", self.termination_block, 1, 1024)
        check("appearance_groups", self.appearance_groups, 0, 1024)
        check("refine_margin", self.refine_margin, 0.0, 2.0)
        if self.surface_from_map not in ("auto", "on", "off"):
            raise ConfigError(
                f"{where}: model.surface_from_map = {self.surface_from_map!r}; allowed: auto, on, off"
            )
        check("surface_geometry_footprint", self.surface_geometry_footprint, 0.01, 10.0)
        check("surface_see_through_px", self.surface_see_through_px, 0, 32)
        check("surface_see_through_rel", self.surface_see_through_rel, 0.0, 10.0)
        check("surface_speckle_px", self.surface_speckle_px, 0, 100_000)
        check("surface_fill_px", self.surface_fill_px, 0, 32)
        check("surface_fill_rel", self.surface_fill_rel, 0.0, 10.0)
        check("surface_nearest_fill_px", self.surface_nearest_fill_px, 0.0, 10_000.0)
        check("surface_plane_inlier_m", self.surface_plane_inlier_m, 0.001, 1.0)
        check("surface_plane_normal_deg", self.surface_plane_normal_deg, 1.0, 90.0)
        check("surface_plane_neighbours", self.surface_plane_neighbours, 3, 1000)
        check("surface_plane_min_points", self.surface_plane_min_points, 3, 10_000_000)
        check("surface_plane_cell_m", self.surface_plane_cell_m, 0.01, 10.0)
        check("surface_plane_max", self.surface_plane_max, 0, 256)
        check("surface_plane_max_points", self.surface_plane_max_points, 100, 10_000_000)
        check("surface_plane_refit", self.surface_plane_refit, 0.0, 10.0)
        check("min_view_support", self.min_view_support, 1, 1000)
        check("min_opacity", self.min_opacity, 0.0, 1.0)
        check("max_render_pixels", self.max_render_pixels, 1, 4096 * 4096)
        check("max_segment_points", self.max_segment_points, 1, 100_000_000)
