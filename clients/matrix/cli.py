"""``govnesf matrix``: run the scenario matrix (docs/how-to/scenario-matrix.md).

    govnesf matrix --split heldout --out matrix-heldout      # the reported matrix (~30 min, 2 cores)
    govnesf matrix --quick --out /tmp/matrix-quick           # two tiny scenarios, about a minute
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from clients.matrix.driver import RunSettings, run_scenario
from clients.matrix.report import write_outputs
from clients.matrix.scenarios import DEFAULT_SCENARIOS, SPLITS, build_matrix, quick_matrix


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="govnesf matrix", description=__doc__.split("\n\n")[0])
    p.add_argument("--split", choices=SPLITS, default="heldout",
                   help="seeds: heldout (seed %% 3 == 0), tune (the others) or all")
    p.add_argument("--scenarios", type=int, default=DEFAULT_SCENARIOS, help="scenarios per split")
    p.add_argument("--quick", action="store_true", help="two tiny scenarios (tests, a first look)")
    p.add_argument("--only", default="", help="comma-separated scenario indices to run (default: all)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--gt-samples", type=int, default=None, help="ground-truth surface samples per room")
    p.add_argument("--min-class-points", type=int, default=None,
                   help="each class seen is asked at no fewer points (samples on its own surfaces; "
                        "default 50, quick 10; 0: area-uniform samples only)")
    p.add_argument("--settle-timeout", type=float, default=120.0,
                   help="longest wait for the node to settle, s")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="node_set",
                   help="a node setting for every node of the run (as `govnesf serve --set`), to compare "
                        "a setting on the tuning split; repeatable")
    args = p.parse_args(argv)
    for item in args.node_set:
        if "=" not in item or not item.split("=", 1)[0].strip():
            p.error(f"--set {item!r}: expected KEY=VALUE")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    scenarios = quick_matrix() if args.quick else build_matrix(args.split, args.scenarios)
    if args.only:
        try:
            keep = {int(x) for x in args.only.split(",") if x.strip()}
        except ValueError:
            p.error(f"--only {args.only!r}: expected comma-separated integers")
        scenarios = [s for s in scenarios if s.index in keep]
    gt = args.gt_samples or (1500 if args.quick else 6000)
    min_class = args.min_class_points if args.min_class_points is not None else (10 if args.quick else 50)
    if gt < 1 or min_class < 0:
        p.error(f"--gt-samples {gt} must be >= 1 and --min-class-points {min_class} >= 0")
    settings = RunSettings(gt_samples=gt, min_class_points=min_class, novel_views=1 if args.quick else 3,
                           settle_timeout_s=args.settle_timeout, log_dir=args.out / "logs",
                           node_settings=tuple(args.node_set))
    args.out.mkdir(parents=True, exist_ok=True)
    settings.log_dir.mkdir(exist_ok=True)  # type: ignore[union-attr]
    lines = args.out / "scenarios.jsonl"
    lines.write_text("")
    rows = []
    started = time.perf_counter()
    for i, s in enumerate(scenarios):
        print(f"[{i + 1}/{len(scenarios)}] {s.name}", flush=True)
        row = run_scenario(s, settings, progress=lambda msg: print(f"    {msg}", flush=True))
        rows.append(row)
        with lines.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(f"    done in {row['wall_s']:.0f} s ({time.perf_counter() - started:.0f} s so far)", flush=True)
    header = (f"Scenario matrix: split {'quick' if args.quick else args.split}, {len(rows)} scenarios, "
              f"{time.perf_counter() - started:.0f} s.\n")
    paths = write_outputs(rows, args.out, header)
    print(paths["markdown"].read_text())
    print("wrote " + ", ".join(str(v) for v in [lines, *paths.values()]), file=sys.stderr)
    return 0
