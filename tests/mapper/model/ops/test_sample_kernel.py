"""The compiled per-pair sampling of ``sample_views_indexed`` (``mapper.model.ops.sample_kernel``)
equals the torch path."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mapper.model.field import GovNeSF, PointViewSamples
from mapper.model.ops import sample_kernel
from mapper.model.ops.cost_volume import sample_volume
from mapper.runtime.views import all_views
from tests.mapper.model.test_blend_from_maps import _runtime_with_six_keyframes
from tests.mapper.runtime.test_model_runtime import TINY


def _points(n: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    seen = rng.uniform([-0.6, -0.6, 0.1], [0.6, 0.6, 0.9], (n, 3))
    odd = np.array([[0.0, 0.0, 30.0], [50.0, 50.0, 0.0], [0.0, 0.0, 0.0]])  # above, far behind, centre
    return torch.from_numpy(np.concatenate([seen, odd]).astype(np.float32))


def _window(*, need_ov: bool = False, use_depth: bool = False):  # -> (model, runtime, prep, views)
    """A TINY model's runtime over six keyframes, and all its views as one SourceViews."""
    torch.manual_seed(0)
    model = GovNeSF(TINY).eval()
    runtime, prep = _runtime_with_six_keyframes(model)
    return model, runtime, prep, all_views(runtime._loaded, prep, need_ov=need_ov, use_depth=use_depth)


def _both(model: GovNeSF, *args, **kw) -> tuple[PointViewSamples, PointViewSamples]:
    with torch.no_grad():
        model.compiled_sampling = False
        ref = model.sample_views_indexed(*args, sample_ov=False, **kw)
        model.compiled_sampling = True
        fast = model.sample_views_indexed(*args, sample_ov=False, **kw)
    return ref, fast


@pytest.mark.parametrize("use_depth", [False, True])
def test_compiled_sampling_equals_the_torch_path(use_depth: bool) -> None:
    model, runtime, prep, views = _window(use_depth=use_depth)
    pts = _points(300, seed=1)
    P = pts.shape[0]
    gen = torch.Generator().manual_seed(2)
    idx = torch.randint(0, len(views), (P, 5), generator=gen)
    slots = torch.rand(P, 5, generator=gen) < 0.8  # some padding slots
    ref, fast = _both(model, views, idx, slots, pts, use_depth)
    assert torch.equal(fast.mask, ref.mask)
    assert bool(ref.mask.any()) and bool((~ref.mask).any())
    m = ref.mask
    torch.testing.assert_close(fast.rgb[m], ref.rgb[m], atol=1e-6, rtol=0.0)
    torch.testing.assert_close(fast.features[m], ref.features[m], atol=1e-5, rtol=1e-6)
    assert torch.all(fast.rgb[~m] == 0) and torch.all(fast.features[~m] == 0)  # masked: never read
    assert fast.uv is not None and ref.uv is not None
    torch.testing.assert_close(fast.uv, ref.uv, atol=1e-3, rtol=1e-6)
    torch.testing.assert_close(fast.source_dirs, ref.source_dirs, atol=1e-6, rtol=0.0)
    assert fast.source_range is not None and ref.source_range is not None
    torch.testing.assert_close(fast.source_range, ref.source_range, atol=1e-6, rtol=1e-6)
    assert fast.ov.shape == (P, 5, 0)
    # the layout the network's fast paths want: P fastest
    assert fast.features.stride(0) == 1 and fast.rgb.stride(0) == 1
    # and the same answers downstream
    v, _ = sample_volume(prep.volume, prep.bounds, pts)
    ov_maps = prep.ov_maps(idx, runtime.image_wh)
    with torch.no_grad():
        a = model.point_outputs(ref, v, ov_maps=ov_maps)
        b = model.point_outputs(fast, v, ov_maps=ov_maps)
    assert torch.equal(a.valid, b.valid) and torch.equal(a.num_views, b.num_views)
    torch.testing.assert_close(b.ov, a.ov, atol=1e-5, rtol=1e-5)


def test_depth_test_masks_views_that_disagree() -> None:
    """The depth test is applied (a view whose depth map says nearer surface masks the point), the
    same on both paths."""
    model, _, _, views = _window(use_depth=True)
    assert views.depth_m is not None
    pts = _points(300, seed=3)
    idx = torch.arange(len(views)).expand(pts.shape[0], -1)
    slots = torch.ones(idx.shape, dtype=torch.bool)
    plain_ref, plain = _both(model, views, idx, slots, pts, False)
    ref, dgm = _both(model, views, idx, slots, pts, True)
    assert torch.equal(dgm.mask, ref.mask) and torch.equal(plain.mask, plain_ref.mask)
    assert bool((plain.mask & ~dgm.mask).any())  # the test removed some views
    assert not bool((dgm.mask & ~plain.mask).any())  # and never adds one


