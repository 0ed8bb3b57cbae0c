"""Typed configuration of the mapper node, loaded from TOML (``launch/node.toml``).

Every setting is a field of a frozen dataclass with a comment saying what it means and in which
unit. A TOML file mirrors the dataclasses: top-level keys set :class:`NodeConfig` fields, and a
table (``[window]``) sets the sub-config of the same name. Unknown keys and values of the wrong
type are errors that name the key and the file, so a typo never silently falls back to a default.

Later pipeline stages add their own sub-config (e.g. ``model: ModelConfig``, ``cost_volume:
CostVolumeConfig``, ``global_map: GlobalMapConfig``) as one more field of :class:`NodeConfig`
with a default factory; the loader, the overrides and the error messages need no change.

TOML has no null, so an optional string (``str | None``) is disabled with an empty string::

    events_endpoint = ""   # no PUB socket

Example::

    >>> cfg = config_from_dict({"map_dir": "maps", "window": {"max_keyframes": 8}})
    >>> cfg.window.max_keyframes
    8
    >>> apply_overrides(cfg, {"window.min_translation_m": 0.5}).window.min_translation_m
    0.5
"""

from __future__ import annotations

import dataclasses
import ipaddress
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from govnesf._compat import tomllib
from govnesf.resources import find_data_file
from mapper.errors import ConfigError
from mapper.geometry.config import DenseFlowConfig, StereoConfig, TriangulationConfig
from mapper.map.global_map import GlobalMapConfig
from mapper.map.window import WindowConfig
from mapper.node.store import validate_map_name
from mapper.ov.config import ClipBackendConfig
from mapper.runtime.config import ModelRuntimeConfig

#: Where ``govnesf serve`` looks for its config when ``--config`` is not given: the repo's
#: ``launch/node.toml``, or the copy an installed wheel carries (:mod:`govnesf.resources`).
DEFAULT_CONFIG_PATH = find_data_file("launch/node.toml")


OBJECT_VOCABULARY: tuple[str, ...] = (
    "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf", "picture", "counter",
    "desk", "curtain", "refrigerator", "shower curtain", "toilet", "sink", "bathtub",
)
"""The default ``queries.object_vocabulary``: the object classes of ScanNet's 20-class benchmark
(wall, floor and "other furniture" left out), the field's common indoor label set: what a found
object may be instead of the text asked for (:func:`mapper.node.queries.vocabulary_factor`)."""


