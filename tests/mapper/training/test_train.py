"""mapper.training.train: data-parallel equivalence, exact resume, loss goes down, schedule, config errors.

All runs use a tiny network on the synthetic wall scene of test_data.py (64 x 48 images).
"""

from __future__ import annotations

import os
import socket
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp
from test_data import tiny_model_config, write_text_embeddings, write_tiny_scene

from mapper.model.checkpoint import load_model
from mapper.model.field import GovNeSF
from mapper.training.data import RaySampler, Scene, load_scene
from mapper.training.train import (
    TrainConfig,
    budget_probe_steps,
    learning_rate,
    load_train_config,
    steps_for_budget,
    train,
    train_step,
)


@pytest.fixture(scope="module")
def data_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("traindata")
    write_tiny_scene(root / "train" / "tiny_s0", n_frames=6, seed=0)
    write_tiny_scene(root / "train" / "tiny_s1", n_frames=5, seed=1)
    write_tiny_scene(root / "val" / "tiny_s9", n_frames=5, seed=9)
    write_text_embeddings(root / "val")
    return root


def _cfg(root: Path, out: Path, **kw: object) -> TrainConfig:
    base: dict[str, object] = dict(
        preset="tiny",
        train_dir=str(root / "train"),
        val_dir=str(root / "val"),
        out_dir=str(out),
        max_steps=4,
        batch_views=2,
        rays_per_view=24,
        warmup_steps=1,
        lr=3e-3,
        threads=1,
        checkpoint_every=2,
        val_every=1000,
        val_views_per_scene=1,
        val_stride_px=8,
        log_every=1,
    )
    base.update(kw)
    return TrainConfig(**base)  # type: ignore[arg-type]


def _params(path: Path) -> dict[str, torch.Tensor]:
    model, _ = load_model(path)
    return {k: v.clone() for k, v in model.state_dict().items()}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rank_main(rank: int, world: int, port: int, cfg: TrainConfig) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        WORLD_SIZE=str(world),
        LOCAL_RANK=str(rank),
    )
    train(cfg, model_cfg=tiny_model_config(), progress=False)


class _StepClock:
    """A clock that advances ``per_step`` seconds per training step (and never otherwise)."""

    def __init__(self, per_step: float) -> None:
        self.now, self.per_step = 0.0, per_step

    def perf_counter(self) -> float:
        return self.now

    def __getattr__(self, name: str) -> object:  # strftime, gmtime, ... from the real module
        import time

        return getattr(time, name)


