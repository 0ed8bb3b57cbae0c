"""``govnesf serve``: run the mapper node until SIGINT/SIGTERM.

Configuration comes from a TOML file (``--config``, default ``launch/node.toml`` of the repo or of
the installed wheel, or the built-in defaults when that file is absent), then command-line overrides::

    govnesf serve --config launch/node.toml --ingest tcp://127.0.0.1:6000 --map-dir /data/maps \\
        --set window.max_keyframes=20 --set autosave_name=latest

On a robot's network, with CurveZMQ (keys from ``govnesf keys DIR``; docs/how-to/robot-network.md)::

    govnesf serve --config launch/node_robot.toml --curve-dir /etc/govnesf/keys
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

from govnesf._compat import tomllib
from mapper.node.config import DEFAULT_CONFIG_PATH, ConfigError, load_config


def _parse_set(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` pairs; VALUE is parsed as a TOML value, falling back to a plain string."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. --set window.max_keyframes=20")
        try:
            value = tomllib.loads(f"x = {raw}")["x"]
        except tomllib.TOMLDecodeError:
            value = raw
        out[key.strip()] = value
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="govnesf serve", description="Run the GOV-NeSF mapper node.")
    parser.add_argument(
        "--config", help=f"TOML config file (default: {DEFAULT_CONFIG_PATH}, or built-in defaults)"
    )
    parser.add_argument("--ingest", metavar="EP", help="ingest endpoint, e.g. tcp://127.0.0.1:5555")
    parser.add_argument("--query", metavar="EP", help="query endpoint, e.g. tcp://127.0.0.1:5556")
    parser.add_argument("--events", metavar="EP", help='events PUB endpoint; "" disables it')
    parser.add_argument("--map-dir", metavar="DIR", help="directory for saved maps")
    parser.add_argument(
        "--curve-dir", metavar="DIR",
        help="serve with CurveZMQ: keys made by `govnesf keys DIR`; only clients in DIR/allowed/ get "
        "through (docs/how-to/robot-network.md)",
    )
    parser.add_argument(
        "--insecure", action="store_true", default=None,
        help="allow non-loopback binds without --curve-dir (unauthenticated; logged and in status)",
    )
    parser.add_argument(
        "--set", metavar="KEY=VALUE", action="append", default=[],
        help="override any config key (dotted for tables), e.g. window.max_keyframes=20; repeatable",
    )
    parser.add_argument("--log-level", choices=("DEBUG", "INFO", "WARNING", "ERROR"), help="logging level")
    parser.add_argument(
        "--check-config", action="store_true",
        help="validate the config (file and overrides), print 'config ok' and exit without serving",
    )
    return parser


def serve_main(argv: list[str] | None = None) -> int:
    """Entry point of ``govnesf serve``; returns the process exit code."""
    args = build_parser().parse_args(argv)
    try:
        overrides: dict[str, Any] = _parse_set(args.set)
        overrides.update(
            {
                "ingest_endpoint": args.ingest,
                "query_endpoint": args.query,
                "events_endpoint": args.events,
                "map_dir": args.map_dir,
                "curve_dir": args.curve_dir,
                "insecure": args.insecure,
                "log_level": args.log_level,
            }
        )
        config = load_config(args.config, overrides)
    except ConfigError as exc:
        print(f"govnesf serve: {exc}", file=sys.stderr)
        return 2
    if args.check_config:
        print("config ok")
        return 0
    logging.basicConfig(
        level=config.log_level.upper(),
        format="%(asctime)s.%(msecs)03d %(levelname)-7s %(threadName)s %(name)s: %(message)s",
        datefmt="%Y-%m-%dT%H:%M:%S",
        stream=sys.stderr,
    )
    from mapper.node.serve import install_serve_stages
    from mapper.node.service import MapperNode  # after logging is set up

    node = MapperNode(config)
    install_serve_stages(node)  # learned model, triangulation, OV backend (from the config)
    node.install_signal_handlers()
    try:
        node.start()
    except RuntimeError as exc:
        logging.getLogger("mapper.node.cli").error("%s", exc)
        return 3
    return node.run()


if __name__ == "__main__":
    raise SystemExit(serve_main())
