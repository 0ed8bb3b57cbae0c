"""`govnesf evaluate`: the model against its baselines on held-out scenes (docs/how-to/evaluate.md).

    govnesf evaluate --checkpoint checkpoints/cpu-small.json --data data/eval \\
        [--distill checkpoints/distill.json] [--out results.json] [--markdown tables.md] \\
        [--max-points 20000] [--views-per-point all|K] [--source-views N] [--samples S] \\
        [--novel-views N] [--no-2d] [--no-3d] [--no-oracle] [--no-depth-input-rows] \\
        [--no-point-occlusion-rows] [--no-surface-renders]

``--data`` takes scene directories (``govnesf sim record`` exports, ``scripts/make_eval_data.sh``)
or folders of them. Prints progress and the Markdown tables; ``--out`` writes every number as
JSON, ``--markdown`` the tables. Exit status 2 on bad arguments or unreadable inputs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["build_parser", "main"]


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer (>= 1), got {value}")
    return value


def _views_per_point(text: str) -> int | None:
    if text.lower() == "all":
        return None
    try:
        return _positive_int(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected 'all' or a positive integer, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="govnesf evaluate", description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, type=Path, help="GOV-NeSF checkpoint (NAME, NAME.json)")
    p.add_argument("--data", required=True, nargs="+", type=Path,
                   help="scene directories or folders of them (scripts/make_eval_data.sh)")
    p.add_argument("--distill", type=Path, default=None, help="Distill-baseline checkpoint (optional)")
    p.add_argument("--out", type=Path, default=None, help="write all results as JSON here")
    p.add_argument("--markdown", type=Path, default=None, help="write the Markdown tables here")
    p.add_argument("--max-points", type=_positive_int, default=20000,
                   help="3D: at most this many ground-truth points per scene (default 20000)")
    p.add_argument("--views-per-point", type=_views_per_point, default=None, metavar="all|K",
                   help="3D: blend / average at most K nearest views per point (default all)")
    p.add_argument("--source-views", type=_positive_int, default=None,
                   help="2D: source views per novel view (default: the model's)")
    p.add_argument("--samples", type=_positive_int, default=None,
                   help="2D: samples per ray (default: the model's)")
    p.add_argument("--novel-views", type=_positive_int, default=None,
                   help="2D: at most this many novel views per scene (default all)")
    p.add_argument("--pixel-stride", type=_positive_int, default=1,
                   help="2D: evaluate every s-th pixel in rows and columns (default 1 = all)")
    p.add_argument("--no-clip", action="store_true",
                   help="2D: sample rays over [near, far] instead of only inside the volume")
    p.add_argument("--weight-threshold", type=float, default=0.0,
                   help="2D: skip appearance for samples with a smaller weight (default 0 = exact)")
    p.add_argument("--no-2d", action="store_true", help="skip the 2D novel-view evaluation")
    p.add_argument("--no-3d", action="store_true", help="skip the 3D point evaluation")
    p.add_argument("--averaging-border-px", type=float, nargs="+", default=[10.0], metavar="PX",
                   help="3D: averaging rows for these image border cuts (default 10, OpenScene-2D; "
                        "0 = the model's candidate views)")
    p.add_argument("--no-oracle", action="store_true", help="3D: skip the GT-visibility averaging row")
    p.add_argument("--no-surface-renders", action="store_true",
                   help="2D: skip the rows rendered at the sources' measured surfaces (the node's render)")
    p.add_argument("--no-depth-input-rows", action="store_true",
                   help="3D: skip the rows that use no input depth (frustum bounds, rendered-depth DGM)")
    p.add_argument("--no-point-occlusion-rows", action="store_true",
                   help="3D: skip the rows tested against each frame's z-buffer of the evaluated points")
    p.add_argument("--rgb-only-node", action="store_true",
                   help="3D: also stream each scene WITHOUT depth through an in-process node serving "
                   "--checkpoint (the plugins `govnesf serve` installs) and score its segment_points "
                   "answers (rows 'Node RGB-only: ...')")
    p.add_argument("--node-config", default=None,
                   help="node TOML for --rgb-only-node (default: the shipped launch/node.toml)")
    p.add_argument("--training-style", default="apartment", help="style the model was trained on")
    p.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse exits 2 on errors, 0 on --help
        return int(exc.code or 0)
    if not 0.0 <= args.weight_threshold < 1.0:
        print(f"govnesf evaluate: --weight-threshold {args.weight_threshold} out of range [0, 1)",
              file=sys.stderr)
        return 2
    if any(not 0.0 <= b < 1000.0 for b in args.averaging_border_px):
        print(f"govnesf evaluate: --averaging-border-px {args.averaging_border_px} out of range [0, 1000)",
              file=sys.stderr)
        return 2
    if args.no_2d and args.no_3d:
        print("govnesf evaluate: --no-2d and --no-3d together leave nothing to evaluate", file=sys.stderr)
        return 2
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    import torch

    from mapper.model.checkpoint import load_model
    from mapper.model.field import default_device
    from mapper.ov.encoders import get_text_encoder
    from mapper.training import evaluate as ev
    from mapper.training.metrics import NUM_SCANNET_CLASSES

    device = torch.device(args.device) if args.device else default_device()
    try:
        scene_dirs = ev.find_scene_dirs(args.data)
        model, meta = load_model(args.checkpoint, device=device)
        if model.mode != "blend":
            raise ValueError(f"{args.checkpoint}: mode {model.mode!r}; --checkpoint needs a blending model "
                             "(give a Distill checkpoint with --distill)")
        models: dict[str, Any] = {"GOV-NeSF": model}
        metas = {"GOV-NeSF": meta}
        if args.distill is not None:
            dmodel, dmeta = load_model(args.distill, device=device)
            if dmodel.mode != "distill":
                raise ValueError(f"{args.distill}: mode {dmodel.mode!r}, expected a 'distill' checkpoint")
            models["Distill"] = dmodel
            metas["Distill"] = dmeta
    except (FileNotFoundError, ValueError, KeyError) as exc:
        print(f"govnesf evaluate: {exc}", file=sys.stderr)
        return 2

    settings = ev.EvalSettings(
        max_points=args.max_points, views_per_point=args.views_per_point, num_source_views=args.source_views,
        n_samples=args.samples, max_novel_views=args.novel_views, do_2d=not args.no_2d, do_3d=not args.no_3d,
        oracle=not args.no_oracle, clip_to_volume=not args.no_clip,
        pixel_stride=args.pixel_stride, averaging_borders_px=tuple(args.averaging_border_px),
        weight_threshold=args.weight_threshold, no_depth_input=not args.no_depth_input_rows,
        point_occlusion=not args.no_point_occlusion_rows,
        surface_renders=not args.no_surface_renders,
        rgb_only_node=str(args.checkpoint) if args.rgb_only_node else None, node_config=args.node_config,
    )

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, flush=True)

    per_scene: dict[str, Any] = {}
    styles: dict[str, str] = {}
    class_names: list[str] | None = None
    text_emb = None
    t_start = time.perf_counter()
    for d in scene_dirs:
        try:
            scene = ev.load_scene(d)
        except (FileNotFoundError, ValueError, KeyError) as exc:
            print(f"govnesf evaluate: {d}: {exc}", file=sys.stderr)
            return 2
        if text_emb is None:
            class_names = scene.class_names
            emb = get_text_encoder().encode(class_names[:NUM_SCANNET_CLASSES])  # (20, D)
            text_emb = torch.from_numpy(emb)
        ov_dim = int(scene.ov.shape[-1])
        for name, m in models.items():
            if m.cfg.fusion.ov_dim != ov_dim:
                print(f"govnesf evaluate: {d}: OV features are {ov_dim}-d but the {name} model expects "
                      f"{m.cfg.fusion.ov_dim}-d", file=sys.stderr)
                return 2
        log(f"scene {scene.name} ({scene.style}, {len(scene)} frames)")
        key = scene.name
        per_scene[key] = ev.evaluate_scene(scene, models, text_emb, settings, log=log, device=device)
        styles[key] = scene.style
    assert class_names is not None
    summary = ev.summarise(per_scene, styles, class_names)
    report = ev.format_report(summary, training_style=args.training_style)
    summary["settings"] = {k: v for k, v in vars(settings).items()}
    summary["checkpoints"] = {
        name: {"path": str(p), "step": metas[name].get("step"), "preset": metas[name].get("preset")}
        for name, p in (("GOV-NeSF", args.checkpoint), ("Distill", args.distill)) if name in metas
    }
    summary["command"] = "govnesf evaluate " + " ".join(sys.argv[2:] if argv is None else argv)
    summary["seconds"] = time.perf_counter() - t_start
    print(report)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary, indent=1) + "\n")
    if args.markdown is not None:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(report + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
