"""Point heads (mapper.model.point_head) and their distillation (mapper.training.point_head):
files, teacher checks, the runtime's use of a head, the distillation loss and training."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from mapper.map.window import KeyframeWindow
from mapper.model.checkpoint import load_metadata, save_checkpoint
from mapper.model.config import FusionConfig
from mapper.model.field import GovNeSF
from mapper.model.fusion import FusionNet
from mapper.model.point_head import head_paths, load_point_head, save_point_head
from mapper.node.config import WindowConfig
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig
from mapper.training.point_head import Captured, DistillConfig, distill_loss, main, student_config, train_head
from tests.mapper.runtime.test_model_runtime import TINY, FakeEncoder, keyframe, orbit
from tests.model_helpers import tiny_model_config

F_DIM, V_DIM = TINY.encoder.feature_dim, TINY.volume.volume_feature_dim


@pytest.fixture(scope="module")
def model() -> GovNeSF:
    torch.manual_seed(0)
    return GovNeSF(TINY).eval()


def small_head(seed: int = 1) -> tuple[FusionNet, FusionConfig]:
    torch.manual_seed(seed)
    cfg = dataclasses.replace(TINY.fusion, hidden_dim=4, attention_dim=2, num_heads=1)
    return FusionNet(F_DIM, V_DIM, cfg).eval(), cfg


def captured(teacher: FusionNet, P: int = 64, N: int = 5, seed: int = 0) -> Captured:
    """Random inputs (some slots masked, one point with none) and the teacher's OV weights."""
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(P, N, 3, generator=g)
    features = torch.randn(P, N, F_DIM, generator=g)
    v = torch.randn(P, V_DIM, generator=g)
    dirs = torch.nn.functional.normalize(torch.randn(P, N, 3, generator=g), dim=-1)
    rng = torch.rand(P, N, generator=g) * 4 + 0.1
    mask = torch.rand(P, N, generator=g) < 0.7
    mask[0] = False
    with torch.no_grad():
        w = teacher(rgb, features, v, dirs, mask, None, rng).ov_weights
    return Captured(rgb, features, v, dirs, rng, mask, w)


def test_save_and_load_round_trip_with_the_teacher_check(tmp_path: Path) -> None:
    head, cfg = small_head()
    out = save_point_head(tmp_path / "h", head, cfg, feature_dim=F_DIM, volume_feature_dim=V_DIM,
                          teacher_sha256="abc", extra={"note": "x"})
    assert out == head_paths(tmp_path / "h.safetensors")[1]
    loaded, meta = load_point_head(tmp_path / "h.json", teacher_sha256="abc")
    assert meta["note"] == "x" and meta["fusion"]["attention_dim"] == 2
    for (k, a), (k2, b) in zip(head.state_dict().items(), loaded.state_dict().items(), strict=True):
        assert k == k2 and torch.equal(a, b)
    with pytest.raises(ValueError, match="distilled from weights 'abc'"):
        load_point_head(tmp_path / "h", teacher_sha256="other")
    load_point_head(tmp_path / "h")  # no teacher given: not checked


def test_damaged_or_foreign_files_are_refused(tmp_path: Path) -> None:
    head, cfg = small_head()
    kw = dict(feature_dim=F_DIM, volume_feature_dim=V_DIM, teacher_sha256="t")
    save_point_head(tmp_path / "h", head, cfg, **kw)  # type: ignore[arg-type]
    weights, meta_path = head_paths(tmp_path / "h")
    data = bytearray(weights.read_bytes())
    data[-1] ^= 0xFF
    weights.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="SHA-256"):
        load_point_head(tmp_path / "h")
    meta_path.write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(ValueError, match="not a point head"):
        load_point_head(tmp_path / "h")
    with pytest.raises(FileNotFoundError):
        load_point_head(tmp_path / "missing")
    save_point_head(tmp_path / "g", head, cfg, **{**kw, "feature_dim": F_DIM + 1})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="does not fit"):
        load_point_head(tmp_path / "g")


