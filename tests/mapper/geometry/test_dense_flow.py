"""Dense points from posed RGB by DIS optical flow (mapper.geometry.dense_flow): a rendered textured
plane with known depth, pose noise, textureless and non-overlapping pairs, partner agreement, the
thresholds that follow from the expected errors, the config."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapper.geometry.config import DenseFlowConfig
from mapper.geometry.dense_flow import (
    FlowView,
    flow_depth,
    flow_matches,
    flow_view,
    ray_sigma,
    select_flow_partners,
    triangulate_flow,
)
from mapper.geometry.triangulation import project
from mapper.node.config import ConfigError
from tests.mapper.geometry.test_triangulation import (
    PLANE_POSES,
    H,
    K,
    W,
    make_texture,
    plane_depth,
    pose,
    render_plane,
    rot_y,
)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return make_texture()


def plane_view(world_from_cam: np.ndarray, texture: np.ndarray, sent: np.ndarray | None = None) -> FlowView:
    """The plane rendered at ``world_from_cam``, sent with pose ``sent`` (default: the true one)."""
    return flow_view(render_plane(world_from_cam, texture), K, world_from_cam if sent is None else sent, 320)


def rel_errors(out_depth: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    truth = plane_depth(world_from_cam)
    kept = out_depth > 0
    return np.abs(out_depth[kept] - truth[kept]) / truth[kept]


def test_two_views_of_a_textured_plane_give_back_its_depth(texture: np.ndarray) -> None:
    new, partner = plane_view(PLANE_POSES[0], texture), plane_view(PLANE_POSES[1], texture)
    out = flow_depth(new, [partner], DenseFlowConfig())
    rel = rel_errors(out.depth_m, PLANE_POSES[0])
    assert out.depth_m.shape == (H, W) and len(out) > 0.15 * H * W / 4  # stride 2: a quarter of the pixels
    assert np.median(rel) < 0.01 and np.quantile(rel, 0.95) < 0.03
    assert (out.sigma_m[out.depth_m > 0] > 0).all() and set(np.unique(out.n_views)) <= {0, 2}


def test_two_partners_that_must_agree_keep_only_consistent_depths(texture: np.ndarray) -> None:
    new = plane_view(PLANE_POSES[0], texture)
    partners = [plane_view(PLANE_POSES[i], texture) for i in (1, 2)]
    both = flow_depth(new, partners, DenseFlowConfig(min_views=3))
    either = flow_depth(new, partners, DenseFlowConfig(min_views=2))
    assert 0 < len(both) <= len(either)
    assert (both.n_views[both.depth_m > 0] == 3).all()
    assert np.quantile(rel_errors(both.depth_m, PLANE_POSES[0]), 0.95) < 0.02


def noisy(world_from_cam: np.ndarray, shift_m: float, turn_deg: float) -> np.ndarray:
    out = world_from_cam.copy()
    out[:3, :3] = world_from_cam[:3, :3] @ rot_y(turn_deg)
    out[:3, 3] += np.array([shift_m, -shift_m, 0.5 * shift_m])
    return out


def test_pose_noise_degrades_gracefully(texture: np.ndarray) -> None:
    new = plane_view(PLANE_POSES[0], texture)
    errors = []
    for shift, turn in [(0.0, 0.0), (0.01, 0.5), (0.03, 1.5)]:
        partner = plane_view(PLANE_POSES[3], texture, sent=noisy(PLANE_POSES[3], shift, turn))
        out = flow_depth(new, [partner], DenseFlowConfig())
        median = float(np.median(rel_errors(out.depth_m, PLANE_POSES[0]))) if len(out) else 0.0
        errors.append((len(out), median))
    assert errors[0][1] < 0.01
    # more error: the median error grows but stays bounded by what the expected errors let through
    assert all(median < 0.25 for _, median in errors)
    # expecting the larger pose error shrinks what is kept (the parallax the points need grows)
    partner = plane_view(PLANE_POSES[3], texture, sent=noisy(PLANE_POSES[3], 0.03, 1.5))
    strict = flow_depth(new, [partner], DenseFlowConfig(pose_sigma_m=0.03, pose_sigma_deg=1.5))
    assert len(strict) < errors[2][0]


def test_textureless_pair_gives_no_points() -> None:
    flat = np.full((H, W, 3), 128, np.uint8)
    new = flow_view(flat, K, PLANE_POSES[0], 320)
    partner = flow_view(flat, K, PLANE_POSES[1], 320)
    pixel, _, _ = flow_matches(new, partner, DenseFlowConfig())
    assert len(pixel) == 0
    assert len(flow_depth(new, [partner], DenseFlowConfig())) == 0


def test_pair_without_overlap_gives_no_points_and_no_partner(texture: np.ndarray) -> None:
    far_away = pose(rot_y(0.0), (30.0, 0.0, 0.0))  # sees another part of the texture
    new = plane_view(PLANE_POSES[0], texture)
    other = plane_view(far_away, texture)
    assert select_flow_partners(new.posed, [other.posed], DenseFlowConfig()) == []
    out = flow_depth(new, [other], DenseFlowConfig())
    assert len(out) < 0.01 * H * W  # unrelated images: (almost) nothing survives the checks
    turned = pose(rot_y(180.0), (0.0, 0.0, 0.0))  # looks away from the plane
    assert select_flow_partners(new.posed, [plane_view(turned, texture).posed], DenseFlowConfig()) == []


def test_pure_rotation_gives_no_partner_and_no_point(texture: np.ndarray) -> None:
    turned = pose(rot_y(3.0), (0.0, 0.0, 0.0))
    new, partner = plane_view(PLANE_POSES[0], texture), plane_view(turned, texture)
    assert select_flow_partners(new.posed, [partner.posed], DenseFlowConfig()) == []
    assert len(flow_depth(new, [partner], DenseFlowConfig())) == 0  # no parallax


def test_partners_are_ranked_by_overlap_and_baseline_not_recency(texture: np.ndarray) -> None:
    new = plane_view(PLANE_POSES[0], texture).posed
    close = pose(rot_y(0.0), (0.06, 0.0, 0.0))  # overlaps fully, little parallax
    wide = PLANE_POSES[1]  # 0.35 m away
    idx = select_flow_partners(new, [plane_view(wide, texture).posed, plane_view(close, texture).posed],
                               DenseFlowConfig(max_partners=1))
    assert idx == [0]


def test_triangulation_thresholds_follow_the_expected_errors() -> None:
    a = FlowView(K, np.eye(4), np.zeros((H, W), np.uint8))
    b_pose = np.eye(4)
    b_pose[0, 3] = 0.3
    b = FlowView(K, b_pose, np.zeros((H, W), np.uint8))
    xyz = np.array([[0.1, 0.0, 2.0], [0.0, 0.1, 2.5], [-0.2, 0.1, 3.0]])
    uv_a, uv_b = project(K, a.world_from_cam, xyz)[0], project(K, b_pose, xyz)[0]
    cfg = DenseFlowConfig(pose_sigma_m=0.0, pose_sigma_deg=0.0, max_sigma_rel=1.0)
    keep, depth, sigma, parallax, reproj = triangulate_flow(a, b, uv_a, uv_b, cfg)
    assert keep.all() and np.allclose(depth, xyz[:, 2]) and np.allclose(reproj, 0.0, atol=1e-9)
    # sigma = range * sigma_ray / sin(parallax), sigma_ray = flow_sigma_px / f without pose error
    rng = np.maximum(np.linalg.norm(xyz, axis=1), np.linalg.norm(xyz - b_pose[:3, 3], axis=1))
    np.testing.assert_allclose(sigma, rng * (0.5 / 100.0) / np.sin(np.radians(parallax)), rtol=1e-9)
    # a tighter relative limit drops the farther (less parallax) points first
    limit = float(np.mean(np.sort(sigma / depth)[1:]))  # between the second and third point's
    tight = DenseFlowConfig(pose_sigma_m=0.0, pose_sigma_deg=0.0, max_sigma_rel=limit)
    assert triangulate_flow(a, b, uv_a, uv_b, tight)[0].sum() == 2
    # a correspondence 5 px off its epipolar line fails the reprojection test: 3 sigma of the
    # expected ray error is 1.5 px here...
    bad = uv_b + np.array([0.0, 5.0])
    assert not triangulate_flow(a, b, uv_a, bad, cfg)[0].any()
    # ... but passes when a 1 degree pose error is expected (3 * f * sqrt(2) * 1 deg = 7.4 px)
    loose = DenseFlowConfig(pose_sigma_m=0.0, pose_sigma_deg=1.0, max_sigma_rel=1.0)
    assert triangulate_flow(a, b, uv_a, bad, loose)[0].all()
    # rays that diverge (the match on the wrong side): behind the cameras, rejected
    assert triangulate_flow(a, b, uv_a, uv_a + np.array([[15.0, 0.0]]), cfg)[0].sum() == 0
    assert math.isclose(float(ray_sigma(np.array([1.0]), 100.0, cfg)[0]), 0.005)


def test_config_is_validated() -> None:
    DenseFlowConfig().validate("t")
    with pytest.raises(ConfigError, match="dense_flow.preset"):
        DenseFlowConfig(preset="slow").validate("t")
    with pytest.raises(ConfigError, match="dense_flow.min_views"):
        DenseFlowConfig(min_views=3, max_partners=1).validate("t")
    with pytest.raises(ConfigError, match="dense_flow.max_depth_m"):
        DenseFlowConfig(min_depth_m=5.0, max_depth_m=4.0).validate("t")
    with pytest.raises(ValueError, match="rgb must be"):
        flow_view(np.zeros((2, 3, 4, 5), np.uint8), K, np.eye(4), 320)
    with pytest.raises(ValueError, match="world_from_cam"):
        flow_view(np.zeros((H, W, 3), np.uint8), K, np.eye(3), 320)


def test_wide_frames_are_matched_downscaled_with_scaled_intrinsics(texture: np.ndarray) -> None:
    big = np.repeat(np.repeat(render_plane(PLANE_POSES[0], texture), 4, axis=0), 4, axis=1)  # 640 x 480
    view = flow_view(big, K * 4, PLANE_POSES[0], 320)
    assert view.gray.shape == (240, 320)
    np.testing.assert_allclose(view.K, K * 2)
