"""Distill a point head: a narrower FusionNet that gives a checkpoint's OV weights for point answers.

``govnesf distill-point-head`` (``main`` below). Three stages, all on the CPU:

1. **Capture.** Each training scene (``govnesf sim record`` folders, as ``govnesf train`` reads)
   is streamed into an in-process node serving the teacher checkpoint, with the node's default
   window. After ``capture_fractions`` of its frames, ``points_per_capture`` of the scene's true
   surface points (``gt/points.npz``), moved by a Gaussian of ``surface_jitter_m``, go through
   :meth:`ModelRuntime.point_samples` -- the inputs ``segment_points`` hands the network (view
   selection, up to ``model.point_source_views`` views a point, depth-guided masking on every
   other capture), sampled on the torch path (``GovNeSF.compiled_sampling`` off: bit for bit the
   captures the shipped head was made from; the compiled kernel's samples equal them up to float
   rounding) -- and the teacher's OV weights over those views are kept with them.
2. **Train.** The student (the teacher's FusionNet config with ``hidden_dim``, ``attention_dim``,
   ``num_heads`` replaced) learns the teacher's weights: the KL divergence from the teacher's
   softmax over a point's views to the student's, averaged over points, Adam with a cosine
   decay. Deterministic for a seed.
3. **Validate.** Each validation scene is streamed once; ``segment_points`` of its true points
   (its class names as texts) with the teacher and with the student: labels equal, and both 3D
   mIoU against the true labels. Reported in the head's JSON and on stdout.

Example (the committed head, ``checkpoints/cpu-small-point-head``; docs/how-to/train.md)::

    scripts/make_train_data.sh data 12 80
    .venv/bin/govnesf distill-point-head --out checkpoints/cpu-small-point-head

``--validate-only`` runs stage 3 alone for the head at ``--out`` on other scenes, e.g. the held-out
evaluation rooms of both styles (``scripts/make_eval_data.sh``)::

    .venv/bin/govnesf distill-point-head --validate-only --out checkpoints/cpu-small-point-head \
        --val-dirs data/eval
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from mapper.model.config import FusionConfig
from mapper.model.fusion import FusionNet
from mapper.model.point_head import head_paths, load_point_head, save_point_head

log = logging.getLogger(__name__)

__all__ = ["Captured", "DistillConfig", "capture_scene", "distill_loss", "main", "train_head"]


@dataclass(frozen=True)
class DistillConfig:
    """Settings of ``govnesf distill-point-head`` (every one a command-line option)."""

    checkpoint: str = "checkpoints/cpu-small"
    """The teacher checkpoint."""
    train_dirs: tuple[str, ...] = ("data/train",)
    """Scene folders, or roots of them (``scripts/make_train_data.sh``)."""
    val_dirs: tuple[str, ...] = ("data/val",)
    """Validation scenes (never captured for training)."""
    out: str = "out/point_head/cpu-small-point-head"
    """Where the head is written (``NAME`` -> ``NAME.safetensors`` + ``NAME.json``)."""
    hidden_dim: int = 8
    """The student's first MLP_a width (the cpu-small teacher: 32)."""
    attention_dim: int = 4
    """Its attention width (teacher: 16)."""
    num_heads: int = 1
    """Its attention heads (teacher: 4); must divide ``attention_dim``."""
    points_per_capture: int = 4000
    """True surface points drawn per capture (those no keyframe sees are left out)."""
    capture_fractions: tuple[float, ...] = (0.5, 1.0)
    """Captures after these fractions of a scene's frames (the window then holds different views)."""
    surface_jitter_m: float = 0.03
    """Standard deviation of the Gaussian moving each captured point off the surface (m)."""
    steps: int = 3000
    """Adam steps."""
    batch_points: int = 1024
    """Captured points a step."""
    lr: float = 3e-3
    """Peak learning rate (cosine decay to ``min_lr_ratio`` of it)."""
    min_lr_ratio: float = 0.05
    seed: int = 0
    """Seeds the point draws, the batches and the student's initial weights."""
    threads: int = 2
    """torch threads."""
    max_train_scenes: int = 0
    """0 = every scene found."""
    val_points: int = 20000
    """True points a validation scene is segmented on (a random subset)."""

    def __post_init__(self) -> None:
        names = ("hidden_dim", "attention_dim", "num_heads", "points_per_capture", "steps", "batch_points",
                 "threads", "val_points")
        positive = {k: getattr(self, k) for k in names}
        bad = {k: v for k, v in positive.items() if not (isinstance(v, int) and v >= 1)}
        if bad:
            raise ValueError(f"distill-point-head: these must be integers >= 1: {bad}")
        if self.attention_dim % self.num_heads:
            raise ValueError(f"num_heads {self.num_heads} must divide attention_dim {self.attention_dim}")
        if not self.capture_fractions or not all(0.0 < f <= 1.0 for f in self.capture_fractions):
            raise ValueError(f"capture_fractions {self.capture_fractions} must be in (0, 1]")
        if not (self.lr > 0 and 0 <= self.min_lr_ratio <= 1 and self.surface_jitter_m >= 0):
            raise ValueError("lr must be > 0, min_lr_ratio in [0, 1], surface_jitter_m >= 0")