def test_wall_budget_fits_the_steps_the_probe_measured(
    data_root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mapper.training.train as train_mod

    clock = _StepClock(per_step=1.0)
    real_step = train_mod.train_step

    def timed_step(*args: object, **kw: object) -> dict[str, float]:
        clock.now += clock.per_step
        return real_step(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(train_mod, "time", clock)
    monkeypatch.setattr(train_mod, "train_step", timed_step)
    cfg = _cfg(data_root, tmp_path / "fit", max_steps=50, warmup_steps=3, val_dir="")
    # probe: 3 steps of 1 s; 95% of 10 s = 9.5 s, 3 spent: 6 more steps
    result = train(cfg, model_cfg=tiny_model_config(), progress=False, wall_budget_s=10.0)
    assert result["step"] == result["max_steps"] == 9
    # resumed from its checkpoint, the run keeps the 9 steps its budget chose (not the TOML's 50)
    again = train(cfg, model_cfg=tiny_model_config(), progress=False, resume=tmp_path / "fit" / "last.json")
    assert again["step"] == again["max_steps"] == 9
    # steps that get slower than the probe said: past 1.1 x the budget the run stops and exports
    clock.now, clock.per_step = 0.0, 1.0
    slow = _cfg(data_root, tmp_path / "slow", max_steps=50, warmup_steps=3, val_dir="",
                export=str(tmp_path / "slow_export"))
    calls = {"n": 0}

    def slower_step(*args: object, **kw: object) -> dict[str, float]:
        calls["n"] += 1
        clock.now += 1.0 if calls["n"] <= 3 else 5.0  # 1 s in the probe, then 5 s a step
        return real_step(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(train_mod, "train_step", slower_step)
    over = train(slow, model_cfg=tiny_model_config(), progress=False, wall_budget_s=10.0)
    # 9 steps planned; step 4 ends at 8 s, step 5 at 13 s > 1.1 x 10 s: it stops there, exports
    assert over["step"] == over["max_steps"] == 5
    assert (tmp_path / "slow_export.safetensors").is_file()
    assert '"overrun_at_s": 13.0' in (tmp_path / "slow" / "log.jsonl").read_text()


def _rank_main_budget(rank: int, world: int, port: int, cfg: TrainConfig) -> None:
    import torch.distributed as dist

    from mapper.training.train import _agreed, _Dist

    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    dist.init_process_group("gloo", rank=rank, world_size=world)  # one group: train() uses it, leaves it
    try:
        result = train(cfg, model_cfg=tiny_model_config(), progress=False, wall_budget_s=1e6)
        assert result["step"] == result["max_steps"] == cfg.max_steps
        # the choice is rank 0's on every rank, whatever each rank measured
        assert _agreed(100 + rank, _Dist(rank, world, torch.device("cpu"), False)) == 100
        dist.barrier()  # both ranks are done with the group before either tears it down
    finally:
        dist.destroy_process_group()


def test_wall_budget_with_two_processes(data_root: Path, tmp_path: Path) -> None:
    """Both ranks end the budget run together (neither waits on the other's choice) and rank 0
    alone writes the budget record."""
    cfg = _cfg(data_root, tmp_path / "multi", max_steps=3, warmup_steps=2, val_dir="")
    mp.start_processes(_rank_main_budget, args=(2, _free_port(), cfg), nprocs=2, join=True,
                       start_method="spawn")
    log = (tmp_path / "multi" / "log.jsonl").read_text()
    assert log.count('"event": "budget"') == 1 and '"max_steps": 3' in log


def test_two_process_gloo_matches_one_process(data_root: Path, tmp_path: Path) -> None:
    single = _cfg(data_root, tmp_path / "single", max_steps=3)
    result = train(single, model_cfg=tiny_model_config(), progress=False)
    assert result["step"] == 3 and np.isfinite(result["validation"]["miou_2d"])
    multi = _cfg(data_root, tmp_path / "multi", max_steps=3)
    mp.start_processes(_rank_main, args=(2, _free_port(), multi), nprocs=2, join=True, start_method="spawn")
    a, b = _params(tmp_path / "single" / "last"), _params(tmp_path / "multi" / "last")
    moved = 0
    torch.manual_seed(0)  # train() seeds with cfg.seed = 0 before building the model
    init = GovNeSF(tiny_model_config())
    for k in a:
        torch.testing.assert_close(a[k], b[k], atol=2e-5, rtol=1e-4, msg=lambda m, k=k: f"{k}: {m}")
        moved += int(not torch.equal(a[k], init.state_dict()[k]))
    assert moved > len(a) // 2  # the runs actually trained
    assert (tmp_path / "multi" / "log.jsonl").read_text().count('"world_size": 2') == 1


def test_resume_equals_uninterrupted(data_root: Path, tmp_path: Path) -> None:
    train(_cfg(data_root, tmp_path / "full"), model_cfg=tiny_model_config(), progress=False)
    part = _cfg(data_root, tmp_path / "part")
    first = train(part, model_cfg=tiny_model_config(), progress=False, until_step=2)
    assert first["step"] == 2
    second = train(
        part, model_cfg=tiny_model_config(), progress=False, resume=tmp_path / "part" / "last.json"
    )
    assert second["step"] == 4
    a, b = _params(tmp_path / "full" / "last"), _params(tmp_path / "part" / "last")
    for k in a:
        torch.testing.assert_close(a[k], b[k], atol=1e-6, rtol=1e-6, msg=lambda m, k=k: f"{k}: {m}")


def test_few_steps_lower_the_loss_on_a_fixed_batch(data_root: Path) -> None:
    torch.set_num_threads(1)
    cfg = _cfg(
        data_root,
        data_root / "unused",
        max_steps=1000,
        warmup_steps=0,
        lr=1e-2,
        rays_per_view=64,
        batch_views=1,
    )
    sampler = RaySampler([load_scene(data_root / "train" / "tiny_s0")], tiny_model_config(), rays_per_view=64)
    torch.manual_seed(0)
    model = GovNeSF(tiny_model_config())
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    losses = [train_step(model, opt, sampler, cfg, 0, 0, 1, torch.device("cpu"))["loss"] for _ in range(25)]
    assert np.mean(losses[-3:]) < 0.8 * np.mean(losses[:3]), losses


def test_steps_for_budget() -> None:
    # 10 s spent on 5 steps of 2 s: 95 s of a 100 s budget leave 85 s, 42 more steps
    assert steps_for_budget(100.0, 10.0, 5, 2.0, 10_000) == 47
    assert steps_for_budget(100.0, 10.0, 5, 2.0, 20) == 20  # never past the config's max_steps
    assert steps_for_budget(5.0, 10.0, 5, 2.0, 10_000) == 5  # over budget already: stop where it is
    with pytest.raises(ValueError, match="per_step_s"):
        steps_for_budget(100.0, 1.0, 2, 0.0, 10)
    assert budget_probe_steps(TrainConfig(warmup_steps=500)) == 20
    assert budget_probe_steps(TrainConfig(warmup_steps=5)) == 5
    assert budget_probe_steps(TrainConfig(warmup_steps=0)) == 2


def test_wall_budget_fixes_max_steps_after_the_probe(data_root: Path, tmp_path: Path) -> None:
    cfg = _cfg(data_root, tmp_path / "budget", max_steps=6, warmup_steps=3, val_dir="",
               export=str(tmp_path / "export"))
    # a budget far beyond the run: max_steps stays the config's, the probe is logged
    result = train(cfg, model_cfg=tiny_model_config(), progress=False, wall_budget_s=1e6)
    assert result["step"] == result["max_steps"] == 6
    log = (tmp_path / "budget" / "log.jsonl").read_text()
    assert '"event": "budget"' in log and '"probe_steps": 3' in log
    # no validation scenes: the complete run still writes its export, with the budget recorded
    model, meta = load_model(tmp_path / "export")
    assert meta["step"] == 6 and meta["wall_budget"]["max_steps"] == 6
    assert meta["train_config"]["max_steps"] == 6
    # a budget spent before the probe ends: the run stops there, and its schedule ends there
    short = train(replace(cfg, out_dir=str(tmp_path / "short")), model_cfg=tiny_model_config(),
                  progress=False, wall_budget_s=1e-9)
    assert short["step"] == short["max_steps"] == 1
    with pytest.raises(ValueError, match="wall_budget_s"):
        train(cfg, model_cfg=tiny_model_config(), progress=False, wall_budget_s=-1.0)
    with pytest.raises(ValueError, match="resume or until_step"):
        train(cfg, model_cfg=tiny_model_config(), progress=False, wall_budget_s=10.0, until_step=2)


def test_learning_rate_schedule() -> None:
    cfg = TrainConfig(max_steps=110, warmup_steps=10, lr=1e-3, min_lr_ratio=0.1)
    assert learning_rate(cfg, 0) == pytest.approx(1e-4)
    assert learning_rate(cfg, 9) == pytest.approx(1e-3)
    assert learning_rate(cfg, 60) == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5))
    assert learning_rate(cfg, 110) == pytest.approx(1e-4)
    lrs = [learning_rate(cfg, s) for s in range(10, 111)]
    assert all(a >= b for a, b in zip(lrs, lrs[1:], strict=False))


def test_config_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="batch_views"):
        TrainConfig(batch_views=0)
    with pytest.raises(ValueError, match="mode"):
        TrainConfig(mode="average")
    bad = tmp_path / "bad.toml"
    bad.write_text('[train]\npreset = "cpu-small"\nlearning_rate = 0.1\n')
    with pytest.raises(ValueError, match="unknown"):
        load_train_config(bad)
    good = tmp_path / "good.toml"
    good.write_text("[train]\nmax_steps = 7\n")
    assert load_train_config(good, max_steps=None).max_steps == 7
    assert load_train_config(good, max_steps=9).max_steps == 9
    with pytest.raises(FileNotFoundError):
        load_train_config(tmp_path / "missing.toml")
    with pytest.raises(ValueError, match="distill_layers"):
        TrainConfig(distill_layers=-1)