@dataclass(frozen=True)
class QueryConfig:
    """Semantic queries (see :mod:`mapper.node.queries`)."""

    default_max_points: int = 200_000
    """``query_points`` returns at most this many points when the request gives no ``max_points``."""

    cluster_radius_m: float = 0.12
    """Points of one text closer than this (metres) join the same object candidate. > 0."""

    min_object_points: int = 15
    """Clusters with fewer points are not reported as objects. >= 1."""

    object_support_points: float = 25.0
    """An object's score (the mean of its top half of point scores) is discounted by its support,
    ``x (1 - exp(-points / object_support_points))`` (x 0.45 at 15 points, 0.86 at 50, 0.98 at
    100), so a few stray high-scoring points do not outrank a well-observed object; objects are
    sorted by that score. 0 = no discount. 0..1000000."""

    object_split_quantile: float = 0.5
    """An object candidate of at least ``2 * min_object_points`` points whose core, its points
    scoring at or above this quantile of its scores, falls apart into two or more groups of at
    least ``min_object_points`` points (``cluster_radius_m`` apart) is reported as those groups
    (four chairs around a table, not one object on the table;
    :func:`mapper.node.queries.split_by_score`).
    0 = never split. 0..0.99."""

    object_split_depth: int = 3
    """How many cuts a candidate may take in all: its core, then (if that stays in one piece) the
    core's own core at the same quantile, and its parts' splits (``object_split_quantile``). 0..16."""

    object_split_clean_share: float = 0.9
    """A stricter core (beyond a candidate's first) counts as fallen apart only when its groups of
    ``min_object_points`` hold at least this share of its points: a chair against a desk breaks
    cleanly (99% of the core in two groups), the top eighth of one large object with noisy scores
    into dust (48-75% in groups). 0..1."""

    object_split_max_points: int = 20_000
    """Candidates with more points than this are never split (room-scale surfaces, not groups of
    furniture: the largest merged table-and-chairs candidate measured had 1 652 points,
    docs/concepts/window-and-map.md); the split's cost is a pass over half a candidate's points. 0 = no limit.
    0..100000000."""

    object_vocabulary: tuple[str, ...] = OBJECT_VOCABULARY
    """What a found object may be instead of the text asked for (a TOML list of strings; default
    :data:`OBJECT_VOCABULARY`, ScanNet's 20 benchmark classes less wall, floor and "other
    furniture"). Words within the negatives' similarity (0.8) of a text asked for are left out.
    See ``object_vocabulary_temperature``."""

    object_vocabulary_temperature: float = 0.0
    """``query_points`` objects: an object's score is multiplied by ``exp(min(0, m) / this)``, ``m``
    the cosine of its mean feature with its text minus its best cosine with a word of
    ``object_vocabulary``: a sofa found for "chair" (its features nearer "sofa") falls behind the
    chairs (:func:`mapper.node.queries.vocabulary_factor`). Points are labelled as before; only the
    objects' scores and order change. Off (0): at 0.05 no top object of 36 changed on the tuning
    split (docs/concepts/window-and-map.md). 0..10."""

    max_objects: int = 32
    """Most object candidates per reply (best first). >= 1."""

    workers: int = 1
    """Threads that answer heavy requests (``render``, ``segment_points``) off the query socket's
    thread, so light ones (``status``, ``query_points``, ``save``, ``load``) never wait behind them.
    0 = answer every request on the query thread, in arrival order (no ``busy``). 0..64."""

    queue_length: int = 4
    """Heavy requests that may wait for a worker; one more (beyond ``workers`` running and this
    many waiting) is answered ``busy`` at once. 1..10000."""

    light_text_chars: int = 256
    """A ``query_points`` whose prompts (texts and negatives, as embedded) hold more characters
    that the text encoder has not embedded yet is answered by the heavy-request pool (it may wait
    there or get ``busy``): embedding 64 prompts of 1 024 characters took 7.3 s, which on the query
    thread delayed every client's ``status``. Everyday prompts ("find the chair") stay light, and
    so does any question once its prompts are embedded. 0 = every ``query_points`` with a new
    prompt goes to the pool. 0..1000000."""

    label_cache_blocks: int = 256
    """``query_points`` keeps its scoring step (best text, cosine, beats the negatives) per block of
    16 384 map rows and text set, across map versions (:class:`mapper.node.queries.BlockLabelCache`),
    so a query after an integrate scores only the blocks whose rows changed. The most blocks kept
    (about 112 KB each; least recently used dropped first); 0 = score every row each time. 0..100000."""

    answer_max_age_s: float = 2.0
    """``query_points`` answers the same question (texts, negatives, min_score, max_points,
    objects) from its last answer when the map has not changed since, or, while frames are
    arriving and the map only grew or was fused into (no ``load``), when that answer is at most
    this old (seconds since its snapshot was taken); a stale answer is returned at once and
    recomputed in the background (once the stream stops, answers are of the current map), so a
    planner asking back to back during a stream is not held up by a recomputation per keyframe
    (:class:`mapper.node.queries.AnswerCache`; replies carry ``answer_reused`` / ``answer_age_ms``
    in ``timing_ms``, and ``map_version`` says which version answered). 0 = only answers of the
    current map version are reused. 0..3600."""

    answer_cache_entries: int = 32
    """Most distinct ``query_points`` questions whose last answer is kept (least recently asked
    dropped first); 0 = never reuse an answer. 0..10000."""

    answer_cache_mb: float = 64.0
    """Most memory the kept answers' arrays may take (least recently asked dropped first; an
    answer larger than this is not kept). 0..100000."""

    map_radius_voxels: float = 2.5
    """``segment_points`` / ``render`` answer a point no window keyframe sees from the global
    map's nearest point with a feature within this many map voxels (``global_map.voxel_size_m``);
    0 = window only. 0..100."""

    spatial_sort: bool = True
    """``segment_points`` with ``average`` / ``average_depth`` answers points that do not come in a
    spatially coherent order (e.g. a shuffled or randomly sampled cloud) in Z-order of map voxels
    instead, and returns the answers in the request's order: the averaging kernel reads the OV taps
    neighbouring points share once (:func:`mapper.node.queries.spatial_order`; the same answers,
    measured in docs/results.md). False = the request's order."""

    map_when_more_confident: bool = True
    """``segment_points`` also answers a point the window sees from that nearest map point when the
    map names another text with a higher cosine than the window's answer (keyframes that left the
    window saw the point better than those in it; the reply's ``source`` says map); ``render`` labels
    the same where the render found a surface. False = the window's answer wherever it has one.
    ``segment_points`` answers without a depth test use ``map_blend`` instead where it is > 0."""

    map_blend: float = 0.75
    """Where both the window and the global map answer a ``segment_points`` point (the nearest map
    point with a feature within ``map_radius_voxels``), the answer is the best text of the blended
    cosines ``(1 - map_blend) * window + map_blend * map`` (score = that blended cosine;
    ``source`` says map where the blend changed the window's label). The map fused every keyframe
    that ever saw the point with depth (each observation visible by construction), the window
    blends only its own keyframes, visible or not: measured in docs/concepts/window-and-map.md. Applies to the
    answers without a depth test (``average``, ``govnesf`` without ``use_depth``; the others, and
    ``render`` labels, keep the ``map_when_more_confident`` rule: measured, the blend did not help
    them) while at least half of the window's keyframes carry input depth (the map's points are
    then measured surfaces); else ``map_blend_without_depth``. 0 = the ``map_when_more_confident``
    rule everywhere. 0..1."""

    map_blend_without_depth: float = 0.0
    """``map_blend`` while fewer than half of the window's keyframes carry input depth (an RGB-only
    robot: the map's points come from triangulation, plane-sweep stereo and the model's rendered
    depth, and their features were sampled at those estimated surfaces). 0 (default) = the
    ``map_when_more_confident`` rule: measured in docs/concepts/window-and-map.md, 0.75 there cost
    3-4 points. 0..1."""

    point_occlusion: bool = True
    """``average_depth`` without input depth: keyframes without depth count a point where the
    request's own points do not hide it in that keyframe (its z-buffer of them,
    :func:`mapper.geometry.splat.occluder_depths`, each point covering
    ``model.point_occlusion_footprint`` times the request's median point spacing), as the learned
    model's ``model.point_occlusion`` does for ``govnesf`` with ``use_depth``. Off: only keyframes
    with input depth count for ``average_depth``."""

    evicted_views: str = "both"
    """Keep what keyframes that left the window saw (:mod:`mapper.map.evicted_views`): when a
    keyframe leaves, a worker adds its OV sample at every global-map voxel it counts for to a
    running mean per voxel; the averaging then counts a point's nearest map voxel's mean (within
    ``map_radius_voxels``) as that many more views, i.e. as a window that never evicted, and the
    map answers from that mean at its voxels (for ``govnesf`` mixed with the voxel's learned
    feature, ``evicted_views_learned_weight``). ``"both"`` (default): two channels, the views
    whose depth confirms the voxel (``average_depth``; keyframes with input depth) and every view
    the voxel falls in (``average``); ``"depth"``: the first only (half the worker's time and
    memory); ``"off"``: the window's views only. Measured on the scenario matrix's tuning split
    (docs/concepts/window-and-map.md): +0.7 to +11 mIoU once settled on five of the six streams
    with depth, one room's ``average`` -1.6. Costs D x 4 bytes a voxel per channel (status
    ``evicted_views.bytes``; 384-d, "both": 3 KB a voxel) and 0.2-0.3 s of a worker a keyframe."""

    evicted_views_occlusion: bool = True
    """The ``all`` channel of ``evicted_views`` (every view a voxel falls in) leaves out, for a
    keyframe with input depth, the voxels behind what that keyframe measured (more than 25% of the
    depth behind it at their pixel): a camera in one room does not record its view of the room
    behind the wall. Keyframes without depth record every voxel in their image, as before.
    Measured in docs/concepts/window-and-map.md: on the tuning split's six streams with depth
    ``average`` +0.1 to +2.4 (``govnesf`` -0.7 to +0.3); a room's ``average`` after a second room
    streamed 12 m away -1.6 instead of -2.7. False: every voxel in the image."""

    evicted_views_learned_weight: float = 0.5
    """For ``govnesf`` (not answered by averaging), the map's answer at a voxel that holds evicted
    views: ``(1 - w)`` x the voxel's own feature (where the model's blend was written before its
    keyframes left: ``global_map.learned_features``) + ``w`` x the evicted views' mean; the
    averaging methods take the evicted views' mean alone. 0..1."""

    evicted_views_max_pending: int = 64
    """Keyframes that left the window and wait for the ``evicted_views`` worker; beyond this the
    oldest waiting is dropped (counted in status ``evicted_views.dropped``). 1..100000."""

    evicted_views_max_pending_mb: float = 256.0
    """... and at most this much of their colour, depth and OV maps (MB; a 640 x 480 keyframe with a
    384-d OV map at 1/4 resolution holds about 16 MB): the oldest waiting beyond it is dropped too
    (counted the same way; the newest always waits). 0 = by count only. 0..100000."""

    learned_average_mix: float = 0.0
    """``govnesf`` answers (not fallen back) are mixed with the averaging's over the same window
    (``average``; ``average_depth`` with ``use_depth``): the best text of ``(1 - w)`` x the model's
    cosines + ``w`` x the averaging's where both answer (:func:`mapper.node.answers.segment.mix_answers`).
    0 = the model alone. 0..1."""
    learned_evicted_views: float = 0.5
    """``govnesf`` answers (not fallen back) where views of keyframes that left the window count
    for a point: mixed with those views' own mean (the nearest voxel's, ``evicted_views``, and the
    kept views of ``evicted_frames_mb`` where the request's other points do not hide the point in
    them, the test ``point_occlusion`` makes; :func:`mapper.node.backends.average.evicted_cosines`)
    by ``w`` x their share of the point's views, ``evicted / (evicted + window)``
    (:func:`mapper.node.answers.segment.mix_answers`): the model's answer stands for the window's
    views and those that left count as the averaging counts them, so the learned answer does not
    lose what the averaging keeps of them. Not where ``map_blend`` applies (answers without a depth
    test while the window has depth): ``learned_evicted_views_blended`` there.
    Measured on the tuning split in docs/concepts/window-and-map.md. 0 = off. 0..1."""

    learned_evicted_views_blended: float = 1.0
    """``learned_evicted_views`` for the answers ``map_blend`` applies to (``govnesf`` without a
    depth test while the window's keyframes carry depth): the model's cosines mixed with the views
    that left the window by this x their share of the point's views, before the map's blend. The
    averaging counts those views by their number; without this the learned answer took them only
    through the map's blend, beside the voxel's learned feature. On the six tuning streams with
    depth (paired on the same maps, docs/concepts/window-and-map.md): ``govnesf`` - ``average`` worst
    -3.19 -> -1.58, median +2.11 -> +2.33, ``govnesf`` itself -0.3 to +1.6; 0.5 / 0.75: worst -2.32 /
    -1.97. 0 = off (the map's blend alone). 0..1."""

    learned_toward_average: float = 3.0
    """Do no harm per point: a ``govnesf`` answer (not fallen back) is mixed with the averaging's
    whole answer (``average``, or ``average_depth`` with ``use_depth``: its window's and the map's,
    as that method answers) where the averaging's answer is this many times as decided as the
    learned one's, the margin of each (its best text's cosine minus the second best's) telling how
    decided it is: by ``d = margin_avg - this x margin_learned``, the best text of ``(1 - w)`` x the
    learned cosines + ``w`` x the averaging's, ``w = min(1, d / learned_toward_average_ramp)``
    where ``d > 0``; a point only the averaging answers takes its answer; the reply's ``fallback``
    marks the points whose label the averaging's answer changed
    (:func:`mapper.node.answers.segment.toward_averaging`). Where the two disagree on the scenario
    matrix's tuning streams, the averaging is right more often than the model where its margin is
    3 or more times the model's, the model where it is below (docs/concepts/answers.md, with the
    measured effect). 0 = off. 0..100."""

    learned_toward_average_ramp: float = 0.02
    """The margin lead (cosine) over which ``learned_toward_average``'s weight goes from 0 to 1.
    0.0001..1."""

    evicted_frames_mb: float = 256.0
    """With ``evicted_views`` "both": keep the keyframes without input depth that leave the window
    as reduced views (pose, intrinsics, the OV map area-averaged to ``evicted_frames_cells``; never
    the RGB; :mod:`mapper.map.evicted_frames`), up to this much memory (MB; beyond it the oldest is
    dropped into the per-voxel means, counted in status ``evicted_views.frames_dropped``).
    ``average`` then counts every kept view a point falls in as one more view of its average, and
    ``govnesf``'s map answer mixes their mean as it mixes the voxels' (``evicted_views_learned_weight``):
    without depth the map has few voxels on walls and floors, so the per-voxel means miss most points.
    0 = off (keyframes without depth go to the per-voxel means). On the tuning split's six
    RGB-only streams: window median ``average`` 24.3 -> 32.5, ``govnesf`` 24.8 -> 31.7; one
    stream with odometry drift ``average`` -5.0, as low as the node holding every keyframe there
    (docs/concepts/window-and-map.md). 0..100000."""

    evicted_frames_learned: bool = False
    """With the learned model served: each keyframe without depth, while it is still in the window
    (the pre-eviction worker; one that left first is skipped), also gets the model's blended
    features at its kept view's cells (the model's rendered surface through each cell,
    :func:`mapper.node.backends.learned.learned_view_map`), kept beside its reduced OV map (twice the
    memory of a kept view) and read by ``govnesf``'s answers from the kept views; the averaging
    methods read the OV maps as before. Off: on the scenario matrix's streams, sent as fast as acks
    come back, the worker reached 4 of 52 keyframes before they left (window studio stream,
    ``govnesf`` 45.5 -> 45.2); computed for the keyframes that had left too, 45.5 -> 42.5. Computed
    in time, half a window before each keyframe leaves (``global_map.learned_features_batch`` 15, 1200
    cells), the learned maps still cost ``govnesf`` 0.5-5.7 on four RGB-only tuning streams (office
    wall-hugging 41.8 -> 36.1; not diagnosed further)."""
    evicted_frames_depth_tested: str = "first"
    """Where depth-tested answers (DGM: ``govnesf`` with ``use_depth``; ``average_depth``) in a window
    of keyframes without depth take the kept views of evicted keyframes (``evicted_frames_mb``):
    ``"first"``: before the map's voxels, as ``govnesf`` without the test does (a voxel of an
    RGB-only map holds the few observations its swept or triangulated points carried; the kept
    views, every view of the point that left the window); ``"fill"``: only at points neither the
    window nor a map voxel within ``map_radius_voxels`` answers. On the six RGB-only tuning
    streams, paired on the same maps (``benchmarks/studies/query_settings.py``): DGM 32.0 -> 38.1 and
    ``average_depth`` 28.0 -> 35.3 on the studio revisit, the others -0.4 to +0.1 / -0.7 to +1.6."""

    evicted_frames_cells: int = 1200
    """Most cells of a kept evicted view's OV map (``evicted_frames_mb``): area-averaged to the
    largest size of the map's aspect within this (a 160 x 120 keyframe's 40 x 30 map is kept whole, a
    320 x 240 one's 80 x 60 becomes 40 x 30); float32, 384-d: 1.5 KB a cell, 1.8 MB a view, about 140
    views in the default ``evicted_frames_mb``. On the tuning split's six RGB-only streams 1200 instead
    of 300 took the window's ``average`` to the node holding every keyframe on all six (window - all
    worst -5.3 -> 0.0), ``govnesf`` -6.7 -> -5.8 and DGM -8.3 -> -5.7 (docs/concepts/window-and-map.md);
    a request's time is the same (100k points against 60 kept views: 172 / 167 ms). 1..100000."""

    learned_fallback: str = "geometry"
    """Do no harm: when ``segment_points`` with ``govnesf`` is answered by averaging instead
    (``average``, or ``average_depth`` with ``use_depth``; the reply's ``fallback`` says so per
    point). ``"geometry"``: while the window's keyframes mostly lack input depth and the node's
    geometry work (integration, triangulation and stereo, rendered-depth points) is pending: the
    learned model's volume follows that geometry, and asked before it settled it answered far below
    averaging. ``"pending"``: also while any other background work is pending (the learned features
    written into the map, integration with depth). ``"off"``: always the learned model."""

    max_settle_wait_s: float = 30.0
    """The longest a request's ``settle_timeout_s`` may make it wait for the node's background work
    (longer requests wait this long). 0..600 seconds."""

    def validate(self, where: str) -> None:
        if self.evicted_views not in ("off", "depth", "both"):
            raise ConfigError(f"{where}: queries.evicted_views = {self.evicted_views!r}: must be one of "
                              "'off', 'depth', 'both'")
        _check_range(where, "queries.evicted_views_learned_weight", self.evicted_views_learned_weight,
                     0.0, 1.0)
        _check_range(where, "queries.learned_average_mix", self.learned_average_mix, 0.0, 1.0)
        _check_range(where, "queries.learned_evicted_views", self.learned_evicted_views, 0.0, 1.0)
        _check_range(where, "queries.learned_evicted_views_blended", self.learned_evicted_views_blended,
                     0.0, 1.0)
        _check_range(where, "queries.learned_toward_average", self.learned_toward_average, 0.0, 100.0)
        _check_range(where, "queries.learned_toward_average_ramp", self.learned_toward_average_ramp,
                     1e-4, 1.0)
        _check_range(where, "queries.evicted_views_max_pending", self.evicted_views_max_pending, 1, 100_000)
        _check_range(where, "queries.evicted_views_max_pending_mb", self.evicted_views_max_pending_mb,
                     0.0, 100_000.0)
        _check_range(where, "queries.evicted_frames_mb", self.evicted_frames_mb, 0.0, 100_000.0)
        _check_range(where, "queries.evicted_frames_cells", self.evicted_frames_cells, 1, 100_000)
        _check_range(where, "queries.workers", self.workers, 0, 64)
        _check_range(where, "queries.queue_length", self.queue_length, 1, 10_000)
        _check_range(where, "queries.map_radius_voxels", self.map_radius_voxels, 0.0, 100.0)
        _check_range(where, "queries.map_blend", self.map_blend, 0.0, 1.0)
        _check_range(where, "queries.map_blend_without_depth", self.map_blend_without_depth, 0.0, 1.0)
        _check_range(where, "queries.label_cache_blocks", self.label_cache_blocks, 0, 100_000)
        _check_range(where, "queries.answer_max_age_s", self.answer_max_age_s, 0.0, 3600.0)
        _check_range(where, "queries.answer_cache_entries", self.answer_cache_entries, 0, 10_000)
        _check_range(where, "queries.answer_cache_mb", self.answer_cache_mb, 0.0, 100_000.0)
        _check_range(where, "queries.default_max_points", self.default_max_points, 1, 100_000_000)
        _check_range(where, "queries.cluster_radius_m", self.cluster_radius_m, 1e-3, 10.0)
        _check_range(where, "queries.min_object_points", self.min_object_points, 1, 1_000_000)
        _check_range(where, "queries.object_support_points", self.object_support_points, 0.0, 1_000_000.0)
        _check_range(where, "queries.object_split_quantile", self.object_split_quantile, 0.0, 0.99)
        _check_range(where, "queries.object_split_depth", self.object_split_depth, 0, 16)
        _check_range(where, "queries.object_split_max_points", self.object_split_max_points, 0, 100_000_000)
        _check_range(where, "queries.object_split_clean_share", self.object_split_clean_share, 0.0, 1.0)
        _check_range(where, "queries.light_text_chars", self.light_text_chars, 0, 1_000_000)
        _check_range(where, "queries.max_objects", self.max_objects, 1, 10_000)
        if self.evicted_frames_depth_tested not in ("fill", "first"):
            raise ConfigError(f"{where}: queries.evicted_frames_depth_tested must be \"fill\" or \"first\", "
                              f"got {self.evicted_frames_depth_tested!r}")
        _check_range(where, "queries.object_vocabulary_temperature", self.object_vocabulary_temperature,
                     0.0, 10.0)
        if not all(w.strip() for w in self.object_vocabulary) or len(self.object_vocabulary) > 1024:
            raise ConfigError(f"{where}: queries.object_vocabulary must be at most 1024 non-empty words")
        _check_range(where, "queries.max_settle_wait_s", self.max_settle_wait_s, 0.0, 600.0)
        if self.learned_fallback not in ("off", "geometry", "pending"):
            raise ConfigError(f"{where}: queries.learned_fallback = {self.learned_fallback!r}: must be "
                              "one of 'off', 'geometry', 'pending'")


