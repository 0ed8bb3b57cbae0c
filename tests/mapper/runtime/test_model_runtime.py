"""Tests for mapper.runtime.model_runtime: incremental volume through the window, renders, z-depth,
empty-space skipping vs dense sampling, segmentation, not_ready paths. Tiny random-init model, tiny frames."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
import torch

from mapper.map.window import Keyframe, KeyframeWindow
from mapper.model.field import GovNeSF
from mapper.model.ops.cost_volume import bounds_from_points, build_cost_volume, cost_volume_features
from mapper.node.config import ConfigError, WindowConfig
from mapper.runtime import prepared
from mapper.runtime.density import density
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig, RuntimeNotReady
from mapper.runtime.prepared import RENDER_VOLUMES_KEPT, overlapping_views, render_prep
from mapper.runtime.views import view_groups
from tests.model_helpers import look_at, tiny_model_config

TINY = tiny_model_config(ov_dim=6, max_voxels=2048, n_samples=16)
D = 6
SPACE = "test-space"
TEXT_EMB = np.eye(3, D, dtype=np.float32)  # "a" -> e0, "b" -> e1, "c" -> e2


class FakeEncoder:
    space = SPACE
    dim = D

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        return np.stack([TEXT_EMB["abc".index(t[0])] for t in texts])


def keyframe(
    seq: int,
    eye: Sequence[float],
    target: Sequence[float] = (0.0, 0.0, 0.5),
    *,
    wh: tuple[int, int] = (40, 30),
    ov: np.ndarray | None | str = "random",
    depth_m: float | None = 2.0,
) -> Keyframe:
    w, h = wh
    rng = np.random.default_rng(seq)
    if isinstance(ov, str):
        ov = rng.standard_normal((max(1, h // 6), max(1, w // 6), D)).astype(np.float16)
    return Keyframe(
        seq=seq,
        stamp_ns=seq,
        camera="cam0",
        K=np.array([0.8 * w, 0.8 * w, w / 2, h / 2]),
        world_from_cam=look_at(eye, target),
        rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        depth_m=None if depth_m is None else np.full((h, w), depth_m, np.float32),
        ov=ov,
        ov_space=SPACE if ov is not None else None,
    )


def orbit(i: int, radius: float = 2.0, centre: Sequence[float] = (0.0, 0.0)) -> tuple[float, float, float]:
    a = 0.5 * i
    return (centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a), 1.2)


@pytest.fixture(scope="module")
def model() -> GovNeSF:
    torch.manual_seed(0)
    return GovNeSF(TINY).eval()


def make_runtime(model: GovNeSF, **overrides: object) -> ModelRuntime:
    cfg = ModelRuntimeConfig(device="cpu", chunk_rays=512, **overrides)  # type: ignore[arg-type]
    return ModelRuntime(cfg, model=model, text_encoder=lambda space: FakeEncoder())


def test_incremental_volume_equals_batch_build_through_adds_and_evictions(model: GovNeSF) -> None:
    runtime = make_runtime(model)
    window = KeyframeWindow(WindowConfig(max_keyframes=4, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i in range(7):
        window.consider(keyframe(i, orbit(i)))
        if i % 2 == 0:  # sometimes several changes are applied at once
            runtime.sync()
    runtime.sync()
    volume = runtime.cost_volume
    assert volume is not None
    assert sorted(volume.view_ids, key=id) == sorted(window.keyframes, key=id)  # exactly the window
    entries = [runtime._volume.entries[k] for k in volume.view_ids]
    mean, var, count = build_cost_volume(
        volume.bounds,
        torch.stack([e.features for e in entries]),
        torch.stack([e.K for e in entries]),
        torch.stack([e.world_from_cam for e in entries]),
        runtime.image_wh,
    )
    inc_mean, inc_var, inc_count = volume.statistics()
    assert torch.equal(inc_count, count)
    assert torch.allclose(inc_mean, mean, atol=1e-5) and torch.allclose(inc_var, var, atol=1e-5)
    assert runtime.views_added - runtime.views_removed == len(runtime) == 4


def test_callbacks_only_record_and_cancel_out(model: GovNeSF) -> None:
    runtime = make_runtime(model)
    window = KeyframeWindow(WindowConfig(max_keyframes=2, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i in range(5):
        window.consider(keyframe(i, orbit(i)))
    assert len(runtime) == 0 and runtime.version == 0  # nothing computed in the callbacks
    assert runtime.pending == 2  # 3 keyframes came and went before anything was applied
    assert runtime.sync() == 2 and len(runtime) == 2 and runtime.views_added == 2


def test_bounds_follow_the_robot_and_rebuild_is_counted(model: GovNeSF) -> None:
    runtime = make_runtime(model)
    window = KeyframeWindow(WindowConfig(max_keyframes=3, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i in range(3):
        window.consider(keyframe(i, orbit(i)))
    runtime.sync()
    first = runtime.bounds
    assert first is not None and runtime.rebuilds == 0
    for i in range(3, 6):  # the robot drives 10 m along x and looks around there
        window.consider(keyframe(i, orbit(i, centre=(10.0, 0.0)), target=(10.0, 0.0, 0.5)))
        runtime.sync()
    moved = runtime.bounds
    assert moved is not None and runtime.rebuilds >= 1
    assert moved.origin_m[0] > first.max_corner_m[0]  # now covers the new place only (window of 3)
    lo, hi = np.array(moved.origin_m), np.array(moved.max_corner_m)
    assert np.all((lo <= [10.0, 0.0, 0.5]) & ([10.0, 0.0, 0.5] <= hi))


def test_frames_of_any_size_and_without_ov_or_depth(model: GovNeSF) -> None:
    runtime = make_runtime(model)
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    window.consider(keyframe(0, orbit(0), wh=(64, 48)))
    window.consider(keyframe(1, orbit(1), wh=(20, 15), ov=np.ones((1, 1, D), np.float32)))
    window.consider(keyframe(2, orbit(2), wh=(33, 17), ov=None, depth_m=None))
    runtime.sync()
    assert len(runtime) == 3
    for entry in runtime._volume.entries.values():
        assert tuple(entry.rgb.shape) == (3, 24, 32)
        assert entry.ov is None or tuple(entry.ov.shape) == (D, 6, 8)
    # K scaled with the image: the principal point stays at the image centre.
    assert all(torch.allclose(e.K[2:], torch.tensor([16.0, 12.0])) for e in runtime._volume.entries.values())
    frame = runtime.render(
        [20.0, 20.0, 8.0, 6.0], look_at((2.2, 0.3, 1.0), (0, 0, 0.5)), 16, 12, ["rgb", "label"], ["a"]
    )
    assert frame.rgb is not None and frame.label is not None


def test_render_outputs_shapes_dtypes_ranges(model: GovNeSF) -> None:
    runtime = make_runtime(model)
    window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i in range(4):
        window.consider(keyframe(i, orbit(i)))
    pose = look_at((2.0, 0.5, 1.1), (0, 0, 0.5))
    frame = runtime.render(
        [20.0, 20.0, 10.0, 7.5], pose, 20, 15, ["rgb", "depth", "label", "score"], ["a", "b", "c"]
    )
    assert frame.rgb is not None and frame.rgb.shape == (15, 20, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth_m is not None and frame.depth_m.shape == (15, 20) and frame.depth_m.dtype == np.float32
    assert frame.label is not None and frame.label.shape == (15, 20) and frame.label.dtype == np.int32
    assert frame.score is not None and frame.score.shape == (15, 20, 3) and frame.score.dtype == np.float32
    assert frame.opacity is not None and np.all((frame.opacity >= 0) & (frame.opacity <= 1 + 1e-5))
    assert np.all(np.isfinite(frame.depth_m)) and np.all(frame.depth_m >= 0) and frame.depth_m.max() > 0
    assert np.all((frame.label >= -1) & (frame.label < 3))
    assert np.all(np.abs(frame.score) <= 1 + 1e-5)
    drawn = frame.opacity >= runtime.config.min_opacity
    assert np.all(frame.label[~drawn] == -1) and np.all(frame.depth_m[~drawn] == 0)
    only_depth = runtime.render(
        [20.0, 20.0, 10.0, 7.5], look_at((2.0, 0.5, 1.1), (0, 0, 0.5)), 20, 15, ["depth"]
    )
    assert only_depth.rgb is None and only_depth.label is None and only_depth.score is None
    np.testing.assert_allclose(only_depth.depth_m, frame.depth_m, atol=1e-5)


class SlabDensity:
    """A density field replacing the network's: ``sigma_max`` inside a slab of x (world), a tiny
    background elsewhere (so dense and skipping differ only by what skipping leaves out)."""

    def __init__(self, model: GovNeSF, x0: float, x1: float, sigma_max: float, background: float) -> None:
        self.model, self.x0, self.x1 = model, x0, x1
        self.sigma_max, self.background = sigma_max, background

    def __call__(
        self, volume: torch.Tensor, bounds: object, points: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        x = points[:, 0]
        inside = torch.sigmoid((x - self.x0) * 60) * torch.sigmoid((self.x1 - x) * 60)
        sigma = self.background + self.sigma_max * inside
        return sigma, torch.zeros(points.shape[0], volume.shape[0])


@pytest.fixture()
def slab_runtime(model: GovNeSF, monkeypatch: pytest.MonkeyPatch) -> ModelRuntime:
    """Keyframes facing a wall at x = 2 m (volume x from about -0.3 to 4.3 m), the density replaced
    by a slab x in [2.0, 2.2]."""
    runtime = make_runtime(model, samples_per_ray=64, occupancy_threshold=0.05, min_weight=1e-4)
    window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i, y in enumerate((-0.6, 0.0, 0.6)):  # the first one without depth: its frustum (to 4 m) counts
        window.consider(keyframe(i, (0.0, y, 1.0), (2.0, y, 1.0), depth_m=2.0 if i else None))
    runtime.sync()
    monkeypatch.setattr(model, "density_at", SlabDensity(model, 2.0, 2.2, 50.0, 1e-3))
    return runtime


def test_depth_is_z_depth_along_the_optical_axis(slab_runtime: ModelRuntime) -> None:
    # Camera at the origin looking along +x with a wide field of view: the wall at x = 2 m has
    # z-depth 2 m at every pixel, while the ray distance grows to 2 / cos(angle) at the corners.
    pose = look_at((0.0, 0.0, 1.0), (1.0, 0.0, 1.0))
    frame = slab_runtime.render([12.0, 12.0, 8.0, 6.0], pose, 16, 12, ["depth"], empty_space_skipping=False)
    assert frame.depth_m is not None and frame.opacity is not None
    assert np.all(frame.opacity > 0.99)
    # corner ray: |dir| / dir_z = sqrt(1 + (7.5/12)^2 + (5.5/12)^2) = 1.26, so its ray distance is
    # ~2.5 m; the z-depth of every pixel is the wall's 2 m (the soft slab edge absorbs from ~1.95 m).
    np.testing.assert_allclose(frame.depth_m, 2.0, atol=0.05)
    assert frame.depth_m.std() < 0.01


def test_empty_space_skipping_matches_dense_sampling(slab_runtime: ModelRuntime) -> None:
    pose = look_at((0.3, 0.2, 1.1), (2.0, -0.1, 0.9))
    K = [10.0, 10.0, 10.0, 7.5]
    dense = slab_runtime.render(
        K, pose, 20, 15, ["rgb", "depth", "score"], ["a", "b"], empty_space_skipping=False
    )
    skip = slab_runtime.render(
        K, pose, 20, 15, ["rgb", "depth", "score"], ["a", "b"], empty_space_skipping=True
    )
    assert skip.stats["samples"] == dense.stats["samples"]
    assert skip.stats["density_evals"] < 0.8 * dense.stats["density_evals"]
    assert skip.stats["appearance_evals"] < 0.2 * dense.stats["appearance_evals"]
    assert dense.rgb is not None and skip.rgb is not None and dense.depth_m is not None
    assert np.abs(dense.rgb.astype(int) - skip.rgb.astype(int)).max() <= 3  # of 255
    np.testing.assert_allclose(skip.depth_m, dense.depth_m, atol=0.02)
    np.testing.assert_allclose(skip.opacity, dense.opacity, atol=0.01)
    np.testing.assert_allclose(skip.score, dense.score, atol=0.02)


def test_segment_labels_points_that_views_see_and_minus_one_elsewhere(model: GovNeSF) -> None:
    runtime = make_runtime(model, source_views=2, view_cell_m=0.25)
    window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    b_feature = np.broadcast_to(TEXT_EMB[1], (4, 5, D)).astype(np.float32)  # every view says "b"
    for i in range(5):
        window.consider(keyframe(i, orbit(i), ov=b_feature))
    rng = np.random.default_rng(0)
    seen = rng.uniform([-0.4, -0.4, 0.3], [0.4, 0.4, 0.7], (300, 3)).astype(np.float32)
    unseen = np.array([[0.0, 0.0, 30.0], [50.0, 50.0, 0.0]], np.float32)  # above / far behind every camera
    label, score, timing = runtime.segment(np.concatenate([seen, unseen]), ["a", "b", "c"])
    assert label.dtype == np.int32 and score.dtype == np.float32 and label.shape == (302,)
    assert np.all(label[:300] == 1) and np.allclose(
        score[:300], 1.0, atol=1e-4
    )  # blend of identical features
    assert np.all(label[300:] == -1) and np.all(score[300:] == 0)
    assert timing["total"] > 0
    depth_label, _, _ = runtime.segment(seen, ["a", "b"], use_depth=True)
    assert depth_label.shape == (300,) and np.all(depth_label >= -1)
    empty_label, empty_score, _ = runtime.segment(np.zeros((0, 3), np.float32), ["a"])
    assert empty_label.shape == (0,) and empty_score.shape == (0,)


def test_segment_cosines_are_the_segment_answers_with_every_text(model: GovNeSF) -> None:
    """``segment_cosines`` (the node blends them with the map's): the same labels and scores as
    ``segment``, and per text the cosine of the blended feature (argmax = label, max = score, zero
    rows where unseen)."""
    runtime = make_runtime(model, source_views=2, view_cell_m=0.25)
    window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    rng = np.random.default_rng(1)
    for i in range(5):
        ov = rng.standard_normal((4, 5, D)).astype(np.float32)  # features that disagree across views
        window.consider(keyframe(i, orbit(i), ov=ov))
    pts = np.concatenate([rng.uniform([-0.4, -0.4, 0.3], [0.4, 0.4, 0.7], (200, 3)),
                          [[0.0, 0.0, 30.0]]]).astype(np.float32)  # fmt: skip
    texts = ["a", "b", "c"]
    label, score, _ = runtime.segment(pts, texts)
    label_c, score_c, cos, _ = runtime.segment_cosines(pts, texts)
    assert cos.shape == (201, 3) and cos.dtype == np.float32
    np.testing.assert_array_equal(label_c, label)
    np.testing.assert_allclose(score_c, score, atol=1e-6)
    seen = label >= 0
    assert seen[:200].all() and not seen[200]
    np.testing.assert_array_equal(np.argmax(cos[seen], axis=1), label[seen])
    np.testing.assert_allclose(cos[seen].max(axis=1), score[seen], atol=1e-6)
    assert (cos[~seen] == 0).all() and (np.abs(cos) <= 1 + 1e-5).all()


def test_view_groups_use_at_most_k_views_that_see_the_points(model: GovNeSF) -> None:
    runtime = make_runtime(model, source_views=2, view_cell_m=0.3)
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i in range(8):
        window.consider(keyframe(i, orbit(i)))
    prep = runtime._volume.prepare()
    points = torch.rand(500, 3) - torch.tensor([0.5, 0.5, 0.0])
    groups = view_groups(runtime._loaded, prep, points, torch.ones(len(prep), dtype=torch.bool))
    assert groups and sum(len(idx) for idx, _ in groups) <= 500
    for idx, views in groups:
        assert 1 <= len(views) <= 2
        from mapper.model.ops.geometry import in_view, invert_pose, project_points

        uv, z = project_points(
            points[idx].expand(len(views), -1, -1), prep.K[views], invert_pose(prep.world_from_cam[views])
        )
        assert bool(in_view(uv, z, *runtime.image_wh).any(dim=0).all())  # every point seen by its set


def test_not_ready_without_checkpoint_keyframes_or_ov(model: GovNeSF, tmp_path: Path) -> None:
    missing = tmp_path / "nowhere" / "model.safetensors"
    no_model = ModelRuntime(ModelRuntimeConfig(checkpoint=str(missing), device="cpu"))
    assert not no_model.ready and no_model.load_error and str(missing) in no_model.load_error
    with pytest.raises(RuntimeNotReady, match="nowhere"):
        no_model.render([10.0, 10.0, 5.0, 5.0], np.eye(4), 10, 10, ["rgb"])

    runtime = make_runtime(model)
    window = KeyframeWindow(WindowConfig(max_keyframes=4))
    runtime.attach(window)
    with pytest.raises(RuntimeNotReady, match="no keyframes"):
        runtime.segment(np.zeros((3, 3), np.float32), ["a"])
    window.consider(keyframe(0, orbit(0), ov=None))
    window.consider(keyframe(1, orbit(1), ov=None))
    frame = runtime.render(
        [10.0, 10.0, 8.0, 6.0], look_at((2.0, 0.0, 1.0), (0, 0, 0.5)), 16, 12, ["rgb", "depth"]
    )
    assert frame.rgb is not None and frame.depth_m is not None  # geometry works without ov
    with pytest.raises(RuntimeNotReady, match="OV features"):
        runtime.render(
            [10.0, 10.0, 8.0, 6.0], look_at((2.0, 0.0, 1.0), (0, 0, 0.5)), 16, 12, ["label"], ["a"]
        )
    with pytest.raises(RuntimeNotReady, match="OV features"):
        runtime.segment(np.zeros((3, 3), np.float32), ["a"])


def test_bad_requests_are_refused_with_the_value_and_range(model: GovNeSF) -> None:
    runtime = make_runtime(model, max_render_pixels=100)
    with pytest.raises(ValueError, match="max_render_pixels"):
        runtime.render([10.0, 10.0, 5.0, 5.0], np.eye(4), 20, 20, ["rgb"])
    with pytest.raises(ValueError, match="subset"):
        runtime.render([10.0, 10.0, 5.0, 5.0], np.eye(4), 5, 5, ["normals"])
    with pytest.raises(ValueError, match="texts"):
        runtime.render([10.0, 10.0, 5.0, 5.0], np.eye(4), 5, 5, ["label"])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        runtime.segment(np.zeros((4, 2), np.float32), ["a"])
    with pytest.raises(ConfigError, match="model.view_selection"):
        ModelRuntimeConfig(view_selection="random").validate("node.toml")
    with pytest.raises(ConfigError, match=r"model.far_m = 0.1 must exceed"):
        ModelRuntimeConfig(near_m=0.5, far_m=0.1).validate("node.toml")
    ModelRuntimeConfig().validate("defaults")


@pytest.mark.skipif(
    not (Path(__file__).resolve().parents[3] / "checkpoints" / "cpu-small.json").exists(),
    reason="no trained checkpoint in checkpoints/",
)
def test_default_checkpoint_loads_and_serves_a_tiny_render() -> None:
    runtime = ModelRuntime(
        ModelRuntimeConfig(device="cpu", samples_per_ray=8), text_encoder=lambda s: FakeEncoder()
    )
    assert runtime.ready, runtime.load_error
    assert runtime.image_wh == runtime.model.cfg.image_wh  # type: ignore[union-attr]
    window = KeyframeWindow(WindowConfig(max_keyframes=3, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i in range(2):
        window.consider(keyframe(i, orbit(i), ov=None))
    frame = runtime.render(
        [6.0, 6.0, 4.0, 3.0], look_at((2.2, 0.3, 1.1), (0, 0, 0.5)), 8, 6, ["rgb", "depth"]
    )
    assert frame.rgb is not None and frame.rgb.shape == (6, 8, 3) and frame.depth_m is not None


def test_point_source_views_sets_the_views_of_point_answers_only(model: GovNeSF) -> None:
    """``point_source_views`` 0 or below ``source_views`` answers with ``source_views``; more views give
    larger view groups for ``segment`` / ``point_features``; renders keep ``source_views``."""
    rng = np.random.default_rng(1)
    pts = rng.uniform([-0.4, -0.4, 0.3], [0.4, 0.4, 0.7], (300, 3)).astype(np.float32)
    answers = {}
    cases = (("default", {"point_source_views": 0}), ("same", {"point_source_views": 1}),
             ("more", {"point_source_views": 5}))
    for name, extra in cases:
        runtime = make_runtime(model, source_views=2, view_cell_m=0.25, **extra)
        window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
        runtime.attach(window)
        for i in range(6):
            window.consider(keyframe(i, orbit(i)))
        runtime.sync()
        assert runtime.source_views == 2
        label, score, _ = runtime.segment(pts, ["a", "b", "c"])
        feats, valid = runtime.point_features(pts)
        prep = runtime._volume.prepare()
        groups = view_groups(runtime._loaded, prep, torch.from_numpy(pts), prep.has_ov,
                             runtime.point_source_views)
        answers[name] = (label, score, feats, max(v.numel() for _, v in groups))
    for a, b in zip(answers["default"][:3], answers["same"][:3], strict=True):
        np.testing.assert_array_equal(a, b)
    assert answers["default"][3] == 2 and answers["more"][3] == 5
    assert not np.array_equal(answers["more"][2], answers["default"][2])  # other views, other features
    with pytest.raises(ConfigError, match="point_source_views"):
        ModelRuntimeConfig(point_source_views=300).validate("test")


def test_surface_render_at_an_opaque_surface_matches_the_march(slab_runtime: ModelRuntime) -> None:
    # The slab's front face is opaque (50 / m): the march's colour, scores and depth come from
    # just behind x = 2 m; rendering every pixel AT the march's surface gives the same image with
    # one appearance evaluation a pixel and no density evaluation.
    pose = look_at((0.3, 0.2, 1.1), (2.0, -0.1, 0.9))
    K = [10.0, 10.0, 10.0, 7.5]
    march = slab_runtime.render(K, pose, 20, 15, ["rgb", "depth", "score"], ["a", "b"])
    assert march.depth_m is not None and march.rgb is not None and march.score is not None
    opaque = march.opacity > 0.99  # (rays leaving the volume box through its sides are not)
    assert opaque.mean() > 0.5
    known = np.where(opaque, march.depth_m, 0.0).astype(np.float32)
    surface = slab_runtime.render(
        K, pose, 20, 15, ["rgb", "depth", "score"], ["a", "b"], surface_depth_m=known
    )
    n = int(opaque.sum())
    assert surface.stats["surface_rays"] == n
    assert surface.depth_m is not None and surface.rgb is not None and surface.score is not None
    np.testing.assert_allclose(surface.depth_m[opaque], march.depth_m[opaque], rtol=1e-5)
    np.testing.assert_array_equal(surface.opacity[opaque], 1.0)
    # the same colour (of 255) but where a pixel's view set differs (view selection per cell)
    diff = np.abs(surface.rgb[opaque].astype(int) - march.rgb[opaque].astype(int)).max(axis=-1)
    assert np.mean(diff <= 4) >= 0.95 and diff.mean() <= 2.0
    close = np.abs(surface.score[opaque] - march.score[opaque]).max(axis=-1) <= 0.03
    assert close.mean() >= 0.95
    everywhere = slab_runtime.render(
        K, pose, 20, 15, ["rgb"], surface_depth_m=np.full((15, 20), 2.0, np.float32)
    )
    # one density (for its volume feature) and one appearance evaluation a pixel, no march
    assert everywhere.stats["density_evals"] == 300 and everywhere.stats["appearance_evals"] == 300


def test_surface_pixels_leave_the_others_marched_as_before(slab_runtime: ModelRuntime) -> None:
    pose = look_at((0.3, 0.2, 1.1), (2.0, -0.1, 0.9))
    K = [10.0, 10.0, 10.0, 7.5]
    march = slab_runtime.render(K, pose, 20, 15, ["rgb", "depth", "label"], ["a", "b"])
    known = np.zeros((15, 20), np.float32)
    known[:, :8] = 2.5  # a surface that is not the slab's: taken as given
    mixed = slab_runtime.render(K, pose, 20, 15, ["rgb", "depth", "label"], ["a", "b"], surface_depth_m=known)
    assert mixed.stats["surface_rays"] == 15 * 8
    assert mixed.depth_m is not None and march.depth_m is not None and mixed.rgb is not None
    np.testing.assert_allclose(mixed.depth_m[:, :8], 2.5, rtol=1e-5)
    np.testing.assert_allclose(mixed.depth_m[:, 8:], march.depth_m[:, 8:], atol=1e-5)
    assert march.rgb is not None and mixed.label is not None and march.label is not None
    assert np.abs(mixed.rgb[:, 8:].astype(int) - march.rgb[:, 8:].astype(int)).max() <= 1
    np.testing.assert_array_equal(mixed.label[:, 8:], march.label[:, 8:])
    at_3m = np.full((15, 20), 3.0, np.float32)
    depth_only = slab_runtime.render(K, pose, 20, 15, ["depth"], surface_depth_m=at_3m)
    assert depth_only.stats["appearance_evals"] == 0 and depth_only.stats["density_evals"] == 0
    np.testing.assert_allclose(depth_only.depth_m, 3.0, rtol=1e-5)  # type: ignore[arg-type]


def test_surface_depth_is_checked_before_any_work(slab_runtime: ModelRuntime) -> None:
    pose = look_at((0.3, 0.2, 1.1), (2.0, -0.1, 0.9))
    K = [10.0, 10.0, 10.0, 7.5]
    for bad, what in (
        (np.ones((15, 19), np.float32), "shape"),
        (np.full((15, 20), np.nan, np.float32), "finite"),
        (np.full((15, 20), -1.0, np.float32), ">= 0"),
    ):
        with pytest.raises(ValueError, match=what):
            slab_runtime.render(K, pose, 20, 15, ["rgb"], surface_depth_m=bad)



# -- render volumes over the keyframes that overlap the view (render_volume_views) ---------------


def _orbit_runtime(model: GovNeSF, n_keyframes: int, **overrides: object) -> ModelRuntime:
    runtime = make_runtime(model, **overrides)
    window = KeyframeWindow(
        WindowConfig(max_keyframes=n_keyframes, min_translation_m=0.05, min_rotation_deg=5)
    )
    runtime.attach(window)
    for i in range(n_keyframes):  # a full circle around the origin, every camera looking at it
        window.consider(keyframe(i, orbit(i, radius=2.0), depth_m=1.5))
    runtime.sync()
    return runtime


def test_render_volume_is_the_batch_volume_of_the_views_that_overlap_the_render(model: GovNeSF) -> None:
    runtime = _orbit_runtime(model, 8)
    with runtime._volume.lock:
        prep = runtime._volume.prepare()
        kf = 5
        K, pose = prep.K[kf], prep.world_from_cam[kf]
        w, h = runtime.image_wh
        chosen = overlapping_views(runtime._loaded, prep, K, pose, w, h, 3)
        local = render_prep(runtime._loaded, model, prep, K, pose, w, h, 3)
    # the keyframe at the render pose sees all it observed: first; then the largest shares
    from mapper.model.ops.geometry import in_view, invert_pose, project_points

    shares = []
    for e in prep.extents:
        uv, z = project_points(e[None], K[None], invert_pose(pose)[None])
        shares.append(float(in_view(uv, z, w, h)[0].float().mean()))
    assert chosen.tolist()[0] == kf and shares[kf] == 1.0
    others = [shares[i] for i in range(len(shares)) if i not in chosen.tolist()]
    assert min(shares[int(i)] for i in chosen) >= max(others)
    idx = chosen
    points = torch.cat([prep.extents[int(i)] for i in idx])
    lo, hi = np.array(local.bounds.origin_m), np.array(local.bounds.max_corner_m)
    inside = ((points.numpy() >= lo) & (points.numpy() <= hi)).all(axis=1)
    assert inside.mean() > 0.95  # the bounds cover what those keyframes observed
    assert local.bounds != prep.bounds and local.volume.shape[1:] == tuple(local.bounds.dims)
    with torch.no_grad():
        mean, var, count = build_cost_volume(local.bounds, prep.features[idx], prep.K[idx],
                                             prep.world_from_cam[idx], runtime.image_wh)
        direct = model.volume_features(cost_volume_features(mean, var, count))
    assert torch.allclose(local.volume, direct, atol=1e-5)
    # the blend still reads every window keyframe
    assert local.rgb is prep.rgb and local.features is prep.features and local.K is prep.K
    # outside the render volume: no density, and the window's volume features for the blend
    with torch.no_grad():
        outside = torch.tensor([[float(prep.bounds.max_corner_m[0]) - 0.01, *((lo + hi) / 2)[1:]]],
                               dtype=torch.float32)
        assert float(outside[0, 0]) > hi[0]  # inside the window's box, outside the render volume's
        sigma_l, v_l = density(model, local, outside)
        _, v_w = density(model, prep, outside)
    assert float(sigma_l[0]) == 0.0 and torch.equal(v_l, v_w)
    # cached for this version and this set of views; another set is another volume
    with runtime._volume.lock:
        assert render_prep(runtime._loaded, model, runtime._volume.prepare(), K, pose, w, h, 3) is local
        assert render_prep(runtime._loaded, model, runtime._volume.prepare(), K, pose, w, h, 4) is not local


def test_render_volume_views_zero_or_a_small_window_render_from_the_window(model: GovNeSF) -> None:
    pose = look_at((2.0, 0.5, 1.1), (0, 0, 0.5))
    K = [20.0, 20.0, 10.0, 7.5]
    runtime = _orbit_runtime(model, 6)
    off = runtime.render(K, pose, 20, 15, ["rgb", "depth"])  # config default: 0
    assert runtime.config.render_volume_views == 0
    for same in (runtime.render(K, pose, 20, 15, ["rgb", "depth"], volume_views=0),
                 runtime.render(K, pose, 20, 15, ["rgb", "depth"], volume_views=6)):  # the whole window
        assert np.array_equal(off.rgb, same.rgb) and np.array_equal(off.depth_m, same.depth_m)
    local = runtime.render(K, pose, 20, 15, ["rgb", "depth"], volume_views=3)
    configured = _orbit_runtime(model, 6, render_volume_views=3).render(K, pose, 20, 15, ["rgb", "depth"])
    assert local.depth_m is not None and np.isfinite(local.depth_m).all()
    assert np.array_equal(local.depth_m, configured.depth_m)
    assert not np.array_equal(local.depth_m, off.depth_m)
    assert local.stats["render_volume_views"] == 3 and off.stats["render_volume_views"] == 0
    as_numpy = runtime.render(K, pose, 20, 15, ["depth"], volume_views=np.int64(3))  # type: ignore[arg-type]
    assert as_numpy.stats["render_volume_views"] == 3
    assert runtime.render(K, pose, 20, 15, ["depth"], volume_views=1).stats["render_volume_views"] == 0
    # a view that sees none of what the keyframes observed falls back to the window's volume
    away = look_at((10.0, 0.0, 1.2), (20.0, 0.0, 1.2))  # 10 m out, looking further away
    with runtime._volume.lock:
        prep = runtime._volume.prepare()
        K_t = torch.tensor(K, dtype=torch.float32)
        away_t = torch.from_numpy(away).float()
        assert render_prep(runtime._loaded, model, prep, K_t, away_t, 20, 15, 3) is prep
    for bad in (-1, 257, 2.5, True):
        with pytest.raises(ValueError, match="volume_views"):
            runtime.render(K, pose, 20, 15, ["depth"], volume_views=bad)  # type: ignore[arg-type]


def test_render_volumes_are_cached_per_keyframe_set_and_the_oldest_dropped(model: GovNeSF) -> None:
    runtime = _orbit_runtime(model, 12)
    w, h = runtime.image_wh
    with runtime._volume.lock:
        prep = runtime._volume.prepare()
        K = prep.K[0]
        built = [render_prep(runtime._loaded, model, prep, K, prep.world_from_cam[i], w, h, 3)
                 for i in range(12)]
        keys = list(prep.render_volumes)
        assert len(keys) == RENDER_VOLUMES_KEPT < len({id(b) for b in built})
        assert all(list(k) == sorted(k) for k in keys)  # a set of keyframes, whatever the order
        # the newest are kept: rendering the last pose again is a cache hit, the first is rebuilt
        assert render_prep(runtime._loaded, model, prep, K, prep.world_from_cam[11], w, h, 3) is built[11]
        assert render_prep(runtime._loaded, model, prep, K, prep.world_from_cam[0], w, h, 3) is not built[0]
        # a render volume shares the window's OV gather table
        assert prep.ov is not None
        maps = built[11].ov_maps(torch.tensor([0, 1]), runtime.image_wh)
        assert maps.table is prep.ov_table and built[11].ov_table is None


def test_render_volumes_leave_out_what_lies_outside_the_window_box(
    model: GovNeSF, monkeypatch: pytest.MonkeyPatch
) -> None:
    runtime = _orbit_runtime(model, 6)
    w, h = runtime.image_wh
    chosen = torch.tensor([1, 2, 3])
    monkeypatch.setattr(prepared, "overlapping_views", lambda *args: chosen)
    with runtime._volume.lock:
        prep = runtime._volume.prepare()
        K, pose = prep.K[1], prep.world_from_cam[1]
        before = render_prep(runtime._loaded, model, prep, K, pose, w, h, 3)
        prep.render_volumes.clear()
        # keyframe 2 also "observed" as many points 1 km away (a wild pose; far more than the 1% the
        # bounds' quantiles trim)
        wild = torch.tensor([1000.0, 0.0, 0.0]).expand(prep.extents[2].shape[0], 3)
        prep.extents[2] = torch.cat([prep.extents[2], wild])
        after = render_prep(runtime._loaded, model, prep, K, pose, w, h, 3)
    assert after is not before and after.bounds == before.bounds  # as if the wild points were not there


def test_render_volume_views_is_validated() -> None:
    for bad in (-1, 257, 2.5e9, 2.5, True):
        with pytest.raises(ConfigError, match="render_volume_views"):
            ModelRuntimeConfig(render_volume_views=bad).validate()  # type: ignore[arg-type]


def test_render_volumes_follow_new_view_extents_without_depth(model: GovNeSF) -> None:
    """RGB-only keyframes: points given later by set_view_extent (triangulation) move the bounds of
    the render volumes even when the window's own volume does not change."""
    runtime = make_runtime(model)
    window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    frames = [keyframe(i, orbit(i), depth_m=None) for i in range(6)]
    for kf in frames:
        window.consider(kf)
    runtime.sync()
    w, h = runtime.image_wh
    with runtime._volume.lock:
        prep = runtime._volume.prepare()
        K, pose = prep.K[2], prep.world_from_cam[2]
        before = render_prep(runtime._loaded, model, prep, K, pose, w, h, 3)
    assert before is not prep and len(prep.render_volumes) == 1
    # the keyframes of that render volume observed a small cluster near the origin; the others keep
    # their frusta, so the window's box (over all of them) stays and its volume is not rebuilt
    with runtime._volume.lock:
        chosen_before = overlapping_views(runtime._loaded, prep, K, pose, w, h, 3).tolist()
    rng = np.random.default_rng(0)
    clusters = {i: rng.normal((0.0, 0.0, 0.5), 0.05, (32, 3)) for i in chosen_before}
    for i, cluster in clusters.items():
        kf = frames[i]
        runtime.set_view_extent((kf.camera, kf.seq, kf.stamp_ns), cluster)
    version = runtime.version
    runtime.sync()
    with runtime._volume.lock:
        assert runtime.version == version and runtime._volume.prepare() is prep  # the window's volume stayed
        assert not prep.render_volumes  # its render volumes were dropped
        assert all(np.allclose(prep.extents[i].numpy(), c, atol=1e-6) for i, c in clusters.items())
        after = render_prep(runtime._loaded, model, prep, K, pose, w, h, 3)
        chosen = overlapping_views(runtime._loaded, prep, K, pose, w, h, 3)
    expected = bounds_from_points(
        torch.cat([prep.extents[int(i)] for i in chosen]), max_voxels=model.cfg.volume.max_voxels,
        min_voxel_size_m=model.cfg.volume.min_voxel_size_m, margin_m=runtime.config.bounds_margin_m,
    )
    assert after.bounds == expected and after.bounds != before.bounds