def test_distill_head_sizes_reach_the_model_config() -> None:
    from mapper.model.config import get_preset
    from mapper.training.train import _with_fusion_options

    preset = get_preset("cpu-small", ov_dim=384)
    assert _with_fusion_options(preset, TrainConfig()) is preset
    head = TrainConfig(mode="distill", distill_hidden_dim=256, distill_layers=2)
    sized = _with_fusion_options(preset, head)
    assert (sized.fusion.distill_hidden_dim, sized.fusion.distill_layers) == (256, 2)
    assert sized.fusion.ov_dim == 384 and sized.encoder == preset.encoder
    ranged = _with_fusion_options(preset, TrainConfig(range_encoding=True))
    assert ranged.fusion.range_encoding and not preset.fusion.range_encoding


def test_launch_configs_load() -> None:
    root = Path(__file__).resolve().parents[3] / "launch"
    names = ("train_cpu_small.toml", "train_cpu_small_geo.toml", "train_cpu_small_paper_loss.toml",
             "train_cpu_small_distill.toml", "train_cpu_small_real.toml",
             "train_cpu_small_finetune_real.toml", "train_cpu_small_finetune_los.toml", "train_paper.toml")
    for name in names:
        if (root / name).is_file():
            cfg = load_train_config(root / name)
            assert cfg.batch_views >= 1
    real = load_train_config(root / "train_cpu_small_real.toml")  # run G: the real mix, held-out poses
    assert real.extra_train_weight > 0 and real.extra_holdout_every == 10 and real.depth_weight > 0
    # cpu-small's three stages: each starts from the previous one's export, the last writes the
    # shipped checkpoint
    stage1 = load_train_config(root / "train_cpu_small.toml")
    stage2 = load_train_config(root / "train_cpu_small_finetune_real.toml")
    stage3 = load_train_config(root / "train_cpu_small_finetune_los.toml")
    assert stage2.init_weights == stage1.export and stage3.init_weights == stage2.export
    assert stage3.export == "checkpoints/cpu-small" and stage3.surface_weight > 0
    assert len({stage1.out_dir, stage2.out_dir, stage3.out_dir}) == 3
    # the GPU runs (scripts/gpu/train_gpu.sh): G1 is stage 1's recipe at a GPU's budget, G2 adds the
    # geometry losses, G3 is G2 on the gpu-medium network; each writes its own folder
    g1, g2, g3 = (load_train_config(root / f"train_{n}.toml")
                  for n in ("gpu_small", "gpu_small_geo", "gpu_medium"))
    assert (g1.point_ov_weight, g1.visibility_weight) == (stage1.point_ov_weight, stage1.visibility_weight)
    assert g1.depth_weight == g1.surface_weight == 0 and g2.depth_weight > 0 and g2.surface_weight > 0
    assert g1.preset == g2.preset == "cpu-small" and g3.preset == "gpu-medium"
    assert (g3.depth_weight, g3.surface_weight) == (g2.depth_weight, g2.surface_weight)
    assert len({g1.out_dir, g2.out_dir, g3.out_dir}) == 3
    assert all(c.train_dir == "data_gpu/train" for c in (g1, g2, g3))