@dataclass(frozen=True)
class LimitsConfig:
    """Bounds on what the node queues for its peers (TOML table ``[limits]``;
    docs/how-to/robot-network.md)."""

    sndhwm: int = 100
    """ZeroMQ send high-water mark of every node socket (messages queued per peer). A peer that
    does not read its replies gets at most this many queued; further replies to it are dropped and
    counted (``replies_dropped`` in status); the PUB socket drops notices to a slow subscriber.
    1..1000000."""

    rcvhwm: int = 100
    """ZeroMQ receive high-water mark of every node socket (messages queued per peer before ZeroMQ
    stops reading from that connection). 1..1000000."""

    events_queue_max: int = 1000
    """Most ``map_updated`` notices waiting for the events thread; beyond it the oldest is dropped
    and counted (``events_dropped`` in status). 1..1000000."""

    query_share: float = 0.3
    """Ingest first: while frames are arriving, each query-serving thread (the query socket's and
    every ``queries.workers`` thread) pauses after a request so that it computes at most this
    fraction of the time (a request that took 30 ms is followed by a 70 ms pause at 0.3). 1 = no
    pauses. 0.05..1."""

    ingest_active_s: float = 0.5
    """Frames count as arriving when one was handled within this many seconds. 0.01..60."""

    query_pause_max_s: float = 0.5
    """Longest pause after one request (seconds). 0..10."""

    curve_reload_interval_s: float = 5.0
    """With ``curve_dir``: how often (seconds) the node checks ``allowed/`` for added or removed
    client keys. 0.1..3600."""

    blas_threads: int = 1
    """Threads of the BLAS libraries loaded in the node's process (numpy's OpenBLAS, OpenCV's), set
    when the node is made and again when it starts (``threadpoolctl``). OpenBLAS's idle threads
    spin for a while after each product, taking a core from the compiled kernels and torch that
    run next (with two cores: the averaging kernel at one core's speed); the node's numpy
    products are small. 0 = leave BLAS as it is. 0..1024."""

    def validate(self, where: str) -> None:
        _check_range(where, "limits.sndhwm", self.sndhwm, 1, 1_000_000)
        _check_range(where, "limits.blas_threads", self.blas_threads, 0, 1024)
        _check_range(where, "limits.rcvhwm", self.rcvhwm, 1, 1_000_000)
        _check_range(where, "limits.events_queue_max", self.events_queue_max, 1, 1_000_000)
        _check_range(where, "limits.curve_reload_interval_s", self.curve_reload_interval_s, 0.1, 3600.0)
        _check_range(where, "limits.query_share", self.query_share, 0.05, 1.0)
        _check_range(where, "limits.ingest_active_s", self.ingest_active_s, 0.01, 60.0)
        _check_range(where, "limits.query_pause_max_s", self.query_pause_max_s, 0.0, 10.0)


