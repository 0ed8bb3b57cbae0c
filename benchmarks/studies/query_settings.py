"""Answer-time settings compared on the same maps: scenario-matrix streams, one node each, every
variant of the ``[queries]`` settings asked of the same settled node.

Settings read when a request is answered (``queries.learned_evicted_views``,
``queries.evicted_views_learned_weight``, ``queries.map_blend``, ...) do not change what the node
builds, so their variants are compared here on one map per scenario, a paired comparison without
the run-to-run noise of two streams: each scenario of the scenario matrix (``clients.matrix``) is
prepared as the matrix prepares it, streamed into a node built in this process as ``govnesf
serve`` builds it (default settings, ``--set`` to change one), and once nothing is pending,
``segment_points`` at the ground-truth surface points is asked with every method under each
variant (the node's ``queries`` settings replaced in place between variants). Prints the 3D mIoU
per scenario and variant (``average`` / ``govnesf`` / ``average_depth`` / DGM), then per variant
the median and worst scenario of ``govnesf`` - ``average``, DGM - ``average_depth`` (streams with
depth) and of each method against the first variant.

Run (2-4 minutes a scenario on 2 cores)::

    python benchmarks/studies/query_settings.py --split tune \\
        --variants '{"off": {"learned_evicted_views": 0.0}, "on": {"learned_evicted_views": 0.5}}'
    python benchmarks/studies/query_settings.py --split tune --index 3 6 \\
        --variants '{"w1": {"map_blend": 1.0}}'

Choose settings on tuning seeds only (``--split tune``); the held-out split is for the report.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import tempfile
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from clients.harness import mean_iou
from clients.matrix.driver import RunSettings, prepare
from clients.matrix.scenarios import Scenario, build_matrix
from clients.sim.scenes import CLASS_NAMES

METHODS = (("average", False), ("govnesf", False), ("average_depth", True), ("govnesf", True))
NAMES = ("average", "govnesf", "average_depth", "dgm")
LEADS = (("govnesf - average", ("govnesf", "average")), ("dgm - average_depth", ("dgm", "average_depth")))
SETTLE_TIMEOUT_S = 600.0


def parse_variants(text: str) -> dict[str, dict[str, Any]]:
    """``{"name": {"queries_field": value}}`` from JSON, each field checked against
    :class:`mapper.node.config.QueryConfig`; ``ValueError`` naming what is wrong."""
    from mapper.node.config import ConfigError, QueryConfig

    try:
        variants = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--variants is not JSON: {exc}") from None
    if not (isinstance(variants, dict) and variants and all(isinstance(v, dict) for v in variants.values())):
        raise ValueError('--variants must be an object of objects: {"name": {"field": value}}')
    fields = {f.name for f in dataclasses.fields(QueryConfig)}
    for name, settings in variants.items():
        unknown = sorted(set(settings) - fields)
        if unknown:
            raise ValueError(f"variant {name!r}: {', '.join(unknown)} not a [queries] setting")
        try:  # values in range, before anything streams
            dataclasses.replace(QueryConfig(), **settings).validate(f"variant {name!r}")
        except (ConfigError, TypeError) as exc:
            raise ValueError(str(exc)) from None
    return variants


@contextlib.contextmanager
def settled_node(prep: Any, overrides: dict[str, Any]) -> Iterator[tuple[Any, float]]:
    """A node built in this process as ``govnesf serve`` builds it (default settings and
    ``overrides``, dotted keys), the prepared scenario (:func:`clients.matrix.driver.prepare`)
    streamed into it and nothing pending (at most ``SETTLE_TIMEOUT_S``): yields (the node, seconds
    to stream and settle); stopped on exit."""
    from mapper.node.config import load_config
    from mapper.node.serve import install_serve_stages
    from mapper.node.service import MapperNode
    from protocol.messages import encode

    with tempfile.TemporaryDirectory(prefix="govnesf-study-") as tmp:
        cfg = load_config(None, {
            "map_dir": tmp, "autosave_name": "", "save_on_exit": False, "load_autosave_on_start": False,
            "ingest_endpoint": f"ipc://{tmp}/ingest", "query_endpoint": f"ipc://{tmp}/query",
            "events_endpoint": "", **overrides,
        })  # fmt: skip
        node = MapperNode(cfg)
        install_serve_stages(node)
        node.start()
        try:
            started = time.perf_counter()
            for frame in prep.frames:
                node.handle_ingest(encode(frame))
            while not node.ctx.settled() and time.perf_counter() - started < SETTLE_TIMEOUT_S:
                time.sleep(0.5)
            yield node, time.perf_counter() - started
        finally:
            node.stop()


def answer_variants(
    scenario: Scenario, variants: dict[str, dict[str, Any]], overrides: dict[str, Any]
) -> dict[str, dict[str, float]]:
    """Per variant, the 3D mIoU of each method (``NAMES``; the depth-tested ones only where
    the node answers them) on one settled node streamed with ``scenario``."""
    from protocol.messages import Segmentation, SegmentPoints, decode, encode

    prep = prepare(scenario, RunSettings())
    out: dict[str, dict[str, float]] = {}
    with settled_node(prep, overrides) as (node, took):
        print(f"{scenario.name}: streamed and settled in {took:.0f} s", flush=True)
        queries = node.ctx.config.queries
        defaults = {k: getattr(queries, k) for v in variants.values() for k in v}
        for name, settings in variants.items():
            for key, value in {**defaults, **settings}.items():
                object.__setattr__(queries, key, value)  # frozen: replaced in place between variants
            queries.validate("--variants")
            scores: dict[str, float] = {}
            for label, (method, use_depth) in zip(NAMES, METHODS, strict=True):
                msg = SegmentPoints(xyz=prep.gt_xyz, texts=list(CLASS_NAMES), method=method,  # type: ignore[arg-type]
                                    use_depth=use_depth)
                reply = decode(node.handle_query(encode(msg)), direction="reply")
                if isinstance(reply, Segmentation):
                    pred = np.asarray(reply.label, np.int64)
                    scores[label] = 100.0 * mean_iou(pred, prep.gt_label, len(CLASS_NAMES))[0]
            out[name] = scores
            print(f"  {name:>12}: " + "  ".join(f"{k} {v:.1f}" for k, v in scores.items()), flush=True)
    return out


def summary(results: dict[str, dict[str, dict[str, float]]], depth: dict[str, bool]) -> list[str]:
    """Lines: per variant, median and worst over scenarios of the learned methods' lead over the
    averaging and of each method against the first variant."""
    names = list(next(iter(results.values())))
    lines = []
    for variant in names:
        parts = []
        for lead, (a, b) in LEADS:
            xs = [r[variant][a] - r[variant][b] for s, r in results.items()
                  if a in r[variant] and b in r[variant] and (b != "average_depth" or depth[s])]
            if xs:
                parts.append(f"{lead} median {np.median(xs):+.2f} worst {min(xs):+.2f}")
        for method in NAMES:
            xs = [r[variant][method] - r[names[0]][method] for r in results.values()
                  if method in r[variant] and method in r[names[0]]]
            if xs and variant != names[0]:
                parts.append(f"{method} vs {names[0]} median {np.median(xs):+.2f} worst {min(xs):+.2f}")
        lines.append(f"{variant}: " + "; ".join(parts))
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="tune", choices=("tune", "heldout"))
    p.add_argument("--index", type=int, nargs="*", help="scenario indices in the split (default: all)")
    p.add_argument("--variants", required=True, help='JSON {"name": {"queries_field": value}}; "base" '
                   "(the node's settings) is compared first")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a node setting for every run, VALUE as JSON (repeat)")
    args = p.parse_args(argv)
    try:
        variants = {"base": {}, **parse_variants(args.variants)}
        bad = [item for item in args.set if "=" not in item]
        if bad:
            raise ValueError(f"--set {bad[0]!r}: expected KEY=VALUE")
        overrides = {k: json.loads(v) for k, v in (item.split("=", 1) for item in args.set)}
    except ValueError as exc:  # JSONDecodeError is one; a --set without "="
        p.error(str(exc))
    matrix = build_matrix(args.split)
    indices = args.index if args.index else list(range(len(matrix)))
    bad = [i for i in indices if not 0 <= i < len(matrix)]
    if bad:
        p.error(f"--index {bad}: the {args.split} split has {len(matrix)} scenarios")
    results, depth = {}, {}
    for i in indices:
        scenario = matrix[i]
        results[scenario.name] = answer_variants(scenario, variants, overrides)
        depth[scenario.name] = scenario.depth
    for line in summary(results, depth):
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
