"""The pure-torch ray-casting backend (`TorchRaycaster`) and the backend choice.

* exact answers on a hand-built unit square: hits from the front and from behind (double-sided),
  misses for parallel rays and rays that start past it, the lowest face id on a shared edge,
  the nearest of two surfaces; culled and brute-force testing give the same answers;
* on generated rooms it agrees with Open3D (face ids, hit distances, whole rendered views);
* `GOVNESF_SIM_RAYCAST` / `backend=` and `GOVNESF_SIM_RAYCAST_DEVICE` / `device=` choose it, bad
  names raise ValueError, and without open3d the simulator falls back to it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from numpy.typing import ArrayLike

from clients.sim.raycast import (
    RAYCAST_DEVICE_ENV,
    RAYCAST_ENV,
    SceneRenderer,
    TorchRaycaster,
    camera_rays,
    coherent_ray_order,
    raycast_backend,
    torch_device,
)
from clients.sim.robot import default_intrinsics, robot_trajectory
from clients.sim.scenes import Scene, generate_scene
from govnesf._extras import MissingExtraError

ROOT = Path(__file__).resolve().parents[3]

# the unit square in the plane z = 0, split along its diagonal (0, 0)-(1, 1)
SQUARE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
SQUARE_T = np.array([[0, 1, 2], [0, 2, 3]], np.int64)  # face 0: x > y, face 1: y > x
DOWN = [0.0, 0.0, -1.0]


def _has_open3d() -> bool:
    try:
        import open3d  # noqa: F401
    except ImportError:
        return False
    return True


needs_open3d = pytest.mark.skipif(
    not _has_open3d(), reason="open3d is not installed (the [sim] extra has no open3d wheel here), "
    "so there is no reference to compare the torch backend with")


def _cast(rc: TorchRaycaster, origins: ArrayLike, dirs: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    d = np.asarray(dirs, np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return rc.cast(np.asarray(origins, np.float64).reshape(-1, 3), d)


@pytest.fixture(params=[True, False], ids=["cull", "brute"])
def square(request: pytest.FixtureRequest) -> TorchRaycaster:
    return TorchRaycaster(SQUARE_V, SQUARE_T, device="cpu", cull=request.param)


def test_rays_straight_at_the_square_hit_the_right_face(square: TorchRaycaster) -> None:
    t, face = _cast(square, [[0.75, 0.25, 1.0], [0.25, 0.75, 2.5], [0.9, 0.05, 0.3]], [DOWN] * 3)
    np.testing.assert_array_equal(face, [0, 1, 0])
    np.testing.assert_allclose(t, [1.0, 2.5, 0.3], atol=1e-6)
    assert t.dtype == np.float64 and face.dtype == np.int64
    # oblique: from above the origin corner towards a point inside face 0
    target = np.array([0.75, 0.25, 0.0])
    t, face = _cast(square, [[0.0, 0.0, 1.0]], [target - [0.0, 0.0, 1.0]])
    assert face[0] == 0
    np.testing.assert_allclose(t, np.sqrt(0.75**2 + 0.25**2 + 1.0), atol=1e-6)


def test_rays_from_behind_hit_double_sided(square: TorchRaycaster) -> None:
    t, face = _cast(square, [[0.75, 0.25, -2.0], [0.2, 0.6, -0.5]], [[0, 0, 1.0]] * 2)
    np.testing.assert_array_equal(face, [0, 1])
    np.testing.assert_allclose(t, [2.0, 0.5], atol=1e-6)


def test_misses(square: TorchRaycaster) -> None:
    origins = [
        [-1.0, 0.5, 0.5],   # parallel to the square, above it
        [-1.0, 0.5, 0.0],   # parallel, in its plane (det = 0 exactly)
        [-1.0, 0.3, -0.2],  # parallel, below it
        [0.75, 0.25, -1.0],  # starts past the square, going away from it
        [0.75, 0.25, 1.0],  # going up, away from it
        [1.5, 0.5, 1.0],    # beside the square
        [-0.01, 0.5, 1.0],  # just outside its edge x = 0
    ]
    dirs = [[1.0, 0, 0], [1.0, 0, 0], [1.0, 1, 0], DOWN, [0, 0, 1.0], DOWN, DOWN]
    t, face = _cast(square, origins, dirs)
    np.testing.assert_array_equal(face, -1)
    assert np.isinf(t).all() and (t > 0).all()


def test_shared_edge_goes_to_the_lowest_face_id(square: TorchRaycaster) -> None:
    # straight down onto the diagonal, and obliquely through it from either side
    on_edge = [[0.5, 0.5, 1.0], [0.1, 0.1, 0.7], [0.3, 0.3, 2.0], [0.9, 0.9, 0.2]]
    t, face = _cast(square, on_edge, [DOWN] * 4)
    np.testing.assert_array_equal(face, 0)
    np.testing.assert_allclose(t, [1.0, 0.7, 2.0, 0.2], atol=1e-6)
    p = np.array([0.4, 0.4, 0.0])
    origins = [[0.4 + 0.3, 0.4 - 0.3, 1.0], [0.4 - 0.3, 0.4 + 0.3, 1.0], [0.4, 0.4, -1.0]]
    t, face = _cast(square, origins, p - np.array(origins))
    np.testing.assert_array_equal(face, 0)
    # the same square with the faces listed the other way round: the tie goes to the new face 0
    swapped = TorchRaycaster(SQUARE_V, SQUARE_T[::-1].copy(), device="cpu", cull=square.cull)
    _, face = _cast(swapped, on_edge, [DOWN] * 4)
    np.testing.assert_array_equal(face, 0)
    _, face = _cast(swapped, [[0.75, 0.25, 1.0]], [DOWN])  # off the edge: the geometry decides
    assert face[0] == 1


def test_nearest_of_two_surfaces_wins(square: TorchRaycaster) -> None:
    # a second square 1 m below the first, listed first (lower ids): the nearer surface still wins
    v = np.concatenate([SQUARE_V - [0, 0, 1], SQUARE_V])
    tri = np.concatenate([SQUARE_T, SQUARE_T + 4])
    rc = TorchRaycaster(v, tri, device="cpu", cull=square.cull)
    t, face = _cast(rc, [[0.75, 0.25, 1.0], [0.75, 0.25, -2.0], [0.25, 0.75, -0.5]],
                    [DOWN, [0, 0, 1.0], DOWN])
    np.testing.assert_array_equal(face, [2, 0, 1])
    np.testing.assert_allclose(t, [1.0, 1.0, 0.5], atol=1e-6)


def test_no_rays_and_no_triangles() -> None:
    rc = TorchRaycaster(SQUARE_V, SQUARE_T, device="cpu")
    t, face = rc.cast(np.zeros((0, 3)), np.zeros((0, 3)))
    assert t.shape == face.shape == (0,)
    empty = TorchRaycaster(np.zeros((0, 3)), np.zeros((0, 3), np.int64), device="cpu")
    t, face = _cast(empty, [[0.5, 0.5, 1.0]], [DOWN])
    assert face[0] == -1 and np.isinf(t[0])


def test_chunking_and_matmul_precision_do_not_change_answers(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tiny blocks (many chunks, bundles split) and a process-wide TF32/bf16 matmul setting give
    the same hits; the setting and torch's thread count are as they were afterwards."""
    scene = generate_scene(2)
    rng = np.random.default_rng(0)
    o = rng.uniform(scene.room_min + 0.2, scene.room_max - 0.2, (3000, 3))
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ref_t, ref_f = TorchRaycaster(scene.vertices, scene.triangles, device="cpu").cast(o, d)
    assert (ref_f >= 0).all()  # inside a closed room every ray hits
    small = TorchRaycaster(scene.vertices, scene.triangles, device="cpu")
    monkeypatch.setattr(small, "max_pairs", 5000)
    monkeypatch.setattr(small, "bundle_rays", 37)
    before, threads = torch.get_float32_matmul_precision(), torch.get_num_threads()
    torch.set_float32_matmul_precision("medium")
    try:
        t, f = small.cast(o, d)
        assert torch.get_float32_matmul_precision() == "medium"
    finally:
        torch.set_float32_matmul_precision(before)
    assert torch.get_num_threads() == threads  # (casting on the CPU runs on `cpu_threads` threads)
    assert (f == ref_f).mean() > 0.999
    np.testing.assert_allclose(t[f == ref_f], ref_t[f == ref_f], atol=1e-5)


