"""Which part of an answer is right: the learned window, the averaging's window, or the views that left.

Each scenario of the scenario matrix (``--split`` / ``--index``) is streamed into a node built in
this process as ``govnesf serve`` builds it (default settings, ``--set`` to change one), and once
nothing is pending ``segment_points`` is asked at the ground-truth points with ``govnesf`` and
``average`` (the replies' 3D mIoU). Then, at the points that the window's keyframes see and that
views of keyframes that left the window also count for (the voxels' evicted views and the kept
views: the averaging's ``want_evicted`` answer), three answers are compared, each alone: the learned
model over the window (``govnesf``'s backend, before any mix), the averaging over the window's views
only (no evicted views), and the evicted views' own mean. Printed per scenario: each one's share of
correct labels there, and how often the two window answers agree with the evicted views' (neither
used those views: a held-out check the node could make).

Run (1-2 minutes a scenario on 2 cores)::

    python benchmarks/studies/evicted_evidence.py --split tune --index 10 11 4

Choose settings on tuning seeds only (``seed % 3 != 0``); the held-out split is for the report.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from benchmarks.studies.query_settings import settled_node
from clients.harness import mean_iou
from clients.matrix.driver import RunSettings, prepare
from clients.matrix.scenarios import Scenario, build_matrix
from clients.sim.scenes import CLASS_NAMES


def _labels(cos: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(N,) the best text where ``seen``, -1 elsewhere."""
    return np.where(seen, np.argmax(cos, axis=1), -1) if cos.shape[1] else np.full(seen.shape[0], -1)


def evidence(scenario: Scenario, overrides: dict[str, Any]) -> dict[str, Any]:
    """The figures of one scenario (module docstring)."""
    from mapper.node.queries import segment_average_cosines
    from protocol.messages import Segmentation, SegmentPoints, decode, encode

    prep = prepare(scenario, RunSettings())
    texts, xyz, gt = list(CLASS_NAMES), np.asarray(prep.gt_xyz, np.float32), prep.gt_label
    out: dict[str, Any] = {"scenario": scenario.name}
    with settled_node(prep, overrides) as (node, _):
        for method in ("govnesf", "average"):
            reply = decode(node.handle_query(encode(SegmentPoints(xyz=xyz, texts=texts, method=method))),
                           direction="reply")
            assert isinstance(reply, Segmentation), reply
            out[method] = 100.0 * mean_iou(np.asarray(reply.label, np.int64), gt, len(texts))[0]
        learned = node.segment.backends["govnesf"].segment(
            SegmentPoints(xyz=xyz, texts=texts, method="govnesf"), True)
        averaging = node.segment.backends["average"].segment(  # type: ignore[call-arg]
            SegmentPoints(xyz=xyz, texts=texts, method="average"), True, want_evicted=True)
        with node.ctx.state.lock:
            keyframes = list(node.ctx.state.window.keyframes)
        views = [(k.ov, k.K, k.world_from_cam, (k.width, k.height), k.depth_m) for k in keyframes
                 if k.ov is not None]
        assert averaging.text_emb is not None and learned.cos is not None
        emb = averaging.text_emb
        window_cos, window_views = segment_average_cosines(xyz, views, emb, use_depth=False)
    lab_learned = _labels(learned.cos, learned.answered())
    lab_window = _labels(window_cos, window_views > 0)
    evicted = averaging.evicted_views if averaging.evicted_views is not None else np.zeros(len(gt))
    lab_evicted = (_labels(averaging.evicted_cos, evicted > 0) if averaging.evicted_cos is not None
                   else np.full(len(gt), -1))
    where = (lab_learned >= 0) & (lab_window >= 0) & (lab_evicted >= 0)
    out["points"], out["with_evicted"] = int(len(gt)), int(where.sum())
    if where.any():
        for name, lab in (("learned", lab_learned), ("window_average", lab_window), ("evicted", lab_evicted)):
            out[f"{name}_right"] = float(np.mean(lab[where] == gt[where]))
        out["learned_agrees_evicted"] = float(np.mean(lab_learned[where] == lab_evicted[where]))
        out["window_average_agrees_evicted"] = float(np.mean(lab_window[where] == lab_evicted[where]))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="tune", choices=("tune", "heldout"))
    p.add_argument("--index", type=int, nargs="*", help="scenario indices in the split (default: all)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a node setting (repeat)")
    args = p.parse_args(argv)
    overrides: dict[str, Any] = {}
    for item in args.set:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            p.error(f"--set {item!r}: expected KEY=VALUE")
        try:
            overrides[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            overrides[key.strip()] = raw
    scenarios = build_matrix(args.split)
    try:
        chosen = [scenarios[i] for i in args.index] if args.index else scenarios
    except IndexError:
        p.error(f"--index: the {args.split} split has {len(scenarios)} scenarios")
    for scenario in chosen:
        row = evidence(scenario, overrides)
        print(json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