def test_geometry_and_visibility_supervision_terms(data_root: Path) -> None:
    """With the levers on, train_step reports every term, and a few steps on a fixed batch lower
    the depth and line-of-sight losses; with them off, the report is the paper's terms only."""
    torch.set_num_threads(1)
    scene = load_scene(data_root / "train" / "tiny_s0")
    sampler = RaySampler([scene], tiny_model_config(), rays_per_view=64)
    sample = sampler.sample(0, 0)
    assert sample.target_t is not None and sample.target_t.shape == (64,)
    assert bool((sample.target_t > 0).any())
    common = dict(max_steps=1000, warmup_steps=0, lr=1e-2, rays_per_view=64, batch_views=1)
    cfg = _cfg(
        data_root,
        data_root / "unused",
        depth_weight=1.0,
        surface_weight=1.0,
        point_ov_weight=1.0,
        visibility_weight=0.5,
        **common,  # type: ignore[arg-type]
    )
    torch.manual_seed(0)
    model = GovNeSF(tiny_model_config())
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    runs = [train_step(model, opt, sampler, cfg, 0, 0, 1, torch.device("cpu")) for _ in range(20)]
    for key in ("loss", "color", "ov", "depth", "surface", "point_ov", "visibility"):
        assert all(np.isfinite(r[key]) for r in runs), key
    for key in ("depth", "surface"):
        first, last = np.mean([r[key] for r in runs[:3]]), np.mean([r[key] for r in runs[-3:]])
        assert last < first, (key, [r[key] for r in runs])
    paper = _cfg(data_root, data_root / "unused", **common)  # type: ignore[arg-type]
    plain = train_step(GovNeSF(tiny_model_config()), opt, sampler, paper, 0, 0, 1, torch.device("cpu"))
    assert not {"depth", "surface", "point_ov", "visibility"} & set(plain)


