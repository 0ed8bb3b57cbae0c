"""How much weight the global map's answer should get where the window answers too
(``queries.map_blend``): a sweep over the weight, for every ``segment_points`` method, on recorded
sim scenes, bounded window against unbounded.

For each scene (``scripts/make_eval_data.sh`` / ``scripts/make_train_data.sh`` layout:
``frames.govrec``, ``gt/points.npz``, ``gt/class_names.json``) the real ``MapperNode`` with the
learned plugin (in-process, as ``benchmarks/studies/bench_whole_map.py``) ingests the recorded frames with
a window that holds every keyframe ("unbounded") and one of a third of them ("bounded"). At the
scene's ground-truth points it then takes, once, the window's per-text cosines of each method
(``govnesf``: ``ModelRuntime.segment_cosines``; ``average`` / ``average_depth``:
``segment_average_cosines``) and the cosines of the nearest global-map point with a feature within
``queries.map_radius_voxels``, and scores each rule on the same cosines (no re-run per weight):

* ``window``: the window only; ``map``: the map only (-1 where no map point is near);
* ``more confident``: the rule before the blend (``map_blend = 0``);
* ``blend w``: the best text of ``(1 - w) window + w map`` where both answer (``blend_with_map``).

Prints one Markdown table per method: bounded mIoU per scene, bounded minus unbounded, and the
means. ``--json`` also writes every number.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/studies/map_blend_sweep.py data/val/apartment_s100[0-2] \\
        data/eval/*_s200[0-2]                                                     # about 2 min
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks" / "studies"))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

WEIGHTS = (0.5, 0.667, 0.75, 0.8, 0.9)
METHODS = ("average", "average_depth", "govnesf")


def scene_cosines(scene: Path, max_keyframes: int | None) -> dict[str, np.ndarray]:
    """Stream ``scene`` into a fresh node (window of ``max_keyframes``; None = every keyframe) and
    return the ground truth, each method's window cosines and the map's at the scene's points."""
    import bench_whole_map as bw

    from mapper.node.config import QueryConfig
    from mapper.node.queries import segment_average_cosines

    frames = bw._frames(scene)
    gt = np.load(scene / "gt" / "points.npz")
    xyz = gt["xyz"].astype(np.float32)
    texts = json.loads((scene / "gt" / "class_names.json").read_text())
    with tempfile.TemporaryDirectory(prefix="govnesf-blend-") as tmp:
        node, blender, runtime = bw._node(Path(tmp), max_keyframes or 10_000,
                                          radius_voxels=QueryConfig().map_radius_voxels,
                                          learned=True, more_confident=True, blend=0.75)  # fmt: skip
        try:
            bw._run(frames, node, blender)
            emb = np.asarray(node.ctx.text_encoder("sweep").encode(texts), np.float32)
            label, _, cos_g, _ = runtime.segment_cosines(xyz, texts)
            out: dict[str, np.ndarray] = {"gt": gt["label"].astype(np.int64), "govnesf": cos_g,
                                          "govnesf_seen": label >= 0}  # fmt: skip
            with node.state.lock:
                keyframes = node.state.window.keyframes
            for method, depth in (("average", False), ("average_depth", True)):
                views = [(k.ov, k.K, k.world_from_cam, (k.width, k.height), k.depth_m) for k in keyframes
                         if k.ov is not None and (not depth or k.depth_m is not None)]  # fmt: skip
                cos, n = segment_average_cosines(xyz, views, emb, use_depth=depth)
                out[method], out[method + "_seen"] = cos, n > 0
            snap = node.state.global_map.snapshot()
            rows = snap.nearest_with_feature(xyz, node.ctx.map_radius_m)
            hit = rows >= 0
            map_cos = np.zeros((xyz.shape[0], len(texts)), np.float32)
            assert snap.feat is not None
            feat = snap.feat[rows[hit]].astype(np.float32)
            map_cos[hit] = (feat / np.maximum(np.linalg.norm(feat, axis=1, keepdims=True), 1e-12)) @ emb.T
            out["map"], out["map_seen"] = map_cos, hit
        finally:
            node.stop()
    return out


def rule_labels(c: dict[str, np.ndarray], method: str) -> dict[str, np.ndarray]:
    """Every rule's labels (-1 = no answer) for one method's window cosines and the map's."""
    from mapper.node.queries import best_text, blend_with_map, map_more_confident

    win, seen = c[method], c[method + "_seen"]
    mp, hit = c["map"], c["map_seen"]
    lw, sw = best_text(win, seen)
    lm, sm = best_text(mp, hit)
    out = {"window": lw, "map": lm}
    cur = np.where(seen, lw, lm)
    take = seen & hit & map_more_confident(lm, sm, lw, sw)
    cur[take] = lm[take]
    out["more confident (before)"] = cur
    for w in WEIGHTS:
        both = seen & hit
        mixed = np.where(both[:, None], blend_with_map(win, mp, w), np.where(seen[:, None], win, mp))
        out[f"blend {w:g}"] = best_text(mixed, seen | hit)[0]
    return out


def main(argv: list[str] | None = None) -> int:
    import bench_whole_map as bw

    from clients.harness import mean_iou

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="+", type=Path)
    parser.add_argument("--json", type=Path, help="also write every number here")
    args = parser.parse_args(argv)
    results: dict[str, dict[str, dict[str, dict[str, float]]]] = {m: {} for m in METHODS}
    for scene in args.scenes:
        n_kf = bw._count_keyframes(bw._frames(scene))
        runs = {"unbounded": None, "bounded": max(1, math.ceil(n_kf / 3))}
        for run, max_kf in runs.items():
            c = scene_cosines(scene, max_kf)
            n_texts = c["map"].shape[1]
            for method in METHODS:
                for rule, labels in rule_labels(c, method).items():
                    cell = results[method].setdefault(rule, {}).setdefault(scene.name, {})
                    cell[run] = round(100 * mean_iou(labels, c["gt"], n_texts)[0], 2)
            print(f"{scene.name} {run} ({max_kf or 'every'} keyframe(s)) done", file=sys.stderr, flush=True)
    names = [s.name for s in args.scenes]
    for method in METHODS:
        print(f"\n`{method}`: bounded mIoU (bounded minus unbounded) per scene\n")
        print("| rule | " + " | ".join(names) + " | mean bounded | mean unbounded | mean gap |")
        print("|---|" + "---|" * (len(names) + 3))
        for rule, cells in results[method].items():
            b = [cells[n]["bounded"] for n in names]
            u = [cells[n]["unbounded"] for n in names]
            row = " | ".join(f"{x:.1f} ({x - y:+.1f})" for x, y in zip(b, u, strict=True))
            mb, mu = float(np.mean(b)), float(np.mean(u))
            print(f"| {rule} | {row} | {mb:.2f} | {mu:.2f} | {mb - mu:+.2f} |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
