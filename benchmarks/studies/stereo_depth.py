"""Plane-sweep stereo (mapper.geometry.plane_sweep) against true depth: simulated rooms and the real
ICL-NUIM sequence.

For every k-th frame of a sequence (the reference), the partners the node would choose
(``mapper.geometry.triangulation.select_partners`` among the previous ``--candidates`` frames, the
best ``stereo.max_sources``) are swept against, as the triangulation worker does, in sequence order
so that the geometric consistency check can use earlier references' swept depths. Reported per
sequence, pooled over references, for three stages:

* ``swept``: every depth the sweep kept (score, texture, range, uniqueness filters);
* ``consistent``: those ``stereo.min_agreeing`` partners agree with (what joins the global map);
* ``filled``: the consistent depths with their holes filled along the image (the DGM prior);

each with its density (share of pixels with a depth), the median / p90 relative error against
the sequence's true depth, the share off by more than 10% and by more than 25% (the DGM
tolerance), and the sweep's cost per reference (ms, this process, ``--threads``).

Usage::

    python benchmarks/studies/stereo_depth.py                          # demo room, studio seed 9, ICL
    python benchmarks/studies/stereo_depth.py --sim 3:apartment --real none --set prior_fill_px=16

The real sequence is read from ``../shared/data/icl_livingroom1`` (skipped, said so, when absent),
at ``--real-width`` (default 160: the node's working size, ``stereo.max_width`` 200).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from mapper.geometry.config import StereoConfig, TriangulationConfig  # noqa: E402
from mapper.geometry.plane_sweep import (  # noqa: E402
    StereoView,
    agreeing_views,
    depth_range,
    fill_depth,
    gray_image,
    sweep_depth,
)
from mapper.geometry.triangulation import PosedView, select_partners  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
REAL = ROOT.parent / "shared" / "data" / "icl_livingroom1"


def sim_sequence(seed: int, style: str, frames: int) -> list[dict[str, Any]]:
    from clients.sim.export import RecordConfig, SimStream

    config = RecordConfig(seed=seed, frames=frames, width=160, height=120, depth=True, ov=False,
                          novel_views=0, style=style)  # fmt: skip
    stream = SimStream.build(config)
    return [{"rgb": f.rgb, "depth": f.depth_m, "K": np.asarray(f.K, np.float64),
             "pose": np.asarray(f.world_from_cam, np.float64)} for f, _ in stream.frames()]  # fmt: skip


def real_sequence(width: int) -> list[dict[str, Any]]:
    sys.path.insert(0, str(ROOT / "benchmarks" / "studies"))
    from real_rgb_only_map import resized  # type: ignore[import-not-found]
    from real_sequence import ICL_K, load_sequence  # type: ignore[import-not-found]

    frames, _ = load_sequence(REAL, ICL_K)
    out = []
    for f in frames:
        rgb, depth, K = resized(f, width)  # area-averaged colour, nearest depth, K scaled
        out.append({"rgb": rgb, "depth": depth, "K": K, "pose": np.asarray(f.world_from_cam, np.float64)})
    return out


def measure(seq: list[dict[str, Any]], cfg: StereoConfig, every: int, candidates: int) -> dict[str, Any]:
    tcfg = TriangulationConfig()
    h, w = seq[0]["rgb"].shape[:2]
    views = [PosedView(f["K"], f["pose"], w, h) for f in seq]
    grays = [gray_image(f["rgb"]) for f in seq]
    swept: dict[int, np.ndarray] = {}
    errs: dict[str, list[np.ndarray]] = {"swept": [], "consistent": [], "filled": []}
    dens: dict[str, list[float]] = {k: [] for k in errs}
    seconds = []
    for i in range(1, len(seq), every):
        lo = max(0, i - candidates)
        chosen = [lo + j for j in select_partners(views[i], views[lo:i], tcfg)][: cfg.max_sources]
        if len(chosen) < cfg.top_k:
            continue
        truth = seq[i]["depth"]
        # the node sets the range from the keyframe's triangulated points; here from a sparse sample
        # of the true depth (the range only, never the answer)
        span = depth_range(truth[::8, ::8][truth[::8, ::8] > 0], cfg) or (cfg.min_depth_m, cfg.fallback_far_m)
        started = time.perf_counter()
        ref = StereoView(seq[i]["K"], seq[i]["pose"], grays[i])
        sources = [StereoView(seq[c]["K"], seq[c]["pose"], grays[c]) for c in chosen]
        out = sweep_depth(ref, sources, *span, cfg)
        swept[i] = out.depth_m
        others = [(seq[c]["K"], seq[c]["pose"], swept.get(c, np.zeros_like(out.depth_m))) for c in chosen]
        agree, _ = agreeing_views(seq[i]["K"], seq[i]["pose"], out.depth_m, others, cfg.consistency_rel)
        kept = np.where(out.valid & (agree >= cfg.min_agreeing), out.depth_m, 0.0).astype(np.float32)
        filled = fill_depth(grays[i], kept, cfg.prior_fill_px, sigma_gray=cfg.prior_fill_sigma,
                            max_spread=cfg.prior_fill_spread) if cfg.prior_fill_px else kept  # fmt: skip
        seconds.append(time.perf_counter() - started)
        for name, depth in (("swept", out.depth_m), ("consistent", kept), ("filled", filled)):
            m = (depth > 0) & (truth > 0)
            errs[name].append(np.abs(depth[m] - truth[m]) / truth[m])
            dens[name].append(float((depth > 0).mean()))
    row: dict[str, Any] = {"references": len(seconds), "ms_per_reference": 1e3 * float(np.mean(seconds))}
    for name, parts in errs.items():
        e = np.concatenate(parts) if parts else np.zeros(0)
        row[name] = {
            "density": float(np.mean(dens[name])) if dens[name] else 0.0,
            "median_rel": float(np.median(e)) if e.size else None,
            "p90_rel": float(np.quantile(e, 0.9)) if e.size else None,
            "over_10pct": float(np.mean(e > 0.10)) if e.size else None,
            "over_25pct": float(np.mean(e > 0.25)) if e.size else None,
        }
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sim", nargs="*", default=["3:apartment", "9:studio"], help="SEED:STYLE simulated rooms")
    p.add_argument("--frames", type=int, default=240, help="frames of each simulated stream")
    p.add_argument("--every", type=int, default=4, help="every N-th frame is a reference")
    p.add_argument("--candidates", type=int, default=40, help="previous frames a reference may pair with")
    p.add_argument("--real", default=str(REAL), help="ICL-NUIM folder, or 'none'")
    p.add_argument("--real-width", type=int, default=160)
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="StereoConfig overrides")
    p.add_argument("--threads", type=int, default=1, help="OpenCV threads")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    for spec in args.sim:
        seed, _, _style = spec.partition(":")
        if not seed.isdigit():
            raise SystemExit(f"--sim: expected SEED:STYLE with an integer seed, got {spec!r}")
    cv2.setNumThreads(args.threads)
    cfg = StereoConfig()
    kinds = {f.name: type(getattr(cfg, f.name)) for f in fields(cfg)}
    for item in args.set:
        key, _, value = item.partition("=")
        if key not in kinds:
            raise SystemExit(f"--set: unknown stereo setting {key!r}")
        typed = value.lower() in ("1", "true") if kinds[key] is bool else kinds[key](value)
        cfg = replace(cfg, **{key: typed})
    rows = []
    for spec in args.sim:
        seed, _, style = spec.partition(":")
        row = {"sequence": f"sim {style} seed {seed}",
               **measure(sim_sequence(int(seed), style or "apartment", args.frames), cfg, args.every,
                         args.candidates)}  # fmt: skip
        rows.append(row)
        print(json.dumps(row), flush=True)
    if args.real != "none":
        if not Path(args.real).is_dir():
            print(f"real sequence: {args.real} not found, skipped", flush=True)
        else:
            row = {"sequence": f"ICL-NUIM living room 1 at {args.real_width} px",
                   **measure(real_sequence(args.real_width), cfg, max(1, args.every // 2), args.candidates)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    print("\n| sequence | stage | density | median rel. error | p90 | > 10% | > 25% | ms / reference |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        for stage in ("swept", "consistent", "filled"):
            s = r[stage]
            med = "-" if s["median_rel"] is None else f"{100 * s['median_rel']:.1f}%"
            p90 = "-" if s["p90_rel"] is None else f"{100 * s['p90_rel']:.1f}%"
            o10 = "-" if s["over_10pct"] is None else f"{100 * s['over_10pct']:.1f}%"
            o25 = "-" if s["over_25pct"] is None else f"{100 * s['over_25pct']:.1f}%"
            print(f"| {r['sequence']} | {stage} | {100 * s['density']:.1f}% | {med} | {p90} | {o10} | "
                  f"{o25} | {r['ms_per_reference']:.0f} |")
    if args.json:
        args.json.write_text(json.dumps({"config": cfg.__dict__, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