def test_coherent_ray_order_is_a_permutation_that_tiles_an_image() -> None:
    K = default_intrinsics(64, 48)
    d = camera_rays(K, 64, 48).reshape(-1, 3)
    order = coherent_ray_order(np.zeros_like(d), d)
    np.testing.assert_array_equal(np.sort(order), np.arange(len(d)))
    # a bundle of 64 consecutive rays covers a compact patch, not a whole image row
    rows, cols = np.divmod(order[:64], 64)
    assert np.ptp(cols) < 20 and np.ptp(rows) < 20


# ---------------------------------------------------------------------------------------------
# agreement with Open3D on generated rooms

W, H = 80, 60


@pytest.fixture(scope="module", params=[(1, "apartment"), (5, "apartment"), (3, "studio")],
                ids=lambda p: f"{p[1]}-{p[0]}")
def room(request: pytest.FixtureRequest) -> tuple[Scene, np.ndarray]:
    seed, style = request.param
    scene = generate_scene(seed, style)
    return scene, robot_trajectory(scene, 40, seed=3)[::8]


@needs_open3d
@pytest.mark.parametrize("cull", [True, False], ids=["cull", "brute"])
def test_cast_agrees_with_open3d(room: tuple[Scene, np.ndarray], cull: bool) -> None:
    scene, poses = room
    o3d_rc = SceneRenderer(scene, backend="open3d")
    torch_rc = TorchRaycaster(scene.vertices, scene.triangles, device="cpu", cull=cull)
    d_cam = camera_rays(default_intrinsics(W, H), W, H).reshape(-1, 3)
    for pose in poses:
        d = d_cam @ pose[:3, :3].T
        o = np.broadcast_to(pose[:3, 3], d.shape)
        t_ref, f_ref = o3d_rc.cast(o, d)
        t, f = torch_rc.cast(o, d)
        same = f == f_ref
        assert same.mean() >= 0.995, f"same face for {same.mean():.4f} of the pixels"
        both = same & (f >= 0)
        assert np.abs(t[both] - t_ref[both]).max() < 1e-4
        assert ((f >= 0) == (f_ref >= 0)).all()


