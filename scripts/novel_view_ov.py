"""Add SimLSeg features at the ground-truth novel views of a `govnesf sim record` directory.

The evaluation (``mapper.training.evaluate``) compares rendered OV features at ``gt/novel_views.npz`` with
the 2D model run on the ground-truth image at that view (the paper's "LSeg at the novel view"
row). The mapper never imports ``clients``, so this script (which may import both layers'
neighbours) re-renders each novel view with the simulator and runs SimLSeg on it, writing

    DIR/gt/novel_ov.npy    (V, h, w, D) float16, SimLSeg features of the V novel views

SimLSeg draws its confusions from ``(seed, frame_index)``; novel view k uses frame index
``NOVEL_FRAME_OFFSET + k`` so its draws are a fresh observation, independent of every stream
frame (as a 2D model run on a new image would be).

Usage: python scripts/novel_view_ov.py DIR [DIR ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

NOVEL_FRAME_OFFSET = 1_000_000
"""Frame index of novel view 0 for SimLSeg's random draws (far beyond any stream frame)."""


def add_novel_view_ov(data_dir: Path) -> Path:
    """Render the novel views of one recording, run SimLSeg, write ``gt/novel_ov.npy``."""
    from clients.sim.raycast import SceneRenderer
    from clients.sim.scenes import CLASS_NAMES, generate_scene
    from clients.sim.simlseg import SimLSeg, SimLSegConfig
    from clients.sim.text import get_text_encoder

    gt = data_dir / "gt"
    info = json.loads((gt / "scene.json").read_text())
    cfg = info["config"]
    novel = np.load(gt / "novel_views.npz", allow_pickle=False)
    poses, Ks = novel["world_from_cam"], novel["K"]  # (V, 4, 4), (V, 4)
    width, height = int(cfg["width"]), int(cfg["height"])
    scene = generate_scene(int(cfg["seed"]), str(cfg["style"]))
    renderer = SceneRenderer(scene)
    stride = cfg.get("ov_stride")
    sl_cfg = SimLSegConfig() if stride is None else SimLSegConfig(stride=int(stride))
    simlseg = SimLSeg(CLASS_NAMES, get_text_encoder(), seed=int(cfg["seed"]), config=sl_cfg)
    feats = []
    for k in range(len(poses)):
        view = renderer.render(Ks[k], poses[k], width, height)
        if not np.array_equal(view.label, novel["label"][k]):
            raise RuntimeError(f"{data_dir}: novel view {k} re-renders differently from gt/novel_views.npz "
                               "(simulator changed since recording?); re-record the directory")
        feats.append(simlseg.features(view, frame_index=NOVEL_FRAME_OFFSET + k, K=Ks[k]))
    out = gt / "novel_ov.npy"
    np.save(out, np.stack(feats).astype(np.float16))  # (V, h, w, D)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dirs", nargs="+", type=Path, help="directories written by `govnesf sim record`")
    args = p.parse_args(argv)
    for d in args.dirs:
        if not (d / "gt" / "novel_views.npz").is_file():
            print(f"{d}: no gt/novel_views.npz (record with novel views)", file=sys.stderr)
            return 2
        print(add_novel_view_ov(d))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
