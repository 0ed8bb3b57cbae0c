"""Tests of the semantic queries: phrasing normalisation, negatives, scoring, clustering, limits,
and the averaging segmentation baseline. Natural phrasings are checked with the real
all-MiniLM-L6-v2 text encoder on a synthetic map whose features are class-name embeddings."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mapper.map.global_map import GlobalMapSnapshot
from mapper.node.config import QueryConfig
from mapper.node.queries import (
    DEFAULT_NEGATIVES,
    cluster_points,
    normalise_query,
    query_points,
    segment_average,
)
from mapper.ov.encoders import get_text_encoder
from protocol.errors import ProtocolError

CONFIG = QueryConfig(cluster_radius_m=0.12, min_object_points=10)

# object name -> box centre (x, y, z), half size (m)
OBJECTS = {
    "chair": [((1.0, 1.0, 0.45), 0.2), ((3.0, 1.0, 0.45), 0.2)],
    "table": [((2.0, 1.0, 0.7), 0.35)],
    "bed": [((4.8, 3.0, 0.6), 0.5)],
    "sofa": [((1.0, 4.0, 0.55), 0.45)],
}


def _box_surface(centre: tuple[float, float, float], half: float, step: float = 0.05) -> np.ndarray:
    g = np.arange(-half, half + 1e-9, step)
    a, b = np.meshgrid(g, g, indexing="ij")
    a, b = a.ravel(), b.ravel()
    faces = [np.stack([a, b, np.full_like(a, s * half)], 1) for s in (-1, 1)]
    faces += [np.stack([a, np.full_like(a, s * half), b], 1) for s in (-1, 1)]
    faces += [np.stack([np.full_like(a, s * half), a, b], 1) for s in (-1, 1)]
    return np.concatenate(faces) + np.asarray(centre)


def make_snapshot(
    names_and_points: list[tuple[str, np.ndarray]],
    noise: float = 0.03,
    seed: int = 0,
    with_features: bool = True,
) -> GlobalMapSnapshot:
    """A snapshot whose features are the class-name embeddings plus noise (per dimension)."""
    encoder = get_text_encoder()
    rng = np.random.default_rng(seed)
    xyz = np.concatenate([p for _, p in names_and_points]).astype(np.float32)
    emb = encoder.encode([n for n, _ in names_and_points])
    sizes = [len(p) for _, p in names_and_points]
    feat = np.repeat(emb, sizes, axis=0)
    feat = feat + noise * rng.normal(size=feat.shape).astype(np.float32)
    feat /= np.linalg.norm(feat, axis=1, keepdims=True)
    n = xyz.shape[0]
    return GlobalMapSnapshot(
        version=1, map_version=5, voxel_size_m=0.05, xyz=xyz,
        feat=feat.astype(np.float16) if with_features else None,
        weight=np.ones(n, np.float32), feat_weight=np.full(n, 1.0 if with_features else 0.0, np.float32),
        hits=np.ones(n, np.int32), last_seen_ns=np.zeros(n, np.int64),
    )  # fmt: skip


@pytest.fixture(scope="module")
def room() -> GlobalMapSnapshot:
    parts: list[tuple[str, np.ndarray]] = []
    for name, boxes in OBJECTS.items():
        for centre, half in boxes:
            parts.append((name, _box_surface(centre, half)))
    g = np.arange(0.0, 6.0, 0.05)
    x, y = np.meshgrid(g, g, indexing="ij")
    floor = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    wall = np.stack([x.ravel(), np.full(x.size, 6.0), y.ravel() / 2.5], 1)
    parts += [("floor", floor), ("wall", wall)]
    return make_snapshot(parts)


def ask(snapshot: GlobalMapSnapshot, texts: list[str], **kwargs: object):  # noqa: ANN201
    opts: dict[str, object] = {"negatives": None, "min_score": None, "max_points": None, "objects": True}
    opts.update(kwargs)
    return query_points(snapshot, get_text_encoder(), texts, config=CONFIG, **opts)  # type: ignore[arg-type]


def _nearest_object(centroid: np.ndarray) -> tuple[str, float]:
    centres = [(name, np.asarray(c)) for name, boxes in OBJECTS.items() for c, _ in boxes]
    dist, name = min((float(np.linalg.norm(centroid - c)), name) for name, c in centres)
    return name, dist


@pytest.mark.parametrize(
    "text, expected",
    [
        ("find the chair", "chair"),
        ("Where is a place to sit?", "place to sit"),
        ("show me the table", "table"),
        ("please, can you show me the bed", "bed"),
        ("navigate to the sofa please", "sofa"),
        ("Locate my keys.", "keys"),
        ("  chair  ", "chair"),
        ("the", "the"),
        ("a place to sleep", "place to sleep"),
        ("findings", "findings"),  # a command word only at a word boundary
    ],
)
def test_normalise_query(text: str, expected: str) -> None:
    assert normalise_query(text) == expected


@pytest.mark.parametrize(
    "text, allowed",
    [
        ("find the chair", {"chair"}),
        ("show me the table", {"table"}),
        ("where is the bed", {"bed"}),
        ("a place to sleep", {"bed"}),
        ("where is a place to sit", {"chair", "sofa"}),
    ],
)
def test_natural_phrasings_find_the_right_object(
    room: GlobalMapSnapshot, text: str, allowed: set[str]
) -> None:
    reply = ask(room, [text])
    assert reply.objects, f"no object for {text!r}"
    top = reply.objects[0]
    name, dist = _nearest_object(top.centroid)
    assert name in allowed and dist < 0.2, (text, name, dist)
    assert top.text == text
    assert reply.map_version == 5 and reply.timing_ms["total"] >= 0


def test_points_labels_scores_and_objects_are_consistent(room: GlobalMapSnapshot) -> None:
    reply = ask(room, ["chair", "table"])
    assert reply.xyz.shape[0] == reply.score.shape[0] == reply.label.shape[0] > 0
    assert np.all(np.diff(reply.score) <= 0)  # best first
    assert set(np.unique(reply.label)) == {0, 1}
    # floor and wall points lose to the negatives
    assert np.all(reply.xyz[:, 2] > 0.04) and np.all(reply.xyz[:, 1] < 5.9)
    # the two chairs are the two best "chair" candidates (a sofa may follow, with a lower score)
    chairs = [o for o in reply.objects if o.text == "chair"]
    assert sorted(_nearest_object(o.centroid)[0] for o in chairs[:2]) == ["chair", "chair"]
    assert all(_nearest_object(o.centroid)[1] < 0.05 for o in chairs[:2])
    tables = [o for o in reply.objects if o.text == "table"]
    assert _nearest_object(tables[0].centroid)[0] == "table"
    for o in reply.objects:
        assert np.all(o.aabb_min <= o.centroid) and np.all(o.centroid <= o.aabb_max)
        assert o.n_points >= CONFIG.min_object_points
    assert [o.score for o in reply.objects] == sorted((o.score for o in reply.objects), reverse=True)


def test_negatives_veto_background_but_not_asked_for_structure(room: GlobalMapSnapshot) -> None:
    # a vague text matches little beyond the negatives; with no negatives every point gets a label
    none = ask(room, ["chair"], negatives=[])
    default = ask(room, ["chair"])
    assert none.xyz.shape[0] == room.xyz.shape[0] > default.xyz.shape[0]
    # asking for the wall drops the negative "wall" instead of vetoing every wall point
    wall = ask(room, ["walls"])
    assert wall.objects and wall.objects[0].centroid[1] > 5.9
    assert "wall" in DEFAULT_NEGATIVES
    # negatives that all name the texts leave no background: the default set stands in for them
    same = ask(room, ["chair"], negatives=["chair", "a chair"])
    assert same.xyz.shape[0] == default.xyz.shape[0] < room.xyz.shape[0]


def test_min_score_and_max_points(room: GlobalMapSnapshot) -> None:
    base = ask(room, ["chair"], negatives=[])
    threshold = float(np.median(base.score))
    high = ask(room, ["chair"], negatives=[], min_score=threshold)
    assert 0 < high.xyz.shape[0] < base.xyz.shape[0] and high.score.min() >= threshold
    few = ask(room, ["chair"], negatives=[], max_points=50, objects=False)
    assert few.xyz.shape[0] == 50 and few.objects == []
    np.testing.assert_allclose(few.score, base.score[:50])


def test_map_without_features_is_not_ready() -> None:
    snap = make_snapshot([("chair", _box_surface((0, 0, 0), 0.2))], with_features=False)
    with pytest.raises(ProtocolError, match="none carries an open-vocabulary feature") as info:
        ask(snap, ["chair"])
    assert info.value.code == "not_ready"


def test_cluster_points_min_points_and_separation() -> None:
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 0.3, (40, 3))
    b = rng.uniform(0, 0.3, (25, 3)) + [2.0, 0, 0]
    c = rng.uniform(0, 0.05, (4, 3)) + [5.0, 0, 0]  # too small
    xyz = np.concatenate([a, b, c]).astype(np.float32)
    score = np.concatenate([np.full(40, 0.5), np.full(25, 0.9), np.full(4, 1.0)]).astype(np.float32)
    clusters = cluster_points(xyz, score, np.zeros(len(xyz), np.int64), radius_m=0.2, min_points=10)
    assert [c.indices.size for c in clusters] == [25, 40]  # sorted by score
    np.testing.assert_allclose(clusters[0].centroid, b.mean(0), atol=1e-6)


def test_segment_average_labels_seen_points_and_leaves_unseen_at_minus_one() -> None:
    """Two views of the plane z = 2: left half of the image shows class 0, right half class 1."""
    d = 4
    emb = np.eye(d, dtype=np.float32)[:2]
    width, height = 40, 30
    K = np.array([40.0, 40.0, 20.0, 15.0])
    ov = np.zeros((height // 5, width // 5, d), np.float32)
    ov[:, : ov.shape[1] // 2, 0] = 1.0
    ov[:, ov.shape[1] // 2:, 1] = 1.0
    depth = np.full((height, width), 2.0, np.float32)
    views = [(ov, K, np.eye(4), (width, height), depth)] * 2
    pts = np.array([[-0.5, 0.0, 2.0], [0.5, 0.0, 2.0], [30.0, 0.0, 2.0], [-0.5, 0.0, 1.0]], np.float32)
    label, score, n = segment_average(pts, views, emb, use_depth=False)
    assert label.tolist()[:3] == [0, 1, -1] and score[2] == 0.0 and n.tolist()[:3] == [2, 2, 0]
    assert score[0] > 0.99
    # the depth test drops the views for a point in front of the surface
    label_d, _, n_d = segment_average(pts, views, emb, use_depth=True)
    assert label_d.tolist() == [0, 1, -1, -1] and n_d[3] == 0


def test_object_scores_are_discounted_by_support() -> None:
    """A small cluster of high scores no longer outranks a large, slightly lower-scoring one; the
    discount is 1 - exp(-n / support_points), off at 0; the reference clustering agrees."""
    from mapper.node.queries import support_factor

    rng = np.random.default_rng(0)
    big = rng.uniform(0, 0.5, (400, 3)) + [2.0, 0.0, 0.0]  # a dense 0.5 m cube of 400 points
    small = rng.uniform(0, 0.05, (16, 3))  # 16 points, far from it
    xyz = np.concatenate([big, small]).astype(np.float32)
    score = np.concatenate([np.full(400, 0.45), np.full(16, 0.6)]).astype(np.float32)
    label = np.zeros(len(xyz), np.int64)
    plain = cluster_points(xyz, score, label, radius_m=0.2, min_points=10)
    assert [c.indices.size for c in plain] == [16, 400]  # by the mean of the top half only
    for reference in (False, True):
        ranked = cluster_points(xyz, score, label, radius_m=0.2, min_points=10, support_points=25.0,
                                reference=reference)  # fmt: skip
        assert [c.indices.size for c in ranked] == [400, 16]
        assert ranked[0].score == pytest.approx(0.45 * (1 - np.exp(-400 / 25)), rel=1e-6)
        assert ranked[1].score == pytest.approx(0.6 * (1 - np.exp(-16 / 25)), rel=1e-6)
    assert support_factor(15, 0.0) == 1.0 and support_factor(0, 25.0) == 0.0
    assert support_factor(25, 25.0) == pytest.approx(1 - np.exp(-1))
    assert 0.999 < support_factor(10_000, 25.0) <= 1.0


def _chairs_around_a_table(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Four 'chairs' (dense blobs scoring 0.8-0.9) at the corners of a 'table' (a plate of points
    between them scoring 0.5), all linked at 0.12 m: (xyz (N, 3), score (N,), chair centres (4, 3))."""
    rng = np.random.default_rng(seed)
    centres = np.array([[0.0, 0.0, 0.5], [1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [1.0, 1.0, 0.5]])
    chairs = [rng.normal(c, 0.04, (60, 3)) for c in centres]
    g = np.linspace(0.0, 1.0, 11)  # 0.1 m apart: linked; fewer points than the chairs
    table = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    table = np.concatenate([table, np.full((table.shape[0], 1), 0.5)], 1)
    xyz = np.concatenate(chairs + [table]).astype(np.float32)
    score = np.concatenate([rng.uniform(0.8, 0.9, 240), np.full(table.shape[0], 0.5)]).astype(np.float32)
    return xyz, score, centres


def test_objects_split_where_the_best_points_form_separate_groups() -> None:
    """Chairs around a table, all labelled 'chair': one component, centred on the table; split by
    score, four objects, one at each chair, made of chair points only."""
    from mapper.node.queries import split_by_score

    xyz, score, centres = _chairs_around_a_table()
    label = np.zeros(len(xyz), np.int64)
    whole = cluster_points(xyz, score, label, radius_m=0.12, min_points=15, support_points=25.0)
    assert len(whole) == 1 and np.linalg.norm(whole[0].centroid - [0.5, 0.5, 0.5]) < 0.05
    for reference in (False, True):
        parts = cluster_points(xyz, score, label, radius_m=0.12, min_points=15, support_points=25.0,
                               split_quantile=0.5, split_depth=3, reference=reference)  # fmt: skip
        assert len(parts) == 4
        found = sorted(int(np.argmin(np.linalg.norm(centres - c.centroid, axis=1))) for c in parts)
        assert found == [0, 1, 2, 3]
        for c in parts:
            assert np.linalg.norm(centres - c.centroid, axis=1).min() < 0.05
            assert np.all(c.indices < 240)  # no table point
            again = cluster_points(xyz[c.indices], score[c.indices], label[c.indices], 0.12, 15,
                                   support_points=25.0)  # fmt: skip
            assert len(again) == 1 and again[0].score == pytest.approx(c.score, rel=1e-6)
        assert [c.score for c in parts] == sorted((c.score for c in parts), reverse=True)
    # the same with the split switched off, no splits left, or the candidate above the size limit
    assert len(split_by_score(xyz, score, whole, 0.12, 15, 0.5, 0)) == 1
    assert len(split_by_score(xyz, score, whole, 0.12, 15, 0.5, 3, max_points=len(xyz) - 1)) == 1
    assert len(split_by_score(xyz, score, whole, 0.12, 15, 0.5, 3, max_points=len(xyz))) == 4
    assert len(cluster_points(xyz, score, label, 0.12, 15, split_quantile=0.5, split_depth=3,
                              split_max_points=100)) == 1  # fmt: skip
    assert len(cluster_points(xyz, score, label, 0.12, 15, split_quantile=0.0, split_depth=3)) == 1
    with pytest.raises(ValueError, match="quantile"):
        split_by_score(xyz, score, whole, 0.12, 15, 1.0, 3)


def test_objects_stay_whole_when_their_core_does_not_fall_apart() -> None:
    """A uniformly scored blob, and a blob whose core splits into one big part and crumbs smaller
    than min_points, are kept as they are (same indices, same score)."""
    from mapper.node.queries import split_by_score

    rng = np.random.default_rng(2)
    blob = rng.uniform(0, 0.4, (300, 3)).astype(np.float32)
    flat = np.full(300, 0.7, np.float32)
    varied = rng.uniform(0.5, 0.9, 300).astype(np.float32)
    crumbs = np.concatenate([blob, rng.normal([0.9, 0.0, 0.0], 0.01, (8, 3)).astype(np.float32),
                             np.linspace([0.4, 0, 0], [0.9, 0, 0], 6).astype(np.float32)])  # fmt: skip
    crumb_score = np.concatenate([varied, np.full(8, 0.95, np.float32), np.full(6, 0.4, np.float32)])
    for xyz, score in ((blob, flat), (blob, varied), (crumbs, crumb_score)):
        whole = cluster_points(xyz, score, np.zeros(len(xyz), np.int64), 0.12, 15)
        kept = split_by_score(xyz, score, whole, 0.12, 15, 0.5, 3)
        assert [c.indices.tolist() for c in kept] == [c.indices.tolist() for c in whole]
        assert [c.score for c in kept] == [c.score for c in whole]


def test_object_split_config_is_checked() -> None:
    from mapper.errors import ConfigError
    from mapper.node.config import config_from_dict

    assert config_from_dict({}).queries.object_split_quantile == 0.5
    bad = (("object_split_quantile", 1.0), ("object_split_quantile", -0.1), ("object_split_depth", -1),
           ("object_split_max_points", -5), ("object_split_clean_share", 1.5),
           ("object_split_clean_share", -0.1))
    for key, value in bad:
        with pytest.raises(ConfigError, match=f"queries.{key}"):
            config_from_dict({"queries": {key: value}})


def _grid_box(lo: tuple[float, ...], hi: tuple[float, ...], step: float = 0.05) -> np.ndarray:
    axes = [np.arange(a, b + 1e-9, step) for a, b in zip(lo, hi, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def test_a_stricter_core_splits_a_chair_from_the_desk_it_touches() -> None:
    """A chair (best scores) against a desk whose far end also scores high for "chair" and whose
    middle, between them, scores above the candidate's median: the top half stays in one piece; the
    top quarter is the chair and the desk's end, two clean parts."""
    from mapper.node.queries import split_by_score

    chair = _grid_box((0.0, 0.0, 0.0), (0.25, 0.25, 0.2))
    bridge = _grid_box((0.3, 0.0, 0.0), (0.55, 0.25, 0.2))
    desk_end = _grid_box((0.6, 0.0, 0.0), (0.85, 0.25, 0.2))
    rest = _grid_box((0.3, 0.3, 0.0), (0.85, 1.3, 0.05))  # the rest of the desk, beside the bridge
    xyz = np.concatenate([chair, bridge, desk_end, rest]).astype(np.float32)
    n_c, n_b, n_e = len(chair), len(bridge), len(desk_end)
    assert n_c == n_b == n_e == 180 and len(rest) == 504
    score = np.concatenate([np.full(n_c, 0.9), np.full(n_b, 0.8), np.full(n_e, 0.88),
                            np.full(len(rest), 0.5)]).astype(np.float32)  # fmt: skip
    assert np.quantile(score, 0.5) == pytest.approx(0.8)  # the top half: chair, bridge and the desk's end
    whole = cluster_points(xyz, score, np.zeros(len(xyz), np.int64), 0.12, 15)
    assert len(whole) == 1
    parts = split_by_score(xyz, score, whole, 0.12, 15, 0.5, 3)
    assert sorted(len(p.indices) for p in parts) == sorted([n_c, n_e])
    assert np.linalg.norm(parts[0].centroid - chair.mean(0)) < 1e-5  # the chair, best first
    assert len(split_by_score(xyz, score, whole, 0.12, 15, 0.5, 1)) == 1  # one cut only: as it was


def test_strict_cores_that_fall_into_dust_keep_the_object_whole(room: GlobalMapSnapshot) -> None:
    """The room's bed and table (noisy features): their strict cores break into crumbs and a few
    groups of 15 points that hold 48-75% of the core; below the clean share they stay whole (the top
    object on the bed's centre), while counting any split would report a fragment."""
    for text, name in (("where is the bed", "bed"), ("show me the table", "table")):
        top = ask(room, [text]).objects[0]
        assert _nearest_object(top.centroid)[0] == name and _nearest_object(top.centroid)[1] < 0.2
        dusty = replace(CONFIG, object_split_clean_share=0.0)
        frag = query_points(room, get_text_encoder(), [text], config=dusty, negatives=None, min_score=None,
                            max_points=None, objects=True).objects[0]  # fmt: skip
        assert frag.n_points < top.n_points and _nearest_object(frag.centroid)[1] > 0.3


def test_an_object_another_word_explains_better_falls_behind_the_one_asked_for() -> None:
    # a large sofa whose features also sit near "chair", and a small chair seen through noise:
    # by score alone the sofa is the best "chair"; its mean feature is nearer "sofa" than "chair"
    encoder = get_text_encoder()
    chair_e, sofa_e = encoder.encode(["chair", "sofa"])
    rng = np.random.default_rng(4)
    sofa_xyz = _box_surface((1.0, 4.0, 0.55), 0.45)
    chair_xyz = _box_surface((3.0, 1.0, 0.45), 0.2)
    sofa_f = np.tile(0.8 * sofa_e + 0.6 * chair_e, (len(sofa_xyz), 1))
    chair_f = chair_e + 0.06 * rng.normal(size=(len(chair_xyz), chair_e.size)).astype(np.float32)
    feat = np.concatenate([sofa_f, chair_f])
    feat /= np.linalg.norm(feat, axis=1, keepdims=True)
    xyz = np.concatenate([sofa_xyz, chair_xyz]).astype(np.float32)
    n = len(xyz)
    snapshot = GlobalMapSnapshot(
        version=1, map_version=1, voxel_size_m=0.05, xyz=xyz, feat=feat.astype(np.float16),
        weight=np.ones(n, np.float32), feat_weight=np.ones(n, np.float32), hits=np.ones(n, np.int32),
        last_seen_ns=np.zeros(n, np.int64))
    opts: dict[str, object] = {"negatives": None, "min_score": None, "max_points": None, "objects": True}
    on = replace(CONFIG, object_vocabulary_temperature=0.05)
    plain = query_points(snapshot, encoder, ["find the chair"], config=CONFIG, **opts)  # type: ignore[arg-type]
    ranked = query_points(snapshot, encoder, ["find the chair"], config=on, **opts)  # type: ignore[arg-type]
    assert _nearest_object(plain.objects[0].centroid)[0] == "sofa"
    assert _nearest_object(ranked.objects[0].centroid)[0] == "chair"
    assert [o.score for o in ranked.objects] == sorted((o.score for o in ranked.objects), reverse=True)
    # the points and their labels do not change, only the objects' scores and order
    np.testing.assert_array_equal(plain.xyz, ranked.xyz)
    np.testing.assert_array_equal(plain.score, ranked.score)
    # asking for the sofa too: "sofa" is a text, not an alternative, and the sofa is labelled sofa
    both = query_points(snapshot, encoder, ["chair", "sofa"], config=on, **opts)  # type: ignore[arg-type]
    found = {o.text: _nearest_object(o.centroid)[0] for o in both.objects}
    assert found == {"chair": "chair", "sofa": "sofa"}


def test_vocabulary_factor_against_a_float64_reference() -> None:
    from mapper.node.queries import vocabulary_factor

    rng = np.random.default_rng(0)
    unit = lambda a: a / np.linalg.norm(a, axis=1, keepdims=True)  # noqa: E731
    mean, text, vocab = (unit(rng.normal(size=(k, 16))) for k in (9, 9, 5))
    for temperature in (1e-4, 0.05, 10.0):
        ref = np.exp(np.minimum(0.0, (mean * text).sum(1) - (mean @ vocab.T).max(1)) / temperature)
        got = vocabulary_factor(mean.astype(np.float32), text.astype(np.float32), vocab.astype(np.float32),
                                temperature)
        assert got.dtype == np.float32 and np.all((got >= 0) & (got <= 1))
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-30)
    assert np.all(vocabulary_factor(mean.astype(np.float32), text.astype(np.float32),
                                    np.zeros((0, 16), np.float32), 0.05) == 1.0)


def test_object_vocabulary_config_is_checked() -> None:
    from mapper.node.config import ConfigError, config_from_dict

    cfg = config_from_dict({"queries": {"object_vocabulary": ["lamp", "rug"]}})
    assert cfg.queries.object_vocabulary == ("lamp", "rug")
    with pytest.raises(ConfigError, match="object_vocabulary must be a list of strings"):
        config_from_dict({"queries": {"object_vocabulary": "lamp"}})
    with pytest.raises(ConfigError, match="non-empty"):
        config_from_dict({"queries": {"object_vocabulary": ["lamp", " "]}})
    with pytest.raises(ConfigError, match="object_vocabulary_temperature"):
        config_from_dict({"queries": {"object_vocabulary_temperature": -1.0}})