def test_point_outputs_with_a_copy_of_the_model_fusionnet_are_the_model_answers(model: GovNeSF) -> None:
    twin = copy.deepcopy(model.fusion)
    data = captured(model.fusion, P=32, N=4)
    samples_args = dict(rgb=data.rgb, features=data.features, source_dirs=data.dirs, mask=data.mask,
                        source_range=data.source_range)
    from mapper.model.field import PointViewSamples

    ov = torch.randn(32, 4, TINY.fusion.ov_dim)
    samples = PointViewSamples(ov=ov, uv=None, **samples_args)  # type: ignore[arg-type]
    own = model.point_outputs(samples, data.v)
    with_twin = model.point_outputs(samples, data.v, fusion=twin)
    assert torch.equal(own.ov, with_twin.ov) and torch.equal(own.valid, with_twin.valid)
    head, _ = small_head()
    other = model.point_outputs(samples, data.v, fusion=head)
    assert torch.equal(other.valid, own.valid) and not torch.allclose(other.ov, own.ov)


def test_distill_loss_is_zero_for_the_teacher_and_training_lowers_it(model: GovNeSF) -> None:
    teacher = copy.deepcopy(model.fusion)
    with torch.no_grad():  # a teacher with peaked weights (a random one's are near uniform)
        teacher.mlp_s[2].weight.mul_(40.0)
    data = captured(teacher, P=256, N=5)
    with torch.no_grad():
        assert float(distill_loss(teacher, data)) == pytest.approx(0.0, abs=1e-6)
    f = model.cfg.fusion
    cfg = DistillConfig(hidden_dim=f.hidden_dim, attention_dim=f.attention_dim, num_heads=f.num_heads,
                        steps=150, batch_points=128, lr=1e-2)
    torch.manual_seed(0)
    student = FusionNet(F_DIM, V_DIM, student_config(model.cfg.fusion, cfg))
    with torch.no_grad():
        before = float(distill_loss(student, data))
    assert before > 0.05
    losses = train_head(student, data, cfg, progress=False)
    with torch.no_grad():
        assert len(losses) == 150 and float(distill_loss(student, data)) < 0.5 * before
    assert not student.training  # left in eval mode


def test_captured_cat_pads_masked_slots_and_take_selects_points(model: GovNeSF) -> None:
    a, b = captured(model.fusion, P=8, N=3, seed=1), captured(model.fusion, P=5, N=6, seed=2)
    both = Captured.cat([a, b])
    assert len(both) == 13 and both.mask.shape == (13, 6) and not both.mask[:8, 3:].any()
    assert torch.equal(both.teacher[:8, :3], a.teacher) and torch.equal(both.features[8:], b.features)
    # padding changes nothing: the loss of a padded part equals the part's own
    assert float(distill_loss(model.fusion, both.take(torch.arange(8)))) == pytest.approx(
        float(distill_loss(model.fusion, a)), abs=1e-6)


