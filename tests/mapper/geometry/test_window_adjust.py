"""The window's poses adjusted jointly from matches (mapper.geometry.window_adjust): the Sampson
distance against a float64 point-to-line reference, its gradient against finite differences, exact
and noisy matches across a path of views, outliers, fixed views, views without matches, the
rotation-warped dense matches of a rendered plane, the config."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.geometry.config import DenseFlowConfig, TriangulationConfig
from mapper.geometry.dense_flow import flow_view
from mapper.geometry.pose_refine import perturbed, pose_change
from mapper.geometry.triangulation import project
from mapper.geometry.window_adjust import (
    PairMatches,
    _fundamentals,
    _sampson,
    _sampson_gradient,
    adjust_poses,
    pair_matches,
    rotations,
    sampson_px,
)
from mapper.node.config import ConfigError
from tests.mapper.geometry.test_triangulation import PLANE_POSES, K, make_texture, pose, render_plane, rot_y


def path_poses(n: int) -> np.ndarray:
    """``n`` cameras on an arc, each turned a little, looking at the points of :func:`scene`."""
    return np.stack([pose(rot_y(-6.0 + 2.0 * i), (0.12 * i - 0.5, 0.03 * np.sin(i), 0.02 * i))
                     for i in range(n)])


def scene(n: int = 600, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-2.5, 2.5, n), rng.uniform(-1.5, 1.5, n), rng.uniform(2.5, 6.0, n)])


def matches_of(truth: np.ndarray, xyz: np.ndarray, partners: int = 3, noise_px: float = 0.0,
               outliers: float = 0.0, seed: int = 0) -> list[PairMatches]:
    """Each view matched with its ``partners`` predecessors by projecting the true points."""
    rng = np.random.default_rng(seed)
    out = []
    for a in range(1, len(truth)):
        for b in range(max(0, a - partners), a):
            uv_a, za = project(K, truth[a], xyz)
            uv_b, zb = project(K, truth[b], xyz)
            seen = (za > 0) & (zb > 0) & (uv_a >= 0).all(1) & (uv_a <= [160, 120]).all(1) & \
                (uv_b >= 0).all(1) & (uv_b <= [160, 120]).all(1)
            uv_a, uv_b = uv_a[seen], uv_b[seen] + rng.normal(0.0, noise_px, (int(seen.sum()), 2))
            bad = rng.random(len(uv_b)) < outliers
            uv_b[bad] = rng.uniform([0, 0], [160, 120], (int(bad.sum()), 2))
            out.append(PairMatches(a, b, uv_a, uv_b))
    return out


def sent_poses(truth: np.ndarray, t_m: float, r_deg: float, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([perturbed(p, rng.normal(0, t_m, 3), np.radians(rng.normal(0, r_deg, 3))) for p in truth])


def errors(truth: np.ndarray, poses: np.ndarray) -> np.ndarray:
    return np.array([pose_change(t, p) for t, p in zip(truth, poses, strict=True)])


def test_sampson_distance_matches_a_float64_point_to_line_reference() -> None:
    a, b = pose(np.eye(3), (0, 0, 0)), pose(rot_y(-8.0), (0.4, 0.05, -0.1))
    xyz = scene(50)
    uv_a, uv_b = project(K, a, xyz)[0], project(K, b, xyz)[0]
    assert np.abs(sampson_px(K, K, a, b, uv_a, uv_b)).max() < 1e-9  # exact matches lie on their lines
    # moved along one image axis, a match is off its line by the point-to-line distance in b; the
    # Sampson distance (both images) is that distance scaled by the share of the gradient in b
    moved = uv_b + np.array([0.0, 2.0])
    F = _fundamentals(K[None], K[None], a[None, :3, :3], a[None, :3, 3], b[None, :3, :3], b[None, :3, 3])[0]
    xa = np.column_stack([uv_a, np.ones(len(uv_a))])
    xb = np.column_stack([moved, np.ones(len(moved))])
    lines = xa @ F.T  # epipolar lines in b
    line_dist = np.abs(np.einsum("mi,mi->m", xb, lines)) / np.hypot(lines[:, 0], lines[:, 1])
    lines_a = xb @ F
    share = np.hypot(lines[:, 0], lines[:, 1]) / np.sqrt(
        lines[:, 0] ** 2 + lines[:, 1] ** 2 + lines_a[:, 0] ** 2 + lines_a[:, 1] ** 2)
    got = np.abs(sampson_px(K, K, a, b, uv_a, moved))
    np.testing.assert_allclose(got, line_dist * share, rtol=1e-9)


def test_sampson_gradient_matches_finite_differences() -> None:
    rng = np.random.default_rng(3)
    F = rng.normal(size=(5, 3, 3))
    uv_a, uv_b = rng.uniform(0, 160, (5, 2)), rng.uniform(0, 120, (5, 2))
    grad = _sampson_gradient(F, uv_a, uv_b)
    numeric = np.zeros_like(grad)
    for k in range(9):
        d = np.zeros(9)
        d[k] = 1e-7
        hi = _sampson(F + d.reshape(3, 3), uv_a, uv_b)
        lo = _sampson(F - d.reshape(3, 3), uv_a, uv_b)
        numeric[:, k] = (hi - lo) / 2e-7
    np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-7)


def test_rotations_are_rodrigues() -> None:
    v = np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.3], [0.0, np.pi / 2, 0.0]])
    R = rotations(v)
    np.testing.assert_allclose(R[0], np.eye(3))
    np.testing.assert_allclose(R[2], rot_y(90.0), atol=1e-12)
    np.testing.assert_allclose(R[1] @ R[1].T, np.eye(3), atol=1e-12)


def test_exact_matches_cut_rotation_and_translation_errors() -> None:
    truth = path_poses(12)
    sent = sent_poses(truth, 0.02, 1.0)
    cfg = TriangulationConfig(pose_max_evaluations=200)
    out = adjust_poses(np.tile(K, (12, 1)), sent, matches_of(truth, scene()), cfg)
    before, after = errors(truth, sent), errors(truth, out.world_from_cam)
    assert out.accepted.all() and set(out.reason) == {"refined"}
    assert np.median(after[:, 1]) < 0.5 * np.median(before[:, 1])  # rotation
    assert np.median(after[:, 0]) < np.median(before[:, 0])  # translation: the baselines' lengths stay free
    assert np.nanmedian(out.error_after_px) < 0.1 * np.nanmedian(out.error_before_px)


def test_noisy_matches_and_outliers_still_help_and_the_robust_loss_beats_plain_squares() -> None:
    truth = path_poses(12)
    sent = sent_poses(truth, 0.02, 1.0, seed=4)
    pairs = matches_of(truth, scene(), noise_px=0.5, outliers=0.15, seed=2)
    cfg = TriangulationConfig(pose_max_evaluations=200)
    robust = errors(truth, adjust_poses(np.tile(K, (12, 1)), sent, pairs, cfg).world_from_cam)
    plain = errors(truth, adjust_poses(np.tile(K, (12, 1)), sent, pairs,
                                       TriangulationConfig(pose_huber_px=100.0, pose_max_evaluations=200,
                                                           pose_min_gain=0.0)).world_from_cam)
    before = errors(truth, sent)
    assert np.median(robust[:, 1]) < 0.5 * np.median(before[:, 1])
    assert np.median(robust[:, 0]) < np.median(before[:, 0])
    assert np.median(robust[:, 1]) < 0.7 * np.median(plain[:, 1])


def test_fixed_views_and_views_without_matches_keep_their_pose() -> None:
    truth = path_poses(6)
    sent = sent_poses(truth, 0.02, 1.0, seed=5)
    pairs = [p for p in matches_of(truth, scene()) if 5 not in (p.a, p.b)]  # view 5 unmatched
    fixed = np.zeros(6, bool)
    fixed[0] = True
    out = adjust_poses(np.tile(K, (6, 1)), sent, pairs, TriangulationConfig(), fixed=fixed)
    assert out.reason[0] == "fixed" and out.reason[5] == "no matches" and out.matches[5] == 0
    np.testing.assert_array_equal(out.world_from_cam[[0, 5]], sent[[0, 5]])
    assert not out.accepted[[0, 5]].any() and out.accepted[1:5].all()


def test_a_view_sent_far_off_is_left_out_a_far_move_refused_and_no_pairs_change_nothing() -> None:
    truth = path_poses(6)
    sent = sent_poses(truth, 0.02, 1.0, seed=6)
    sent[3] = perturbed(sent[3], np.array([0.0, 0.3, 0.0]), np.zeros(3))  # 30 cm off: 15 sigmas
    out = adjust_poses(np.tile(K, (6, 1)), sent, matches_of(truth, scene()), TriangulationConfig())
    assert out.reason[3] == "inconsistent"  # left out, at its pose as sent
    after, before = errors(truth, out.world_from_cam), errors(truth, sent)
    others = [0, 1, 2, 4, 5]
    assert np.median(after[others, 1]) < 0.5 * np.median(before[others, 1])  # the others not bent to it
    tight = adjust_poses(np.tile(K, (6, 1)), sent, matches_of(truth, scene()),
                         TriangulationConfig(pose_max_sigmas=0.1))
    assert "too far" in tight.reason
    np.testing.assert_array_equal(out.world_from_cam[~out.accepted], sent[~out.accepted])
    none = adjust_poses(np.tile(K, (6, 1)), sent, [], TriangulationConfig())
    np.testing.assert_array_equal(none.world_from_cam, sent)
    assert set(none.reason) == {"no matches"}
    with pytest.raises(ValueError, match="rows"):
        adjust_poses(np.tile(K, (5, 1)), sent, [], TriangulationConfig())


def test_a_start_at_an_earlier_solution_lands_at_the_same_poses() -> None:
    truth = path_poses(8)
    sent = sent_poses(truth, 0.02, 1.0, seed=7)
    pairs = matches_of(truth, scene())
    cfg = TriangulationConfig(pose_max_evaluations=200)
    first = adjust_poses(np.tile(K, (8, 1)), sent, pairs, cfg)
    again = adjust_poses(np.tile(K, (8, 1)), sent, pairs, cfg, start=first.world_from_cam)
    moves = errors(first.world_from_cam, again.world_from_cam)
    assert moves[:, 0].max() < 1e-3 and moves[:, 1].max() < 0.02


def test_rotation_warped_dense_matches_of_a_turned_view_lie_on_the_true_epipolar_lines() -> None:
    texture = make_texture()
    a_pose = PLANE_POSES[0]
    b_pose = pose(PLANE_POSES[0][:3, :3] @ rot_y(12.0), tuple(PLANE_POSES[0][:3, 3] + [0.25, 0.0, 0.05]))
    flow = DenseFlowConfig()
    # the views are sent 1 degree off: the warp needs only the rough rotation
    sent_b = perturbed(b_pose, np.zeros(3), np.radians([1.0, 0.0, 0.0]))  # a tilt: off the lines
    a = flow_view(render_plane(a_pose, texture), K, a_pose, 320)
    b = flow_view(render_plane(b_pose, texture), K, sent_b, 320)
    cfg = TriangulationConfig(pose_pair_matches=100)
    m = pair_matches(a, b, 0, 1, cfg, flow)
    assert m is not None and 50 <= len(m) <= 100 and (m.a, m.b) == (0, 1)
    true_err = np.abs(sampson_px(a.K, b.K, a_pose, b_pose, m.uv_a, m.uv_b))
    assert np.median(true_err) < 0.3  # on the lines of the true poses
    sent_err = np.abs(sampson_px(a.K, b.K, a_pose, sent_b, m.uv_a, m.uv_b))
    assert np.median(sent_err) > 3 * np.median(true_err)  # and off those of the pose as sent
    blank = flow_view(np.full((120, 160, 3), 128, np.uint8), K, b_pose, 320)
    assert pair_matches(a, blank, 0, 1, cfg, flow) is None  # nothing textured, no matches


@pytest.mark.parametrize("key,value", [("pose_method", "bundle"), ("pose_window", 1), ("pose_partners", 0),
                                       ("pose_pair_matches", 4), ("pose_flow_sigma_px", 0.0),
                                       ("pose_max_evaluations", 1)])
def test_config_ranges(key: str, value: object) -> None:
    with pytest.raises(ConfigError, match=f"triangulation.{key}"):
        TriangulationConfig(**{key: value}).validate("test")  # type: ignore[arg-type]