def test_dispatch() -> None:
    """The torch path where the kernel does not apply: OV samples asked for, autograd."""
    model, _, _, views = _window(need_ov=True)
    pts = _points(20, seed=4)
    idx = torch.zeros(pts.shape[0], 2, dtype=torch.long)
    slots = torch.ones(idx.shape, dtype=torch.bool)
    with torch.no_grad():
        full = model.sample_views_indexed(views, idx, slots, pts, False)  # OV sampled: torch
        lean = model.sample_views_indexed(views, idx, slots, pts, False, sample_ov=False)  # compiled
    assert full.ov.shape[-1] > 0
    m = full.mask
    torch.testing.assert_close(lean.features[m], full.features[m], atol=1e-5, rtol=1e-6)
    graded = model.sample_views_indexed(views, idx, slots, pts, False, sample_ov=False)  # autograd on: torch
    assert torch.equal(graded.features, full.features)


def test_kernel_edge_cases() -> None:
    """No pairs, every slot padding, a point on the camera centre: finite outputs, nothing seen."""
    eye = np.eye(4, dtype=np.float32)[None]
    K = np.array([[10.0, 10.0, 2.0, 2.0]], np.float32)
    table = (np.ones((16, 3), np.float32), (4, 4))
    feats = (np.ones((16, 2), np.float32), (4, 4))
    pairs = sample_kernel.pair_args(eye, K, np.zeros((1, 3), np.float32), (4, 4), 1e-6, table, feats, None,
                                    0.1)
    out = sample_kernel.sample_pairs(np.zeros((0, 3), np.float32), np.zeros((2, 0), np.int64),
                                     np.zeros((2, 0), np.bool_), pairs, threads=1)
    assert out[0].shape == (5, 0) and out[1].shape == (0,)
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], np.float32)
    idx = np.zeros((1, 3), np.int64)
    every = np.ones((1, 3), np.bool_)
    samples, mask, dirs, dist, uv = sample_kernel.sample_pairs(pts, idx, every, pairs, threads=2)
    assert mask.tolist() == [False, True, False]  # on the camera, in front, behind
    assert np.isfinite(samples).all() and np.isfinite(dirs).all() and np.isfinite(uv).all()
    assert dist.tolist() == [0.0, 1.0, 1.0] and samples[:, 1].tolist() == [1.0] * 5
    _, padded, *_ = sample_kernel.sample_pairs(pts, idx, np.zeros((1, 3), np.bool_), pairs, threads=1)
    assert not padded.any()


def test_compiled_sampling_refuses_bad_indices_and_shapes() -> None:
    """An index past the views or mismatched shapes raise ValueError (the kernel never reads out of
    bounds), as the torch path raises for them."""
    model, _, _, views = _window()
    pts = _points(10, seed=6)
    slots = torch.ones(pts.shape[0], 2, dtype=torch.bool)
    with torch.no_grad():
        for bad in (len(views), -1):
            idx = torch.zeros(pts.shape[0], 2, dtype=torch.long)
            idx[3, 1] = bad
            with pytest.raises(ValueError, match="view_idx must index"):
                model.sample_views_indexed(views, idx, slots, pts, False, sample_ov=False)
        idx = torch.zeros(pts.shape[0], 2, dtype=torch.long)
        with pytest.raises(ValueError, match="do not fit"):
            model.sample_views_indexed(views, idx, slots[:, :1], pts, False, sample_ov=False)


def test_node_warms_the_point_kernels(tmp_path: Path) -> None:
    """A node serving a CPU model warms the point answers' kernels at start (node.ctx.kernel_modules),
    each a module with a ``warm_up``."""
    import importlib

    from mapper.node.backends.learned import install_learned_backend
    from mapper.node.config import config_from_dict
    from mapper.node.service import MapperNode
    from tests.mapper.runtime.test_model_runtime import make_runtime

    cfg = config_from_dict({"map_dir": str(tmp_path), "autosave_name": "", "save_on_exit": False})
    node = MapperNode(cfg)
    try:
        # the evicted views' kernel too (queries.evicted_views, on by default)
        assert node.ctx.kernel_modules == ["mapper.map.query_kernels", "mapper.map.evicted_views"]
        install_learned_backend(node, make_runtime(GovNeSF(TINY).eval(), source_views=3))
        assert node.ctx.kernel_modules[2:] == [
            "mapper.model.ops.sample_kernel",
            "mapper.model.ops.fusion_kernel",
            "mapper.model.ops.answer_kernel",
        ]
        for module in node.ctx.kernel_modules:
            assert callable(importlib.import_module(module).warm_up)
    finally:
        node.stop()