_CLIP_DEFAULTS: dict[str, Any] = {f.name: f.default for f in dataclasses.fields(ClipBackendConfig)}
"""Defaults of :class:`mapper.ov.clip.ClipBackendConfig`, reused by :class:`OvBackendConfig`."""

OV_BACKEND_KINDS = ("", "clip")
"""``ov_backend.kind`` values: "" (none) and "clip" (:class:`mapper.ov.clip.ClipDenseBackend`)."""


@dataclass(frozen=True)
class OvBackendConfig:
    """The in-process open-vocabulary backend (:mod:`mapper.node.workers.ov_features`): dense features for
    keyframes that arrive without ``ov``, and the text encoder of its space. Off by default.

    The CLIP fields are those of :class:`mapper.ov.clip.ClipBackendConfig` (same meaning and
    defaults; TOML has no null, so "native" / "width // 64" are written as 0). Missing or invalid
    weight files do not stop the node: it serves everything else, and semantic requests that would
    need the backend answer ``not_ready`` naming the path and the reason (also in ``status``)."""

    kind: str = ""
    """"" = no in-process backend (features only from frames' ``ov``); "clip" = MaskCLIP dense
    features from local CLIP ViT weights, in the space ``openclip:<model_name>``."""

    weights_path: str = ""
    """Local CLIP ViT checkpoint (a plain state dict, ``.pt`` / ``.pth`` / ``.bin`` or
    ``.safetensors``; docs/how-to/clip-weights.md). Required when kind = "clip". Relative to the node's
    working directory. Nothing is ever downloaded."""

    bpe_path: str = ""
    """Local ``bpe_simple_vocab_16e6.txt.gz`` (CLIP's BPE merges). Required when kind = "clip"."""

    model_name: str = _CLIP_DEFAULTS["model_name"]
    """Names the embedding space only: ``ov_space = "openclip:<model_name>"``. 1..64 characters
    from ``A-Za-z0-9_.@/+-``. A pinned ``ov_space`` must equal that space."""

    device: str = _CLIP_DEFAULTS["device"]
    """"auto" (cuda if available, else cpu), "cpu", "cuda" or "cuda:N"."""

    dtype: str = _CLIP_DEFAULTS["dtype"]
    """"float32", "float16" (cuda only) or "bfloat16"."""

    input_size: int = 0
    """Short side (pixels) images are resized to for dense features; 0 = the model's native image
    size (224 for ViT-B/16). 0 or 16..4096."""

    activation: str = _CLIP_DEFAULTS["activation"]
    """"quick_gelu" (OpenAI weights) or "gelu" (open_clip LAION / DataComp weights)."""

    vision_heads: int = 0
    """Attention heads of the image tower; 0 = width // 64 (ViT-B, ViT-L). 0..1024."""

    text_heads: int = 0
    """Attention heads of the text tower; 0 = width // 64. 0..1024."""

    max_pending: int = 32
    """Most keyframes waiting for features; beyond it the oldest is dropped (``dropped`` in
    status). 1..100000."""

    @property
    def space(self) -> str:
        """The embedding space the backend produces (``openclip:<model_name>``)."""
        return f"openclip:{self.model_name}"

    def clip_config(self) -> ClipBackendConfig:
        """The :class:`ClipBackendConfig` these fields describe (raises ``ValueError`` if invalid)."""
        return ClipBackendConfig(
            weights_path=self.weights_path,
            bpe_path=self.bpe_path,
            model_name=self.model_name,
            device=self.device,
            dtype=self.dtype,
            input_size=self.input_size or None,
            activation=self.activation,
            vision_heads=self.vision_heads or None,
            text_heads=self.text_heads or None,
        )

    def validate(self, where: str) -> None:
        if self.kind not in OV_BACKEND_KINDS:
            raise ConfigError(
                f"{where}: ov_backend.kind {self.kind!r} is not one of "
                f"{', '.join(repr(k) for k in OV_BACKEND_KINDS)} (\"\" = none)"
            )
        if self.input_size != 0:
            _check_range(where, "ov_backend.input_size", self.input_size, 16, 4096)
        _check_range(where, "ov_backend.vision_heads", self.vision_heads, 0, 1024)
        _check_range(where, "ov_backend.text_heads", self.text_heads, 0, 1024)
        _check_range(where, "ov_backend.max_pending", self.max_pending, 1, 100_000)
        if self.kind == "clip":
            for key in ("weights_path", "bpe_path"):
                if not getattr(self, key):
                    raise ConfigError(
                        f"{where}: ov_backend.{key} must name a local file when ov_backend.kind = 'clip' "
                        "(see docs/how-to/clip-weights.md; nothing is downloaded)"
                    )
        try:
            self.clip_config()
        except ValueError as exc:
            raise ConfigError(f"{where}: ov_backend: {exc}") from None


