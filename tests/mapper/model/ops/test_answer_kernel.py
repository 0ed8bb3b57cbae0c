"""The learned point answers in one compiled pass (``mapper.model.ops.answer_kernel``) equal the
three kernels run one after the other."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from mapper.model.config import FusionConfig
from mapper.model.fusion import FusionNet
from mapper.model.ops import answer_kernel
from mapper.model.ops.cost_volume import sample_volume
from mapper.runtime import points as point_answers
from tests.mapper.model.ops.test_sample_kernel import _points, _window
from tests.mapper.runtime.test_model_runtime import TEXT_EMB


def _problem(use_depth: bool, n_slots: int = 5, seed: int = 1):  # -> (model, runtime, prep, views, args)
    model, runtime, prep, views = _window(use_depth=use_depth)
    pts = _points(300, seed=seed)
    gen = torch.Generator().manual_seed(seed + 1)
    idx = torch.randint(0, len(views), (pts.shape[0], n_slots), generator=gen)
    slots = torch.rand(pts.shape[0], n_slots, generator=gen) < 0.8  # some padding slots
    slots[:40, 2:] = False  # a block of points using only the first two slots (trailing padding dropped)
    slots[-1] = False  # a point with no slot at all
    v, _ = sample_volume(prep.volume, prep.bounds, pts)
    texts = torch.from_numpy(TEXT_EMB)
    return model, runtime, prep, views, (idx, slots, pts, v, texts)


def _reference(model, views, idx, slots, pts, use_depth, v, texts, ov_maps, fusion=None):
    with torch.no_grad():
        samples = model.sample_views_indexed(views, idx, slots, pts, use_depth, sample_ov=False)
        return model.point_cosines(samples, v, texts, ov_maps=ov_maps, fusion=fusion)


@pytest.mark.parametrize("use_depth", [False, True])
def test_one_pass_equals_the_three_kernels(use_depth: bool) -> None:
    model, runtime, prep, views, (idx, slots, pts, v, texts) = _problem(use_depth)
    ov_maps = prep.ov_maps(idx, runtime.image_wh)
    ref_cos, ref_valid, ref_n = _reference(model, views, idx, slots, pts, use_depth, v, texts, ov_maps)
    with torch.no_grad():
        assert model.answer_kernel_applies(views, pts, ov_maps.table)
        cos, valid, n = model.point_cosines_indexed(views, idx, slots, pts, use_depth, v, texts, ov_maps)
    assert torch.equal(valid, ref_valid) and torch.equal(n, ref_n)
    assert bool(valid.any()) and not bool(valid.all())  # some points seen, some not
    torch.testing.assert_close(cos, ref_cos, atol=1e-6, rtol=1e-6)
    assert torch.all(cos[~valid] == 0)


def test_a_point_head_with_range_encoding() -> None:
    """Another network in place of the model's FusionNet (a point head), with the range encoding's
    log distances computed in the kernel."""
    model, runtime, prep, views, (idx, slots, pts, v, texts) = _problem(False, seed=5)
    torch.manual_seed(3)
    cfg = dataclasses.replace(FusionConfig(), hidden_dim=8, attention_dim=4, num_heads=1,
                              ov_dim=texts.shape[1], range_encoding=True)
    head = FusionNet(model.cfg.encoder.feature_dim, model.cfg.volume.volume_feature_dim, cfg).eval()
    ov_maps = prep.ov_maps(idx, runtime.image_wh)
    ref_cos, ref_valid, _ = _reference(model, views, idx, slots, pts, False, v, texts, ov_maps, fusion=head)
    with torch.no_grad():
        cos, valid, _ = model.point_cosines_indexed(views, idx, slots, pts, False, v, texts, ov_maps,
                                                    fusion=head)
    assert torch.equal(valid, ref_valid)
    torch.testing.assert_close(cos, ref_cos, atol=1e-5, rtol=1e-5)


def test_the_block_size_changes_nothing() -> None:
    model, runtime, prep, views, (idx, slots, pts, v, texts) = _problem(True, n_slots=4, seed=7)
    rgb_t, feat_t, _ = views.channel_last()
    ov_maps = prep.ov_maps(idx, runtime.image_wh)
    from mapper.model.ops.geometry import camera_centers, invert_pose
    from mapper.model.ops.sample_kernel import pair_args

    def run(block: int):  # -> (cos, valid, num_views)
        assert views.depth_m is not None
        pairs = pair_args(
            invert_pose(views.world_from_cam).numpy(), views.K.numpy(),
            camera_centers(views.world_from_cam).numpy(), views.image_wh, 1e-6,
            (rgb_t.numpy(), (views.rgb.shape[-1], views.rgb.shape[-2])),
            (feat_t.numpy(), (views.features.shape[-1], views.features.shape[-2])),
            (views.depth_m.numpy(), (views.depth_m.shape[-1], views.depth_m.shape[-2])),
            model.cfg.render.depth_mask_ratio,
        )
        return answer_kernel.answer_points(
            model.fusion.point_kernel_weights(), pts.numpy(), idx.T.numpy(), slots.T.numpy(), pairs,
            v.numpy(), (ov_maps.table.numpy(), ov_maps.map_wh), texts.numpy(), threads=2, block=block,
        )

    first = run(1)
    for block in (3, 64, 1024):  # up to float rounding: the network's loops vectorise by block
        cos, valid, num_views = run(block)
        np.testing.assert_allclose(cos, first[0], atol=1e-6, rtol=0.0)
        np.testing.assert_array_equal(valid, first[1])
        np.testing.assert_array_equal(num_views, first[2])


def test_no_points_and_bad_shapes() -> None:
    model, runtime, prep, views, (idx, slots, pts, v, texts) = _problem(False)
    ov_maps = prep.ov_maps(idx, runtime.image_wh)
    with torch.no_grad():
        cos, valid, n = model.point_cosines_indexed(views, idx[:0], slots[:0], pts[:0], False, v[:0], texts,
                                                    ov_maps)
        assert cos.shape == (0, texts.shape[0]) and valid.shape == (0,) and n.shape == (0,)
        with pytest.raises(ValueError, match="do not fit"):
            model.point_cosines_indexed(views, idx, slots[:-1], pts, False, v, texts, ov_maps)
        with pytest.raises(ValueError, match="must index"):
            model.point_cosines_indexed(views, idx + len(views), slots, pts, False, v, texts, ov_maps)
        with pytest.raises(ValueError, match="do not fit"):
            model.point_cosines_indexed(views, idx, slots, pts, False, v, texts[:, :3], ov_maps)
    # and where it does not apply (autograd), it says so instead of answering differently
    assert not model.answer_kernel_applies(views, pts.requires_grad_(True), ov_maps.table)


@pytest.mark.parametrize("chunk", [65536, 256])
def test_the_runtime_answers_the_same_either_way(chunk: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """``model.fused_point_answers`` on (in one call, or in calls of 256 points) and off: the same
    labels and scores from ``segment``."""
    monkeypatch.setattr(point_answers, "FUSED_CHUNK_POINTS", chunk)
    model, runtime, _, _ = _window(use_depth=False)
    pts = _points(700, seed=11).numpy()
    texts = ["a chair", "b table", "c wall"]
    answers = []
    for fused in (True, False):
        runtime.config = dataclasses.replace(runtime.config, fused_point_answers=fused)
        for use_depth in (False, True):
            label, score, cos, _ = runtime.segment_cosines(pts, texts, use_depth=use_depth)
            answers.append((label, score, cos))
    for a, b in zip(answers[:2], answers[2:], strict=True):
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_allclose(a[1], b[1], atol=1e-6)
        np.testing.assert_allclose(a[2], b[2], atol=1e-6)
    assert (answers[0][0] >= 0).any()


@pytest.mark.parametrize("use_depth", [False, True])
def test_the_features_themselves_equal_point_outputs(use_depth: bool) -> None:
    """``point_features_indexed``: the blended OV features, as ``point_outputs(...).ov``."""
    model, runtime, prep, views, (idx, slots, pts, v, texts) = _problem(use_depth, seed=13)
    ov_maps = prep.ov_maps(idx, runtime.image_wh)
    with torch.no_grad():
        samples = model.sample_views_indexed(views, idx, slots, pts, use_depth, sample_ov=False)
        ref = model.point_outputs(samples, v, ov_maps=ov_maps)
        feats, valid, n = model.point_features_indexed(views, idx, slots, pts, use_depth, v, ov_maps)
    assert feats.shape == ref.ov.shape
    assert torch.equal(valid, ref.valid) and torch.equal(n, ref.num_views)
    torch.testing.assert_close(feats, ref.ov, atol=1e-6, rtol=1e-5)
    assert torch.all(feats[~valid] == 0)
    with torch.no_grad(), pytest.raises(ValueError, match="no embedding"):  # no texts: not the features
        model.point_cosines_indexed(views, idx, slots, pts, use_depth, v, texts[:0], ov_maps)


def test_the_runtime_point_features_the_same_either_way() -> None:
    """``ModelRuntime.point_features`` (the learned features written into the global map): the one
    pass against one pass per view group."""
    model, runtime, _, _ = _window(use_depth=False)
    pts = _points(700, seed=17).numpy()
    answers = []
    for fused in (True, False):
        runtime.config = dataclasses.replace(runtime.config, fused_point_answers=fused)
        answers.append(runtime.point_features(pts))
    np.testing.assert_array_equal(answers[0][1], answers[1][1])
    assert answers[0][1].any() and not answers[0][1].all()
    np.testing.assert_allclose(answers[0][0], answers[1][0], atol=1e-5, rtol=1e-4)
