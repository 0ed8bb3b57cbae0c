"""``govnesf train``: train the GOV-NeSF model (see docs/how-to/train.md).

Examples:
    govnesf train --config launch/train_cpu_small.toml
    govnesf train --config launch/train_cpu_small.toml --resume out/train/cpu-small/last.json
    govnesf train --config launch/train_gpu_small.toml --wall-budget-s 300   # as many steps as fit
    torchrun --nproc_per_node 2 -m mapper.training.cli_train --config launch/train_cpu_small.toml
"""

from __future__ import annotations

import argparse
import shlex
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mapper.training.train import TrainConfig

__all__ = ["main"]


def _seconds(text: str) -> float:
    """A positive, finite number of seconds (argparse type)."""
    import math

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} out of range: a finite number of seconds > 0")
    return value


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="govnesf train", description="Train the GOV-NeSF model.")
    p.add_argument("--config", required=True, help="TOML file with a [train] table (launch/train_*.toml)")
    p.add_argument("--resume", default=None, help="training checkpoint to continue from (OUT/last.json)")
    p.add_argument("--max-steps", type=int, default=None, help="override max_steps (length of the schedule)")
    p.add_argument(
        "--until-step",
        type=int,
        default=None,
        help="stop after this many completed steps (resume later with --resume)",
    )
    p.add_argument(
        "--wall-budget-s",
        type=_seconds,
        default=None,
        metavar="S",
        help="seconds for the training steps: time the first steps, then run as many as fit "
        "(at most max_steps; the schedule follows; not with --resume / --until-step)",
    )
    p.add_argument("--out", default=None, help="override out_dir (training checkpoints and log.jsonl)")
    p.add_argument(
        "--export", default=None, help="override export (weights-only checkpoint, e.g. checkpoints/x)"
    )
    p.add_argument("--mode", choices=("blend", "distill"), default=None, help="override mode")
    p.add_argument("--threads", type=int, default=None, help="override torch threads per process")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--evaluate",
        default=None,
        metavar="CKPT",
        help="do not train: validate a checkpoint on the config's val_dir and print JSON",
    )
    p.add_argument("--val-views", type=int, default=None, help="with --evaluate: novel views per scene")
    p.add_argument("--val-stride", type=int, default=None, help="with --evaluate: render every N-th pixel")
    return p


def _evaluate(cfg: TrainConfig, path: str, views_per_scene: int | None, stride_px: int) -> int:
    """Validate a checkpoint (all novel views unless limited) and print the metrics as JSON."""
    import json
    import time

    from mapper.model.checkpoint import load_model
    from mapper.model.field import default_device
    from mapper.training.data import find_scenes, load_scene, validation_views
    from mapper.training.train import class_text_embeddings, validate

    device = default_device()
    model, meta = load_model(path, device=device)
    scenes = [load_scene(p, with_novel_views=True) for p in find_scenes(cfg.val_dir)]
    views = validation_views(scenes, model.cfg.num_source_views, views_per_scene=views_per_scene)
    text = class_text_embeddings(cfg.val_dir, scenes[0].class_names)
    t0 = time.perf_counter()
    tc = meta.get("train_config", {})
    res = validate(
        model,
        views,
        text,
        stride_px=stride_px,
        depth_guided_masking=bool(tc.get("depth_guided_masking", False)),
        clip_to_volume=bool(tc.get("clip_to_volume", False)),
        device=device,
    )
    res["checkpoint"] = str(path)
    res["weights_dtype"] = meta.get("weights_dtype")
    res["eval_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(res, indent=2))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    from mapper.training.train import load_train_config, train

    try:
        cfg = load_train_config(
            args.config,
            max_steps=args.max_steps,
            out_dir=args.out,
            export=args.export,
            mode=args.mode,
            threads=args.threads,
        )
    except (OSError, ValueError) as exc:
        print(f"govnesf train: {exc}", file=sys.stderr)
        return 2
    if args.evaluate and args.wall_budget_s is not None:
        print("govnesf train: --wall-budget-s trains; it does not combine with --evaluate", file=sys.stderr)
        return 2
    if args.wall_budget_s is not None and (args.resume or args.until_step is not None):
        print("govnesf train: --wall-budget-s does not combine with --resume or --until-step (a resumed "
              "budget run keeps the max_steps its budget chose)", file=sys.stderr)
        return 2
    if args.evaluate:
        return _evaluate(cfg, args.evaluate, args.val_views, args.val_stride or cfg.val_stride_px)
    command = "govnesf train " + shlex.join(sys.argv[1:] if argv is None else argv)
    result = train(
        cfg,
        resume=args.resume,
        until_step=args.until_step,
        command=command,
        progress=not args.no_progress,
        wall_budget_s=args.wall_budget_s,
    )
    val = result["validation"]
    if val:
        print(
            f"step {result['step']}: 2D mIoU {val['miou_2d']:.4f}, PSNR {val['psnr']:.2f} dB, "
            f"wall {result['train_wall_s']:.0f} s"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
