"""``govnesf train``: train the GOV-NeSF model (see docs/TRAINING.md).

Examples:
    govnesf train --config launch/train_cpu_small.toml
    govnesf train --config launch/train_cpu_small.toml --resume out/train/cpu-small/last.json
    torchrun --nproc_per_node 2 -m mapper.cli_train --config launch/train_cpu_small.toml
"""

from __future__ import annotations

import argparse
import shlex
import sys

__all__ = ["main"]


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
    p.add_argument("--out", default=None, help="override out_dir (training checkpoints and log.jsonl)")
    p.add_argument(
        "--export", default=None, help="override export (weights-only checkpoint, e.g. checkpoints/x)"
    )
    p.add_argument("--mode", choices=("blend", "distill"), default=None, help="override mode")
    p.add_argument("--threads", type=int, default=None, help="override torch threads per process")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    from mapper.train import load_train_config, train

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
    command = "govnesf train " + shlex.join(sys.argv[1:] if argv is None else argv)
    result = train(
        cfg, resume=args.resume, until_step=args.until_step, command=command, progress=not args.no_progress
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
