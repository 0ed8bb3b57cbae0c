"""mapper.model.checkpoint: safetensors + JSON round trips, no pickle, integrity checks."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
import torch

from mapper.model.checkpoint import (
    checkpoint_paths,
    config_from_dict,
    config_to_dict,
    load_metadata,
    load_model,
    load_training_state,
    save_checkpoint,
)
from mapper.model.config import PRESETS, get_preset
from mapper.model.field import GovNeSF


def _tiny_model(mode: str = "blend") -> GovNeSF:
    torch.manual_seed(0)
    return GovNeSF(get_preset("cpu-small", ov_dim=8, num_source_views=3), mode=mode)  # type: ignore[arg-type]


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_config_round_trip(name: str) -> None:
    cfg = PRESETS[name]
    assert config_from_dict(json.loads(json.dumps(config_to_dict(cfg)))) == cfg
    with pytest.raises(ValueError, match="unknown fields"):
        config_from_dict({**config_to_dict(cfg), "bogus": 1})


@pytest.mark.parametrize("mode", ["blend", "distill"])
def test_weights_round_trip_is_exact(tmp_path: Path, mode: str) -> None:
    model = _tiny_model(mode)
    json_path = save_checkpoint(tmp_path / "ck", model, metadata={"step": 7, "metrics": {"miou_2d": 0.5}})
    for name in ("ck", "ck.json", "ck.safetensors"):
        loaded, meta = load_model(tmp_path / name)
        assert not loaded.training and loaded.mode == mode and loaded.cfg == model.cfg
        for (k, a), (k2, b) in zip(model.state_dict().items(), loaded.state_dict().items(), strict=True):
            assert k == k2 and torch.equal(a, b), k
    assert meta["step"] == 7 and meta["metrics"]["miou_2d"] == 0.5 and json_path.name == "ck.json"


def test_half_weights_are_float16_on_disk_and_float32_loaded(tmp_path: Path) -> None:
    model = _tiny_model()
    save_checkpoint(tmp_path / "h", model, half=True)
    raw = (tmp_path / "h.safetensors").read_bytes()
    header = json.loads(raw[8 : 8 + struct.unpack("<Q", raw[:8])[0]])
    dtypes = {v["dtype"] for k, v in header.items() if k != "__metadata__"}
    assert dtypes == {"F16"}  # plain safetensors header, no pickle anywhere
    loaded, meta = load_model(tmp_path / "h")
    assert meta["weights_dtype"] == "float16"
    for a, b in zip(model.state_dict().values(), loaded.state_dict().values(), strict=True):
        assert b.dtype == torch.float32
        torch.testing.assert_close(a, b, atol=1e-3, rtol=1e-3)


def test_training_state_resumes_optimizer(tmp_path: Path) -> None:
    model = _tiny_model()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-4)
    for _ in range(2):
        opt.zero_grad()
        sum((p.float() ** 2).sum() for p in model.parameters()).backward()
        opt.step()
    rng = torch.get_rng_state()
    save_checkpoint(
        tmp_path / "t", model, metadata={"step": 2}, optimizer=opt, extra_tensors={"rng.torch": rng}
    )
    model2 = GovNeSF(model.cfg)
    opt2 = torch.optim.AdamW(model2.parameters(), lr=5.0)
    meta, extra = load_training_state(tmp_path / "t.json", model2, opt2)
    assert meta["step"] == 2 and torch.equal(extra["rng.torch"], rng)
    s1, s2 = opt.state_dict(), opt2.state_dict()
    assert s2["param_groups"][0]["lr"] == 1e-3
    for idx in s1["state"]:
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(s1["state"][idx][key], s2["state"][idx][key])
    # weights-only checkpoints cannot resume an optimiser; a different model is refused
    save_checkpoint(tmp_path / "w", model)
    with pytest.raises(ValueError, match="no training state"):
        load_training_state(tmp_path / "w", GovNeSF(model.cfg), opt2)
    with pytest.raises(ValueError, match="cannot resume"):
        load_training_state(tmp_path / "t", GovNeSF(model.cfg, mode="distill"))


def test_corrupt_or_foreign_files_are_refused(tmp_path: Path) -> None:
    model = _tiny_model()
    save_checkpoint(tmp_path / "c", model)
    weights, json_path, _ = checkpoint_paths(tmp_path / "c")
    data = bytearray(weights.read_bytes())
    data[-1] ^= 0xFF
    weights.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="SHA-256"):
        load_model(tmp_path / "c")
    json_path.write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(ValueError, match="format"):
        load_metadata(json_path)
    with pytest.raises(FileNotFoundError):
        load_model(tmp_path / "absent")
    with pytest.raises(ValueError, match="reserved"):
        save_checkpoint(tmp_path / "r", model, metadata={"config": {}})