def test_photometric_augmentation_is_deterministic_and_off_by_default(data_root: Path) -> None:
    scene = load_scene(data_root / "train" / "tiny_s0")
    plain = RaySampler([scene], tiny_model_config(), rays_per_view=16, seed=3)
    jitter = RaySampler([scene], tiny_model_config(), rays_per_view=16, seed=3, photometric_prob=1.0)
    a, b, c = plain.sample(2, 1), jitter.sample(2, 1), jitter.sample(2, 1)
    assert torch.equal(a.origins, b.origins) and torch.equal(a.target_ov, b.target_ov)  # same rays
    assert not torch.equal(a.target_rgb, b.target_rgb)
    assert torch.equal(b.target_rgb, c.target_rgb) and torch.equal(b.sources.rgb, c.sources.rgb)
    assert float(b.sources.rgb.min()) >= 0.0 and float(b.sources.rgb.max()) <= 1.0
    with pytest.raises(ValueError, match="photometric_prob"):
        RaySampler([scene], tiny_model_config(), rays_per_view=16, photometric_prob=1.5)
    with pytest.raises(ValueError, match="surface_band_m"):
        TrainConfig(surface_band_m=0.0)


def test_init_weights_fine_tunes_from_a_checkpoint(data_root: Path, tmp_path: Path) -> None:
    train(_cfg(data_root, tmp_path / "base", max_steps=2), model_cfg=tiny_model_config(), progress=False)
    base = _params(tmp_path / "base" / "last")
    tuned_cfg = _cfg(
        data_root, tmp_path / "tuned", max_steps=1, lr=1e-12, init_weights=str(tmp_path / "base" / "last")
    )
    result = train(tuned_cfg, model_cfg=tiny_model_config(), progress=False)
    assert result["step"] == 1  # a fresh schedule: the base run's 2 steps do not count
    tuned = _params(tmp_path / "tuned" / "last")
    torch.manual_seed(0)
    init = GovNeSF(tiny_model_config()).state_dict()
    differs_from_init = 0
    for k in base:  # one step at lr 1e-12 leaves the loaded weights where they were
        torch.testing.assert_close(tuned[k], base[k], atol=1e-6, rtol=0, msg=lambda m, k=k: f"{k}: {m}")
        differs_from_init += int(not torch.equal(tuned[k], init[k]))
    assert differs_from_init > len(base) // 2


