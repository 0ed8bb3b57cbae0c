"""Ray-cast renderer: known-plane depth, pixel-centre convention, depth back-projects onto the
mesh, label image matches face labels, normals face the camera."""

from __future__ import annotations

import numpy as np
import pytest

from clients.sim.raycast import SceneRenderer, camera_rays, tone_map
from clients.sim.robot import default_intrinsics, look_at, robot_trajectory
from clients.sim.scenes import LABEL_OF, Light, Scene, Texture, generate_scene

W, H = 64, 48


def _quad_scene(corners: np.ndarray, label: int = 3) -> Scene:
    """A Scene holding one quad (4, 3) (two triangles)."""
    tris = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    v = corners.astype(np.float32)
    n = np.cross(v[1] - v[0], v[2] - v[0])
    n = np.tile(n / np.linalg.norm(n), (2, 1)).astype(np.float32)
    return Scene(
        seed=0, style="apartment", vertices=v, triangles=tris, face_label=np.full(2, label, np.int32),
        face_instance=np.zeros(2, np.int32), instances=[], room_min=np.full(3, -50.0),
        room_max=np.full(3, 50.0), face_colour=np.full((2, 3), 0.5, np.float32),
        face_colour2=np.full((2, 3), 0.2, np.float32), face_texture=np.full(2, int(Texture.CHECKER), np.int8),
        face_texture_scale=np.full(2, 0.3, np.float32), face_normal=n,
        light=Light(np.zeros(3), np.ones(3), 0.7, 0.3, 3.0), structures=[])


@pytest.fixture(scope="module")
def room() -> tuple[Scene, SceneRenderer, np.ndarray]:
    scene = generate_scene(1)
    return scene, SceneRenderer(scene), robot_trajectory(scene, 40, seed=3)


