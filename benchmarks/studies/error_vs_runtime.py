"""Error against run time: 3D mIoU vs source views per point, 2D mIoU vs samples per ray.

For learned blending (GOV-NeSF) and for averaging, on held-out scenes (scripts/make_eval_data.sh):

* 3D: ground-truth points seen by > 1 view, each blended from at most K views per point (the K
  nearest of the views that see it; K = 4, 8, 16, all), without depth. Learned blending:
  ``mapper.training.evaluate.blend_points``; averaging: ``mapper.model.baselines.average_features`` over the K
  nearest views that pass its tests. Time: seconds per 100k points for the blend itself (the
  cost volume is built once per map and reported separately).
* 2D: novel views rendered with S samples per ray (16, 32, 64) from the model's source views.
  Averaging here is the same renderer (same density and colour) with the OV blending weights
  replaced by the plain mean over the views that see each sample (the last layer of MLP_s
  zeroed: constant logits). Time: seconds per rendered frame (at ``--pixel-stride``).

Timings are wall-clock on whatever machine runs this (the numbers in docs/how-to/evaluate.md say
which); they are not pass/fail criteria.

Usage:
    python benchmarks/studies/error_vs_runtime.py --checkpoint checkpoints/cpu-small.json \\
        --data data/eval/apartment_s2000 data/eval/studio_s2000 [--max-points 10000] \\
        [--views 4 8 16 all] [--samples 16 32 64] [--novel-views 2] [--pixel-stride 2] \\
        [--out out/eval/error_vs_runtime.json] [--markdown out/eval/error_vs_runtime.md] \
        [--plot out/eval/error_vs_runtime.png]
    python benchmarks/studies/error_vs_runtime.py --plot-from out/eval/error_vs_runtime.json \
        --plot docs/images/error_vs_runtime.png      # re-plot a saved run (its JSON or Markdown)

The plot (matplotlib): one panel per study (3D, 2D) and style, mIoU against run time (log
scale), both methods; the Pareto front over both (no other setting is at least as fast and at
least as accurate) is marked and connected.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from mapper.model.baselines import average_features
from mapper.model.checkpoint import load_model
from mapper.model.field import GovNeSF
from mapper.training import evaluate as ev
from mapper.training.metrics import (
    NUM_SCANNET_CLASSES,
    average_over_scenes,
    predict_labels,
    scores_from_labels,
)


def averaging_model(model: GovNeSF) -> GovNeSF:
    """A copy whose OV weights are uniform over the views that see a sample (plain averaging)."""
    avg = copy.deepcopy(model)
    last = avg.fusion.mlp_s[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    return avg.eval()


def parse_views(values: list[str]) -> list[int | None]:
    out: list[int | None] = []
    for v in values:
        if v == "all":
            out.append(None)
        elif v.isdigit() and int(v) > 0:
            out.append(int(v))
        else:
            raise SystemExit(f"--views: expected positive integers or 'all', got {v!r}")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", type=Path)
    p.add_argument("--data", nargs="+", type=Path)
    p.add_argument("--max-points", type=int, default=10000)
    p.add_argument("--views", nargs="+", default=["4", "8", "16", "all"])
    p.add_argument("--samples", nargs="+", type=int, default=[16, 32, 64])
    p.add_argument("--novel-views", type=int, default=2)
    p.add_argument("--pixel-stride", type=int, default=2)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--markdown", type=Path, default=None)
    p.add_argument("--plot", type=Path, default=None, help="write a PNG plot with the Pareto front")
    p.add_argument("--plot-from", type=Path, default=None,
                   help="plot a saved run (its --out JSON or --markdown file) instead of running")
    args = p.parse_args(argv)
    if args.plot_from is not None:
        if args.plot is None:
            print("--plot-from needs --plot PATH.png", file=sys.stderr)
            return 2
        saved = load_results(args.plot_from)
        plot_results(saved, args.plot)
        print(f"wrote {args.plot}")
        return 0
    if args.checkpoint is None or not args.data:
        print("--checkpoint and --data are required (or --plot-from)", file=sys.stderr)
        return 2
    if args.max_points < 1 or args.novel_views < 1 or args.pixel_stride < 1 or min(args.samples) < 1:
        print("--max-points, --novel-views, --pixel-stride and --samples must be >= 1", file=sys.stderr)
        return 2
    views_list = parse_views(args.views)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from mapper.ov.encoders import get_text_encoder

    model, meta = load_model(args.checkpoint)
    avg_model = averaging_model(model)
    scenes = [ev.load_scene(d) for d in ev.find_scene_dirs(args.data)]
    text = torch.from_numpy(get_text_encoder().encode(scenes[0].class_names[:NUM_SCANNET_CLASSES]))
    settings = ev.EvalSettings(max_points=args.max_points)

    rows3d: dict[tuple[str, str, str], list] = {}  # (style, method, K) -> [(scores, s/100k)]
    rows2d: dict[tuple[str, str, int], list] = {}
    for scene in scenes:
        print(f"scene {scene.name} ({scene.style})", flush=True)
        keep = ev._subset(scene, settings)
        gt = scene.points_label[keep]
        pts = torch.from_numpy(scene.points_xyz[keep])
        views, bounds = ev.scene_sources(model, scene)
        t0 = time.perf_counter()
        with torch.no_grad():
            volume = model.build_volume(views, bounds)
        vol_s = time.perf_counter() - t0
        K = torch.from_numpy(scene.K).float()
        poses = torch.from_numpy(scene.world_from_cam).float()
        avg_views = ev._avg_views(scene)
        # Warm-up (first-call allocations and kernel selection would otherwise be billed to K = 4).
        ev.blend_points(model, views, volume, bounds, pts[:512], views_per_point=views_list[0])
        average_features(pts[:512], avg_views, use_depth=False)
        for k in views_list:
            kname = "all" if k is None else str(k)
            t0 = time.perf_counter()
            pb = ev.blend_points(model, views, volume, bounds, pts, views_per_point=k)
            secs = time.perf_counter() - t0
            s = scores_from_labels(gt, np.asarray(predict_labels(pb.ov, text)))
            rows3d.setdefault((scene.style, "learned blending", kname), []).append((s, secs * 1e5 / len(gt)))
            t0 = time.perf_counter()
            vw = None if k is None else ev.nearest_view_selection(pts, K, poses, scene.image_wh, k)
            feats, _ = average_features(pts, avg_views, use_depth=False, view_weights=vw)
            secs_a = time.perf_counter() - t0
            sa = scores_from_labels(gt, np.asarray(predict_labels(feats, text)))
            rows3d.setdefault((scene.style, "averaging", kname), []).append((sa, secs_a * 1e5 / len(gt)))
            print(f"  3d K={kname:>3}: blend mIoU {100 * s.miou:.1f} ({secs * 1e5 / len(gt):.1f} s/100k), "
                  f"avg mIoU {100 * sa.miou:.1f} ({secs_a * 1e5 / len(gt):.1f} s/100k); volume {vol_s:.1f} s",
                  flush=True)
        assert scene.novel is not None
        nv = scene.novel
        n_nv = nv.K.shape[0]
        idx_views = np.linspace(0, n_nv - 1, min(args.novel_views, n_nv)).round().astype(int)
        st = args.pixel_stride
        off = st // 2
        for n_samples in args.samples:
            for name, m in (("learned blending", model), ("averaging", avg_model)):
                gts, preds, secs_list = [], [], []
                for v in idx_views:
                    t0 = time.perf_counter()
                    chosen = ev.novel_view_sources(scene, int(v), m.cfg.num_source_views)
                    src, b = ev.scene_sources(m, scene, chosen)
                    with torch.no_grad():
                        vol = m.build_volume(src, b)
                        _, ov = ev.render_view(m, src, vol, b, nv.K[v], nv.world_from_cam[v], scene.image_wh,
                                               pixel_stride=st, n_samples=n_samples, clip_to_volume=True)
                    secs_list.append(time.perf_counter() - t0)
                    preds.append(np.asarray(predict_labels(ov.reshape(-1, ov.shape[-1]), text)))
                    gts.append(nv.label[v][off::st, off::st].reshape(-1))
                s = scores_from_labels(np.concatenate(gts), np.concatenate(preds))
                rows2d.setdefault((scene.style, name, n_samples), []).append((s, float(np.mean(secs_list))))
                print(f"  2d S={n_samples}: {name} mIoU {100 * s.miou:.1f} "
                      f"({np.mean(secs_list):.1f} s/frame)", flush=True)

    def agg(items: list) -> tuple[float, float]:
        return average_over_scenes([s for s, _ in items]).miou, float(np.mean([t for _, t in items]))

    lines = [f"Checkpoint {args.checkpoint} (step {meta.get('step')}), {len(scenes)} scenes, "
             f"{args.max_points} points per scene, 2D: {args.novel_views} novel views per scene at pixel "
             f"stride {args.pixel_stride}.", "",
             "| style | method | views per point | 3D mIoU | s / 100k points |", "|---|---|---|---|---|"]
    out: dict = {"checkpoint": str(args.checkpoint), "step": meta.get("step"), "3d": [], "2d": []}
    def order3d(item: tuple) -> tuple:
        (style, method, kname), _ = item
        return style, method, float("inf") if kname == "all" else int(kname)

    for (style, method, kname), items in sorted(rows3d.items(), key=order3d):
        miou, t = agg(items)
        lines.append(f"| {style} | {method} | {kname} | {100 * miou:.1f} | {t:.1f} |")
        out["3d"].append({"style": style, "method": method, "views_per_point": kname, "miou": miou,
                          "seconds_per_100k": t})
    lines += ["", "| style | method | samples per ray | 2D mIoU | s / frame |", "|---|---|---|---|---|"]
    for (style, method, n_samples), items in sorted(rows2d.items()):
        miou, t = agg(items)
        lines.append(f"| {style} | {method} | {n_samples} | {100 * miou:.1f} | {t:.1f} |")
        out["2d"].append({"style": style, "method": method, "samples": n_samples, "miou": miou,
                          "seconds_per_frame": t})
    report = "\n".join(lines)
    print(report)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1) + "\n")
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(report + "\n")
    if args.plot:
        plot_results(out, args.plot)
    return 0


def load_results(path: Path) -> dict:
    """A saved run: the ``--out`` JSON, or the ``--markdown`` tables (the layout this script
    prints, also used in docs/how-to/evaluate.md), as ``{"3d": [...], "2d": [...]}``."""
    text = path.read_text()
    if path.suffix == ".json":
        return json.loads(text)
    out: dict = {"3d": [], "2d": []}
    header = ""
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 5:
            header = ""
            continue
        if cells[0] == "style":
            header = line
            continue
        try:
            miou, t = float(cells[3]) / 100.0, float(cells[4])
        except ValueError:
            continue
        if "2D mIoU" in header:
            out["2d"].append({"style": cells[0], "method": cells[1], "samples": int(cells[2]), "miou": miou,
                              "seconds_per_frame": t})
        elif "3D mIoU" in header:
            out["3d"].append({"style": cells[0], "method": cells[1], "views_per_point": cells[2],
                              "miou": miou, "seconds_per_100k": t})
    return out


def pareto_front(times: list[float], mious: list[float]) -> list[int]:
    """Indices of the settings no other setting dominates (at most as slow and at least as accurate,
    one of them strictly), fastest first.

    >>> pareto_front([1.0, 2.0, 3.0, 1.5], [0.4, 0.5, 0.45, 0.3])
    [0, 1]
    """
    order = sorted(range(len(times)), key=lambda i: (times[i], -mious[i]))
    front, best = [], -np.inf
    for i in order:
        if mious[i] > best:
            front.append(i)
            best = mious[i]
    return front


def plot_results(results: dict, path: Path) -> None:
    """mIoU against run time per study and style, both methods, the Pareto front marked (PNG)."""
    from govnesf._extras import require

    matplotlib = require("matplotlib", "bench")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401  (the tick locators used below, as matplotlib.ticker.*)

    studies = [("3d", "seconds_per_100k", "views_per_point", "s per 100k points", "views per point"),
               ("2d", "seconds_per_frame", "samples", "s per frame", "samples per ray")]
    styles = sorted({r["style"] for k, *_ in studies for r in results.get(k, [])})
    panels = [(s, st) for s in studies if results.get(s[0]) for st in styles]
    if not panels:
        raise ValueError("nothing to plot: the results hold no 3d or 2d rows")
    cols = len(styles)
    rows = len(panels) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.0 * rows), squeeze=False)
    colours = {"learned blending": "tab:blue", "averaging": "tab:orange"}
    for n, ((kind, tkey, pkey, tlabel, plabel), style) in enumerate(panels):
        ax = axes[n // cols][n % cols]
        items = [r for r in results[kind] if r["style"] == style]
        times = [float(r[tkey]) for r in items]
        mious = [100.0 * float(r["miou"]) for r in items]
        for method in sorted({r["method"] for r in items}):
            idx = [i for i, r in enumerate(items) if r["method"] == method]
            ax.plot([times[i] for i in idx], [mious[i] for i in idx], "o-", color=colours.get(method),
                    label=method, alpha=0.8)
            for i in idx:
                ax.annotate(str(items[i][pkey]), (times[i], mious[i]), textcoords="offset points",
                            xytext=(4, 4), fontsize=8)
        front = pareto_front(times, mious)
        ax.plot([times[i] for i in front], [mious[i] for i in front], "k--", drawstyle="steps-post",
                linewidth=1.0, label="Pareto front")
        ax.scatter([times[i] for i in front], [mious[i] for i in front], s=140, facecolors="none",
                   edgecolors="black", linewidths=1.5)
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.set_xlabel(tlabel)
        ax.set_ylabel(f"{kind.upper()} mIoU (%)")
        ax.set_title(f"{style}: {kind.upper()}, by {plabel}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