def test_init_weights_refuses_another_config_or_mode(data_root: Path, tmp_path: Path) -> None:
    train(_cfg(data_root, tmp_path / "base", max_steps=1), model_cfg=tiny_model_config(), progress=False)
    src = str(tmp_path / "base" / "last")
    other = replace(tiny_model_config(), num_source_views=tiny_model_config().num_source_views + 1)
    with pytest.raises(ValueError, match="num_source_views"):
        train(_cfg(data_root, tmp_path / "a", init_weights=src), model_cfg=other, progress=False)
    with pytest.raises(ValueError, match="mode 'blend'"):
        train(
            _cfg(data_root, tmp_path / "b", init_weights=src, mode="distill"),
            model_cfg=tiny_model_config(),
            progress=False,
        )
    with pytest.raises(FileNotFoundError, match="not found"):
        train(_cfg(data_root, tmp_path / "c", init_weights=str(tmp_path / "nowhere")),
              model_cfg=tiny_model_config(), progress=False)  # fmt: skip
    assert not any((tmp_path / d / "last.json").exists() for d in "abc")


def test_init_weights_adds_the_range_encoding(data_root: Path, tmp_path: Path) -> None:
    """A checkpoint without the range encoding fine-tunes into a run with it: everything loads, the
    new layer starts at zero, and the export records the new config."""
    train(_cfg(data_root, tmp_path / "base", max_steps=2), model_cfg=tiny_model_config(), progress=False)
    base = _params(tmp_path / "base" / "last")
    tuned_cfg = _cfg(data_root, tmp_path / "tuned", max_steps=1, lr=1e-12, range_encoding=True,
                     init_weights=str(tmp_path / "base" / "last"))  # fmt: skip
    train(tuned_cfg, model_cfg=tiny_model_config(), progress=False)
    model, _ = load_model(tmp_path / "tuned" / "last")
    assert model.cfg.fusion.range_encoding
    tuned = model.state_dict()
    added = sorted(set(tuned) - set(base))
    assert added == ["fusion.range_encoding.bias", "fusion.range_encoding.weight"]
    for k in base:
        torch.testing.assert_close(tuned[k], base[k], atol=1e-6, rtol=0, msg=lambda m, k=k: f"{k}: {m}")
    for k in added:
        assert float(tuned[k].abs().max()) < 1e-6
    # the other way round (a checkpoint WITH it into a run without) is refused
    with pytest.raises(ValueError, match="range_encoding"):
        train(_cfg(data_root, tmp_path / "back", max_steps=1, init_weights=str(tmp_path / "tuned" / "last")),
              model_cfg=tiny_model_config(), progress=False)  # fmt: skip


def test_depth_guided_masking_prob_draws_per_example() -> None:
    from mapper.training.train import uses_depth_guided_masking

    seeds = range(4000)
    half = TrainConfig(depth_guided_masking_prob=0.5)
    draws = [uses_depth_guided_masking(half, s) for s in seeds]
    assert 0.46 < float(np.mean(draws)) < 0.54
    assert draws == [uses_depth_guided_masking(half, s) for s in seeds]  # the same on a rerun
    assert not any(uses_depth_guided_masking(TrainConfig(), s) for s in seeds)
    always = TrainConfig(depth_guided_masking_prob=1.0)
    assert all(uses_depth_guided_masking(always, s) for s in seeds)
    assert all(uses_depth_guided_masking(TrainConfig(depth_guided_masking=True), s) for s in seeds)
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="depth_guided_masking_prob"):
            TrainConfig(depth_guided_masking_prob=bad)