def test_camera_rays_through_pixel_centres() -> None:
    K = np.array([50.0, 40.0, 32.0, 24.0])
    d = camera_rays(K, W, H)
    assert d.shape == (H, W, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    # pixel (col 31, row 23) has its centre at (31.5, 23.5): half a pixel left of / above cx, cy
    np.testing.assert_allclose(d[23, 31, :2] / d[23, 31, 2], [-0.5 / 50.0, -0.5 / 40.0])
    np.testing.assert_allclose(d[0, 0, :2] / d[0, 0, 2], [(0.5 - 32) / 50.0, (0.5 - 24) / 40.0])


def test_fronto_parallel_plane_renders_at_its_depth() -> None:
    # a big wall at world x = 3, camera at the origin looking along +x
    d = 3.0
    scene = _quad_scene(np.array([[d, -20, -20], [d, 20, -20], [d, 20, 20], [d, -20, 20]]))
    pose = look_at(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    K = default_intrinsics(W, H, 80.0)
    view = SceneRenderer(scene).render(K, pose, W, H)
    np.testing.assert_allclose(view.depth_m, d, rtol=1e-5)
    dirs = camera_rays(K, W, H)
    np.testing.assert_allclose(view.ray_dist_m, d / dirs[..., 2], rtol=1e-5)
    assert (view.label == 3).all() and (view.instance == 0).all()
    np.testing.assert_allclose(view.normal_cam, np.broadcast_to([0.0, 0.0, -1.0], (H, W, 3)), atol=1e-6)
    assert view.rgb.dtype == np.uint8 and view.rgb.std() > 3.0  # textured, not flat


def test_tilted_camera_depth_back_projects_onto_plane() -> None:
    # floor plane z = 0, camera 1.2 m above it, looking down and sideways
    scene = _quad_scene(np.array([[-30, -30, 0], [30, -30, 0], [30, 30, 0], [-30, 30, 0]]))
    pose = look_at(np.array([0.3, -0.2, 1.2]), np.array([2.0, 1.0, 0.0]), roll_rad=0.1)
    K = np.array([45.0, 47.0, 30.0, 25.0])
    view = SceneRenderer(scene).render(K, pose, W, H)
    hit = view.depth_m > 0
    assert hit.mean() > 0.5
    jj, ii = np.nonzero(hit)
    z = view.depth_m[hit].astype(np.float64)
    x_cam = np.stack([(ii + 0.5 - K[2]) / K[0] * z, (jj + 0.5 - K[3]) / K[1] * z, z], 1)
    world = x_cam @ pose[:3, :3].T + pose[:3, 3]
    np.testing.assert_allclose(world[:, 2], 0.0, atol=1e-4)


def test_pixel_centre_convention_at_an_edge() -> None:
    # a wall covering only camera x > 0.25 px at depth 2: with centres at i + 0.5, column cx
    # (centre 0.5 px right of the axis) is hit, column cx - 1 is not
    K = np.array([40.0, 40.0, 32.0, 24.0])
    d = 2.0
    edge = 0.25 / K[0] * d  # camera x of the edge
    # camera looks along world +x; camera +x (right) is world -y
    scene = _quad_scene(np.array([[d, -edge, -10], [d, -edge, 10], [d, -20, 10], [d, -20, -10]]))
    view = SceneRenderer(scene).render(K, look_at(np.zeros(3), np.array([1.0, 0, 0])), W, H)
    assert (view.depth_m[:, 32:] > 0).all()
    assert (view.depth_m[:, :32] == 0).all()
    assert (view.label[:, :32] == -1).all()


Room = tuple[Scene, SceneRenderer, np.ndarray]


def test_scene_depth_back_projects_onto_mesh_and_labels_match(room: Room) -> None:
    o3d = pytest.importorskip("open3d", reason="closest points on the mesh come from Open3D")
    scene, renderer, poses = room
    K = default_intrinsics(W, H)
    mesh = o3d.t.geometry.RaycastingScene()
    mesh.add_triangles(o3d.core.Tensor(scene.vertices), o3d.core.Tensor(scene.triangles.astype(np.uint32)))
    for pose in poses[::13]:
        view = renderer.render(K, pose, W, H)
        assert (view.depth_m > 0).all()  # a closed room: every ray hits something
        jj, ii = np.mgrid[0:H, 0:W]
        z = view.depth_m.astype(np.float64)
        x_cam = np.stack([(ii + 0.5 - K[2]) / K[0] * z, (jj + 0.5 - K[3]) / K[1] * z, z], -1).reshape(-1, 3)
        world = (x_cam @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
        ans = mesh.compute_closest_points(o3d.core.Tensor(world))
        gap = np.linalg.norm(ans["points"].numpy() - world, axis=1)
        assert np.percentile(gap, 99) < 2e-3 and gap.max() < 1e-2
        face_label = scene.face_label[ans["primitive_ids"].numpy().astype(np.int64)]
        assert (face_label == view.label.reshape(-1)).mean() > 0.97
        np.testing.assert_allclose(np.linalg.norm(view.normal_cam, axis=-1), 1.0, atol=1e-4)
        rays = camera_rays(K, W, H)
        assert ((view.normal_cam * rays).sum(-1) <= 1e-6).all()  # normals face the camera
        np.testing.assert_allclose(view.depth_m, view.ray_dist_m * rays[..., 2], rtol=1e-5)


def test_render_is_deterministic_and_textured(room: tuple[Scene, SceneRenderer, np.ndarray]) -> None:
    scene, renderer, poses = room
    K = default_intrinsics(W, H)
    a = renderer.render(K, poses[5], W, H)
    b = SceneRenderer(scene).render(K, poses[5], W, H)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.label, b.label)
    floor = a.label == LABEL_OF["floor"]
    if floor.sum() > 50:
        assert a.rgb[floor].std(0).max() > 4.0


@pytest.mark.parametrize("K, width, height", [
    (np.array([-1.0, 40, 32, 24]), W, H),
    (np.array([40.0, 40, 32]), W, H),
    (np.array([40.0, 40, 32, 24]), 0, H),
])
def test_bad_camera_raises(room: tuple[Scene, SceneRenderer, np.ndarray], K: np.ndarray, width: int,
                           height: int) -> None:
    with pytest.raises(ValueError, match="K|size"):
        room[1].render(K, np.eye(4), width, height)


def test_non_rotation_pose_raises(room: tuple[Scene, SceneRenderer, np.ndarray]) -> None:
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="rotation"):
        room[1].render(default_intrinsics(W, H), bad, W, H)


def test_tone_map_is_monotone_and_never_clips() -> None:
    x = np.linspace(0.0, 5.0, 2001)
    y = tone_map(x)
    np.testing.assert_allclose(y[x <= 0.75], x[x <= 0.75])   # linear below the knee
    assert (np.diff(y) > 0).all() and y.max() < 1.0             # keeps contrast, never clips
    assert abs((y[1] - y[0]) / (x[1] - x[0]) - 1.0) < 1e-9
    k = np.searchsorted(x, 0.75)
    assert abs((y[k + 1] - y[k]) / (x[k + 1] - x[k]) - 1.0) < 0.01  # slope continuous at the knee