@dataclass
class Captured:
    """What the point answers' network sees for P points over N view slots, and the teacher's
    answer; every tensor float32 (mask bool), contiguous."""

    rgb: Tensor  # (P, N, 3)
    features: Tensor  # (P, N, F)
    v: Tensor  # (P, Dv)
    dirs: Tensor  # (P, N, 3)
    source_range: Tensor  # (P, N)
    mask: Tensor  # (P, N) bool
    teacher: Tensor  # (P, N) the teacher's OV weights (0 where masked)

    def __len__(self) -> int:
        return int(self.rgb.shape[0])

    @staticmethod
    def cat(parts: Sequence[Captured]) -> Captured:
        """One batch of every part, slots padded (masked) to the widest part's N."""
        n = max(int(p.mask.shape[1]) for p in parts)

        def pad(t: Tensor) -> Tensor:
            extra = n - t.shape[1]
            if extra == 0:
                return t
            shape = (t.shape[0], extra, *t.shape[2:])
            return torch.cat([t, t.new_zeros(shape)], dim=1)

        fields = {}
        for f in dataclasses.fields(Captured):
            ts = [getattr(p, f.name) for p in parts]
            fields[f.name] = torch.cat(ts if f.name == "v" else [pad(t) for t in ts])
        return Captured(**fields)

    def take(self, idx: Tensor) -> Captured:
        return Captured(**{f.name: getattr(self, f.name)[idx] for f in dataclasses.fields(Captured)})


def _scene_dirs(roots: Sequence[str]) -> list[Path]:
    from mapper.training.data import find_scenes

    out: list[Path] = []
    for root in roots:
        out.extend(find_scenes(root))
    return out


def _stream(scene: Path, checkpoint: str) -> Iterator[tuple[float, Any, Any]]:
    """Stream ``scene``'s recording into an in-process node serving ``checkpoint`` (its own FusionNet
    for point answers: ``model.point_head = ""``); yields
    (fraction of the frames ingested, node, runtime) after every frame."""
    from mapper.node.backends.learned import install_learned_backend
    from mapper.node.config import config_from_dict
    from mapper.node.service import MapperNode
    from mapper.runtime.model_runtime import ModelRuntime
    from protocol.recording import read_recording

    frames = list(read_recording(scene / "frames.govrec"))
    with tempfile.TemporaryDirectory() as tmp:
        cfg = config_from_dict({"map_dir": tmp, "autosave_name": "", "save_on_exit": False,
                                "model": {"checkpoint": checkpoint, "point_head": ""}})
        node = MapperNode(cfg)
        runtime = ModelRuntime(cfg.model)
        if runtime.model is None:
            raise RuntimeError(runtime.load_error or f"no model from {checkpoint}")
        install_learned_backend(node, runtime)
        try:
            for i, frame in enumerate(frames):
                node.handle_ingest(frame)
                yield (i + 1) / len(frames), node, runtime
        finally:
            node.stop()


@torch.no_grad()
def capture_scene(scene: Path, cfg: DistillConfig, gen: np.random.Generator) -> list[Captured]:
    """Stage 1 for one scene (see the module docstring)."""
    truth = np.load(scene / "gt" / "points.npz")["xyz"].astype(np.float32)
    todo = sorted(cfg.capture_fractions)
    out: list[Captured] = []
    for frac, node, runtime in _stream(scene, cfg.checkpoint):
        if not todo or frac < todo[0]:
            continue
        todo.pop(0)
        node.ctx.drain_integrations()
        pick = gen.choice(truth.shape[0], size=min(cfg.points_per_capture, truth.shape[0]), replace=False)
        pts = truth[pick] + gen.normal(0.0, cfg.surface_jitter_m, size=(pick.size, 3)).astype(np.float32)
        use_depth = len(out) % 2 == 1
        teacher = runtime.model.fusion
        # the torch sampling path, so that a capture is bit for bit what it was when the shipped
        # head was made; the compiled path's samples equal it up to float rounding (and zeros in
        # masked slots, which the network never reads)
        runtime.model.compiled_sampling = False
        for _, s, v in runtime.point_samples(pts, use_depth=use_depth):
            fused = teacher(s.rgb, s.features, v, s.source_dirs, s.mask, None, s.source_range)
            rng = s.source_range if s.source_range is not None else torch.zeros_like(fused.ov_weights)
            out.append(Captured(
                rgb=s.rgb.contiguous(), features=s.features.contiguous(), v=v.contiguous(),
                dirs=s.source_dirs.contiguous(), source_range=rng.contiguous(),
                mask=s.mask.contiguous(), teacher=fused.ov_weights.contiguous(),
            ))
    return out