@dataclass(frozen=True)
class NodeConfig:
    """Everything ``govnesf serve`` needs. Sub-configs are nested dataclasses (TOML tables)."""

    ingest_endpoint: str = "tcp://127.0.0.1:5555"
    """ZeroMQ endpoint the node binds a ROUTER on for ``frame`` messages."""

    query_endpoint: str = "tcp://127.0.0.1:5556"
    """ZeroMQ endpoint the node binds a ROUTER on for queries (status, save, load, ...)."""

    events_endpoint: str | None = "tcp://127.0.0.1:5557"
    """ZeroMQ endpoint the node binds a PUB on for ``map_updated`` notices; "" (None) disables it."""

    allow_remote: bool = False
    """Binding to a non-loopback address (``tcp://*:5555``, ``tcp://0.0.0.0:...``, a LAN address)
    is refused unless this is true (or ``curve_dir`` / ``insecure`` is set): exposing the node is
    an explicit choice. Even then the node refuses at start-up to serve such a bind without CURVE
    unless ``insecure`` (see ``curve_dir``)."""

    curve_dir: str | None = None
    """CurveZMQ key directory made by ``govnesf keys DIR`` (docs/how-to/robot-network.md): ingest, query and
    events are served with CURVE (authenticated, encrypted) and only clients whose public key is a
    file in ``DIR/allowed/`` get through; others get no reply. "" (None) = no CURVE."""

    insecure: bool = False
    """Serve non-loopback endpoints without CURVE anyway (the node logs a warning at start-up and
    ``status`` reports ``security.mode = "insecure"``). Without it, and without ``curve_dir``, a
    non-loopback bind is refused at start-up."""

    map_dir: str = "maps"
    """Directory for saved maps; save/load never read or write outside it. A relative path is
    relative to the working directory of the node. Created on first save."""

    max_message_bytes: int = 64 * 1024 * 1024
    """Largest accepted message (bytes); larger ones get a ``too_large`` error. Messages above
    four times this are dropped by ZeroMQ itself (the peer is disconnected) to bound memory."""

    ov_space: str | None = None
    """Pin the open-vocabulary embedding space (e.g. "minilm-l6-v2"); "" (None) means the first
    keyframe carrying ``ov`` sets it. Frames with another space get ``ov_space_mismatch``."""

    autosave_name: str | None = None
    """Map name for periodic and final saves ("" / None: no automatic saves)."""

    autosave_interval_s: float = 0.0
    """Seconds between automatic saves of a changed map to ``autosave_name``; 0 disables periodic
    saves (a final save on shutdown still happens when ``save_on_exit`` and ``autosave_name``)."""

    save_on_exit: bool = True
    """On SIGINT/SIGTERM, save the map to ``autosave_name`` (if set) before exiting."""

    load_autosave_on_start: bool = True
    """At start, load ``autosave_name`` from ``map_dir`` when that file exists (so a node restarted
    after a crash serves the last saved map). A file that cannot be loaded is renamed aside
    (``NAME.govmap.unreadable``) and the node starts empty."""

    follow_map: str | None = None
    """Serve a read-only copy of the map of this name in ``map_dir``, saved by another node (its
    ``autosave_name``, with ``autosave_interval_s``): loaded at start and again whenever the file
    changes (:mod:`mapper.node.follower`); frames are rejected, ``save`` and ``load`` refused.
    "" (None): the node maps what it receives."""

    follow_interval_s: float = 2.0
    """How often a follower (``follow_map``) checks the file for a new save (seconds). 0.05..3600."""

    poll_interval_s: float = 0.1
    """How often the socket threads wake up to check for shutdown (seconds). 0.001..5."""

    log_level: str = "INFO"
    """Python logging level: DEBUG, INFO, WARNING, ERROR."""

    window: WindowConfig = field(default_factory=WindowConfig)
    """Keyframe window settings (TOML table ``[window]``)."""

    global_map: GlobalMapConfig = field(default_factory=GlobalMapConfig)
    """Global semantic point map settings (TOML table ``[global_map]``)."""

    queries: QueryConfig = field(default_factory=QueryConfig)
    """Semantic query settings (TOML table ``[queries]``)."""

    model: ModelRuntimeConfig = field(default_factory=ModelRuntimeConfig)
    """Learned GOV-NeSF model runtime (TOML table ``[model]``): checkpoint, device, sampling."""

    serve_model: bool = True
    """Load the learned model at start-up and serve ``render`` and ``segment_points`` method
    ``govnesf``. False = a node without torch model work (baselines and ``query_points`` only)."""

    ov_backend: OvBackendConfig = field(default_factory=OvBackendConfig)
    """In-process open-vocabulary backend (TOML table ``[ov_backend]``): features for keyframes
    without ``ov`` and the text encoder of its space. Off (kind = "") by default."""

    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    """Sparse points triangulated from posed RGB for keyframes without depth (TOML table
    ``[triangulation]``; :mod:`mapper.node.workers.triangulation`): global-map points and the
    learned model's volume bounds for RGB-only robots."""

    stereo: StereoConfig = field(default_factory=StereoConfig)
    """Dense depth by plane-sweep stereo for keyframes without depth (TOML table ``[stereo]``;
    :mod:`mapper.geometry.plane_sweep`, run by the triangulation worker after a keyframe's points):
    global-map points and the depth prior for RGB-only robots."""

    dense_flow: DenseFlowConfig = field(default_factory=DenseFlowConfig)
    """Dense points by optical flow for keyframes without depth (TOML table ``[dense_flow]``;
    :mod:`mapper.geometry.dense_flow`, worker :mod:`mapper.node.workers.flow_points`): global-map
    points for RGB-only robots. Off by default."""

    limits: LimitsConfig = field(default_factory=LimitsConfig)
    """Socket high-water marks and queue bounds (TOML table ``[limits]``)."""

    def validate(self, where: str) -> None:
        """Check ranges and cross-field rules; raise :class:`ConfigError` naming ``where``."""
        for key in ("ingest_endpoint", "query_endpoint", "events_endpoint"):
            endpoint = getattr(self, key)
            if endpoint is None:
                continue
            _check_endpoint(where, key, endpoint, self.allow_remote or bool(self.curve_dir) or self.insecure)
        endpoints = [e for e in (self.ingest_endpoint, self.query_endpoint, self.events_endpoint) if e]
        if len(set(endpoints)) != len(endpoints):
            raise ConfigError(f"{where}: ingest, query and events endpoints must differ, got {endpoints}")
        if not self.map_dir:
            raise ConfigError(f"{where}: map_dir must not be empty")
        _check_range(where, "max_message_bytes", self.max_message_bytes, 1024, 2**31 - 1)
        _check_range(where, "autosave_interval_s", self.autosave_interval_s, 0.0, 1e9)
        _check_range(where, "poll_interval_s", self.poll_interval_s, 0.001, 5.0)
        if self.log_level.upper() not in ("DEBUG", "INFO", "WARNING", "ERROR"):
            raise ConfigError(
                f"{where}: log_level {self.log_level!r} is not one of DEBUG, INFO, WARNING, ERROR"
            )
        if self.autosave_name is not None:
            try:
                validate_map_name(self.autosave_name)
            except ValueError as exc:
                raise ConfigError(f"{where}: autosave_name: {exc}") from None
        _check_range(where, "follow_interval_s", self.follow_interval_s, 0.05, 3600.0)
        if self.follow_map is not None:
            try:
                validate_map_name(self.follow_map)
            except ValueError as exc:
                raise ConfigError(f"{where}: follow_map: {exc}") from None
            if self.autosave_name is not None:
                raise ConfigError(f"{where}: follow_map {self.follow_map!r} and autosave_name "
                                  f"{self.autosave_name!r}: a follower never saves; set one of them")
        self.window.validate(where)
        self.global_map.validate(where)
        self.queries.validate(where)
        self.model.validate(where)
        self.ov_backend.validate(where)
        self.triangulation.validate(where)
        self.stereo.validate(where)
        self.dense_flow.validate(where)
        self.limits.validate(where)
        if self.ov_backend.kind and self.ov_space is not None and self.ov_space != self.ov_backend.space:
            raise ConfigError(
                f"{where}: ov_space = {self.ov_space!r} is pinned, but ov_backend.kind = "
                f"{self.ov_backend.kind!r} produces features in {self.ov_backend.space!r}; set ov_space to "
                f"{self.ov_backend.space!r} or \"\", or turn the backend off (ov_backend.kind = \"\")"
            )