@needs_open3d
def test_top_down_grid_agrees_with_open3d(room: tuple[Scene, np.ndarray]) -> None:
    """Parallel rays from a grid of origins (the export's top-down label map)."""
    scene, _ = room
    lo, hi = scene.room_min, scene.room_max
    gx, gy = np.meshgrid(np.arange(lo[0] + 0.05, hi[0], 0.1), np.arange(lo[1] + 0.05, hi[1], 0.1))
    o = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, hi[2] - 0.01)], 1)
    d = np.tile(DOWN, (len(o), 1))
    t_ref, f_ref = SceneRenderer(scene, backend="open3d").cast(o, d)
    t, f = SceneRenderer(scene, backend="torch", device="cpu").cast(o, d)
    same = f == f_ref
    assert same.mean() >= 0.995
    assert np.abs(t[same & (f >= 0)] - t_ref[same & (f >= 0)]).max() < 1e-4


@needs_open3d
def test_rendered_views_agree_with_open3d(room: tuple[Scene, np.ndarray]) -> None:
    scene, poses = room
    ref = SceneRenderer(scene, backend="open3d")
    tr = SceneRenderer(scene, backend="torch", device="cpu")
    assert (ref.backend, tr.backend) == ("open3d", "torch")
    K = default_intrinsics(W, H)
    for pose in poses:
        a, b = ref.render(K, pose, W, H), tr.render(K, pose, W, H)
        assert (a.label == b.label).mean() >= 0.995
        assert (np.abs(a.depth_m - b.depth_m) < 1e-4).mean() >= 0.995
        assert ((a.depth_m > 0) == (b.depth_m > 0)).all()
        # (no rgb check: the tile texture's floor(q) flips for hits a float32 ulp either side of
        # the floor plane z = 0, so even Open3D's own rounding decides some floor pixels' colour)


# ---------------------------------------------------------------------------------------------
# choosing the backend and the device


@pytest.fixture
def tiny_scene() -> Scene:
    return generate_scene(0)


def test_env_and_keyword_choose_the_backend(monkeypatch: pytest.MonkeyPatch, tiny_scene: Scene) -> None:
    monkeypatch.setenv(RAYCAST_ENV, "torch")
    assert raycast_backend() == "torch"
    assert SceneRenderer(tiny_scene).backend == "torch"
    monkeypatch.setenv(RAYCAST_ENV, " Torch ")  # case and spaces do not matter
    assert raycast_backend() == "torch"
    if _has_open3d():
        assert SceneRenderer(tiny_scene, backend="open3d").backend == "open3d"  # the keyword wins
        monkeypatch.setenv(RAYCAST_ENV, "open3d")
        assert SceneRenderer(tiny_scene).backend == "open3d"
        assert SceneRenderer(tiny_scene, backend="torch").backend == "torch"
    for unset in ("", "auto"):
        monkeypatch.setenv(RAYCAST_ENV, unset)
        assert raycast_backend() == ("open3d" if _has_open3d() else "torch")
    monkeypatch.delenv(RAYCAST_ENV)
    assert SceneRenderer(tiny_scene).backend == ("open3d" if _has_open3d() else "torch")


def test_bad_backend_names_raise(monkeypatch: pytest.MonkeyPatch, tiny_scene: Scene) -> None:
    monkeypatch.setenv(RAYCAST_ENV, "embree")
    with pytest.raises(ValueError, match=r"SIM_RAYCAST='embree' is not a ray-casting backend.*open3d, torch"):
        SceneRenderer(tiny_scene)
    monkeypatch.delenv(RAYCAST_ENV)
    with pytest.raises(ValueError, match=r"backend='cuda' is not a ray-casting backend"):
        SceneRenderer(tiny_scene, backend="cuda")