def test_distill_config_and_cli_refuse_bad_settings(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(ValueError, match="num_heads"):
        DistillConfig(attention_dim=6, num_heads=4)
    with pytest.raises(ValueError, match="capture_fractions"):
        DistillConfig(capture_fractions=(0.0,))
    with pytest.raises(ValueError, match="steps"):
        DistillConfig(steps=0)
    assert main(["--steps", "0"]) == 2
    assert main(["--train-dirs", str(tmp_path / "none"), "--val-dirs", str(tmp_path)]) == 2
    no_head = ["--validate-only", "--out", str(tmp_path / "no-head"), "--val-dirs"]
    assert main([*no_head, str(tmp_path / "none")]) == 2
    tmp_path.joinpath("scene").mkdir()
    tmp_path.joinpath("scene", "frames.govrec").write_bytes(b"")
    assert main([*no_head, str(tmp_path / "scene")]) == 2
    err = capsys.readouterr().err
    assert "error:" in err and "no point head" in err


def _window_runtime(model: GovNeSF, **overrides: object) -> tuple[ModelRuntime, KeyframeWindow]:
    cfg = ModelRuntimeConfig(device="cpu", chunk_rays=512, **overrides)  # type: ignore[arg-type]
    runtime = ModelRuntime(cfg, model=model, text_encoder=lambda space: FakeEncoder())
    window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i in range(5):
        window.consider(keyframe(i, orbit(i)))
    return runtime, window


def test_runtime_point_answers_use_the_head_and_point_samples_match_segment(model: GovNeSF) -> None:
    runtime, _ = _window_runtime(model, source_views=2, view_cell_m=0.25)
    pts = np.random.default_rng(0).uniform([-0.4, -0.4, 0.3], [0.4, 0.4, 0.7], (200, 3)).astype(np.float32)
    own_label, own_score, _ = runtime.segment(pts, ["a", "b", "c"])
    chunks = runtime.point_samples(pts)
    covered = torch.cat([sub for sub, _, _ in chunks])
    assert covered.numel() == torch.unique(covered).numel() == int((own_label >= 0).sum())
    for sub, s, v in chunks:
        assert s.mask.shape[0] == sub.numel() == v.shape[0] and v.shape[1] == V_DIM
    runtime.point_head = copy.deepcopy(model.fusion)  # the same network as a head: the same answers
    twin_label, twin_score, _ = runtime.segment(pts, ["a", "b", "c"])
    assert np.array_equal(twin_label, own_label) and np.allclose(twin_score, own_score, atol=1e-6)
    runtime.point_head, _ = small_head()
    _, head_score, _ = runtime.segment(pts, ["a", "b", "c"])
    assert not np.allclose(head_score, own_score, atol=1e-4)


def _checkpoint(tmp_path: Path) -> Path:
    torch.manual_seed(3)
    cfg = tiny_model_config(ov_dim=6)
    save_checkpoint(tmp_path / "ck", GovNeSF(cfg).eval())
    return tmp_path / "ck.json"


def test_runtime_loads_auto_explicit_and_refuses_a_foreign_head(tmp_path: Path) -> None:
    ck = _checkpoint(tmp_path)
    sha = load_metadata(ck)["weights_sha256"]
    head, cfg = small_head()
    kw = dict(feature_dim=F_DIM, volume_feature_dim=V_DIM)
    # auto without a head beside the checkpoint: the model's own network, served
    rt = ModelRuntime(ModelRuntimeConfig(checkpoint=str(ck), device="cpu"))
    assert rt.ready and rt.point_head is None
    save_point_head(tmp_path / "ck-point-head", head, cfg, teacher_sha256=sha, **kw)
    rt = ModelRuntime(ModelRuntimeConfig(checkpoint=str(ck), device="cpu"))
    assert rt.ready and rt.point_head is not None
    rt = ModelRuntime(ModelRuntimeConfig(checkpoint=str(ck), device="cpu", point_head=""))
    assert rt.ready and rt.point_head is None
    # auto beside a head of other weights: a warning, the model's own network
    save_point_head(tmp_path / "ck-point-head", head, cfg, teacher_sha256="other", **kw)
    rt = ModelRuntime(ModelRuntimeConfig(checkpoint=str(ck), device="cpu"))
    assert rt.ready and rt.point_head is None
    # named explicitly: refused, the model not served, the reason kept
    rt = ModelRuntime(ModelRuntimeConfig(checkpoint=str(ck), device="cpu",
                                         point_head=str(tmp_path / "ck-point-head")))
    assert not rt.ready and rt.load_error is not None and "distilled from weights 'other'" in rt.load_error
    rt = ModelRuntime(ModelRuntimeConfig(checkpoint=str(ck), device="cpu", point_head=str(tmp_path / "nope")))
    assert not rt.ready and rt.load_error is not None and "was not found" in rt.load_error


def test_the_shipped_head_belongs_to_the_shipped_checkpoint() -> None:
    root = Path(__file__).resolve().parents[3]
    meta = json.loads((root / "checkpoints" / "cpu-small-point-head.json").read_text())
    teacher = load_metadata(root / "checkpoints" / "cpu-small.json")
    assert meta["teacher_weights_sha256"] == teacher["weights_sha256"]
    rt = ModelRuntime(ModelRuntimeConfig(device="cpu"))
    assert rt.ready and rt.point_head is not None
    assert rt.point_head.attention.num_heads == meta["fusion"]["num_heads"]
