"""OpenScene-2D style multi-view averaging on a tiny synthetic setup."""

import numpy as np
import pytest
import torch

from mapper.model.baselines import OVView, average_features

W, H = 64, 48
K = np.array([50.0, 50.0, 32.0, 24.0])


def look_from(center, target):
    """world_from_cam of an OpenCV camera at ``center`` looking at ``target`` (+z up world)."""
    center, target = np.asarray(center, float), np.asarray(target, float)
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = center
    return pose


def const_map(vec, h=12, w=16):
    return np.tile(np.asarray(vec, np.float16), (h, w, 1))


POINT = np.array([[0.0, 0.0, 1.0]])
FEAT_A = [1.0, 0.0, 0.0]
FEAT_B = [0.0, 1.0, 0.0]


def two_views(occluded_in_b: bool):
    pose_a = look_from([-2.0, 0.0, 1.0], POINT[0])
    pose_b = look_from([0.0, -3.0, 1.0], POINT[0])
    depth_a = np.full((H, W), 2.0, np.float32)  # the point is 2 m in front of camera a: visible
    depth_b = np.full((H, W), 1.2 if occluded_in_b else 3.0, np.float32)  # z = 3 m
    return [
        OVView(const_map(FEAT_A), K, pose_a, (W, H), depth_a),
        (const_map(FEAT_B), K, pose_b, (W, H), depth_b),  # a plain tuple works too
    ]


def test_occluded_view_is_excluded_with_depth_but_not_without():
    views = two_views(occluded_in_b=True)
    f_nodepth, n_nodepth = average_features(POINT, views, use_depth=False)
    f_depth, n_depth = average_features(POINT, views, use_depth=True)
    assert n_nodepth.tolist() == [2] and n_depth.tolist() == [1]
    s = 1 / np.sqrt(2)
    np.testing.assert_allclose(f_nodepth.numpy(), [[s, s, 0.0]], atol=1e-6)
    np.testing.assert_allclose(f_depth.numpy(), [FEAT_A], atol=1e-6)
    # Not occluded: the depth test keeps both.
    _, n_visible = average_features(POINT, two_views(occluded_in_b=False), use_depth=True)
    assert n_visible.tolist() == [2]


def test_depth_tolerance_is_relative_to_the_measured_depth():
    pose = look_from([-2.0, 0.0, 1.0], POINT[0])  # point at z = 2 m
    for depth, counted in [(2.5, True), (2.7, False), (1.61, True), (1.59, False), (0.0, False)]:
        view = (const_map(FEAT_A), K, pose, (W, H), np.full((H, W), depth, np.float32))
        # |d - 2| <= 0.25 d  <=>  1.6 <= d <= 2.667
        _, n = average_features(POINT, [view], use_depth=True)
        assert n.item() == int(counted), depth


def test_border_cut_behind_camera_and_unseen_points():
    pose = look_from([-2.0, 0.0, 1.0], POINT[0])
    # u = 50 * y / 2 + 32: a point 1.05 m sideways projects at u = 32 + 26.25 = 58.25 > 64 - 10
    sideways = np.array([[0.0, -1.05, 1.0], [0.0, -0.5, 1.0], [-4.0, 0.0, 1.0]])
    view = (const_map(FEAT_A), K, pose, (W, H), None)
    feats, n = average_features(sideways, [view], use_depth=False)
    assert n.tolist() == [0, 1, 0]  # border cut, inside, behind the camera
    assert torch.all(feats[0] == 0) and torch.all(feats[2] == 0)
    _, n_border0 = average_features(sideways, [view], use_depth=False, border_px=0)
    assert n_border0.tolist() == [1, 1, 0]
    # use_depth without any depth map: nothing counts.
    _, n_nodepth = average_features(sideways, [view], use_depth=True)
    assert n_nodepth.tolist() == [0, 0, 0]