def test_without_open3d_auto_falls_back_to_torch(monkeypatch: pytest.MonkeyPatch, tiny_scene: Scene) -> None:
    monkeypatch.setitem(sys.modules, "open3d", None)  # `import open3d` now raises ModuleNotFoundError
    monkeypatch.delenv(RAYCAST_ENV, raising=False)
    r = SceneRenderer(tiny_scene)
    assert r.backend == "torch"
    pose = robot_trajectory(tiny_scene, 5, seed=0)[2]
    view = r.render(default_intrinsics(32, 24), pose, 32, 24)
    assert (view.label >= 0).all() and (view.depth_m > 0).all()
    with pytest.raises(MissingExtraError, match=r"govnesf\[sim\]"):
        SceneRenderer(tiny_scene, backend="open3d")
    monkeypatch.setenv(RAYCAST_ENV, "open3d")
    with pytest.raises(MissingExtraError, match="GOVNESF_SIM_RAYCAST=torch"):
        SceneRenderer(tiny_scene)


def test_a_broken_open3d_falls_back_to_torch_in_auto(monkeypatch: pytest.MonkeyPatch) -> None:
    """Installed but failing to import (as without libusb-1.0): auto warns and takes torch; asking
    for open3d shows the error."""
    import clients.sim.raycast as raycast

    def broken() -> None:
        raise ImportError("libusb-1.0.so.0: cannot open shared object file")

    monkeypatch.setattr(raycast, "_open3d", broken)
    monkeypatch.delenv(RAYCAST_ENV, raising=False)
    with pytest.warns(RuntimeWarning, match="libusb-1.0.so.0"):
        assert raycast.raycast_backend() == "torch"
    with pytest.raises(ImportError, match="libusb"):
        raycast.raycast_backend("open3d")


def test_device_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(RAYCAST_DEVICE_ENV, raising=False)
    auto = torch_device()
    assert auto.type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert torch_device("auto") == auto
    monkeypatch.setenv(RAYCAST_DEVICE_ENV, "cpu")
    assert torch_device() == torch.device("cpu")
    rc = TorchRaycaster(SQUARE_V, SQUARE_T)
    assert rc.device == torch.device("cpu") and rc.cull  # culling on by default on the CPU
    assert TorchRaycaster(SQUARE_V, SQUARE_T, device="cpu", cull=False).cull is False
    monkeypatch.setenv(RAYCAST_DEVICE_ENV, "gpu-please")
    with pytest.raises(ValueError, match="SIM_RAYCAST_DEVICE='gpu-please': not a usable torch device"):
        torch_device()
    with pytest.raises(ValueError, match="device='nonsense'"):
        torch_device("nonsense")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device='cuda'"):
            torch_device("cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_cuda_matches_cpu() -> None:
    scene = generate_scene(1)
    pose = robot_trajectory(scene, 40, seed=3)[10]
    d = camera_rays(default_intrinsics(W, H), W, H).reshape(-1, 3) @ pose[:3, :3].T
    o = np.broadcast_to(pose[:3, 3], d.shape)
    gpu = TorchRaycaster(scene.vertices, scene.triangles, device="cuda")
    assert gpu.device.type == "cuda" and not gpu.cull
    t_gpu, f_gpu = gpu.cast(o, d)
    t_cpu, f_cpu = TorchRaycaster(scene.vertices, scene.triangles, device="cpu").cast(o, d)
    assert (f_gpu == f_cpu).mean() >= 0.999
    np.testing.assert_allclose(t_gpu[f_gpu == f_cpu], t_cpu[f_gpu == f_cpu], atol=1e-5)


def test_record_runs_without_open3d(tmp_path: Path) -> None:
    """`govnesf sim record` in a fresh interpreter where open3d cannot be imported: the torch
    backend renders it, and open3d is never loaded."""
    out = tmp_path / "rec"
    code = textwrap.dedent(f"""
        import sys
        sys.modules["open3d"] = None
        from clients.sim.cli import main
        rc = main(["record", "--seed", "2", "--frames", "3", "--width", "32", "--height", "24", "--depth",
                   "--no-ov", "--novel-views", "1", "--points-per-m2", "20", "--previews", "1", "--quiet",
                   "--out", {str(out)!r}])
        assert sys.modules["open3d"] is None
        raise SystemExit(rc)
        """)
    env = {k: v for k, v in os.environ.items() if k != RAYCAST_ENV}  # auto: torch, as open3d is blocked
    env.update(HF_HUB_OFFLINE="1", OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, env=env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (out / "frames.govrec").is_file() and (out / "gt" / "stream.npz").is_file()
