"""Multi-view consistency of rendered-depth points (mapper.node.workers.depth_points): exact synthetic
cases for :func:`sparse_agreement`, :func:`view_agreement` and :func:`consistency_mask`.

The camera: 10 x 10 pixels, f = 10, principal point (5, 5), pixel centres at +0.5; looking along
+z from the origin unless said otherwise; a fronto-parallel plane at z = 2 renders depth 2 everywhere."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from mapper.node.config import GlobalMapConfig
from mapper.node.workers.depth_points import consistency_mask, sparse_agreement, view_agreement

K = np.array([10.0, 10.0, 5.0, 5.0])


@dataclass(frozen=True)
class View:
    K: np.ndarray
    world_from_cam: np.ndarray
    depth_m: np.ndarray


def pose(t: tuple[float, float, float] = (0.0, 0.0, 0.0), flip: bool = False) -> np.ndarray:
    """Camera-to-world; ``flip``: rotated 180 degrees about y (looking along -z)."""
    out = np.eye(4)
    if flip:
        out[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    out[:3, 3] = t
    return out


def plane_view(
    t: tuple[float, float, float] = (0.0, 0.0, 0.0), depth: float = 2.0, flip: bool = False
) -> View:
    return View(K, pose(t, flip), np.full((10, 10), depth, np.float32))


def point_at_pixel(col: int, row: int, z: float) -> np.ndarray:
    """(1, 3) the world point (reference camera) at the centre of pixel (col, row), z-depth ``z``."""
    return np.array([[(col + 0.5 - 5.0) / 10.0 * z, (row + 0.5 - 5.0) / 10.0 * z, z]])


def disc(col: int, row: int, radius: int) -> np.ndarray:
    rr, cc = np.mgrid[0:10, 0:10]
    return (rr - row) ** 2 + (cc - col) ** 2 <= radius * radius


def test_a_triangulated_point_that_agrees_marks_its_disc_of_pixels() -> None:
    neighbour, agrees = sparse_agreement(plane_view(), point_at_pixel(3, 4, 2.02), np.array([0.01]),
                                         radius_px=1, sigmas=3.0, min_tolerance_m=0.05)
    np.testing.assert_array_equal(neighbour, disc(3, 4, 1))
    assert neighbour.sum() == 5
    np.testing.assert_array_equal(agrees, neighbour)


def test_a_disagreeing_point_is_a_neighbour_that_does_not_agree_unless_its_sigma_covers_it() -> None:
    view, xyz = plane_view(), point_at_pixel(3, 4, 2.5)
    neighbour, agrees = sparse_agreement(view, xyz, np.array([0.01]), radius_px=1, sigmas=3.0,
                                         min_tolerance_m=0.05)
    assert neighbour.sum() == 5 and not agrees.any()
    # tolerance = max(3 * 0.2, 0.05) = 0.6 >= 0.5: agrees
    _, agrees = sparse_agreement(view, xyz, np.array([0.2]), radius_px=1, sigmas=3.0, min_tolerance_m=0.05)
    assert agrees.sum() == 5
    # the voxel floor: tolerance = max(3 * 0.01, 0.6) = 0.6
    _, agrees = sparse_agreement(view, xyz, np.array([0.01]), radius_px=1, sigmas=3.0, min_tolerance_m=0.6)
    assert agrees.sum() == 5


def test_points_behind_the_camera_or_outside_the_image_are_no_neighbours() -> None:
    behind = -point_at_pixel(3, 4, 2.0)  # z = -2: would project onto the mirrored pixel
    outside = np.array([[5.0, 0.0, 2.0]])  # u = 30
    xyz = np.concatenate([behind, outside])
    neighbour, agrees = sparse_agreement(plane_view(), xyz, np.array([0.01, 0.01]), radius_px=2,
                                         sigmas=3.0, min_tolerance_m=10.0)
    assert not neighbour.any() and not agrees.any()
    neighbour, _ = sparse_agreement(plane_view(), np.zeros((0, 3)), np.zeros(0), radius_px=2, sigmas=3.0,
                                    min_tolerance_m=0.1)
    assert not neighbour.any()


def test_views_that_agree_confirm_the_pixels_they_see() -> None:
    # the second camera 0.5 m to the right: pixel column c of the reference lands on column c - 2
    agrees = view_agreement(plane_view(), [plane_view((0.5, 0.0, 0.0))], tolerance_m=0.1, min_baseline_m=0.1)
    assert agrees[:, 2:].all() and not agrees[:, :2].any()
    # a camera on the far side looking back (z' = 4 - 2 = 2 there): the mirrored columns, all inside
    agrees = view_agreement(plane_view(), [plane_view((0.0, 0.0, 4.0), flip=True)], tolerance_m=0.1,
                            min_baseline_m=0.1)
    assert agrees.all()


def test_disagreeing_too_close_and_behind_views_confirm_nothing() -> None:
    ref = plane_view()
    assert not view_agreement(ref, [plane_view((0.5, 0.0, 0.0), depth=3.0)], tolerance_m=0.1,
                              min_baseline_m=0.1).any()
    # 5 cm baseline < 10 cm: a render from nearly the same pose is no second view
    assert not view_agreement(ref, [plane_view((0.05, 0.0, 0.0))], tolerance_m=10.0, min_baseline_m=0.1).any()
    # the plane lies 2 m behind a camera at z = 4 looking along +z: no evidence even with a huge tolerance
    assert not view_agreement(ref, [plane_view((0.0, 0.0, 4.0))], tolerance_m=10.0, min_baseline_m=0.1).any()
    assert not view_agreement(ref, [], tolerance_m=10.0, min_baseline_m=0.0).any()


def test_consistency_mask_points_overrule_views_and_no_evidence_rejects() -> None:
    config = GlobalMapConfig(voxel_size_m=0.05, rendered_consistency_voxels=2.0,
                             rendered_consistency_sigmas=3.0, rendered_consistency_radius_px=1)
    ref = plane_view()
    ref.depth_m[0, 0] = 0.0  # no rendered surface there: never kept, never counted
    wrong = point_at_pixel(6, 6, 2.5)  # disagrees with the rendered 2.0 (tolerance max(0.03, 0.1))
    right = point_at_pixel(8, 1, 2.05)
    xyz, sigma = np.concatenate([wrong, right]), np.array([0.01, 0.01])
    keep, counts = consistency_mask(ref, xyz, sigma, [plane_view((0.5, 0.0, 0.0))], config)
    expected = np.zeros((10, 10), bool)
    expected[:, 2:] = True  # the other view confirms these
    expected |= disc(8, 1, 1)  # the agreeing point
    expected &= ~disc(6, 6, 1)  # the disagreeing point overrules the view
    expected[0, 0] = False
    np.testing.assert_array_equal(keep, expected)
    assert counts == {"checked": 99, "by_points": 5, "by_views": int(expected.sum()) - 5,
                      "rejected": 99 - int(expected.sum())}
    keep, counts = consistency_mask(ref, np.zeros((0, 3)), np.zeros(0), [], config)
    assert not keep.any() and counts["rejected"] == 99
    # without view agreement (global_map.rendered_view_agreement): only the agreeing point's disc
    keep, counts = consistency_mask(ref, xyz, sigma, [plane_view((0.5, 0.0, 0.0))], config, by_views=False)
    np.testing.assert_array_equal(keep, disc(8, 1, 1))
    assert counts["by_views"] == 0 and counts["by_points"] == 5 and counts["rejected"] == 94


def test_view_agreement_mode_follows_the_stereo_setting(tmp_path) -> None:
    from mapper.node.config import ConfigError, config_from_dict
    from mapper.node.service import MapperNode
    from mapper.node.workers.depth_points import RenderedDepthPoints
    from mapper.node.workers.triangulation import SparseTriangulation

    with pytest.raises(ConfigError, match="rendered_view_agreement"):
        config_from_dict({"global_map": {"rendered_view_agreement": "maybe"}})
    answers = {}
    for mode, stereo in (("auto", True), ("auto", False), ("on", True), ("off", False)):
        node = MapperNode(config_from_dict({
            "map_dir": str(tmp_path / "maps"), "autosave_name": "", "save_on_exit": False,
            "serve_model": False, "global_map": {"rendered_view_agreement": mode},
            "stereo": {"enabled": stereo},
        }))
        try:
            points = RenderedDepthPoints(node.ctx, runtime=None)  # type: ignore[arg-type]
            without = points._view_agreement()  # no triangulation plugin installed: nothing sweeps
            SparseTriangulation(node.ctx).install()
            answers[(mode, stereo)] = (without, points._view_agreement())
        finally:
            node.stop()
    assert answers == {("auto", True): (True, False), ("auto", False): (True, True),
                       ("on", True): (True, True), ("off", False): (False, False)}


# ---- the plugin ----------------------------------------------------------------------------------
def _plugin_run(tmp_path, consistency: bool, sparse=None):
    import torch

    from mapper.model.field import GovNeSF
    from mapper.node.config import config_from_dict
    from mapper.node.service import MapperNode
    from protocol.messages import encode
    from tests.mapper.node.workers.test_depth_points import _frame, _install
    from tests.mapper.runtime.test_model_runtime import TINY

    torch.manual_seed(0)
    model = GovNeSF(TINY).eval()
    node = MapperNode(config_from_dict({
        "map_dir": str(tmp_path / f"maps{consistency}"), "autosave_name": "", "save_on_exit": False,
        "window": {"max_keyframes": 6, "min_translation_m": 0.05},
        "global_map": {"rendered_min_opacity": 0.0, "rendered_min_views": 3, "rendered_depth_stride": 2,
                       "min_weight": 0.0, "rendered_consistency": consistency,
                       "rendered_consistency_views": 2},
    }))
    try:
        points = _install(node, model)
        points.sparse_source = sparse
        for seq in range(5):
            node.handle_ingest(encode(_frame(seq)))
        assert points.process_pending() == 5
        return points.stats()
    finally:
        node.stop()


@pytest.mark.slow  # two in-process nodes with the tiny model
def test_the_plugin_filters_rendered_pixels_and_counts_them(tmp_path) -> None:
    off = _plugin_run(tmp_path, False)
    assert off["consistency"]["checked"] == 0 and off["points"] > 0
    calls: list[int] = []

    def sparse() -> tuple[np.ndarray, np.ndarray]:
        calls.append(1)
        return np.zeros((0, 3)), np.zeros(0)

    on = _plugin_run(tmp_path, True, sparse)
    c = on["consistency"]
    assert len(calls) == 5 and c["enabled"] and c["checked"] > 0 and c["by_points"] == 0
    assert c["checked"] == c["by_views"] + c["rejected"]
    assert on["points"] <= off["points"] and on["integrated"] == 5
