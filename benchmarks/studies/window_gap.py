"""Where the window loses against every keyframe: a scenario's points by the reply's ``source``.

One scenario of the scenario matrix (``clients.matrix``: a split and an index, or any combination
of its axes given as JSON) is streamed, as the matrix does, into a node at the default window and
into the same node holding every keyframe; once both settled, ``segment_points`` at the
ground-truth surface points for ``average``, ``govnesf`` and DGM (``govnesf`` with
``use_depth``). For each method it prints the 3D mIoU of both nodes, the classes behind the gap,
and, by the window node's ``source`` (0 none, 1 window, 2 map), how many points and how many of
them each node labels correctly, with the every-keyframe node's sources for the same points: a gap
from points nothing answers (no map point near) reads differently from one where the window's own
views answer worse.

Run (a few minutes a scenario on 2 cores)::

    python benchmarks/studies/window_gap.py --split tune --index 6
    python benchmarks/studies/window_gap.py --scenario '{"seed": 7, "layout": "corridor", "path": "sparse",
        "width": 160, "height": 120, "hfov_deg": 70, "effect": "jpeg", "pose_error": "noise_3cm",
        "ov_noise": "calibrated", "depth": true}' --set queries.evicted_views=off

Choose settings on tuning seeds only (``seed % 3 != 0``); the held-out split is for the report.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np

from clients.harness import mean_iou
from clients.matrix.driver import RunSettings, _settle, node_client, prepare, stream
from clients.matrix.scenarios import FRAMES, Scenario, build_matrix
from clients.sim.scenes import CLASS_NAMES

METHODS = (("average", "average", False), ("govnesf", "govnesf", False), ("dgm", "govnesf", True))
"""(name, ``segment_points`` method, ``use_depth``) asked of both nodes."""


def scenario_of(args: argparse.Namespace) -> Scenario:
    """The scenario the arguments name (``--scenario`` JSON, else ``--split`` / ``--index``)."""
    if args.scenario:
        spec = json.loads(args.scenario)
        return Scenario(index=99, frames=FRAMES[spec["path"]], **spec)
    return build_matrix(args.split)[args.index]


def answers(
    scenario: Scenario, prep: Any, which: str, settings: list[str]
) -> dict[str, tuple[np.ndarray, ...]]:
    """(label, source) per method of a fresh node (``window`` or ``all``) once settled."""
    out: dict[str, tuple[np.ndarray, ...]] = {}
    run = RunSettings(node_settings=tuple(settings))
    with node_client(scenario, which, run) as client:
        stream(client, prep)
        _settle(client, run.settle_timeout_s)
        for name, method, use_depth in METHODS:
            seg = client.segment_points(prep.gt_xyz, list(CLASS_NAMES), method=method,
                                        use_depth=use_depth, timeout_s=run.request_timeout_s)
            out[name] = (seg.label.astype(np.int64), np.asarray(seg.source))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="tune", choices=("tune", "heldout"))
    p.add_argument("--index", type=int, default=0, help="the scenario's index in the split")
    p.add_argument("--scenario", default="", help="a scenario as JSON (every axis but index and frames)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a node setting (repeat)")
    p.add_argument("--save", default="", metavar="NPZ", help="also write both nodes' labels and sources here")
    args = p.parse_args(argv)
    for item in args.set:
        if "=" not in item or not item.split("=", 1)[0].strip():
            p.error(f"--set {item!r}: expected KEY=VALUE")
    try:
        scenario = scenario_of(args)
    except (ValueError, KeyError, TypeError, IndexError) as exc:  # bad JSON, a missing axis, no such index
        p.error(f"no such scenario ({type(exc).__name__}: {exc}); give --split/--index within the split "
                "or --scenario with every axis but index and frames")
    print(scenario.name, flush=True)
    prep = prepare(scenario, RunSettings())
    got = {which: answers(scenario, prep, which, args.set) for which in ("window", "all")}
    gt, n_texts = prep.gt_label, len(CLASS_NAMES)
    if args.save:
        np.savez_compressed(args.save, gt=gt, xyz=prep.gt_xyz, **{
            f"{which}_{method}_{part}": got[which][method][k]
            for which in got for method, _, _ in METHODS for k, part in enumerate(("label", "source"))})
    for method, _, _ in METHODS:
        (lw, sw), (la, sa) = got["window"][method], got["all"][method]
        (m_w, iou_w), (m_a, iou_a) = mean_iou(lw, gt, n_texts), mean_iou(la, gt, n_texts)
        print(f"{method}: mIoU window {100 * m_w:.1f}, every keyframe {100 * m_a:.1f}")
        print("  classes by their share of the gap (IoU window / every keyframe, points): " + ", ".join(
            f"{CLASS_NAMES[c]} {100 * iou_w[c]:.0f}/{100 * iou_a[c]:.0f} ({int(np.sum(gt == c))})"
            for c in sorted(iou_w, key=lambda c: iou_w[c] - iou_a[c])[:5]))
        for source, name in enumerate(("none", "window", "map")):
            sel = sw == source
            if not sel.any():
                continue
            right_w, right_a = np.mean(lw[sel] == gt[sel]), np.mean(la[sel] == gt[sel])
            print(f"  window node source {name}: {int(sel.sum())} points, correct {right_w:.3f} "
                  f"(every keyframe {right_a:.3f}; its sources {np.bincount(sa[sel], minlength=3).tolist()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
