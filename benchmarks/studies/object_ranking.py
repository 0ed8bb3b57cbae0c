"""How ``query_points`` ranks the objects it finds, compared on the same maps: scenario-matrix
streams, one settled node each, every variant of the object settings asked of the same map.

Object settings (``queries.object_vocabulary_temperature``, ``queries.object_support_points``, ...)
are read when a ``query_points`` is answered, so their variants are compared on one map per
scenario (a paired comparison, without the run-to-run noise of two streams): each scenario of the
scenario matrix (``clients.matrix``) is prepared as the matrix prepares it and streamed into a node
built in this process as ``govnesf serve`` builds it (``query_settings.settled_node``); once nothing
is pending, "find the <class>" is asked for the classes the matrix asks in that room (the chair and
two others) under each variant, on the node's map snapshot (:func:`mapper.node.queries.query_points`
with the variant's ``[queries]`` settings). An object counts as found when the top object lies within
``FOUND_RADIUS_M`` of an instance of the class, as in the matrix. Prints per scenario and variant the
top object's distance per class, then per variant how many chairs and how many of all the objects
asked were found, with and without depth.

Run (1-2 minutes a scenario on 2 cores)::

    python benchmarks/studies/object_ranking.py --split tune \\
        --variants '{"off": {"object_vocabulary_temperature": 0.0},
                     "t05": {"object_vocabulary_temperature": 0.05}}'

Choose settings on tuning seeds only (``--split tune``); the held-out split is for the report.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Any

from clients.harness import chair_distance
from clients.matrix.driver import FOUND_RADIUS_M, RunSettings, prepare
from clients.matrix.scenarios import build_matrix

sys.path.insert(0, str(Path(__file__).resolve().parent))  # its sibling, run as a file or imported
from query_settings import parse_variants, settled_node  # noqa: E402


def found_objects(scenario: Any, variants: dict[str, dict[str, Any]], overrides: dict[str, Any]
                  ) -> dict[str, dict[str, float | None]]:
    """Per variant, the top object's distance (m) to an instance of each class asked (None: no
    object)."""
    from mapper.node.queries import query_points
    from mapper.ov.encoders import get_text_encoder

    prep = prepare(scenario, RunSettings(gt_samples=500, min_class_points=0))
    out: dict[str, dict[str, float | None]] = {}
    with settled_node(prep, overrides) as (node, took):
        print(f"{scenario.name}: streamed and settled in {took:.0f} s", flush=True)
        snapshot = node.ctx.state.global_map.snapshot()
        encoder = get_text_encoder(prep.frames[0].ov_space)
        base = node.ctx.config.queries
        for name, settings in variants.items():
            config = dataclasses.replace(base, **settings)
            row: dict[str, float | None] = {}
            for cls in prep.object_classes:
                reply = query_points(snapshot, encoder, [f"find the {cls}"], negatives=None, min_score=None,
                                     max_points=None, objects=True, config=config)
                dist = (chair_distance(reply.objects[0].centroid, prep.stream.scene, cls)
                        if reply.objects else math.inf)
                row[cls] = dist if math.isfinite(dist) else None
            out[name] = row
    return out


def tally(rows_by_scenario: list[tuple[bool, dict[str, dict[str, float | None]]]]
          ) -> dict[str, dict[str, list[int]]]:
    """Per variant, ``[found, asked]`` for the chair and for every class asked, with depth (``d``)
    and without (``rgb``), from each scenario's (depth, :func:`found_objects`) rows; found = the top
    object within ``FOUND_RADIUS_M``."""
    out: dict[str, dict[str, list[int]]] = {}
    for depth, rows in rows_by_scenario:
        kind = "d" if depth else "rgb"
        for name, row in rows.items():
            counts = out.setdefault(name, {k: [0, 0] for k in ("chair d", "chair rgb", "all d", "all rgb")})
            for cls, d in row.items():
                hit = int(d is not None and d <= FOUND_RADIUS_M)
                for key in ([f"chair {kind}"] if cls == "chair" else []) + [f"all {kind}"]:
                    counts[key][0] += hit
                    counts[key][1] += 1
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="tune", choices=("tune", "heldout"))
    p.add_argument("--index", type=int, nargs="*", help="scenario indices in the split (default: all)")
    p.add_argument("--variants", required=True, help='JSON: {"name": {"queries_field": value}}')
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a node setting (repeat)")
    p.add_argument("--out", default="", help="also write the rows here (JSON lines)")
    args = p.parse_args(argv)
    try:
        variants = parse_variants(args.variants)
    except ValueError as exc:
        p.error(str(exc))
    from mapper.node.cli import _parse_set  # KEY=VALUE as `govnesf serve --set` reads them
    from mapper.node.config import ConfigError

    try:
        overrides: dict[str, Any] = _parse_set(args.set)
    except ConfigError as exc:
        p.error(str(exc))
    scenarios = build_matrix(args.split)
    try:
        chosen = [scenarios[i] for i in args.index] if args.index else scenarios
    except IndexError:
        p.error(f"--index: the {args.split} split has {len(scenarios)} scenarios")
    seen: list[tuple[bool, dict[str, dict[str, float | None]]]] = []
    for scenario in chosen:
        rows = found_objects(scenario, variants, overrides)
        seen.append((scenario.depth, rows))
        for name, row in rows.items():
            print(f"  {name:>10}: " + ", ".join(
                f"{cls} {'-' if d is None else f'{d:.2f} m'}" for cls, d in row.items()), flush=True)
        if args.out:
            with open(args.out, "a", encoding="utf-8") as fh:
                record = {"scenario": scenario.name, "depth": scenario.depth, "rows": rows}
                fh.write(json.dumps(record) + "\n")
    print(f"\nfound within {FOUND_RADIUS_M:.2f} m (found / asked):")
    for name, counts in tally(seen).items():
        print(f"  {name:>10}: " + ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in counts.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