# --------------------------------------------------------------------------------------------
# loading


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> NodeConfig:
    """Read a TOML file into a validated :class:`NodeConfig`, then apply ``overrides``.

    ``path=None`` uses :data:`DEFAULT_CONFIG_PATH` when it exists and the built-in defaults
    otherwise (the installed wheel ships the file; a build without it still runs).
    ``overrides`` maps dotted keys (``"window.max_keyframes"``) to values; ``None`` values are
    skipped so that unset command-line options can be passed straight through.
    """
    if path is None:
        cfg = config_from_dict({}, where="defaults")
        if DEFAULT_CONFIG_PATH.is_file():
            cfg = _load_file(DEFAULT_CONFIG_PATH)
    else:
        cfg = _load_file(Path(path))
    return apply_overrides(cfg, overrides or {})


def _load_file(path: Path) -> NodeConfig:
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"config file {str(path)!r} not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    return config_from_dict(data, where=str(path))


def config_from_dict(data: dict[str, Any], where: str = "<dict>") -> NodeConfig:
    """Build and validate a :class:`NodeConfig` from a TOML-shaped dict; ``where`` names the source."""
    cfg = _build(NodeConfig, data, where, prefix="")
    cfg.validate(where)
    return cfg


def apply_overrides(cfg: NodeConfig, overrides: dict[str, Any], where: str = "command line") -> NodeConfig:
    """Return a copy of ``cfg`` with dotted keys replaced (``{"window.max_keyframes": 5}``).

    Values are type-checked like TOML values; ``None`` values are ignored.
    """
    data = to_dict(cfg)
    for dotted, value in overrides.items():
        if value is None:
            continue
        parts = dotted.split(".")
        node: dict[str, Any] = data
        for part in parts[:-1]:
            child = node.get(part)
            if not isinstance(child, dict):
                raise ConfigError(f"{where}: unknown config key {dotted!r}")
            node = child
        if parts[-1] not in node or isinstance(node[parts[-1]], dict):
            raise ConfigError(f"{where}: unknown config key {dotted!r}")
        node[parts[-1]] = value
    new = _build(NodeConfig, data, where, prefix="")
    new.validate(where)
    return new


