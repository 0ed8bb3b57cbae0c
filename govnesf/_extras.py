"""Optional dependencies: import them by name and fail with the extra that installs them.

``pip install govnesf`` installs the core (protocol, client library, node, learned model, text
queries). Everything else lives in an extra (``pyproject.toml``,
docs/getting-started/install.md); code that needs one imports it through :func:`require`, so a
missing package says which extra to install::

    o3d = require("open3d", "sim", "the simulator's ray casting")
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["EXTRAS", "MissingExtraError", "require"]

EXTRAS: dict[str, str] = {
    "sim": "the simulated robot and world (Open3D ray casting, trimesh mesh export)",
    "rerun": "logging to the Rerun viewer (--rerun FILE.rrd)",
    "import": "dataset and bag importers beyond the core's image formats",
    "clip": "the in-process CLIP feature backend (its BPE tokenizer)",
    "bench": "the benchmarks' PNG plots (matplotlib)",
}
"""Extra name -> what it adds (the keys are ``[project.optional-dependencies]`` of pyproject.toml)."""


class MissingExtraError(ImportError):
    """An optional package is not installed; the message names the extra that installs it."""

    def __init__(self, module: str, extra: str, purpose: str = "") -> None:
        what = purpose or EXTRAS.get(extra, f"the [{extra}] features")
        super().__init__(
            f"{module!r} is not installed; it is needed for {what}. Install the extra: "
            f"pip install 'govnesf[{extra}]' (or 'govnesf[all]')",
            name=module,
        )
        self.module = module
        self.extra = extra


def require(module: str, extra: str, purpose: str = "") -> ModuleType:
    """Import ``module`` (dotted names allowed) or raise :class:`MissingExtraError` naming ``extra``.

    Only a missing ``module`` (or one of its parent packages) becomes a MissingExtraError; any
    other ImportError raised while importing it (a broken install, a missing shared library) is
    re-raised unchanged, since installing the extra again would not fix it.
    """
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; extras: {', '.join(EXTRAS)}")
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        parts = module.split(".")
        missing = {".".join(parts[: i + 1]) for i in range(len(parts))}
        if exc.name not in missing:
            raise
        raise MissingExtraError(module, extra, purpose) from exc
