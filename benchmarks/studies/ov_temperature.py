"""Does a temperature on the learned OV blending logits help 3D segmentation with DGM?

With Depth Guided Masking the learned blend scores about a point below plain averaging over the
views that pass the depth test (docs/how-to/evaluate.md). Dividing FusionNet's OV blending logits by a
temperature ``t`` moves the blend from the learned weights (``t = 1``) towards a uniform average
over the same views (``t`` large); this measures every ``t`` on the same points with and without
DGM, next to the averaging rows over the model's candidate views (0 px border), using the
evaluation's own code (``mapper.training.evaluate.evaluate_scene``, 3D only). Tune on validation
scenes (``data/val``), not on the held-out ones.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/studies/ov_temperature.py data/val/apartment_s100[0-2] \\
        --temperatures 1,1.5,2,3,1000                                            # about 2 min

Prints per-scene mIoU (%) and the mean per row.
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def tempered(model: torch.nn.Module, t: float) -> torch.nn.Module:
    """A copy of ``model`` whose OV blending logits are divided by ``t`` (the last layer of
    FusionNet's ``mlp_s`` scaled by 1 / t: softmax(logits / t), nothing else changes)."""
    if not t > 0:
        raise ValueError(f"temperature {t} must be > 0")
    m = copy.deepcopy(model)
    last = m.fusion.mlp_s[2]  # type: ignore[index]
    with torch.no_grad():
        last.weight.div_(t)
        last.bias.div_(t)
    return m


def scene_table(scenes: list[str], rows: dict[str, list[float]]) -> str:
    """Markdown: one row per name with its per-scene values (%) and their mean."""
    lines = ["| row | " + " | ".join(scenes) + " | mean |", "|---|" + "---|" * (len(scenes) + 1)]
    for name, values in rows.items():
        lines.append(f"| {name} | " + " | ".join(f"{v:.1f}" for v in values) + f" | {np.mean(values):.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from mapper.model.checkpoint import load_model
    from mapper.ov.encoders import get_text_encoder
    from mapper.training import evaluate as ev
    from mapper.training.metrics import NUM_SCANNET_CLASSES

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="+", type=Path)
    parser.add_argument("--checkpoint", default="checkpoints/cpu-small.json")
    parser.add_argument("--temperatures", default="1,1.5,2,3,1000")
    parser.add_argument("--max-points", type=int, default=20000)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    temps = [float(t) for t in args.temperatures.split(",")]
    base, _ = load_model(args.checkpoint, device="cpu")
    models = {f"t = {t:g}": tempered(base, t) for t in temps}
    settings = ev.EvalSettings(max_points=args.max_points, do_2d=False, averaging_borders_px=(0.0,),
                               oracle=False, no_depth_input=False)  # fmt: skip
    rows: dict[str, list[float]] = {}
    for scene_dir in args.scenes:
        scene = ev.load_scene(scene_dir)
        emb = torch.from_numpy(get_text_encoder().encode(scene.class_names[:NUM_SCANNET_CLASSES]))
        for name, result in ev.evaluate_scene(scene, models, emb, settings)["3d"].items():
            rows.setdefault(name, []).append(100 * result.scores().miou)
        print(f"{scene.name} done", file=sys.stderr, flush=True)
    print(scene_table([p.name for p in args.scenes], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
