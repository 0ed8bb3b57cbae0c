"""The gather-based averaging (``average_features`` / ``average_similarities``) against the previous
per-view ``grid_sample`` implementation (``average_features_reference``) on random scenes, for both
implementations: the compiled CPU kernel (``impl="kernel"``, what a CPU device runs) and the torch
path (``impl="torch"``, what other devices run)."""

from typing import Any

import numpy as np
import pytest
import torch

from mapper.model.baselines import OVView, average_features, average_features_reference, average_similarities
from mapper.node.queries import segment_average


def random_scene(seed: int, n_points: int = 3000, n_views: int = 7) -> tuple[np.ndarray, list[OVView]]:
    """Points in a box in front of randomly placed cameras with ov maps of mixed resolutions,
    depth maps (some with holes, one view without) and points on and off the image borders."""
    rng = np.random.default_rng(seed)
    pts = (rng.random((n_points, 3)) * [4.0, 3.0, 2.0] - [2.0, 1.5, -1.0]).astype(np.float32)
    views = []
    for i in range(n_views):
        width, height = int(rng.integers(40, 90)), int(rng.integers(30, 70))
        K = np.array([rng.uniform(20, 60), rng.uniform(20, 60), width / 2, height / 2])
        angle = rng.uniform(-0.4, 0.4)
        world_from_cam = np.eye(4)
        c, s = np.cos(angle), np.sin(angle)
        world_from_cam[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        world_from_cam[:3, 3] = rng.normal(0, 0.3, 3) - [0, 0, 0.5]
        h, w = int(rng.integers(1, 12)), int(rng.integers(1, 16))  # includes 1-pixel-wide maps
        ov = rng.standard_normal((h, w, 24)).astype(np.float16 if i % 2 else np.float32)
        if i == n_views - 1:
            depth = None
        else:
            depth = rng.uniform(0.5, 4.0, (height // 2, width // 2)).astype(np.float32)
            depth[rng.random(depth.shape) < 0.2] = 0.0
        views.append(OVView(ov, K, world_from_cam, (width, height), depth))
    return pts, views


IMPLS = ["kernel", "torch"]


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("use_depth", [False, True])
def test_fast_average_equals_the_reference(seed: int, use_depth: bool, impl: str) -> None:
    pts, views = random_scene(seed)
    options: list[dict[str, Any]] = [{}, {"border_px": 0.0}, {"distance_power": 1.5, "chunk": 500},
                                     {"depth_rel_tol": 0.6}]
    for kwargs in options:
        f_ref, n_ref = average_features_reference(pts, views, use_depth=use_depth, **kwargs)
        f, n = average_features(pts, views, use_depth=use_depth, impl=impl, **kwargs)
        assert torch.equal(n, n_ref)
        assert int((n > 0).sum()) > 100  # the scene exercises the averaging
        assert torch.allclose(f, f_ref, atol=1e-5, rtol=0)


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("use_depth", [False, True])
def test_one_camera_window_equals_the_reference(use_depth: bool, impl: str) -> None:
    # every view of the same size (one robot's camera): the per-view sizes are one value for all
    # pairs (no per-pair gather), as in a node's window
    pts, views = random_scene(4)
    rng = np.random.default_rng(4)
    same = [OVView(rng.standard_normal((5, 7, 24)).astype(np.float32), views[0].K, v.world_from_cam,
                   views[0].image_wh, None if v.depth_m is None else views[0].depth_m) for v in views]
    for chunk, table_bytes in ((16384, 256 << 20), (333, 1)):
        f_ref, n_ref = average_features_reference(pts, same, use_depth=use_depth, chunk=chunk)
        f, n = average_features(pts, same, use_depth=use_depth, chunk=chunk, max_table_bytes=table_bytes,
                                impl=impl)
        assert torch.equal(n, n_ref) and int((n > 0).sum()) > 100
        assert torch.allclose(f, f_ref, atol=1e-5, rtol=0)


@pytest.mark.parametrize("impl", IMPLS)
def test_view_weights_and_table_groups_equal_the_reference(impl: str) -> None:
    pts, views = random_scene(3)
    vw = np.random.default_rng(3).random((len(views), pts.shape[0])).astype(np.float32)
    vw[vw < 0.3] = 0.0
    f_ref, n_ref = average_features_reference(pts, views, use_depth=False, view_weights=vw)
    # a tiny table bound puts every view in its own gather table
    f, n = average_features(pts, views, use_depth=False, view_weights=vw, max_table_bytes=1, chunk=700,
                            impl=impl)
    assert torch.equal(n, n_ref)
    assert torch.allclose(f, f_ref, atol=1e-5, rtol=0)


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("use_depth", [False, True])
def test_similarities_and_segment_average_match_the_reference(use_depth: bool, impl: str) -> None:
    pts, views = random_scene(4)
    texts = np.random.default_rng(4).standard_normal((5, 24)).astype(np.float32)
    texts /= np.linalg.norm(texts, axis=1, keepdims=True)
    f_ref, n_ref = average_features_reference(pts, views, use_depth=use_depth)
    sims_ref = f_ref.numpy() @ texts.T
    sims, n = average_similarities(pts, views, texts, use_depth=use_depth, chunk=1000, impl=impl)
    assert torch.equal(n, n_ref)
    np.testing.assert_allclose(sims.numpy(), sims_ref, atol=1e-5, rtol=0)
    label, score, n_seg = segment_average(pts, views, texts, use_depth=use_depth)  # type: ignore[arg-type]
    seen = n_ref.numpy() > 0
    np.testing.assert_array_equal(n_seg, n_ref.numpy())
    assert (label[~seen] == -1).all() and (score[~seen] == 0).all()
    # labels equal wherever the best text is not a near tie
    top2 = np.sort(sims_ref, axis=1)[:, -2:]
    clear = seen & (top2[:, 1] - top2[:, 0] > 1e-4)
    np.testing.assert_array_equal(label[clear], np.argmax(sims_ref, axis=1)[clear])
    np.testing.assert_allclose(score[seen], sims_ref[seen].max(axis=1), atol=1e-5)


@pytest.mark.parametrize("impl", IMPLS)
def test_no_views_and_bad_input(impl: str) -> None:
    pts, views = random_scene(5, n_points=50)
    f, n = average_features(pts, [], use_depth=False, impl=impl)
    assert f.shape == (50, 0) and int(n.sum()) == 0
    f, n = average_features(pts, [views[-1]], use_depth=True, impl=impl)  # the one view without depth
    assert f.shape == (50, 24) and int(n.sum()) == 0 and float(f.abs().sum()) == 0.0
    s, n = average_similarities(pts, [views[-1]], np.ones((2, 24), np.float32), use_depth=True, impl=impl)
    assert s.shape == (50, 2) and int(n.sum()) == 0 and float(s.abs().sum()) == 0.0
    f, n = average_features(pts[:0], views, use_depth=False, impl=impl)
    assert f.shape == (0, 24) and n.shape == (0,)
    with pytest.raises(ValueError, match="max_table_bytes"):
        average_features(pts, views, use_depth=False, max_table_bytes=0, impl=impl)
    with pytest.raises(ValueError, match="dimension"):
        average_similarities(pts, views, np.ones((2, 7), np.float32), use_depth=False, impl=impl)
    with pytest.raises(ValueError, match="impl"):
        average_features(pts, views, use_depth=False, impl="fast")
    with pytest.raises(ValueError, match="CPU"):
        average_features(pts, views, use_depth=False, impl="kernel", device="meta")


def test_kernel_is_the_same_for_any_thread_count_and_under_concurrent_calls() -> None:
    # every point is summed by one thread in a fixed order: bitwise the same answer for 1 or 2
    # threads, and for calls from several Python threads at once (launches are serialised)
    import threading

    pts, views = random_scene(6, n_points=4000)
    texts = np.random.default_rng(6).standard_normal((3, 24)).astype(np.float32)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one, n_one = average_similarities(pts, views, texts, use_depth=True, impl="kernel")
        torch.set_num_threads(2)
        two, n_two = average_similarities(pts, views, texts, use_depth=True, impl="kernel")
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one, two) and torch.equal(n_one, n_two) and int((n_one > 0).sum()) > 100
    results: list[tuple[torch.Tensor, torch.Tensor]] = []
    errors: list[BaseException] = []

    def call() -> None:
        try:
            results.append(average_similarities(pts, views, texts, use_depth=True, impl="kernel"))
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=call) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(results) == 4
    for sims, n in results:
        assert torch.equal(sims, one) and torch.equal(n, n_one)


@pytest.mark.parametrize("impl", IMPLS)
def test_extreme_points_count_no_view(impl: str) -> None:
    # behind every camera, on a camera's plane and far out (1e30 m, out of every image): no view
    # counts and the rows are zero; near float32's limit (3e38 m: camera coordinates overflow to
    # inf) and on a camera's axis: the same views as the reference, finite features
    _, views = random_scene(7, n_points=10)
    centre = np.asarray(views[0].world_from_cam, np.float64)[:3, 3]
    pts = np.array([[0.0, 0.0, -50.0], centre, [1e30, -1e30, 1e30], [3e38, 3e38, 3e38],
                    [0.0, 0.0, 1e-30]], np.float32)
    f_ref, n_ref = average_features_reference(pts, views, use_depth=False)
    f, n = average_features(pts, views, use_depth=False, impl=impl)
    assert torch.equal(n, n_ref)
    assert int(n[:3].sum()) == 0 and bool(torch.isfinite(f).all()) and float(f[:3].abs().sum()) == 0.0
    assert torch.allclose(f, f_ref, atol=1e-5, rtol=0)


def test_in_view_matrix_equals_torch_projection() -> None:
    # the view selection's (point, view) visibility: the compiled kernel against in_view of
    # project_points, with points behind the cameras, on their planes, on the image edges and far
    from mapper.kernels.average_kernel import in_view_matrix
    from mapper.model.ops.geometry import DEFAULT_EPS, in_view, invert_pose, project_points

    pts, views = random_scene(8, n_points=5000)
    rng = np.random.default_rng(8)
    extra = np.array([[0.0, 0.0, -50.0], [1e30, -1e30, 1e30], [0.0, 0.0, 1e-7]], np.float32)
    pts = np.concatenate([pts, extra, (rng.standard_normal((500, 3)) * 20).astype(np.float32)])
    width, height = 64, 48
    cfw = invert_pose(torch.stack([torch.as_tensor(v.world_from_cam, dtype=torch.float32) for v in views]))
    K = torch.stack([torch.as_tensor(v.K, dtype=torch.float32) for v in views])
    uv, z = project_points(torch.from_numpy(pts).expand(len(views), -1, -1), K, cfw)
    ref = in_view(uv, z, width, height).T.numpy()  # (P, M)
    mine = in_view_matrix(pts, cfw.numpy(), K.numpy(), (width, height), DEFAULT_EPS, threads=2)
    assert mine.shape == ref.shape and 0.05 < ref.mean() < 0.95
    np.testing.assert_array_equal(mine, ref)


def test_kernel_table_reused_for_the_same_views_only() -> None:
    """The kernel's OV table is kept for the same views' ``ov`` objects (a window asked again) and
    made anew for others, with the same answers as a fresh table."""
    import mapper.kernels.average as baselines  # the driver that keeps the table

    pts, views = random_scene(4)
    first, n_first = average_features(pts, views, use_depth=False, impl="kernel")
    table = baselines._TABLE_CACHE[0][1]
    again, n_again = average_features(pts, list(views), use_depth=False, impl="kernel")
    assert baselines._TABLE_CACHE[0][1] is table and not table.flags.writeable
    assert torch.equal(again, first) and torch.equal(n_again, n_first)
    changed = [*views[:-1], views[-1]._replace(ov=np.ascontiguousarray(views[-1].ov[:, ::-1]))]
    other, _ = average_features(pts, changed, use_depth=False, impl="kernel")
    assert baselines._TABLE_CACHE[0][1] is not table
    ref, _ = average_features_reference(pts, changed, use_depth=False)
    torch.testing.assert_close(other, ref, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("use_depth", [False, True])
@pytest.mark.parametrize("seed", [0, 3])
def test_prior_of_left_views_equals_averaging_all_views(seed: int, use_depth: bool) -> None:
    """Views that left (their running mean of ``view_samples`` and count as the prior) plus the views
    still given average exactly as all the views together (float rounding); a point only the left
    views saw is answered from the prior alone with 0 views counted."""
    from mapper.model.baselines import view_samples

    pts, views = random_scene(seed)
    texts = torch.nn.functional.normalize(torch.randn(5, 24, generator=torch.Generator().manual_seed(seed)),
                                          dim=1).numpy()
    left, kept = views[:4], views[4:]
    total = np.zeros((pts.shape[0], 24), np.float64)
    count = np.zeros(pts.shape[0], np.float64)
    for view in left:
        feat, counted = view_samples(pts, view, use_depth=use_depth)
        assert not feat[~counted].any()
        total += feat
        count += counted
    has = count > 0
    mean = (total[has] / count[has, None]).astype(np.float32)
    row = np.full(pts.shape[0], -1, np.int64)
    row[has] = np.arange(int(has.sum()))
    prior = (mean, row, count.astype(np.float32))
    want, n_all = average_similarities(pts, views, texts, use_depth=use_depth)
    got, n_kept = average_similarities(pts, kept, texts, use_depth=use_depth, prior=prior)
    _, n_left = average_similarities(pts, left, texts, use_depth=use_depth)
    assert torch.equal(n_kept + n_left, n_all)
    assert int(((n_kept == 0) & has).sum()) > 10  # some points only the left views saw
    assert torch.allclose(got, want, atol=2e-5, rtol=0)
    # no view given: the prior alone
    alone, n0 = average_similarities(pts, [], texts, use_depth=use_depth, prior=prior)
    want_left, _ = average_similarities(pts, left, texts, use_depth=use_depth)
    assert int(n0.sum()) == 0
    assert torch.allclose(alone, want_left, atol=2e-5, rtol=0)
    with pytest.raises(ValueError, match="prior rows"):
        average_similarities(pts, kept, texts, use_depth=use_depth, prior=(mean, row + 10**6, prior[2]))
    with pytest.raises(ValueError, match="compiled CPU path"):
        average_similarities(pts, kept, texts, use_depth=use_depth, prior=prior, impl="torch")


@pytest.mark.parametrize("use_depth", [False, True])
def test_neighbouring_points_read_shared_taps_once_with_the_same_answers(use_depth: bool) -> None:
    # the kernel sums points two at a time and reads the rows of a cell quad that both points'
    # view has once for both: points next to each other (duplicates, 1 mm apart, a raster of
    # points on a plane) take that path; each answer is still that point's alone, the same as
    # with any other neighbour (a permutation, each point alone) and as the reference
    pts, views = random_scene(6, n_points=400)
    rng = np.random.default_rng(6)
    grid = np.stack(np.meshgrid(np.linspace(-1.0, 1.0, 40), np.linspace(-0.8, 0.8, 30), [1.8]), -1)
    near = np.concatenate([np.repeat(pts, 2, axis=0), pts + rng.normal(0, 1e-3, pts.shape).astype(np.float32),
                           grid.reshape(-1, 3).astype(np.float32)])
    f_ref, n_ref = average_features_reference(near, views, use_depth=use_depth)
    f, n = average_features(near, views, use_depth=use_depth, impl="kernel")
    assert torch.equal(n, n_ref) and int((n > 0).sum()) > 500
    assert torch.allclose(f, f_ref, atol=1e-5, rtol=0)
    perm = rng.permutation(near.shape[0])
    f_perm, n_perm = average_features(near[perm], views, use_depth=use_depth, impl="kernel")
    assert torch.equal(n_perm, n[perm])
    assert torch.allclose(f_perm, f[perm], atol=1e-6, rtol=0)
    alone = [average_features(near[i : i + 1], views, use_depth=use_depth, impl="kernel")[0]
             for i in range(60)]
    assert torch.allclose(torch.cat(alone), f[:60], atol=1e-6, rtol=0)