def student_config(teacher: FusionConfig, cfg: DistillConfig) -> FusionConfig:
    """The teacher's FusionNet config with the student's widths."""
    return dataclasses.replace(teacher, hidden_dim=cfg.hidden_dim, attention_dim=cfg.attention_dim,
                               num_heads=cfg.num_heads)


def distill_loss(student: FusionNet, batch: Captured) -> Tensor:
    """Mean over the points some view sees of KL(teacher || student) over their views."""
    fused = student.forward_reference(batch.rgb, batch.features, batch.v, batch.dirs, batch.mask, None,
                                      batch.source_range)
    logits = student.mlp_s(fused.x_att).squeeze(-1)  # (P, N)
    very_negative = torch.finfo(logits.dtype).min
    log_s = torch.log_softmax(logits.masked_fill(~batch.mask, very_negative), dim=-1)
    t = batch.teacher
    kl = torch.where(batch.mask & (t > 0), t * (torch.log(t.clamp_min(1e-12)) - log_s), torch.zeros_like(t))
    seen = batch.mask.any(dim=1)
    return kl.sum(dim=1)[seen].mean() if bool(seen.any()) else logits.sum() * 0.0


def train_head(student: FusionNet, data: Captured, cfg: DistillConfig, progress: bool = True) -> list[float]:
    """Stage 2: Adam on ``distill_loss``, cosine decay to ``min_lr_ratio``; returns the loss per
    step."""
    gen = torch.Generator().manual_seed(cfg.seed)
    opt = torch.optim.Adam(student.parameters(), lr=cfg.lr)
    losses: list[float] = []
    student.train()
    t0 = time.perf_counter()
    for step in range(cfg.steps):
        cosine = 0.5 * (1 + math.cos(math.pi * step / cfg.steps))
        lr = cfg.lr * (cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * cosine)
        for group in opt.param_groups:
            group["lr"] = lr
        idx = torch.randint(len(data), (cfg.batch_points,), generator=gen)
        loss = distill_loss(student, data.take(idx))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        if progress and (step % 200 == 0 or step == cfg.steps - 1):
            recent = losses[-200:]
            print(f"distill-point-head: step {step + 1}/{cfg.steps} KL {sum(recent) / len(recent):.4f} "
                  f"lr {lr:.2e} ({time.perf_counter() - t0:.0f} s)", flush=True)
    student.eval()
    return losses


@torch.no_grad()
def held_out_kl(student: FusionNet, data: Captured, chunk: int = 4096) -> float:
    """Mean KL(teacher || student) over ``data`` (validation captures)."""
    total, n = 0.0, 0
    for i in range(0, len(data), chunk):
        part = data.take(torch.arange(i, min(i + chunk, len(data))))
        seen = int(part.mask.any(dim=1).sum())
        total += float(distill_loss(student, part)) * seen
        n += seen
    return total / max(n, 1)


def _miou(pred: np.ndarray, truth: np.ndarray, n_classes: int) -> float:
    ious = []
    for c in range(n_classes):
        inter = np.count_nonzero((pred == c) & (truth == c))
        union = np.count_nonzero((pred == c) | (truth == c))
        if np.count_nonzero(truth == c):
            ious.append(inter / union)
    return 100.0 * float(np.mean(ious)) if ious else float("nan")


def validate_scene(scene: Path, head: str, cfg: DistillConfig, gen: np.random.Generator) -> dict[str, float]:
    """Stage 3 for one scene: segment its true points with the teacher and with ``head``."""
    import json

    truth = np.load(scene / "gt" / "points.npz")
    names = json.loads((scene / "gt" / "class_names.json").read_text())
    pick = gen.choice(truth["xyz"].shape[0], size=min(cfg.val_points, truth["xyz"].shape[0]), replace=False)
    pts, labels = truth["xyz"][pick].astype(np.float32), truth["label"][pick]
    row: dict[str, float] = {}
    answers: dict[str, np.ndarray] = {}
    for frac, node, runtime in _stream(scene, cfg.checkpoint):  # one stream: the same window for both
        if frac < 1.0:
            continue
        node.ctx.drain_integrations()
        student, _ = load_point_head(head, teacher_sha256=runtime.metadata["weights_sha256"])
        for name, network in (("teacher", None), ("head", student)):
            runtime.point_head = network
            for use_depth in (False, True):
                key = f"{name}{'_dgm' if use_depth else ''}"
                answers[key], _, _ = runtime.segment(pts, names, use_depth=use_depth)
                row[f"miou_{key}"] = _miou(answers[key], labels, len(names))
    for suffix in ("", "_dgm"):
        same = answers[f"teacher{suffix}"] == answers[f"head{suffix}"]
        row[f"labels_equal{suffix}"] = 100.0 * float(np.mean(same))
    return row