def to_dict(cfg: Any) -> dict[str, Any]:
    """The config as a TOML-shaped dict (None written as ""), e.g. for logging or a status reply."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            out[f.name] = to_dict(value)
        else:
            out[f.name] = "" if value is None else value
    return out


def _build(cls: type, data: dict[str, Any], where: str, prefix: str) -> Any:
    """Construct dataclass ``cls`` from ``data``, checking keys and types against its annotations."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: {prefix.rstrip('.') or 'config'} must be a table, got {data!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    for key in data:
        if key not in names:
            allowed = ", ".join(sorted(names))
            raise ConfigError(f"{where}: unknown config key {prefix + key!r} (allowed here: {allowed})")
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        hint = hints[f.name]
        key = prefix + f.name
        value = data[f.name]
        if dataclasses.is_dataclass(hint):
            kwargs[f.name] = _build(typing.cast(type, hint), value, where, prefix=key + ".")
        else:
            kwargs[f.name] = _coerce(hint, value, where, key)
    return cls(**kwargs)


def _coerce(hint: Any, value: Any, where: str, key: str) -> Any:
    """Check ``value`` against a scalar annotation (str, int, float, bool, ``X | None``)."""
    optional = False
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) != 1:
            raise ConfigError(f"{where}: {key}: unsupported annotation {hint!r}")
        hint, optional = args[0], True
    if optional and (value is None or value == ""):
        return None
    if origin is tuple and typing.get_args(hint) == (str, Ellipsis):  # a TOML list of strings
        if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
            return tuple(value)
        raise ConfigError(f"{where}: {key} must be a list of strings, got {type(value).__name__} {value!r}")
    ok: bool
    if hint is bool:
        ok = isinstance(value, bool)
    elif hint is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif hint is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if ok:
            value = float(value)
    elif hint is str:
        ok = isinstance(value, str)
    else:
        raise ConfigError(f"{where}: {key}: unsupported annotation {hint!r}")
    if not ok:
        name = getattr(hint, "__name__", str(hint))
        raise ConfigError(
            f"{where}: {key} must be {'a' if name != 'int' else 'an'} {name}"
            f"{' or empty string' if optional else ''}, got {type(value).__name__} {value!r}"
        )
    return value