def test_depth_guided_masking_prob_one_trains_as_always_on(data_root: Path, tmp_path: Path) -> None:
    """Probability 1 takes the same steps as ``depth_guided_masking = true``, and masking changes
    the steps (the tiny scenes' depth hides some views)."""
    runs = {"on": {"depth_guided_masking": True}, "p1": {"depth_guided_masking_prob": 1.0}, "off": {}}
    params = {}
    for name, kw in runs.items():
        train(_cfg(data_root, tmp_path / name, max_steps=2, point_ov_weight=1.0, **kw),
              model_cfg=tiny_model_config(), progress=False)  # fmt: skip
        params[name] = _params(tmp_path / name / "last")
    for k in params["on"]:
        assert torch.equal(params["on"][k], params["p1"][k]), k
    assert any(not torch.equal(params["on"][k], params["off"][k]) for k in params["on"])


def test_volume_sources_add_frames_to_the_volume_only(
    data_root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """volume_sources: the cost volume spans more frames than the blend; the example is otherwise the
    same (rays, targets, the blended sources first), and the training step blends only those."""
    torch.set_num_threads(1)
    scene = load_scene(data_root / "train" / "tiny_s0")  # 6 frames; the tiny preset blends 3
    plain = RaySampler([scene], tiny_model_config(), rays_per_view=16, seed=3)
    wide = RaySampler([scene], tiny_model_config(), rays_per_view=16, seed=3, volume_sources=5)
    counts = set()
    for step in range(12):
        a, b = plain.sample(step, 0), wide.sample(step, 0)
        n = len(a.sources.indices)
        assert torch.equal(a.origins, b.origins) and torch.equal(a.target_ov, b.target_ov)
        assert np.array_equal(b.sources.indices[:n], a.sources.indices) and a.blend_sources == 0
        assert target_excluded(b)
        extra = len(b.sources.indices) - n
        assert 0 <= extra <= 2 and b.blend_sources == (n if extra else 0)
        counts.add(extra)
    assert counts == {0, 1, 2}  # the volume's size is drawn per example
    with pytest.raises(ValueError, match="volume_sources"):
        RaySampler([scene], tiny_model_config(), rays_per_view=16, volume_sources=-1)
    # the step: the volume over every source, the rays and point losses over the blended ones
    import mapper.training.train as train_module

    seen: dict[str, list[int]] = {"volume": [], "render": [], "points": []}
    build, render, query = GovNeSF.build_volume, train_module.render_rays, GovNeSF.query_points

    def spy_build(self: GovNeSF, views, bounds):  # type: ignore[no-untyped-def]
        seen["volume"].append(len(views))
        return build(self, views, bounds)

    def spy_render(model, views, *args, **kw):  # type: ignore[no-untyped-def]
        seen["render"].append(len(views))
        return render(model, views, *args, **kw)

    def spy_query(self: GovNeSF, views, *args, **kw):  # type: ignore[no-untyped-def]
        seen["points"].append(len(views))
        return query(self, views, *args, **kw)

    monkeypatch.setattr(GovNeSF, "build_volume", spy_build)
    monkeypatch.setattr(train_module, "render_rays", spy_render)
    monkeypatch.setattr(GovNeSF, "query_points", spy_query)
    cfg = _cfg(data_root, data_root / "unused", batch_views=1, rays_per_view=16, point_ov_weight=1.0,
               visibility_weight=0.5, volume_sources=5)
    model = GovNeSF(tiny_model_config())
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr)
    step = next(s for s in range(12) if wide.sample(s, 0).blend_sources)
    out = train_step(model, opt, wide, cfg, step, 0, 1, torch.device("cpu"))
    assert all(np.isfinite(out[k]) for k in ("loss", "point_ov", "visibility"))
    n_all = len(wide.sample(step, 0).sources.indices)
    assert seen["volume"] == [n_all] and seen["render"] == [3] and seen["points"] == [3] and n_all > 3