def _validate(
    scenes: Sequence[Path], head: str, cfg: DistillConfig, gen: np.random.Generator
) -> tuple[dict[str, dict[str, float]], dict[str, float]]:
    """Stage 3 on every scene, printed; returns the rows by scene and their mean."""
    rows = {s.name: validate_scene(s, head, cfg, gen) for s in scenes}
    for name, row in rows.items():
        print(f"distill-point-head: {name}: " + ", ".join(f"{k} {v:.1f}" for k, v in row.items()), flush=True)
    mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in next(iter(rows.values()))}
    print("distill-point-head: mean " + ", ".join(f"{k} {v:.1f}" for k, v in mean.items()), flush=True)
    return rows, mean


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="govnesf distill-point-head", description=__doc__.split("\n\n")[0])
    d = DistillConfig()
    for f in dataclasses.fields(DistillConfig):
        default = getattr(d, f.name)
        flag = "--" + f.name.replace("_", "-")
        if isinstance(default, tuple):
            kind = float if f.name == "capture_fractions" else str
            p.add_argument(flag, nargs="+", type=kind, default=list(default))
        else:
            p.add_argument(flag, type=type(default), default=default)
    p.add_argument("--no-progress", action="store_true", help="no per-step lines")
    p.add_argument("--validate-only", action="store_true",
                   help="only stage 3: validate the head at --out on the --val-dirs scenes (writes nothing)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(DistillConfig)}
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
    try:
        cfg = DistillConfig(**values)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from mapper.model.checkpoint import load_model

    try:
        val_scenes = _scene_dirs(cfg.val_dirs)
        if args.validate_only:
            if not head_paths(cfg.out)[1].exists():
                raise FileNotFoundError(f"no point head at {cfg.out} (--out)")
            _validate(val_scenes, cfg.out, cfg, np.random.default_rng(cfg.seed))
            return 0
        train_scenes = _scene_dirs(cfg.train_dirs)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if cfg.max_train_scenes:
        train_scenes = train_scenes[: cfg.max_train_scenes]
    if not train_scenes or not val_scenes:
        print(f"error: no scenes under {cfg.train_dirs} / {cfg.val_dirs} (scripts/make_train_data.sh)",
              file=sys.stderr)
        return 2
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    teacher, meta = load_model(cfg.checkpoint)
    gen = np.random.default_rng(cfg.seed)
    t0 = time.perf_counter()
    parts: list[Captured] = []
    for i, scene in enumerate(train_scenes):
        parts.extend(capture_scene(scene, cfg, gen))
        print(f"distill-point-head: captured {scene.name} ({i + 1}/{len(train_scenes)}), "
              f"{sum(len(p) for p in parts)} points ({time.perf_counter() - t0:.0f} s)", flush=True)
    val_parts = [c for s in val_scenes for c in capture_scene(s, cfg, gen)]
    data, val_data = Captured.cat(parts), Captured.cat(val_parts)
    capture_s = time.perf_counter() - t0
    scfg = student_config(teacher.cfg.fusion, cfg)
    student = FusionNet(teacher.cfg.encoder.feature_dim, teacher.cfg.volume.volume_feature_dim, scfg)
    t1 = time.perf_counter()
    losses = train_head(student, data, cfg, progress=not args.no_progress)
    train_s = time.perf_counter() - t1
    val_kl = held_out_kl(student, val_data)
    extra: dict[str, Any] = {
        "distill_config": dataclasses.asdict(cfg), "teacher_checkpoint": cfg.checkpoint,
        "command": "govnesf distill-point-head " + " ".join(argv if argv is not None else sys.argv[1:]),
        "train_points": len(data), "val_points": len(val_data), "capture_s": round(capture_s, 1),
        "train_s": round(train_s, 1), "train_kl_last200": float(np.mean(losses[-200:])),
        "val_kl": val_kl, "torch": torch.__version__,
    }
    dims = {"feature_dim": teacher.cfg.encoder.feature_dim,
            "volume_feature_dim": teacher.cfg.volume.volume_feature_dim,
            "teacher_sha256": meta["weights_sha256"]}
    out = save_point_head(cfg.out, student, scfg, extra=extra, **dims)
    print(f"distill-point-head: wrote {out}; held-out KL {val_kl:.4f}", flush=True)
    rows, mean = _validate(val_scenes, str(out), cfg, gen)
    extra.update(validation=rows, validation_mean=mean)
    save_point_head(cfg.out, student, scfg, extra=extra, **dims)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
