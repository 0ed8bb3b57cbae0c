"""The model and a training step on a CUDA device agree with the CPU (float32, the same weights).

Skipped without a CUDA device (CI has none); scripts/gpu/train_gpu.sh runs it on the GPU machine
before it trains.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch
from test_data import tiny_model_config, write_text_embeddings, write_tiny_scene
from test_train import _cfg as train_cfg

from mapper.model.field import GovNeSF
from mapper.training.data import RaySampler, load_scene
from mapper.training.train import TrainConfig, _loss_for_sample, train

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (none here)")


def _cfg(root: Path, out: Path, **kw: object) -> TrainConfig:
    """test_train's tiny run with every supervision term on."""
    losses: dict[str, object] = dict(max_steps=3, rays_per_view=32, point_ov_weight=1.0,
                                     visibility_weight=0.2, depth_weight=0.1, surface_weight=0.1)
    return train_cfg(root, out, **{**losses, **kw})


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    r = tmp_path_factory.mktemp("cuda")
    write_tiny_scene(r / "train" / "tiny_s0", n_frames=6, seed=0)
    write_tiny_scene(r / "val" / "tiny_s9", n_frames=5, seed=9)
    write_text_embeddings(r / "val")
    return r


@pytest.fixture
def no_tf32():
    """Full float32 matrix products and convolutions on the GPU while a test runs (cuDNN uses TF32,
    10 mantissa bits, by default: the first GPU run here saw the stem's weight gradient 11% (norm)
    away from the CPU's with the loss equal to 1e-3)."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def test_loss_and_gradients_match_the_cpu(root: Path, no_tf32: None) -> None:
    cfg = _cfg(root, root / "unused")
    sampler = RaySampler([load_scene(root / "train" / "tiny_s0")], tiny_model_config(), rays_per_view=32)
    torch.manual_seed(0)
    cpu = GovNeSF(tiny_model_config())
    gpu = GovNeSF(tiny_model_config()).cuda()
    gpu.load_state_dict(cpu.state_dict())
    results = []
    for model, device in ((cpu, torch.device("cpu")), (gpu, torch.device("cuda"))):
        model.train()
        total, terms = _loss_for_sample(model, sampler, cfg, 0, 0, device)
        total.backward()
        grads = {k: p.grad.detach().cpu() for k, p in model.named_parameters() if p.grad is not None}
        results.append((float(total.detach()), terms, grads))
    (a, ta, ga), (b, tb, gb) = results
    assert a == pytest.approx(b, rel=1e-3, abs=1e-5), (ta, tb)
    assert ga.keys() == gb.keys() and len(ga) > 0
    for k in ga:  # each gradient as a whole (sums of many products in another order)
        err = float((gb[k] - ga[k]).norm() / ga[k].norm().clamp_min(1e-8))
        assert err < 2e-2, f"{k}: relative gradient difference {err:.3g}"


def test_a_short_run_on_the_gpu_trains_and_exports(root: Path, tmp_path: Path) -> None:
    cfg = _cfg(root, tmp_path / "run", export=str(tmp_path / "export"))
    result = train(replace(cfg), model_cfg=tiny_model_config(), progress=False, wall_budget_s=1e6)
    assert result["step"] == 3 and next(result["model"].parameters()).is_cuda
    assert torch.isfinite(torch.tensor(result["validation"]["psnr"]))
    assert (tmp_path / "export.safetensors").is_file()