def _check_range(where: str, key: str, value: float, lo: float, hi: float) -> None:
    if not lo <= value <= hi:
        raise ConfigError(f"{where}: {key} = {value!r} out of range {lo}..{hi}")


_LOOPBACK_HOSTS = {"localhost", "127.0.0.1", "::1", "[::1]"}


def _check_endpoint(where: str, key: str, endpoint: str, allow_remote: bool) -> None:
    """Accept ``tcp://HOST:PORT``, ``ipc://PATH``, ``inproc://NAME``; refuse remote binds unless allowed."""
    scheme, sep, rest = endpoint.partition("://")
    if not sep or scheme not in ("tcp", "ipc", "inproc") or not rest:
        raise ConfigError(
            f"{where}: {key} {endpoint!r} is not a ZeroMQ endpoint like tcp://127.0.0.1:5555, "
            "ipc:///tmp/mapper.sock or inproc://name"
        )
    if scheme != "tcp":
        return
    host, colon, port = rest.rpartition(":")
    if not colon or not host or not (port == "*" or (port.isdigit() and 0 < int(port) < 65536)):
        raise ConfigError(f"{where}: {key} {endpoint!r} needs a host and a port 1..65535 (tcp://HOST:PORT)")
    if allow_remote or host in _LOOPBACK_HOSTS:
        return
    try:
        if ipaddress.ip_address(host.strip("[]")).is_loopback:
            return
    except ValueError:
        pass
    raise ConfigError(
        f"{where}: {key} {endpoint!r} binds a non-loopback address; "
        "set curve_dir (authenticated, docs/how-to/robot-network.md) or allow_remote = true to expose "
        "the node"
    )
