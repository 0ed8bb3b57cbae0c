"""The `govnesf` command: a thin dispatcher to the subcommands' own entry points.

Each subcommand lives in its own module and exposes ``main(argv: list[str]) -> int``.
Modules are imported lazily so that ``govnesf replay`` does not import torch. ``govnesf --version``
prints the distribution's version; a subcommand that needs an uninstalled extra (``govnesf sim``
without ``govnesf[sim]``) exits with code 2 and a message naming the extra.
"""

from __future__ import annotations

import importlib
import sys

from govnesf import __version__
from govnesf._extras import MissingExtraError

# subcommand -> (module, function, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str, str]] = {
    "serve": ("mapper.node.cli", "serve_main", "run the mapper node"),
    "replay": ("clients.replay", "main", "replay a .govrec recording into a node"),
    "status": ("clients.cli.query", "status_main", "print a node's status"),
    "save": ("clients.cli.query", "save_main", "save a node's map in its map directory"),
    "load": ("clients.cli.query", "load_main", "load a saved map into a node"),
    "query": ("clients.cli.query", "query_main", "find points and objects matching texts"),
    "import": ("clients.importers.cli", "main", "convert a dataset folder to .govrec"),
    "sim": ("clients.sim.cli", "main", "simulated robot: record or stream procedural rooms"),
    "render": ("clients.cli.render", "main", "render a view from a node"),
    "keys": ("clients.cli.keys", "main", "make CurveZMQ keys for a node and its clients"),
    "bench": ("clients.cli.bench", "main", "start a node, measure it, write JSON + Markdown"),
    "evaluate": ("mapper.training.cli_eval", "main", "evaluate the model against baselines"),
    "matrix": ("clients.matrix.cli", "main", "score nodes on a matrix of held-out scenarios"),
    "train": ("mapper.training.cli_train", "main", "train the GOV-NeSF model"),
    "distill-point-head": ("mapper.training.point_head", "main",
                           "distill a smaller FusionNet for point answers from a checkpoint"),
}


def _usage() -> str:
    lines = ["usage: govnesf <command> [options]   (govnesf --version)", "", "commands:"]
    for name, (_, _, help_) in SUBCOMMANDS.items():
        lines.append(f"  {name:<18} {help_}")
    lines.append("")
    lines.append("Run `govnesf <command> --help` for a command's options.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(_usage())
        return 0 if args else 2
    if args[0] in ("-V", "--version"):
        print(f"govnesf {__version__}")
        return 0
    name, rest = args[0], args[1:]
    if name not in SUBCOMMANDS:
        print(f"govnesf: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name, func_name, _ = SUBCOMMANDS[name]
    try:
        func = getattr(importlib.import_module(module_name), func_name)
        return int(func(rest) or 0)
    except MissingExtraError as exc:
        print(f"govnesf {name}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