def test_bilinear_sampling_of_a_low_resolution_map_and_chunking():
    rng = np.random.default_rng(0)
    views = [
        (rng.standard_normal((12, 16, 5)).astype(np.float16), K,
         look_from([-2.0 + 0.1 * i, 0.3 * i, 1.2], POINT[0]), (W, H), None)
        for i in range(4)
    ]
    pts = rng.uniform(-0.3, 0.3, size=(37, 3)) + POINT
    f1, n1 = average_features(pts, views, use_depth=False, chunk=5)
    f2, n2 = average_features(pts, views, use_depth=False, chunk=1000)
    torch.testing.assert_close(f1, f2)
    assert torch.equal(n1, n2)
    np.testing.assert_allclose(f1.norm(dim=1).numpy()[n1.numpy() > 0], 1.0, atol=1e-5)
    # A map that is linear in u is sampled exactly by bilinear interpolation at interior points.
    ramp = np.tile(np.arange(16, dtype=np.float32)[None, :, None], (12, 1, 1)) + 0.5  # value = u_low
    ramp = np.concatenate([ramp, np.ones_like(ramp)], axis=-1)  # (12, 16, 2)
    pose = look_from([-2.0, 0.0, 1.0], POINT[0])
    pt = np.array([[0.0, -0.3, 1.0]])  # u = 32 + 50 * 0.3 / 2 = 39.5 full res -> 9.875 low res
    f, _ = average_features(pt, [(ramp, K, pose, (W, H), None)], use_depth=False)
    assert f[0, 0] / f[0, 1] == pytest.approx(39.5 / 4, rel=1e-5)


def test_distance_weighting():
    near = (const_map(FEAT_A), K, look_from([-1.0, 0.0, 1.0], POINT[0]), (W, H), None)  # z = 1
    far = (const_map(FEAT_B), K, look_from([0.0, -3.0, 1.0], POINT[0]), (W, H), None)  # z = 3
    f, n = average_features(POINT, [near, far], use_depth=False, distance_power=2.0)
    # weights 1 and 1/9
    expected = np.array([1.0, 1 / 9, 0.0])
    np.testing.assert_allclose(f[0].numpy(), expected / np.linalg.norm(expected), atol=1e-6)


def test_bad_input():
    with pytest.raises(ValueError, match="points must have shape"):
        average_features(np.zeros((3, 2)), [], use_depth=False)
    with pytest.raises(ValueError, match="different dimensions"):
        average_features(POINT, [(np.zeros((4, 4, 3)), K, np.eye(4), (W, H), None),
                                 (np.zeros((4, 4, 5)), K, np.eye(4), (W, H), None)], use_depth=False)


def test_view_weights_exclude_and_weight_views_per_point():
    views = two_views(occluded_in_b=False)
    f, n = average_features(POINT, views, use_depth=False, view_weights=np.array([[True], [False]]))
    assert n.tolist() == [1]
    np.testing.assert_allclose(f.numpy(), [FEAT_A], atol=1e-6)
    f, n = average_features(POINT, views, use_depth=False, view_weights=np.array([[3.0], [1.0]]))
    assert n.tolist() == [2]
    np.testing.assert_allclose(f.numpy(), [[3 / np.sqrt(10), 1 / np.sqrt(10), 0.0]], atol=1e-6)
    with pytest.raises(ValueError, match="view_weights must have shape"):
        average_features(POINT, views, use_depth=False, view_weights=np.ones((3, 1), bool))
    with pytest.raises(ValueError, match=">= 0"):
        average_features(POINT, views, use_depth=False, view_weights=-np.ones((2, 1)))


def test_view_weights_follow_points_across_chunks():
    rng = np.random.default_rng(1)
    views = [(rng.standard_normal((12, 16, 4)).astype(np.float16), K,
              look_from([-2.0 + 0.2 * i, 0.4 * i, 1.1], POINT[0]), (W, H), None) for i in range(3)]
    pts = rng.uniform(-0.3, 0.3, size=(23, 3)) + POINT
    weights = rng.uniform(0.0, 2.0, size=(3, 23)) * (rng.random((3, 23)) > 0.3)
    f1, n1 = average_features(pts, views, use_depth=False, view_weights=weights, chunk=4)
    f2, n2 = average_features(pts, views, use_depth=False, view_weights=weights, chunk=100)
    torch.testing.assert_close(f1, f2)
    assert torch.equal(n1, n2) and n1.max() <= 3
