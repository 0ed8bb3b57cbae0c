"""One shape-check vocabulary for every op (after kornia's ``KORNIA_CHECK_SHAPE``).

``check_shape(x, "N 3", "points")`` raises :class:`ShapeError` with one wording everywhere::

    points: expected shape (N, 3), got (5, 4)

A spec is a space-separated list of dimensions: a number must match exactly, a name matches any
size (and the same name must have the same size wherever it appears in one call, or across calls
that share a ``dims`` dict), ``*`` matches any number of leading dimensions (only first), and
``a|b`` accepts either number. Messages write ``*`` as ``...``, the docstrings' notation
(``(..., 4, 4)``). Works on anything with a ``.shape`` (torch tensors, numpy arrays); imports
neither.

Checks are on by default; ``GOVNESF_SHAPE_CHECKS=0`` in the environment (read at import) turns
them off for speed, as kornia's switch does. They guard the model's public entry points; inputs
from the wire are validated earlier, by ``protocol/``.

>>> import numpy as np
>>> check_shape(np.zeros((5, 3)), "N 3", "points")
{'N': 5}
>>> check_shape(np.zeros((2, 7, 4, 4)), "* 4 4", "world_from_cam")
{}
>>> check_shape(np.zeros((3, 3)), "* 4 4", "world_from_cam")
Traceback (most recent call last):
...
mapper.checks.ShapeError: world_from_cam: expected shape (..., 4, 4), got (3, 3)
>>> check_shape(np.zeros((5, 4)), "N 3", "points")
Traceback (most recent call last):
...
mapper.checks.ShapeError: points: expected shape (N, 3), got (5, 4)
>>> dims = check_shape(np.zeros((5, 3)), "N 3", "points")
>>> check_shape(np.zeros((6,)), "N", "weights", dims)
Traceback (most recent call last):
...
mapper.checks.ShapeError: weights: expected shape (N,) with N = 5, got (6,)
"""

from __future__ import annotations

import os
from typing import Any

__all__ = ["CHECKS_ENABLED", "ShapeError", "check_range", "check_shape", "format_spec"]

CHECKS_ENABLED = os.environ.get("GOVNESF_SHAPE_CHECKS", "1") not in ("0", "false", "off")
"""Global switch (environment ``GOVNESF_SHAPE_CHECKS=0`` turns every check off)."""


class ShapeError(ValueError):
    """An array or tensor has the wrong shape; the message names it, the expected and the actual shape."""


def format_spec(tokens: list[str]) -> str:
    """``["N", "3"]`` -> ``"(N, 3)"``, ``["*", "4"]`` -> ``"(..., 4)"``; a single dimension keeps its
    trailing comma."""
    shown = ["..." if t == "*" else t for t in tokens]
    return "(" + ", ".join(shown) + ("," if len(shown) == 1 else "") + ")"


def check_shape(x: Any, spec: str, name: str, dims: dict[str, int] | None = None) -> dict[str, int]:
    """Check ``x.shape`` against ``spec``; return (and extend) ``dims``, the sizes bound to names.

    Raises:
        ShapeError: naming ``name``, the expected shape and the shape received.
    """
    dims = {} if dims is None else dims
    if not CHECKS_ENABLED:
        return dims
    tokens = spec.split()
    shape = tuple(int(s) for s in x.shape)
    star = bool(tokens) and tokens[0] == "*"
    fixed = tokens[1:] if star else tokens
    if "*" in fixed:
        raise ValueError(f"shape spec {spec!r}: '*' may only come first")

    def fail(extra: str = "") -> ShapeError:
        return ShapeError(f"{name}: expected shape {format_spec(tokens)}{extra}, got {shape}")

    if len(shape) < len(fixed) or (not star and len(shape) != len(fixed)):
        raise fail()
    actual = shape[len(shape) - len(fixed):]
    bound: dict[str, int] = {}
    for token, size in zip(fixed, actual, strict=True):
        if token[0].isdigit():
            if size not in {int(t) for t in token.split("|")}:
                raise fail()
        else:
            want = dims.get(token, bound.get(token))
            if want is not None and want != size:
                raise fail(f" with {token} = {want}")
            bound[token] = size
    dims.update(bound)
    return dims


def check_range(where: str, key: str, value: float, lo: float, hi: float) -> None:
    """A config value within ``lo..hi``, else :class:`mapper.errors.ConfigError` naming ``where``,
    the key, the value and the range (the config dataclasses' ``validate``)."""
    if not lo <= value <= hi:
        from mapper.errors import ConfigError

        raise ConfigError(f"{where}: {key} = {value!r} out of range {lo}..{hi}")
