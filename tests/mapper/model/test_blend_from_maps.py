"""Blending OV features straight from the views' maps (``fusion.blend_from_maps``), the fast path
of ``segment_points`` (method govnesf) and of the learned features written into the global map:
equal to sampling every view (``sample_bilinear``) then blending (``blend``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapper.map.window import KeyframeWindow
from mapper.model.field import GovNeSF, OVMaps
from mapper.model.fusion import blend, blend_from_maps
from mapper.model.ops.cost_volume import sample_volume
from mapper.model.ops.geometry import bilinear_corners, sample_bilinear
from mapper.node.config import WindowConfig
from mapper.runtime.views import source_views
from tests.mapper.runtime.test_model_runtime import TINY, keyframe, make_runtime, orbit


def _maps(m: int, c: int, h: int, w: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.randn(m, c, h, w, generator=torch.Generator().manual_seed(m * 100 + c), dtype=dtype)


@pytest.mark.parametrize("h, w", [(1, 1), (3, 5), (15, 20)])
def test_bilinear_corners_reproduce_grid_sample_with_border_padding(h: int, w: int) -> None:
    img = _maps(1, 2, h, w, torch.float64)[0]
    gen = torch.Generator().manual_seed(h * w)
    # inside, on the edges, far outside (border padding) and exact pixel centres
    size = torch.tensor([w, h], dtype=torch.float64)
    uv = torch.cat([
        torch.rand(200, 2, generator=gen, dtype=torch.float64) * size,
        torch.rand(50, 2, generator=gen, dtype=torch.float64) * 6 * size - 3 * size,
        torch.tensor([[0.0, 0.0], [w, h], [0.5, 0.5], [w - 0.5, h - 0.5]], dtype=torch.float64),
    ])  # fmt: skip
    index, weight = bilinear_corners(uv, w, h)
    assert index.shape == (uv.shape[0], 4) and int(index.min()) >= 0 and int(index.max()) < h * w
    torch.testing.assert_close(weight.sum(-1), torch.ones(uv.shape[0], dtype=torch.float64))
    flat = img.reshape(2, -1)  # (C, h*w)
    mine = (flat[:, index] * weight).sum(-1).T  # (P, C)
    ref, _ = sample_bilinear(img, uv)
    torch.testing.assert_close(mine, ref, rtol=0, atol=1e-12)


def test_bilinear_corners_of_non_finite_coordinates_stay_in_range() -> None:
    uv = torch.tensor([[float("nan"), 1.0], [float("inf"), -float("inf")], [1e30, -1e30]])
    index, weight = bilinear_corners(uv, 4, 3)
    assert int(index.min()) >= 0 and int(index.max()) < 12 and torch.isfinite(weight).all()


@pytest.mark.parametrize("per_point_views", [False, True])
def test_blend_from_maps_equals_sampling_then_blending(per_point_views: bool) -> None:
    m, c, h, w, P, N = 5, 7, 6, 8, 300, 3
    maps = _maps(m, c, h, w)
    gen = torch.Generator().manual_seed(1)
    if per_point_views:
        view_idx = torch.randint(0, m, (P, N), generator=gen)
    else:
        view_idx = torch.tensor([4, 0, 2])
    uv = torch.rand(P, N, 2, generator=gen) * torch.tensor([w + 4.0, h + 4.0]) - 2.0
    mask = torch.rand(P, N, generator=gen) > 0.3
    mask[:10] = False  # points no view sees: all-zero weights -> zero feature
    weights = torch.softmax(torch.randn(P, N, generator=gen), -1) * mask
    table = maps.permute(0, 2, 3, 1).reshape(-1, c).contiguous()
    mine = blend_from_maps(table, (w, h), view_idx, uv, weights)
    vidx = view_idx.expand(P, N)
    values = torch.stack([sample_bilinear(maps[vidx[:, n]], uv[:, n, None])[0][:, 0] for n in range(N)], 1)
    torch.testing.assert_close(mine, blend(weights, values), rtol=1e-5, atol=1e-6)
    assert torch.equal(mine[:10], torch.zeros(10, c))
    empty = blend_from_maps(table, (w, h), view_idx[:0] if per_point_views else view_idx, uv[:0], weights[:0])
    assert empty.shape == (0, c)
    with pytest.raises(ValueError, match="blend_from_maps"):
        blend_from_maps(table[:-1], (w, h), view_idx, uv, weights)


def _runtime_with_six_keyframes(model: GovNeSF):  # -> (ModelRuntime, its prepared window)
    runtime = make_runtime(model, source_views=3)
    window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i in range(6):
        window.consider(keyframe(i, orbit(i)))
    return runtime, runtime._volume.prepare()


def test_point_outputs_from_maps_equal_the_sampled_path() -> None:
    """GovNeSF.point_outputs(..., ov_maps=...) on dummy-ov samples == on fully sampled views."""
    torch.manual_seed(0)
    model = GovNeSF(TINY).eval()
    runtime, prep = _runtime_with_six_keyframes(model)
    seen = np.random.default_rng(2).uniform([-0.6, -0.6, 0.1], [0.6, 0.6, 0.9], (400, 3))
    unseen = np.array([[0.0, 0.0, 30.0], [50.0, 50.0, 0.0]])  # above / far behind every camera
    pts = torch.from_numpy(np.concatenate([seen, unseen]).astype(np.float32))
    views_idx = torch.tensor([5, 1, 3])
    with torch.no_grad():
        for use_depth in (False, True):
            full = source_views(runtime._loaded, prep, views_idx, need_ov=True, use_depth=use_depth)
            ref = model.query_points(full, prep.volume, prep.bounds, pts, depth_guided_masking=use_depth)
            lean = source_views(runtime._loaded, prep, views_idx, need_ov=False, use_depth=use_depth)
            samples = model.sample_views(lean, pts, use_depth)
            v, _ = sample_volume(prep.volume, prep.bounds, pts)
            out = model.point_outputs(samples, v, ov_maps=prep.ov_maps(views_idx, runtime.image_wh))
            torch.testing.assert_close(out.ov, ref.ov, rtol=1e-5, atol=1e-6)
            assert torch.equal(out.valid, ref.valid) and torch.equal(out.num_views, ref.num_views)
            assert bool(ref.valid.any()) and bool((~ref.valid).any())  # both kinds of points
    # the runtime's own answers use this path
    label, _, _ = runtime.segment(pts.numpy(), ["a", "b", "c"])
    assert (label[:400] >= 0).all() and (label[400:] == -1).all()
    samples.uv = None
    with pytest.raises(ValueError, match="needs samples with uv"):
        model.point_outputs(samples, v, ov_maps=OVMaps(prep.ov_table, (1, 1), views_idx, (1, 1)))


def test_cell_inverse_equals_the_row_wise_unique() -> None:
    from mapper.runtime.views import cell_inverse

    gen = torch.Generator().manual_seed(3)
    for cells in (
        torch.randint(-5, 6, (2000, 3), generator=gen),
        torch.randint(-(2**40), 2**40, (50, 3), generator=gen),  # keys would overflow: fallback
        torch.zeros(1, 3, dtype=torch.long),
    ):
        ref = torch.unique(cells, dim=0, return_inverse=True)[1]
        assert torch.equal(cell_inverse(cells), ref)


def test_cell_view_sets_equal_the_dict_of_sorted_tuples() -> None:
    """Cells grouped by their chosen views: the same groups, in the same order (first cell), as
    collecting ``tuple(sorted(chosen views))`` per cell in a dict (the loop it replaced)."""
    from mapper.runtime.views import cell_view_sets

    gen = torch.Generator().manual_seed(5)
    # (300, 5, 3): sets repeat; (150, 62, 16): the largest bit-mask case; (150, 70, 16): rows, not masks
    for n_cells, n_views, k in ((500, 12, 4), (1, 3, 3), (200, 30, 16), (300, 5, 3), (150, 62, 16),
                                (150, 70, 16)):
        order = torch.stack([torch.randperm(n_views, generator=gen)[:k] for _ in range(n_cells)])
        chosen = torch.rand(n_cells, k, generator=gen) < 0.7
        chosen[0] = False  # a cell with no view
        groups: dict[tuple[int, ...], list[int]] = {}
        for c in range(n_cells):
            views = tuple(sorted(int(v) for v, ok in zip(order[c], chosen[c], strict=True) if ok))
            if views:
                groups.setdefault(views, []).append(c)
        cell_group, keys = cell_view_sets(order, chosen, n_views)
        assert [tuple(k.tolist()) for k in keys] == list(groups)
        expected = torch.full((n_cells,), -1, dtype=torch.long)
        for g, cells in enumerate(groups.values()):
            expected[cells] = g
        assert torch.equal(cell_group, expected)


def test_samples_carry_each_views_distance_to_the_point() -> None:
    """sample_views / sample_views_indexed: source_range is |point - camera centre| and agrees with
    source_dirs; a model with the range encoding blends the same on both paths."""
    from dataclasses import replace

    from mapper.model.ops.geometry import camera_centers

    torch.manual_seed(0)
    cfg = replace(TINY, fusion=replace(TINY.fusion, range_encoding=True))
    model = GovNeSF(cfg).eval()
    with torch.no_grad():
        assert model.fusion.range_encoding is not None
        model.fusion.range_encoding.weight.normal_(0.0, 1.0)  # make the distances matter
    runtime, prep = _runtime_with_six_keyframes(model)
    rng = np.random.default_rng(3)
    pts = torch.from_numpy(rng.uniform([-0.6, -0.6, 0.1], [0.6, 0.6, 0.9], (200, 3))).float()
    views = source_views(runtime._loaded, prep, torch.arange(6), need_ov=True, use_depth=False)
    whole = model.sample_views(views, pts, False)
    centres = camera_centers(views.world_from_cam)  # (6, 3)
    offsets = pts[:, None] - centres[None]  # (P, 6, 3)
    assert whole.source_range is not None
    torch.testing.assert_close(whole.source_range, offsets.norm(dim=-1))
    torch.testing.assert_close(whole.source_dirs * whole.source_range[..., None], offsets)
    idx = torch.randint(0, 6, (200, 4), generator=torch.Generator().manual_seed(4))
    part = model.sample_views_indexed(views, idx, torch.ones(200, 4, dtype=torch.bool), pts, False)
    assert part.source_range is not None
    torch.testing.assert_close(part.source_range, whole.source_range.gather(1, idx))
    # without the OV maps read (blended from OVMaps later): the same samples, an empty ov
    lean = model.sample_views_indexed(views, idx, torch.ones(200, 4, dtype=torch.bool), pts, False,
                                      sample_ov=False)
    assert lean.ov.shape == (200, 4, 0)
    for name in ("rgb", "features", "mask", "source_dirs", "source_range", "uv"):
        assert torch.equal(getattr(lean, name), getattr(part, name)), name
    v, _ = sample_volume(prep.volume, prep.bounds, pts)
    with torch.no_grad():
        a = model.point_outputs(part, v)
        ref_samples = model.sample_views(views, pts, False)
        for name in ("rgb", "features", "ov", "mask", "source_dirs", "source_range"):
            t = getattr(ref_samples, name)
            setattr(ref_samples, name, torch.stack([t[p, idx[p]] for p in range(200)]))
        b = model.point_outputs(ref_samples, v)
    torch.testing.assert_close(a.ov, b.ov, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("per_point_views", [False, True])
def test_blend_kernel_equals_the_torch_path(per_point_views: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    # the compiled CPU kernel (float32, no autograd) against the embedding_bag path, with
    # coordinates far outside the maps and non-finite ones (bilinear_corners reads them at 0),
    # zero weights (skipped) and 1-pixel-wide maps
    import mapper.model.fusion as fusion

    gen = torch.Generator().manual_seed(7)
    for m, c, h, w in ((4, 9, 5, 7), (3, 384, 15, 20), (2, 3, 1, 6)):
        P, N = 500, 5
        table = _maps(m, c, h, w).permute(0, 2, 3, 1).reshape(-1, c).contiguous()
        view_idx = torch.randint(0, m, (P, N), generator=gen) if per_point_views else torch.arange(N) % m
        uv = torch.rand(P, N, 2, generator=gen) * torch.tensor([w + 8.0, h + 8.0]) - 4.0
        uv[0, 0, 0], uv[1, 1, 1], uv[2, 2] = float("nan"), float("inf"), torch.tensor([-1e30, 1e30])
        weights = torch.rand(P, N, generator=gen) * (torch.rand(P, N, generator=gen) > 0.25)
        assert fusion._blend_kernel_applies(table, uv, weights)
        mine = blend_from_maps(table, (w, h), view_idx, uv, weights)
        monkeypatch.setattr(fusion, "_blend_kernel_applies", lambda *_: False)
        ref = blend_from_maps(table, (w, h), view_idx, uv, weights)
        monkeypatch.undo()
        assert bool(torch.isfinite(mine).all())
        torch.testing.assert_close(mine, ref, rtol=1e-5, atol=1e-5)
    # autograd, float64 or another device keep the torch path
    grad_table = table.clone().requires_grad_(True)
    assert not fusion._blend_kernel_applies(grad_table, uv, weights)
    assert not fusion._blend_kernel_applies(table.double(), uv.double(), weights)
    with torch.no_grad():
        assert fusion._blend_kernel_applies(grad_table, uv, weights)


def test_blend_kernel_neighbours_sharing_cells_equal_the_torch_path(monkeypatch: pytest.MonkeyPatch) -> None:
    # the kernel blends points two at a time and reads a cell quad that both points' slot has once
    # for both: pairs on the same cells (duplicates and near-duplicates), pairs that share only
    # some slots, and an odd count (the last point alone)
    import mapper.model.fusion as fusion

    gen = torch.Generator().manual_seed(8)
    m, c, h, w, P, N = 3, 384, 15, 20, 301, 6
    table = _maps(m, c, h, w).permute(0, 2, 3, 1).reshape(-1, c).contiguous()
    view_idx = torch.randint(0, m, (P, N), generator=gen)
    view_idx[1::2] = view_idx[0:-1:2]  # neighbours with the same slots' maps
    uv = torch.rand(P, N, 2, generator=gen) * torch.tensor([float(w), float(h)])
    uv[1::2] = uv[0:-1:2] + 0.01 * torch.rand(P // 2, N, 2, generator=gen)
    uv[3::4, ::2] += 3.0  # some slots on other cells
    weights = torch.rand(P, N, generator=gen) * (torch.rand(P, N, generator=gen) > 0.2)
    mine = blend_from_maps(table, (w, h), view_idx, uv, weights)
    monkeypatch.setattr(fusion, "_blend_kernel_applies", lambda *_: False)
    ref = blend_from_maps(table, (w, h), view_idx, uv, weights)
    monkeypatch.undo()
    torch.testing.assert_close(mine, ref, rtol=1e-5, atol=1e-5)
    alone = torch.cat([blend_from_maps(table, (w, h), view_idx[p : p + 1], uv[p : p + 1], weights[p : p + 1])
                       for p in range(40)])
    torch.testing.assert_close(alone, mine[:40], rtol=0, atol=1e-6)


def test_cosines_from_maps_equal_normalised_blend_times_texts(monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled cosine kernel == F.normalize(blend_from_maps(...)) @ texts.T; points whose
    weights are all 0 get cosines 0; sizes that do not fit are refused."""
    import mapper.model.fusion as fusion
    from mapper.model.fusion import cosines_from_maps

    gen = torch.Generator().manual_seed(8)
    m, c, h, w, P, N = 3, 384, 15, 20, 400, 6
    table = _maps(m, c, h, w).permute(0, 2, 3, 1).reshape(-1, c).contiguous()
    view_idx = torch.randint(0, m, (P, N), generator=gen)
    uv = torch.rand(P, N, 2, generator=gen) * torch.tensor([w + 8.0, h + 8.0]) - 4.0
    weights = torch.rand(P, N, generator=gen) * (torch.rand(P, N, generator=gen) > 0.25)
    weights[:5] = 0.0  # no view: a zero blend
    texts = torch.nn.functional.normalize(torch.randn(7, c, generator=gen), dim=-1)
    blended = blend_from_maps(table, (w, h), view_idx, uv, weights)
    ref = torch.nn.functional.normalize(blended, dim=-1) @ texts.T
    mine = cosines_from_maps(table, (w, h), view_idx, uv, weights, texts)
    assert mine.shape == (P, 7) and torch.all(mine[:5] == 0)
    torch.testing.assert_close(mine, ref, rtol=1e-5, atol=1e-5)
    monkeypatch.setattr(fusion, "_blend_kernel_applies", lambda *_: False)
    torch.testing.assert_close(cosines_from_maps(table, (w, h), view_idx, uv, weights, texts), ref)
    monkeypatch.undo()
    with pytest.raises(ValueError, match="cosines_from_maps"):
        cosines_from_maps(table, (w, h), view_idx, uv, weights, texts[:, :10])
    with pytest.raises(ValueError, match="must index the 3 maps"):
        cosines_from_maps(table, (w, h), view_idx + 1, uv, weights, texts)


