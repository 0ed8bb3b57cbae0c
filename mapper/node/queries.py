"""Semantic queries on the map: ``query_points`` ("find the chair") and the averaging baselines of
``segment_points``. See docs/concepts/window-and-map.md for the behaviour in words.

``query_points`` works on an immutable :class:`mapper.map.global_map.GlobalMapSnapshot`:

1. each text is normalised (:func:`normalise_query`: "find the chair" -> "chair", "where is a
   place to sit?" -> "place to sit") and embedded with the map's ``ov_space`` text encoder;
   negatives (default :data:`DEFAULT_NEGATIVES`) are embedded the same way, minus any negative
   that is (nearly) one of the texts, so that asking for "wall" still works (when that leaves
   none of the negatives a request gave, e.g. negatives == texts, the default set minus the
   texts is used: with no background at all a single text would win everywhere);
2. score = cosine of each point's fused feature to its best text; a point is labelled with that
   text only if the score beats every negative's cosine and ``min_score``; the snapshot caches
   the normalised fp32 features in blocks (a new map version renormalises only the blocks whose
   rows changed), so this is one matrix product per block and query;
3. ``max_points`` keeps the best scores; object candidates are the connected components (points
   at most ``cluster_radius_m`` apart, :func:`radius_components`: a cell hash, not every point
   pair) of each text's points with at least ``min_object_points`` points, scored by the mean of
   their top half scores, sorted best first. A component whose best-scoring points fall apart
   into separate groups (the core above its ``object_split_quantile`` score quantile has two or
   more components of ``min_object_points``) is reported as those groups instead: four chairs
   around a table, all above the threshold for "chair", become four chairs, not one object
   centred on the table (:func:`split_by_score`).

``segment_points`` methods ``average`` / ``average_depth`` average the window keyframes' OV
features at the points and pick the best text (:func:`mapper.model.baselines.average_similarities`:
the cosines of the averaged features, computed per chunk without keeping the (N, D) features).

Answers from the whole map (every ``segment_points`` method, and ``render`` labels): where the
window does not see a point, :func:`fill_from_map` takes the global map's nearest point with a
fused feature within a radius (``queries.map_radius_voxels`` map voxels); for a render,
:func:`render_from_map` does the same per pixel (from the rendered surface point, or from a
z-buffered splat of the map where the render found no surface). Each answer says its source:
:data:`SOURCE_NONE`, :data:`SOURCE_WINDOW`, :data:`SOURCE_MAP` (``protocol.messages.ANSWER_SOURCES``).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import re
import sys
import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from mapper.geometry.planes import Plane, fit_planes, plane_depth, point_normals
from mapper.geometry.splat import (
    fill_holes,
    remove_speckles,
    scaled_camera,
    see_through,
    splat_points,
    splat_scale,
    upsample_nearest,
)
from mapper.map.evicted_views import EvictedViewStore
from mapper.map.global_map import GlobalMapSnapshot
from mapper.node.config import OBJECT_VOCABULARY, QueryConfig
from mapper.ov.encoders import TextEncoder
from mapper.runtime.config import ModelRuntimeConfig
from protocol.errors import ProtocolError
from protocol.messages import ObjectCandidate, Points

__all__ = [
    "AnswerCache",
    "DEFAULT_NEGATIVES",
    "NEGATIVE_DROP_SIMILARITY",
    "BlockLabelCache",
    "Cluster",
    "SOURCE_MAP",
    "SOURCE_NONE",
    "evicted_view_cosines",
    "SOURCE_WINDOW",
    "best_text",
    "blend_with_map",
    "cluster_points",
    "fill_from_map",
    "label_from_similarities",
    "label_with_texts",
    "map_surface_depth",
    "normalise_query",
    "OBJECT_VOCABULARY",
    "query_points",
    "rank_by_vocabulary",
    "vocabulary_factor",
    "render_from_map",
    "segment_average",
    "segment_average_cosines",
    "surface_depth",
]

SOURCE_NONE, SOURCE_WINDOW, SOURCE_MAP = 0, 1, 2
"""Codes of the ``source`` array of ``segmentation`` / ``render`` replies (index into
``protocol.messages.ANSWER_SOURCES``)."""

DEFAULT_NEGATIVES: tuple[str, ...] = ("wall", "floor", "ceiling", "object", "thing", "background")
"""Background prompts used when a request has no ``negatives``: the room structure that covers
most of any indoor map, plus generic words ("object", "thing", "background") that absorb points
whose feature is vague. A point must match its text better than all of these."""

NEGATIVE_DROP_SIMILARITY = 0.8
"""A negative whose embedding has at least this cosine with one of the texts is dropped (asking for
"wall" or "walls" must not be vetoed by the negative "wall")."""

_COMMAND_PREFIXES = (
    "please", "hey", "ok", "okay", "robot", "can you", "could you", "would you", "will you", "help me",
    "i want to", "i need to", "i would like to", "i'd like to", "i want", "i need", "find me", "find",
    "show me", "show", "where is", "where's", "where are", "where can i", "locate", "look for",
    "search for", "go to", "take me to", "navigate to", "bring me to", "drive to", "point to",
    "point me to", "highlight", "get", "is there", "are there", "there is", "there are",
)  # fmt: skip
_DETERMINERS = ("the", "a", "an", "my", "some", "any", "this", "that", "these", "those", "our")
_PREFIX_RE = re.compile(
    r"^(?:" + "|".join(re.escape(p) for p in sorted(_COMMAND_PREFIXES, key=len, reverse=True)) + r")\b\s*"
)
_DET_RE = re.compile(r"^(?:" + "|".join(_DETERMINERS) + r")\s+")
_TRAILING_RE = re.compile(r"(?:\s*\b(?:please|for me)\b)?[\s?!.,;:]*$")


def normalise_query(text: str) -> str:
    """Strip command words and a leading determiner from a natural phrasing, keep the noun phrase.

    >>> [normalise_query(t) for t in ["find the chair", "Where is a place to sit?", "show me the table",
    ...                              "chair", "Can you find my keys, please?", "the"]]
    ['chair', 'place to sit', 'table', 'chair', 'keys', 'the']

    Case is folded and whitespace collapsed; if nothing would remain, the folded text is kept.
    """
    folded = " ".join(text.lower().split())
    out = folded
    for _ in range(4):  # "please can you show me the ..." peels several layers
        stripped = _PREFIX_RE.sub("", out, count=1).lstrip(" ,;:")
        if stripped == out:
            break
        out = stripped
    out = _TRAILING_RE.sub("", out)
    out = _DET_RE.sub("", out, count=1)
    out = out.strip(" ,")
    return out or folded


@dataclass(frozen=True)
class Cluster:
    """One connected group of points of one text."""

    label: int
    indices: np.ndarray  # (n,) int64 into the points the clustering was given
    centroid: np.ndarray  # (3,) float64
    aabb_min: np.ndarray  # (3,) float64
    aabb_max: np.ndarray  # (3,) float64
    score: float


def _pair_components(pts: np.ndarray, radius_m: float) -> tuple[int, np.ndarray]:
    """(n_components, (N,) component) of the graph linking points within ``radius_m``, from the
    k-d tree's point pairs (the reference for :func:`radius_components`)."""
    pairs = cKDTree(pts).query_pairs(radius_m, output_type="ndarray")  # (P, 2)
    n = pts.shape[0]
    graph = coo_matrix((np.ones(pairs.shape[0], np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_comp, comp = connected_components(graph, directed=False)
    return int(n_comp), comp


def radius_components(pts: np.ndarray, radius_m: float) -> tuple[int, np.ndarray]:
    """Connected components of the graph linking points (N, 3) float64 at most ``radius_m``
    apart: (n_components, (N,) int64 component id). Points are hashed into cubic cells of side
    ``radius_m / sqrt(3)`` (all points of a cell are linked to each other); two cells up to two
    apart per axis are joined when some pair of their points is within the radius, tested in
    compiled code only while the cells are in different components
    (:func:`mapper.map.query_kernels.component_cells`). The same components as linking every
    point pair (``_pair_components``); ids in order of each component's first cell."""
    from mapper.map.query_kernels import component_cells  # numba: compiled or loaded when first used

    n = pts.shape[0]
    if n == 0:
        return 0, np.zeros(0, np.int64)
    side = radius_m / np.sqrt(3.0) * (1.0 - 1e-9)
    cell = np.floor(pts / side).astype(np.int64)
    cell -= cell.min(axis=0) - 2  # >= 2: neighbours up to 2 cells away keep distinct keys
    dims = cell.max(axis=0) + 3
    if float(np.prod(dims.astype(np.float64))) >= 2.0**62:  # keys would overflow int64: every point pair
        return _pair_components(pts, radius_m)
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")  # points grouped by cell, cells in key order
    sorted_key = key[order]
    first = np.empty(n, bool)
    first[0] = True
    np.not_equal(sorted_key[1:], sorted_key[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    counts = np.diff(np.append(starts, n))
    point_cell = np.empty(n, np.int64)
    point_cell[order] = np.cumsum(first) - 1
    n_comp, cell_label = component_cells(pts[order], sorted_key[starts], dims, starts, counts, radius_m)
    return n_comp, cell_label[point_cell]


def support_factor(n_points: int, support_points: float) -> float:
    """``1 - exp(-n_points / support_points)`` in (0, 1): how much of an object's score a cluster
    of ``n_points`` keeps (1 when ``support_points`` <= 0: no discount)."""
    if support_points <= 0:
        return 1.0
    return float(-np.expm1(-n_points / support_points))


def cluster_points(
    xyz: np.ndarray,  # (N, 3) float32 world metres
    score: np.ndarray,  # (N,) float32
    label: np.ndarray,  # (N,) int labels (>= 0)
    radius_m: float,
    min_points: int,
    *,
    support_points: float = 0.0,
    split_quantile: float = 0.0,
    split_depth: int = 0,
    split_max_points: int = 0,
    split_clean_share: float = 0.9,
    reference: bool = False,
) -> list[Cluster]:
    """Connected components per label (points at most ``radius_m`` apart are linked), keeping the
    components with at least ``min_points`` points; each scored by the mean of its top half of
    scores, times ``1 - exp(-n / support_points)`` for a component of n points when
    ``support_points`` > 0 (:func:`support_factor`). With ``split_quantile`` > 0 and
    ``split_depth`` > 0, a component (of at most ``split_max_points`` points when > 0) whose
    high-scoring core falls apart is replaced by the parts (:func:`split_by_score`). Sorted by
    score, best first. The components come from :func:`radius_components`; ``reference=True``
    takes them from every point pair of a k-d tree, as before (for tests)."""
    if split_quantile > 0 and split_depth > 0:
        whole = cluster_points(xyz, score, label, radius_m, min_points, support_points=support_points,
                               reference=reference)
        return split_by_score(xyz, score, whole, radius_m, min_points, split_quantile, split_depth,
                              support_points=support_points, max_points=split_max_points,
                              clean_share=split_clean_share)
    out: list[Cluster] = []
    if reference:
        return _cluster_points_reference(xyz, score, label, radius_m, min_points, support_points)
    for lab in np.unique(label):
        idx = np.flatnonzero(label == lab)
        if idx.size < min_points:
            continue
        pts = xyz[idx].astype(np.float64)
        n_comp, comp = radius_components(pts, radius_m)
        sizes = np.bincount(comp, minlength=n_comp)
        big = sizes >= min_points
        if not big.any():
            continue
        keep = big[comp]
        members_all = np.flatnonzero(keep)
        members_all = members_all[np.argsort(comp[members_all], kind="stable")]  # by component, ascending
        bounds = np.cumsum(sizes[big])
        for members in np.split(members_all, bounds[:-1]):
            out.append(_scored_cluster(int(lab), idx[members], xyz, score, support_points))
    out.sort(key=lambda c: (-c.score, -c.indices.size))
    return out


def vocabulary_factor(
    mean_feat: np.ndarray,  # (K, D) float32 unit rows: each object's mean feature
    text_emb: np.ndarray,  # (K, D) float32 unit rows: the text each object was found for
    vocab_emb: np.ndarray,  # (V, D) float32 unit rows: what an object may be instead
    temperature: float,
) -> np.ndarray:
    """(K,) float32 in (0, 1]: ``exp(min(0, margin) / temperature)``, the margin being the cosine of
    an object's mean feature with its text minus its best cosine with a vocabulary word. 1 where
    the text explains the object at least as well as every other word (or no word is given); a
    sofa found for "chair" (its feature nearer "sofa" than "chair" by 0.1) keeps exp(-0.1 / T).

    >>> import numpy as np
    >>> e = np.eye(3, dtype=np.float32)
    >>> sofa_like = np.array([[0.6, 0.8, 0.0]], np.float32)   # found for text e0, nearer word e1
    >>> [round(float(f), 3) for f in vocabulary_factor(sofa_like, e[:1], e[1:2], 0.1)]
    [0.135]
    >>> vocabulary_factor(e[:1], e[:1], e[1:2], 0.1).tolist()
    [1.0]
    """
    if vocab_emb.shape[0] == 0 or mean_feat.shape[0] == 0:
        return np.ones(mean_feat.shape[0], np.float32)
    own = np.einsum("kd,kd->k", mean_feat, text_emb)
    other = (mean_feat @ vocab_emb.T).max(axis=1)
    return np.exp(np.minimum(0.0, own - other) / np.float32(temperature)).astype(np.float32)


def rank_by_vocabulary(
    clusters: Sequence[Cluster],
    feat: np.ndarray,  # (N, D) unit rows (float16/32) of the points the clusters index
    text_emb: np.ndarray,  # (T, D) float32 unit rows, by Cluster.label
    vocab_emb: np.ndarray,  # (V, D) float32 unit rows
    temperature: float,
) -> list[Cluster]:
    """The clusters with their scores times :func:`vocabulary_factor` of their mean features,
    sorted best first (``queries.object_vocabulary``)."""
    if not clusters or vocab_emb.shape[0] == 0 or temperature <= 0:
        return list(clusters)
    means = np.stack([np.asarray(feat[c.indices], np.float32).mean(axis=0) for c in clusters])
    means /= np.maximum(np.linalg.norm(means, axis=1, keepdims=True), np.float32(1e-12))
    own = text_emb[np.array([c.label for c in clusters])]
    factor = vocabulary_factor(means, own, vocab_emb, temperature)
    out = [dataclasses.replace(c, score=float(c.score * f)) for c, f in zip(clusters, factor, strict=True)]
    out.sort(key=lambda c: (-c.score, -c.indices.size))
    return out


def _scored_cluster(
    label: int, members: np.ndarray, xyz: np.ndarray, score: np.ndarray, support_points: float
) -> Cluster:
    """A :class:`Cluster` of ``members`` (n,) int64 rows of ``xyz`` (N, 3) / ``score`` (N,): centroid,
    box, and the mean of its top half of scores times :func:`support_factor`."""
    p = xyz[members].astype(np.float64)
    s = np.sort(score[members])[::-1]
    top = s[: max(1, (s.size + 1) // 2)]
    return Cluster(int(label), members, p.mean(axis=0), p.min(axis=0), p.max(axis=0),
                   float(top.mean()) * support_factor(members.size, support_points))


def split_by_score(
    xyz: np.ndarray,  # (N, 3) float32 world metres
    score: np.ndarray,  # (N,) float32
    clusters: Sequence[Cluster],  # of these points (cluster_points)
    radius_m: float,
    min_points: int,
    quantile: float,
    depth: int,
    *,
    support_points: float = 0.0,
    max_points: int = 0,
    clean_share: float = 0.9,
) -> list[Cluster]:
    """Clusters whose best-scoring points form separate groups, split into those groups.

    For a cluster of at least ``2 * min_points`` points (and at most ``max_points`` when > 0:
    larger ones are room-scale surfaces, whose split would cost a pass over half their points and
    name no object), its core is the points scoring at least its ``quantile`` score quantile
    (0.5: the top half); when the core's own components (points at most ``radius_m`` apart)
    include two or more of at least ``min_points`` points, the cluster is replaced by those
    components (core points only: the weaker points between them, a table between chairs, belong
    to neither). A core that stays in one piece (or splits into one big part and crumbs) is cut
    again at its own quantile (the top quarter, eighth, ...: a chair pushed against a desk that
    also scores for "chair" stays joined to it in the top half, and parts in a stricter core),
    where a split counts only if its parts hold at least ``clean_share`` of that core's points (a
    clean break into a few pieces; the top eighth of one large object with noisy scores falls into
    dust, 50-75% of it in parts of ``min_points``); cores and the parts' own splits take at most
    ``depth`` cuts in all. A cluster none of whose cores falls apart is kept whole. Scores as
    :func:`cluster_points`; sorted best first.

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> seats = [rng.normal(c, 0.02, (40, 3)) for c in ((0, 0, 0), (0.6, 0, 0))]   # two chairs
    >>> between = np.stack([np.linspace(0, 0.6, 40), np.zeros(40), np.zeros(40)], 1)  # a table
    >>> xyz = np.concatenate(seats + [between]).astype(np.float32)
    >>> score = np.r_[np.full(80, 0.9), np.full(40, 0.5)].astype(np.float32)
    >>> whole = cluster_points(xyz, score, np.zeros(120, np.int64), 0.12, 15)
    >>> len(whole), [len(c.indices) for c in split_by_score(xyz, score, whole, 0.12, 15, 0.5, 3)]
    (1, [40, 40])
    """
    if not 0.0 < quantile < 1.0:
        raise ValueError(f"quantile {quantile} must be in (0, 1)")
    out: list[Cluster] = []
    todo = [(c, depth) for c in clusters]
    while todo:
        cluster, left = todo.pop()
        members = cluster.indices
        if left <= 0 or members.size < 2 * min_points or 0 < max_points < members.size:
            out.append(cluster)
            continue
        core, split, stricter = members, False, False
        while left > 0 and not split:  # ever stricter cores (the quantile of the last one)
            left -= 1
            s = score[core]
            core = core[s >= np.quantile(s, quantile)]
            if core.size < 2 * min_points:
                break
            n_comp, comp = radius_components(xyz[core].astype(np.float64), radius_m)
            sizes = np.bincount(comp, minlength=n_comp)
            parts = np.flatnonzero(sizes >= min_points)
            split = parts.size >= 2 and (not stricter or sizes[parts].sum() >= clean_share * core.size)
            stricter = True
            for part in parts if split else ():
                sub = _scored_cluster(cluster.label, core[comp == part], xyz, score, support_points)
                todo.append((sub, left))
        if not split:
            out.append(cluster)  # no core fell apart (or only into one part and crumbs): as it was
    out.sort(key=lambda c: (-c.score, -c.indices.size))
    return out


def _cluster_points_reference(
    xyz: np.ndarray,  # (N, 3) float32 world metres
    score: np.ndarray,  # (N,) float32
    label: np.ndarray,  # (N,) int labels (>= 0)
    radius_m: float,
    min_points: int,
    support_points: float = 0.0,
) -> list[Cluster]:
    """The previous :func:`cluster_points` (k-d tree point pairs, one pass per component)."""
    out: list[Cluster] = []
    for lab in np.unique(label):
        idx = np.flatnonzero(label == lab)
        if idx.size < min_points:
            continue
        pts = xyz[idx].astype(np.float64)
        pairs = cKDTree(pts).query_pairs(radius_m, output_type="ndarray")  # (P, 2)
        graph = coo_matrix(
            (np.ones(pairs.shape[0], np.int8), (pairs[:, 0], pairs[:, 1])), shape=(idx.size, idx.size)
        )
        n_comp, comp = connected_components(graph, directed=False)
        sizes = np.bincount(comp, minlength=n_comp)
        for c in np.flatnonzero(sizes >= min_points):
            members = np.flatnonzero(comp == c)
            p = pts[members]
            s = np.sort(score[idx[members]])[::-1]
            top = s[: max(1, (s.size + 1) // 2)]
            cluster = Cluster(
                int(lab), idx[members], p.mean(axis=0), p.min(axis=0), p.max(axis=0),
                float(top.mean()) * support_factor(members.size, support_points),
            )
            out.append(cluster)
    out.sort(key=lambda c: (-c.score, -c.indices.size))
    return out


def label_with_texts(
    features: np.ndarray,  # (N, D) float32 unit rows (zero rows = no feature)
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    negative_emb: np.ndarray,  # (Q, D) float32 unit rows (Q may be 0)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best text per point, its cosine, and whether it beats every negative:
    (label (N,) int64, score (N,) float32, beats_negatives (N,) bool)."""
    sims = features @ np.concatenate([text_emb, negative_emb]).T  # (N, T + Q): one product
    return label_from_similarities(sims, text_emb.shape[0])


def label_from_similarities(
    sims: np.ndarray,  # (N, T + Q) float32 cosines to the T texts, then the Q negatives
    n_texts: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`label_with_texts` from the cosines: (label (N,) int64, score (N,) float32,
    beats_negatives (N,) bool)."""
    label = np.argmax(sims[:, :n_texts], axis=1)
    score = sims[np.arange(sims.shape[0]), label].astype(np.float32)
    if sims.shape[1] > n_texts:
        beats = score > sims[:, n_texts:].max(axis=1)
    else:
        beats = np.ones(score.shape[0], bool)
    return label, score, beats


_LabelEntry = tuple["weakref.ReferenceType[np.ndarray]", np.ndarray, np.ndarray, np.ndarray]
"""A :class:`BlockLabelCache` entry: (the block, label, score, beats_negatives)."""
_LabelResult = tuple[np.ndarray, np.ndarray, np.ndarray]
"""A block's (label, score, beats_negatives)."""


class BlockLabelCache:
    """The scoring step of :func:`query_points` per block of unit features, kept across map
    versions: (label, score, beats_negatives) of each block of
    :meth:`GlobalMapSnapshot.unit_feature_blocks` for one set of text + negative embeddings. A new
    snapshot shares the blocks whose rows did not change, so a query after an integrate scores only
    the changed blocks, and of a block copied from a scored one with a few rows normalised again
    (:meth:`GlobalMapSnapshot.unit_block_patches`) only those rows (every row is scored by
    :func:`mapper.map.query_kernels.row_cosines`, whose bits do not depend on the other rows); a
    repeated query scores nothing.

    Entries are keyed by the block's token (:meth:`GlobalMapSnapshot.unit_block_tokens`) and the
    embeddings' bytes and hold their block weakly: the cache never keeps a block of an old map
    version alive. When a block is freed its entry is retired (the results only, no block), kept
    for the next snapshot's patched copies of it, at most as many retired entries as the last
    scored snapshot had blocks. Least recently used live entries beyond ``max_blocks`` are
    dropped. Thread-safe; 0 blocks = no caching."""

    def __init__(self, max_blocks: int) -> None:
        self.max_blocks = max_blocks
        self._entries: OrderedDict[tuple[int, bytes], _LabelEntry] = OrderedDict()
        self._retired: OrderedDict[tuple[int, bytes], _LabelResult] = OrderedDict()
        self._max_retired = 0
        self._lock = threading.RLock()  # reentrant: a weakref callback may run while it is held
        self.hits = 0
        self.misses = 0
        self.patched = 0
        """Misses answered by rescoring only the changed rows of a copy of a scored block."""

    def __len__(self) -> int:
        """Live entries (their blocks are in use)."""
        return len(self._entries)

    @property
    def retired(self) -> int:
        """Entries of freed blocks kept for patching."""
        return len(self._retired)

    def _forget(self, key: tuple[int, bytes], ref: weakref.ReferenceType[np.ndarray]) -> None:
        """A block was freed: retire its entry."""
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None and entry[0] is ref:
                del self._entries[key]
                if self._max_retired > 0:
                    self._retired[key] = entry[1:]
                    while len(self._retired) > self._max_retired:
                        self._retired.popitem(last=False)

    def _results(self, key: tuple[int, bytes]) -> _LabelResult | None:
        entry = self._entries.get(key)
        if entry is not None:
            return entry[1:]
        return self._retired.get(key)

    def label(
        self,
        snapshot: GlobalMapSnapshot,
        emb: np.ndarray,  # (T + Q, D) float32 unit rows: the texts, then the negatives
        n_texts: int,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`label_from_similarities` of the snapshot's cosines with ``emb``: (label (N,)
        int64, score (N,) float32, beats_negatives (N,) bool), equal to scoring every row now."""
        from mapper.map.query_kernels import row_cosines  # numba: compiled or loaded when first used

        emb = np.ascontiguousarray(emb, np.float32)
        digest = hashlib.blake2b(emb.tobytes() + n_texts.to_bytes(4, "little"), digest_size=16).digest()
        parts = []
        blocks = snapshot.unit_feature_blocks()
        tokens = snapshot.unit_block_tokens()
        patches = snapshot.unit_block_patches()
        with self._lock:
            self._max_retired = len(blocks) if self.max_blocks > 0 else 0
        for block, token, patch in zip(blocks, tokens, patches, strict=True):
            key = (token, digest)
            with self._lock:
                entry = self._entries.get(key)
                if entry is not None and entry[0]() is block:
                    self._entries.move_to_end(key)
                    self.hits += 1
                    parts.append(entry[1:])
                    continue
                parent = None if patch is None else self._results((patch[0], digest))
            if parent is not None and patch is not None:  # rescore only the block's changed rows
                rows = patch[1]
                label, score, beats = (a.copy() for a in parent)
                sims = row_cosines(block, emb, rows)  # (rows, T + Q)
                label[rows], score[rows], beats[rows] = label_from_similarities(sims, n_texts)
                result = (label, score, beats)
            else:  # (rows, T + Q); a map without features (D = 0) scores 0
                sims = (row_cosines(block, emb) if block.shape[1]
                        else np.zeros((block.shape[0], emb.shape[0]), np.float32))
                label, score, beats = label_from_similarities(sims, n_texts)
                result = (label.astype(np.int16), score, beats)  # at most 64 texts: 112 KB a full block
            parts.append(result)
            with self._lock:
                self.misses += 1
                self.patched += parent is not None
                if self.max_blocks > 0:
                    self._entries[key] = (weakref.ref(block, functools.partial(self._forget, key)), *result)
                    self._entries.move_to_end(key)
                    while len(self._entries) > self.max_blocks:
                        self._entries.popitem(last=False)
        if not parts:
            return np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, bool)
        label, score, beats = (np.concatenate([p[i] for p in parts]) for i in range(3))
        return label.astype(np.int64), score, beats


AnswerKey = tuple[
    tuple[str, ...], tuple[str, ...] | None, float | None, int | None, bool,
    tuple[tuple[float, ...], tuple[float, ...]] | None,
]
"""What makes two ``query_points`` requests the same question: texts, negatives, min_score,
max_points, objects, region (:func:`answer_key`)."""


def answer_key(
    texts: Sequence[str],
    negatives: Sequence[str] | None,
    min_score: float | None,
    max_points: int | None,
    objects: bool,
    region: tuple[np.ndarray, np.ndarray] | None = None,  # ((3,), (3,)) world box, metres
) -> AnswerKey:
    """The :class:`AnswerCache` key of a ``query_points`` request."""
    negs = None if negatives is None else tuple(negatives)
    box = None if region is None else (tuple(float(x) for x in region[0]), tuple(float(x) for x in region[1]))
    return (tuple(texts), negs, min_score, max_points, bool(objects), box)


@dataclass(frozen=True)
class _CachedAnswer:
    points: Points
    version: int  # GlobalMapSnapshot.version the answer was computed on
    generation: int  # GlobalMapSnapshot.generation
    taken_s: float  # monotonic time the snapshot was taken
    nbytes: int  # the answer's arrays (and a little per object)


class AnswerCache:
    """Recent ``query_points`` answers, so that a planner asking the same question again and again
    while the robot streams is answered at once instead of recomputing per map version.

    :meth:`get` returns a cached answer when it was computed on the current map version (the
    same answer a new computation would give), or, with ``max_age_s > 0``, on an older version
    of the same map (same generation: no ``load`` or ``clear`` since) at most ``max_age_s``
    seconds ago: a *stale* answer, which the node returns at once (only while frames are
    arriving) and recomputes in the background (stale-while-revalidate). Replies say which
    (``timing_ms``: ``answer_reused``, ``answer_age_ms``; ``map_version`` is the version the
    answer describes). Least recently used questions beyond ``max_entries`` answers or
    ``max_bytes`` of their arrays are dropped (an answer larger than ``max_bytes`` is not kept).
    Thread-safe."""

    def __init__(self, max_age_s: float, max_entries: int, max_bytes: int = 64 << 20) -> None:
        self.max_age_s = max_age_s
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self._entries: OrderedDict[AnswerKey, _CachedAnswer] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.counts = {"computed": 0, "reused_same_version": 0, "reused_stale": 0}

    def __len__(self) -> int:
        return len(self._entries)

    def get(
        self, key: AnswerKey, version: int, generation: int, now_s: float, *, allow_stale: bool = True
    ) -> tuple[Points, float, bool] | None:
        """(answer, age_s, stale) for the question ``key`` on the map at ``version`` /
        ``generation``, or None when it must be computed (``allow_stale=False``: unless the answer
        is of this very version). The answer is a shallow copy with its own ``id`` (None) and
        ``timing_ms`` (``answer_reused`` 1, ``answer_age_ms``)."""
        with self._lock:
            entry = self._entries.get(key)
            if entry is None or entry.generation != generation or entry.version > version:
                return None
            age = max(0.0, now_s - entry.taken_s)
            stale = entry.version != version
            if stale and (not allow_stale or age > self.max_age_s):
                return None
            self._entries.move_to_end(key)
            self.counts["reused_stale" if stale else "reused_same_version"] += 1
        out = copy.copy(entry.points)
        out.id = None
        out.timing_ms = {
            **entry.points.timing_ms, "answer_reused": 1.0, "answer_age_ms": 1e3 * age,
            "computed_total": entry.points.timing_ms.get("total", 0.0),
        }  # fmt: skip
        return out, age, stale

    def current(self, key: AnswerKey, version: int, generation: int) -> bool:
        """Whether the cached answer to ``key`` was computed on this very map version."""
        with self._lock:
            entry = self._entries.get(key)
            return entry is not None and entry.version == version and entry.generation == generation

    def put(self, key: AnswerKey, points: Points, version: int, generation: int, taken_s: float) -> None:
        """Keep ``points`` (computed on a snapshot taken at ``taken_s``) unless a newer answer to
        the same question is already cached; marks it ``answer_reused`` 0."""
        points.timing_ms.setdefault("answer_reused", 0.0)
        points.timing_ms.setdefault("answer_age_ms", 0.0)
        size = _answer_bytes(points)
        with self._lock:
            self.counts["computed"] += 1
            if self.max_entries <= 0 or size > self.max_bytes:
                self._drop(key)
                return
            old = self._entries.get(key)
            if old is not None and old.generation == generation and old.version > version:
                return  # a refresh that finished after a newer computation
            self._drop(key)
            self._entries[key] = _CachedAnswer(points, version, generation, taken_s, size)
            self._bytes += size
            while len(self._entries) > self.max_entries or self._bytes > self.max_bytes:
                self._drop(next(iter(self._entries)))

    def _drop(self, key: AnswerKey) -> None:
        old = self._entries.pop(key, None)
        if old is not None:
            self._bytes -= old.nbytes

    def stats(self) -> dict[str, int]:
        with self._lock:
            return {**self.counts, "entries": len(self._entries), "bytes": self._bytes}


def _answer_bytes(points: Points) -> int:
    arrays = points.xyz.nbytes + points.score.nbytes + points.label.nbytes
    return int(arrays) + 256 * (1 + len(points.objects))


def query_points(
    snapshot: GlobalMapSnapshot,
    encoder: TextEncoder,
    texts: Sequence[str],
    *,
    negatives: Sequence[str] | None,
    min_score: float | None,
    max_points: int | None,
    objects: bool,
    config: QueryConfig,
    label_cache: BlockLabelCache | None = None,
    region: tuple[np.ndarray, np.ndarray] | None = None,  # ((3,), (3,)) world box, metres
) -> Points:
    """Answer a ``query_points`` request on a map snapshot (see the module docstring). With a
    ``label_cache`` the scoring reuses the per-block results of earlier queries with the same
    texts and negatives (the same answer as scoring every row). With ``region`` only the map points
    inside that axis-aligned box (its faces included) match, before ``max_points`` and the objects.

    Raises:
        ProtocolError("not_ready"): the map has no points with OV features yet.
    """
    t0 = time.perf_counter()
    if snapshot.feat is None or snapshot.n_with_features == 0:
        raise ProtocolError(
            "not_ready",
            f"the global map has {len(snapshot)} points and none carries an open-vocabulary feature: "
            "send frames with depth and ov (features in the map's ov_space) before semantic queries",
        )
    if snapshot.feat.shape[1] != encoder.dim:
        raise ProtocolError(
            "not_ready",
            f"the map's features have dimension {snapshot.feat.shape[1]} but the text encoder of "
            f"{encoder.space!r} produces {encoder.dim}; queries cannot be embedded in this map's space",
        )
    clean = [normalise_query(t) for t in texts]
    text_emb = encoder.encode(clean)  # (T, D)
    negs = list(DEFAULT_NEGATIVES if negatives is None else negatives)
    negs = [normalise_query(n) for n in negs]
    neg_emb = encoder.encode(negs) if negs else np.zeros((0, text_emb.shape[1]), np.float32)
    if neg_emb.shape[0]:
        keep_neg = (neg_emb @ text_emb.T).max(axis=1) < NEGATIVE_DROP_SIMILARITY
        neg_emb = neg_emb[keep_neg]
        if neg_emb.shape[0] == 0 and negatives is not None:
            # every negative given names a text (e.g. negatives == texts): with no background left,
            # a single text would win at every map point; fall back to the default set
            defaults = encoder.encode([normalise_query(n) for n in DEFAULT_NEGATIVES])
            neg_emb = defaults[(defaults @ text_emb.T).max(axis=1) < NEGATIVE_DROP_SIMILARITY]
    t1 = time.perf_counter()

    snapshot.unit_feature_blocks()  # cached per map version; unchanged blocks shared with the last
    t2 = time.perf_counter()
    emb = np.concatenate([text_emb, neg_emb])  # (T + Q, D)
    if label_cache is not None:  # changed blocks only
        label, score, beats = label_cache.label(snapshot, emb, text_emb.shape[0])
    else:
        sims = snapshot.similarities(emb)  # (N, T + Q): one product per block
        label, score, beats = label_from_similarities(sims, text_emb.shape[0])
    ok = beats & snapshot.has_feature
    if min_score is not None:
        ok &= score >= min_score
    if region is not None:
        low, high = np.asarray(region[0], np.float64), np.asarray(region[1], np.float64)
        ok &= np.all((snapshot.xyz >= low) & (snapshot.xyz <= high), axis=1)
    sel = np.flatnonzero(ok)
    t3 = time.perf_counter()

    candidates: list[ObjectCandidate] = []
    if objects and sel.size:
        clusters = cluster_points(
            snapshot.xyz[sel], score[sel], label[sel], config.cluster_radius_m, config.min_object_points,
            support_points=config.object_support_points, split_quantile=config.object_split_quantile,
            split_depth=config.object_split_depth, split_max_points=config.object_split_max_points,
            split_clean_share=config.object_split_clean_share,
        )
        ranked = config.object_vocabulary_temperature > 0 and config.object_vocabulary
        if ranked and snapshot.feat is not None:
            vocab = [normalise_query(w) for w in config.object_vocabulary]
            vocab_emb = np.asarray(encoder.encode(vocab), np.float32)
            # words that name a text asked for are not an alternative to it
            vocab_emb = vocab_emb[(vocab_emb @ text_emb.T).max(axis=1) < NEGATIVE_DROP_SIMILARITY]
            clusters = rank_by_vocabulary(clusters, snapshot.feat[sel], np.asarray(text_emb, np.float32),
                                          vocab_emb, config.object_vocabulary_temperature)
        for c in clusters[: config.max_objects]:
            candidates.append(
                ObjectCandidate(
                    text=texts[c.label],
                    centroid=c.centroid,
                    aabb_min=c.aabb_min,
                    aabb_max=c.aabb_max,
                    score=c.score,
                    n_points=int(c.indices.size),
                )
            )
    t4 = time.perf_counter()

    limit = max_points if max_points is not None else config.default_max_points
    if sel.size > limit:
        top = np.argpartition(-score[sel], limit - 1)[:limit]
        sel = sel[top]
    sel = sel[np.argsort(-score[sel], kind="stable")]
    t5 = time.perf_counter()
    return Points(
        map_version=snapshot.map_version,
        xyz=snapshot.xyz[sel].astype(np.float32),
        score=score[sel],
        label=label[sel].astype(np.int32),
        objects=candidates,
        timing_ms={
            "encode_text": 1e3 * (t1 - t0),
            "features": 1e3 * (t2 - t1),
            "score": 1e3 * (t3 - t2),
            "cluster": 1e3 * (t4 - t3),
            "select": 1e3 * (t5 - t4),
            "total": 1e3 * (t5 - t0),
            "map_points": float(len(snapshot)),
        },
    )


def segment_average(
    xyz: np.ndarray,  # (N, 3) float32 world metres
    views: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int], np.ndarray | None]],
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    *,
    use_depth: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenScene-2D averaging baseline: (label (N,) int32, -1 where no view counts; score (N,)
    float32 cosine of the chosen label, 0 where -1; n_views (N,) int64). ``views`` are
    ``(ov (h, w, D), K (4,), world_from_cam (4, 4), (W, H), depth_m (H, W) | None)``."""
    cos, n = segment_average_cosines(xyz, views, text_emb, use_depth=use_depth)
    label, score = best_text(cos, n > 0)
    return label, score, n


def segment_average_cosines(
    xyz: np.ndarray,  # (N, 3) float32 world metres
    views: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int], np.ndarray | None]],
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    *,
    use_depth: bool,
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,  # (P, D) f32, (N,) i64, (N,) f32
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`segment_average` before the choice of a text: (cosines (N, T) float32 of the averaged
    feature with each text, zero rows where nothing counts; n_views (N,) int64, the given views that
    counted). ``prior``: views no longer given, as running means per point
    (:func:`mapper.kernels.average.average_similarities`; the node's evicted keyframes,
    :mod:`mapper.map.evicted_views`). Numpy and the compiled kernel: no torch."""
    from mapper.kernels.average import average_similarities

    torch = sys.modules.get("torch")  # the node's compute threads where torch is loaded, as the model's
    threads = int(torch.get_num_threads()) if torch is not None else 0
    return average_similarities(xyz, list(views), text_emb, use_depth=use_depth, prior=prior, threads=threads)


COHERENT_PAIR_SHARE = 0.5
""":func:`spatial_order` leaves points in their order when at least this share of the consecutive
pairs (0, 1), (2, 3), ... lie within one cell of each other."""


def spatial_order(
    xyz: np.ndarray,  # (N, 3) float32 world metres, finite
    cell_m: float,
) -> np.ndarray | None:  # (N,) int64 permutation, or None
    """The order in which to answer ``segment_points``' points: None (their own order) where they
    already come spatially coherent (at least ``COHERENT_PAIR_SHARE`` of the consecutive pairs
    within ``cell_m`` of each other, e.g. pixels of a depth image in raster order), else the
    permutation that sorts them along a Z-order (Morton) curve of cells of side ``cell_m``
    (stable within a cell). The answering kernels sum neighbouring points together and read the
    OV taps they share once (:func:`mapper.kernels.average_kernel.accumulate_taps`); each point's
    answer does not depend on the order.

    >>> pts = np.array([[0.0, 0, 0], [5, 5, 5], [0.01, 0, 0], [5.01, 5, 5]], np.float32)
    >>> spatial_order(pts, 0.05).tolist()
    [0, 2, 1, 3]
    >>> spatial_order(pts[[0, 2, 1, 3]], 0.05) is None
    True
    """
    n = xyz.shape[0]
    if n < 4:
        return None
    pts = np.asarray(xyz, np.float64)
    step = pts[1 : 2 * (n // 2) : 2] - pts[0 : 2 * (n // 2) : 2]
    if np.mean(np.einsum("ij,ij->i", step, step) <= cell_m * cell_m) >= COHERENT_PAIR_SHARE:
        return None
    from mapper.map.query_kernels import morton_codes  # numba: compiled or loaded when first used

    return np.argsort(morton_codes(pts, pts.min(axis=0), cell_m), kind="stable")


def best_text(
    cos: np.ndarray,  # (N, T) float32 cosines
    seen: np.ndarray,  # (N,) bool: rows that have an answer
) -> tuple[np.ndarray, np.ndarray]:
    """(label (N,) int32 argmax text, -1 where not ``seen``; score (N,) float32 its cosine, 0 there).

    >>> best_text(np.array([[0.1, 0.7], [0.5, 0.2]], np.float32), np.array([True, False]))
    (array([ 1, -1], dtype=int32), array([0.7, 0. ], dtype=float32))
    """
    seen = np.asarray(seen, bool)
    if cos.shape[0] == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.float32)
    label = np.argmax(cos, axis=1).astype(np.int32)
    score = np.take_along_axis(cos, label[:, None].astype(np.int64), axis=1)[:, 0].astype(np.float32)
    label[~seen] = -1
    score[~seen] = 0.0
    return label, score


_MAP_COSINES_MAX_BYTES = 64 << 20
"""Largest (map rows x texts) cosine array a snapshot keeps for the map's answers."""


def _map_similarities(
    snapshot: GlobalMapSnapshot,
    rows: np.ndarray,  # (n,) int64 map rows that carry a feature
    text_emb: np.ndarray,  # (T, D) float32 unit rows
) -> np.ndarray:  # (n, T) float32
    """Cosines of map rows' features with the texts (the rows' fp16 features, normalised, up to
    float32 rounding): from the snapshot's cosines of every row with these texts when it keeps them
    or when computing them all costs about what the request needs (the map has at most twice as
    many rows as are asked for, within ``_MAP_COSINES_MAX_BYTES``; they are then kept for the next
    request, :meth:`GlobalMapSnapshot.similarities_cached`); else of the distinct rows asked for
    only (:meth:`GlobalMapSnapshot.row_similarities`)."""
    kept = snapshot.similarities_cached(text_emb, compute=False)
    if kept is not None:
        return kept[rows]
    n_map = len(snapshot)
    if n_map <= 2 * rows.shape[0] and n_map * text_emb.shape[0] * 4 <= _MAP_COSINES_MAX_BYTES:
        whole = snapshot.similarities_cached(text_emb)
        assert whole is not None
        return whole[rows]
    uniq, inverse = np.unique(rows, return_inverse=True)
    return snapshot.row_similarities(uniq, text_emb)[inverse.ravel()]


def _map_compatible(snapshot: GlobalMapSnapshot, text_emb: np.ndarray) -> bool:
    feat = snapshot.feat
    return feat is not None and snapshot.n_with_features > 0 and feat.shape[1] == text_emb.shape[1]


def map_more_confident(
    map_label: np.ndarray,  # (...) int: the map's best text
    map_score: np.ndarray,  # (...) float: its cosine
    label: np.ndarray,  # (...) int: the window's answer
    score: np.ndarray,  # (...) float: its cosine
) -> np.ndarray:  # (...) bool
    """The ``queries.map_when_more_confident`` rule: the map names another text than the window,
    with a higher cosine (a tie, or the same text, keeps the window's answer)."""
    return (map_label != label) & (map_score > score)


def fill_from_map(
    snapshot: GlobalMapSnapshot,
    xyz: np.ndarray,  # (N, 3) float32 world metres
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    label: np.ndarray,  # (N,) int32 the window's labels (-1 = unseen)
    score: np.ndarray,  # (N,) float32 the window's scores
    window_seen: np.ndarray,  # (N,) bool: the window answered the point
    radius_m: float,
    *,
    more_confident: bool = False,
    window_cos: np.ndarray | None = None,  # (N, T) float32 the window's cosines (rows where seen)
    blend: float = 0.0,
    nearest: np.ndarray | None = None,  # (N,) int64 snapshot.nearest_with_feature(xyz, radius_m), if known
    map_cos: tuple[np.ndarray, np.ndarray] | None = None,  # ((N, T) float32 cosines, (N,) bool where given)
    map_cos_weight: float = 1.0,
    out_cos: np.ndarray | None = None,  # (N, T) float32: filled with the answers' cosines (see below)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Answer the points the window did not from the map: (label (N,) int32, score (N,) float32,
    source (N,) uint8). A point the window saw keeps the window's answer (``SOURCE_WINDOW``); an
    unseen one takes the best text of the nearest map point carrying a feature within
    ``radius_m`` (``SOURCE_MAP``: its cosine as score), else -1 / 0 (``SOURCE_NONE``).

    A point both answer: with ``blend`` > 0 and ``window_cos`` given, the best text of the blended
    cosines (:func:`blend_with_map`, ``queries.map_blend``); else with ``more_confident``, the map's
    answer where the map names another text with a higher cosine than the window's score (views
    that left the window saw it better than the ones in it; where both name the same text the
    window's answer stays); else the window's. A map whose feature dimension is not the texts'
    answers nothing. ``nearest``: every point's nearest map row, when the caller looked it up
    already. ``map_cos``: the map's cosines for some points, used instead of their nearest map
    row's fused feature where that row exists (:func:`evicted_view_cosines`: the views of the
    keyframes that left the window, at the row's voxel), mixed with the row's own as
    ``(1 - map_cos_weight) * own + map_cos_weight * map_cos`` (1: instead of it). ``out_cos``,
    holding the window's cosines where it answered (the caller's), takes every text's cosine of the
    answer where the map answered or blended (the rows the answer's label is the best text of)."""
    label = np.array(label, np.int32, copy=True)
    score = np.array(score, np.float32, copy=True)
    seen = np.asarray(window_seen, bool)
    source = np.where(seen, SOURCE_WINDOW, SOURCE_NONE).astype(np.uint8)
    label[~seen] = -1
    score[~seen] = 0.0
    blending = blend > 0 and window_cos is not None
    if blending:
        window_cos = np.asarray(window_cos, np.float32)
        if window_cos.shape != (seen.shape[0], text_emb.shape[0]):
            raise ValueError(f"window_cos has shape {window_cos.shape}, expected ({seen.shape[0]}, "
                             f"{text_emb.shape[0]})")
    todo = np.arange(seen.shape[0]) if (more_confident or blending) else np.flatnonzero(~seen)
    if todo.size == 0 or not _map_compatible(snapshot, text_emb):
        return label, score, source
    if nearest is not None:
        rows = np.asarray(nearest, np.int64)[todo]
    else:
        rows = snapshot.nearest_with_feature(np.asarray(xyz)[todo], radius_m)
    hit = rows >= 0
    if hit.any():
        sims = _map_similarities(snapshot, rows[hit], text_emb)  # (n, T)
        idx = todo[hit]
        if map_cos is not None:
            given = np.asarray(map_cos[1], bool)[idx]
            sims = np.array(sims, np.float32, copy=True)
            given_cos = np.asarray(map_cos[0], np.float32)[idx[given]]
            if map_cos_weight >= 1.0:
                sims[given] = given_cos
            else:
                w = np.float32(map_cos_weight)
                sims[given] = (np.float32(1.0) - w) * sims[given] + w * given_cos
        if blending:
            assert window_cos is not None
            both = seen[idx]
            sims[both] = blend_with_map(window_cos[idx[both]], sims[both], blend)
        best = np.argmax(sims, axis=1)
        best_score = sims[np.arange(best.shape[0]), best].astype(np.float32)
        if blending:
            changed = ~seen[idx] | (best != label[idx])
            label[idx] = best.astype(np.int32)
            score[idx] = best_score
            source[idx[changed]] = SOURCE_MAP
            if out_cos is not None:
                out_cos[idx] = sims
            return label, score, source
        take = ~seen[idx] | map_more_confident(best, best_score, label[idx], score[idx])
        if out_cos is not None:
            out_cos[idx[take]] = sims[take]
        idx = idx[take]
        label[idx] = best[take].astype(np.int32)
        score[idx] = best_score[take]
        source[idx] = SOURCE_MAP
    return label, score, source


def evicted_view_cosines(
    store: EvictedViewStore,
    snapshot: GlobalMapSnapshot,
    nearest: np.ndarray,  # (N,) int64 each point's nearest map row with a feature (-1: none)
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    min_views: float = 1.0,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The map's answer at each point's nearest voxel from the views of the keyframes that left
    the window (``queries.evicted_views``, :mod:`mapper.map.evicted_views`): cosines (N, T) float32
    of the mean view sample with the texts, and (N,) bool where the voxel has at least
    ``min_views`` such views: of the ``depth`` channel (views whose depth confirms the voxel) where
    it has, else of ``all``. That mean is the averaging over those views at the voxel, the same
    estimate the window makes from its own views; the fused feature instead averages only the
    depth pixels that fell inside the voxel (at 160x120 and ``pixel_stride`` 2, a handful of
    views). None when the store has nothing for these points."""
    if snapshot.keys is None or len(store) == 0 or store.dim != text_emb.shape[1]:
        return None
    nearest = np.asarray(nearest, np.int64)
    hit = nearest >= 0
    if not hit.any():
        return None
    at = np.flatnonzero(hit)
    cos = np.zeros((nearest.shape[0], text_emb.shape[0]), np.float32)
    given = np.zeros(nearest.shape[0], bool)
    got, ok = store.cosines(snapshot.keys[nearest[hit]], text_emb, min_views=min_views)
    cos[at], given[at] = got, ok
    return (cos, given) if given.any() else None


def blend_with_map(
    window_cos: np.ndarray,  # (..., T) the window's cosines
    map_cos: np.ndarray,  # (..., T) the map point's cosines
    weight: float,  # queries.map_blend, 0..1
) -> np.ndarray:  # (..., T) float32
    """The ``queries.map_blend`` rule for an answer both the window and the global map give:
    ``(1 - weight) * window_cos + weight * map_cos``. The map's feature fused every keyframe that
    ever saw the point with depth (each observation at its own depth pixel, so visible), the
    window's blends the keyframes it still holds, including ones that do not see the point.

    >>> [round(float(c), 3) for c in blend_with_map(np.array([0.9, 0.1]), np.array([0.2, 0.6]), 0.75)]
    [0.375, 0.475]
    """
    if not 0.0 <= weight <= 1.0:
        raise ValueError(f"weight {weight} must be in [0, 1]")
    w = np.float32(weight)
    return ((np.float32(1.0) - w) * np.asarray(window_cos, np.float32) + w * np.asarray(map_cos, np.float32))


def _splat_rows(
    snapshot: GlobalMapSnapshot,
    K: np.ndarray,  # (4,) [fx, fy, cx, cy]
    world_from_cam: np.ndarray,  # (4, 4)
    width: int,
    height: int,
) -> np.ndarray:
    """(H, W) int64 map row of the nearest map point with a feature that projects into each pixel
    (z-buffer, :func:`mapper.geometry.splat.splat_points`; each point covers about its voxel's
    footprint, at most 5x5 pixels of the image shrunk by :func:`mapper.geometry.splat.splat_scale`),
    -1 = none."""
    rows = np.flatnonzero(snapshot.feat_weight > 0)
    if rows.size == 0:
        return np.full((height, width), -1, np.int64)
    scale = splat_scale(K, snapshot.voxel_size_m)  # as surface_depth: the footprint unclipped
    K_s, width_s, height_s = scaled_camera(K, width, height, scale)
    index, _ = splat_points(snapshot.xyz[rows], K_s, world_from_cam, width_s, height_s, snapshot.voxel_size_m)
    index = np.ascontiguousarray(upsample_nearest(index, scale, height, width))
    return np.where(index >= 0, rows[np.maximum(index, 0)], -1)


def surface_depth(
    xyz: np.ndarray,  # (N, 3) world points of measured surfaces
    footprint_m: float,  # each point covers about this many metres
    K: np.ndarray,  # (4,) [fx, fy, cx, cy] for width x height
    world_from_cam: np.ndarray,  # (4, 4) camera-to-world
    width: int,
    height: int,
    config: ModelRuntimeConfig,
) -> np.ndarray:  # (H, W) float32 z-depth (m), 0 = no surface
    """The surface each pixel sees among ``xyz``: the z-depth of the nearest point splatted over
    its footprint (:func:`mapper.geometry.splat.splat_points`); minus the pixels that see a point
    through a hole in a nearer surface (:func:`mapper.geometry.splat.see_through`,
    ``config.surface_see_through_px`` / ``_rel``) and, with ``config.surface_speckle_px``, small
    islands (:func:`mapper.geometry.splat.remove_speckles`); then holes up to ``config.surface_fill_px``
    pixels on each side filled where the surface around them agrees within
    ``config.surface_fill_rel`` (:func:`mapper.geometry.splat.fill_holes`). ``render``
    evaluates the model's appearance at these surface points (docs/concepts/rendering.md, "Surfaces from
    the map"). A high-resolution camera (:func:`mapper.geometry.splat.splat_scale` > 1) is splatted
    and filled at 1 / scale of its size and the depth upsampled (nearest), so that the footprints
    and the hole filling see the points as a 160 x 120 camera does."""
    if len(xyz) == 0:
        return np.zeros((height, width), np.float32)
    scale = splat_scale(K, footprint_m)  # a high-resolution camera: splat at a lower one, then upsample
    K_s, width_s, height_s = scaled_camera(K, width, height, scale)
    _, z = splat_points(xyz, K_s, world_from_cam, width_s, height_s, footprint_m)
    hole = see_through(z, config.surface_see_through_px, config.surface_see_through_rel)
    z = remove_speckles(np.where(hole, np.float32(0), z), config.surface_speckle_px, config.surface_fill_rel)
    z = fill_holes(z, config.surface_fill_px, config.surface_fill_rel)
    return np.ascontiguousarray(upsample_nearest(z, scale, height, width))


def geometry_planes(
    xyz: np.ndarray,  # (N, 3) world points of measured RGB-only geometry
    config: ModelRuntimeConfig,
) -> list[Plane]:
    """The planes of an RGB-only robot's measured geometry (``model.surface_plane_*``): at most
    ``surface_plane_max_points`` of the points (a fixed random subset beyond it), their local
    normals, and :func:`mapper.geometry.planes.fit_planes` with normal agreement."""
    pts = np.asarray(xyz, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if config.surface_plane_max == 0 or len(pts) < max(config.surface_plane_min_points, 3):
        return []
    if len(pts) > config.surface_plane_max_points:
        pick = np.random.default_rng(0).choice(len(pts), config.surface_plane_max_points, replace=False)
        pts = pts[np.sort(pick)]
    normals, _ = point_normals(pts, config.surface_plane_neighbours)
    return fit_planes(
        pts, normals=normals, max_normal_deg=config.surface_plane_normal_deg,
        inlier_m=config.surface_plane_inlier_m, min_inliers=config.surface_plane_min_points,
        cell_m=config.surface_plane_cell_m, max_planes=config.surface_plane_max,
    )


class PlaneCache:
    """:func:`geometry_planes` of the latest geometry, refitted only when the number of points
    moved by more than ``config.surface_plane_refit`` (relative) since the last fit, or the config
    changed: a streaming robot's geometry grows with every keyframe, and a fit (a few hundred ms)
    on every render would slow renders down for planes that barely moved. Thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._count = -1
        self._config: ModelRuntimeConfig | None = None
        self._planes: list[Plane] = []
        self.fits = 0
        """Fits so far (the other calls reused the planes)."""

    def planes(self, xyz: np.ndarray, config: ModelRuntimeConfig) -> list[Plane]:
        pts = np.asarray(xyz, np.float64).reshape(-1, 3)
        with self._lock:
            moved = abs(len(pts) - self._count) > config.surface_plane_refit * max(self._count, 0)
            if self._count < 0 or moved or config != self._config:
                self._planes = geometry_planes(pts, config)
                self._count, self._config = len(pts), config
                self.fits += 1
            return self._planes


def with_planes(
    surface: np.ndarray,  # (H, W) float32 z-depth of the measured points, 0 = none
    planes: list[Plane],
    K: np.ndarray,  # (4,) [fx, fy, cx, cy] for width x height
    world_from_cam: np.ndarray,  # (4, 4) camera-to-world
) -> tuple[np.ndarray, int]:
    """``surface`` with its empty pixels (0) set to the nearest supported plane's depth where a
    plane is hit (:func:`mapper.geometry.planes.plane_depth`); and how many pixels that set."""
    if not planes:
        return surface, 0
    height, width = surface.shape
    z_plane, _ = plane_depth(planes, K, world_from_cam, width, height)
    fill = (surface <= 0) & (z_plane > 0)
    return np.where(fill, z_plane, surface).astype(np.float32), int(np.count_nonzero(fill))


def map_surface_depth(
    snapshot: GlobalMapSnapshot,
    K: np.ndarray,  # (4,) [fx, fy, cx, cy] for width x height
    world_from_cam: np.ndarray,  # (4, 4) camera-to-world
    width: int,
    height: int,
    config: ModelRuntimeConfig,
) -> np.ndarray:  # (H, W) float32 z-depth (m), 0 = no map surface
    """:func:`surface_depth` of every global-map point (with or without a feature), each over its
    voxel's footprint."""
    return surface_depth(snapshot.xyz, snapshot.voxel_size_m, K, world_from_cam, width, height, config)


def render_from_map(
    snapshot: GlobalMapSnapshot,
    K: np.ndarray,  # (4,) [fx, fy, cx, cy] for width x height
    world_from_cam: np.ndarray,  # (4, 4) camera-to-world
    width: int,
    height: int,
    depth_m: np.ndarray | None,  # (H, W) rendered z-depth, 0 = no surface; None = unknown
    need: np.ndarray,  # (H, W) bool: pixels the window did not label
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    radius_m: float,
    *,
    splat: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Label the ``need`` pixels of a view from the map: (label (H, W) int32, -1 elsewhere; cos
    (H, W, T) float32, 0 elsewhere; answered (H, W) bool). A pixel with a rendered surface takes
    the nearest map point with a feature within ``radius_m`` of that surface point; one without
    (or without a map point that near) takes the splatted map point that projects into it
    (``splat=False``: stays unanswered)."""
    n_texts = text_emb.shape[0]
    label = np.full((height, width), -1, np.int32)
    cos = np.zeros((height, width, n_texts), np.float32)
    answered = np.zeros((height, width), bool)
    if not need.any() or not _map_compatible(snapshot, text_emb):
        return label, cos, answered
    rows = np.full((height, width), -1, np.int64)
    if depth_m is not None:
        surf = need & (depth_m > 0)
        jj, ii = np.nonzero(surf)
        if jj.size:
            fx, fy, cx, cy = (float(v) for v in K)
            z = depth_m[jj, ii].astype(np.float64)
            p_cam = np.stack([(ii + 0.5 - cx) / fx * z, (jj + 0.5 - cy) / fy * z, z], axis=1)
            pose = np.asarray(world_from_cam, np.float64)
            p_world = p_cam @ pose[:3, :3].T + pose[:3, 3]
            rows[jj, ii] = snapshot.nearest_with_feature(p_world, radius_m)
    rest = need & (rows < 0)
    if splat and rest.any():
        splatted = _splat_rows(snapshot, np.asarray(K, np.float64), world_from_cam, width, height)
        rows[rest] = splatted[rest]
    jj, ii = np.nonzero(need & (rows >= 0))
    if jj.size:
        sims = _map_similarities(snapshot, rows[jj, ii], text_emb)  # (n, T)
        cos[jj, ii] = sims.astype(np.float32)
        label[jj, ii] = np.argmax(sims, axis=1).astype(np.int32)
        answered[jj, ii] = True
    return label, cos, answered


def render_more_confident(
    snapshot: GlobalMapSnapshot,
    K: np.ndarray,  # (4,) [fx, fy, cx, cy] for width x height
    world_from_cam: np.ndarray,  # (4, 4) camera-to-world
    depth_m: np.ndarray,  # (H, W) rendered z-depth, 0 = no surface
    label: np.ndarray,  # (H, W) int32 the window's labels (-1 = none)
    cos: np.ndarray,  # (H, W, T) float32 the window's cosines
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    radius_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`map_more_confident` for a render: the pixels the window labelled where the render
    found a surface, against the map point nearest that surface point (:func:`render_from_map`
    without the splat). Returns the map's (label (H, W), cos (H, W, T)) and ``over`` (H, W) bool,
    the pixels whose answer the map takes."""
    height, width = label.shape
    need = (label >= 0) & (depth_m > 0)
    m_lab, m_cos, m_ans = render_from_map(
        snapshot, K, world_from_cam, width, height, depth_m, need, text_emb, radius_m, splat=False
    )
    over = m_ans & map_more_confident(m_lab, m_cos.max(axis=-1), label, cos.max(axis=-1))
    return m_lab, m_cos, over