def target_excluded(sample) -> bool:  # type: ignore[no-untyped-def]
    return sample.target not in set(sample.sources.indices.tolist())


def _down_scene(occluded_in_last: bool) -> Scene:
    """Three 8x6 frames 2 m above the floor z = 0 looking down, each frame's OV map one constant
    one-hot feature (frame k: e_k); the last frame's depth says 1 m (an occluder) if asked."""
    w, h, d = 8, 6, 4
    K = np.array([4.0, 4.0, 4.0, 3.0])
    poses = []
    for cx in (-0.1, 0.0, 0.1):
        pose = np.eye(4)
        pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
        pose[:3, 3] = [cx, 0.0, 2.0]
        poses.append(pose)
    ov = np.zeros((3, 3, 4, d), np.float16)
    for k in range(3):
        ov[k, ..., k] = 1.0
    depth = np.full((3, h, w), 2.0, np.float32)
    if occluded_in_last:
        depth[2] = 1.0
    return Scene(name="down", rgb=np.zeros((3, h, w, 3), np.uint8), depth_m=depth, ov=ov,
                 K=np.tile(K, (3, 1)), world_from_cam=np.stack(poses),
                 points_m=np.zeros((3, 1, 3), np.float32), class_names=["a", "b", "c", "d"])  # fmt: skip


@pytest.mark.parametrize("occluded", [False, True])
def test_visible_mean_features_average_the_frames_that_see_a_point(occluded: bool) -> None:
    from mapper.training.data import visible_mean_features

    scene = _down_scene(occluded)
    pts = torch.tensor([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]])  # on the floor under every camera; far outside
    mean, count = visible_mean_features(scene, pts)
    seen = 2 if occluded else 3
    assert count.tolist() == [seen, 0]
    expect = torch.zeros(4)
    expect[:seen] = 1.0 / np.sqrt(seen)
    assert torch.allclose(mean[0], expect, atol=1e-6)
    assert torch.equal(mean[1], torch.zeros(4))
    with pytest.raises(ValueError, match=r"\(P, 3\)"):
        visible_mean_features(scene, torch.zeros(3))


def test_point_ov_target_visible_mean_keeps_the_rays_and_trains(data_root: Path) -> None:
    torch.set_num_threads(1)
    scene = load_scene(data_root / "train" / "tiny_s0")
    frame = RaySampler([scene], tiny_model_config(), rays_per_view=32, seed=5)
    mean = RaySampler([scene], tiny_model_config(), rays_per_view=32, seed=5, point_ov_target="visible_mean")
    a, b = frame.sample(1, 0), mean.sample(1, 0)
    assert a.target_ov_point is None and b.target_ov_point is not None
    assert torch.equal(a.origins, b.origins) and torch.equal(a.target_ov, b.target_ov)  # the same example
    assert b.target_t is not None
    hit = b.target_t > 0
    assert bool(hit.any())
    norms = b.target_ov_point[hit].norm(dim=-1)
    assert torch.allclose(norms, torch.ones_like(norms), atol=1e-5)  # the target frame itself sees each point
    assert torch.equal(b.target_ov_point[~hit], b.target_ov[~hit])
    with pytest.raises(ValueError, match="point_ov_target"):
        RaySampler([scene], tiny_model_config(), rays_per_view=8, point_ov_target="labels")
    with pytest.raises(ValueError, match="point_ov_target"):
        TrainConfig(point_ov_target="labels")
    cfg = _cfg(data_root, data_root / "unused", point_ov_weight=1.0, point_ov_target="visible_mean",
               rays_per_view=32, batch_views=1)  # fmt: skip
    model = GovNeSF(tiny_model_config())
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr)
    out = train_step(model, opt, mean, cfg, 1, 0, 1, torch.device("cpu"))
    assert np.isfinite(out["point_ov"]) and out["point_ov"] > 0