def test_point_cosines_equal_the_point_outputs() -> None:
    """GovNeSF.point_cosines (what segment_points answers from) == normalised point_outputs' OV
    features times the texts, from the maps and from sampled OV alike."""
    torch.manual_seed(0)
    model = GovNeSF(TINY).eval()
    runtime, prep = _runtime_with_six_keyframes(model)
    pts = torch.from_numpy(np.random.default_rng(5).uniform([-0.6, -0.6, 0.1], [0.6, 0.6, 0.9], (300, 3)))
    pts = pts.float()
    views_idx = torch.tensor([5, 1, 3])
    assert prep.ov is not None
    texts = torch.nn.functional.normalize(torch.randn(4, prep.ov.shape[1]), dim=-1)
    with torch.no_grad():
        lean = source_views(runtime._loaded, prep, views_idx, need_ov=False, use_depth=False)
        samples = model.sample_views(lean, pts, False)
        v, _ = sample_volume(prep.volume, prep.bounds, pts)
        ov_maps = prep.ov_maps(views_idx, runtime.image_wh)
        out = model.point_outputs(samples, v, ov_maps=ov_maps)
        cos, valid, num_views = model.point_cosines(samples, v, texts, ov_maps=ov_maps)
        full = source_views(runtime._loaded, prep, views_idx, need_ov=True, use_depth=False)
        sampled = model.sample_views(full, pts, False)
        cos_sampled, _, _ = model.point_cosines(sampled, v, texts)
    expected = torch.nn.functional.normalize(out.ov, dim=-1) @ texts.T
    assert torch.equal(valid, out.valid) and torch.equal(num_views, out.num_views) and bool(valid.any())
    torch.testing.assert_close(cos, expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(cos_sampled, expected, rtol=1e-4, atol=1e-5)


def test_contiguous_uv_copies_the_same_values() -> None:
    # the blend kernel's copy of (P, N, 2) pixel pairs: one 8-byte element per pair where the pair
    # is contiguous, numpy's copy otherwise; always C-contiguous float32 and the same values
    from mapper.kernels.average_kernel import _contiguous_uv

    base = np.random.default_rng(0).random((16, 301, 2)).astype(np.float32)
    base[0, 0] = [np.nan, np.inf]
    for uv in (base.transpose(1, 0, 2), base, base[:, ::2], base.astype(np.float64).transpose(1, 0, 2),
               base[:, :, ::-1].transpose(1, 0, 2), base[:0].transpose(1, 0, 2)):
        out = _contiguous_uv(uv)
        assert out.dtype == np.float32 and out.flags.c_contiguous and out.shape == uv.shape
        np.testing.assert_array_equal(out, uv.astype(np.float32))
