"""Colour tables and colour maps shared by the CLI outputs (PNG, PLY) and the Rerun logger.

A leaf module (numpy only), so that ``clients.cli.*`` and ``clients.rerun_log`` both use it
without importing each other.

>>> viridis(np.array([0.0, 1.0])).round(3).tolist()
[[0.267, 0.004, 0.329], [0.992, 0.906, 0.145]]
>>> colorize_labels(np.array([[0, -1]])).tolist()
[[[31, 119, 180], [0, 0, 0]]]
"""

from __future__ import annotations

import numpy as np

__all__ = ["LABEL_COLORS", "VIRIDIS", "colorize_depth", "colorize_labels", "score_colours", "viridis"]

LABEL_COLORS = np.array(
    [
        [31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
        [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207],
    ],
    dtype=np.uint8,
)  # fmt: skip
"""Label colours (matplotlib's tab10), cycled for more than 10 texts."""

VIRIDIS = np.array(
    [[68, 1, 84], [72, 40, 120], [62, 74, 137], [49, 104, 142], [38, 130, 142],
     [31, 158, 137], [53, 183, 121], [109, 205, 89], [180, 222, 44], [253, 231, 37]],
    dtype=np.float64,
)  # fmt: skip
"""Anchor colours (0..255) of matplotlib's viridis colormap, evenly spaced."""


def viridis(t: np.ndarray) -> np.ndarray:  # (N,) in [0, 1] -> (N, 3) float64 RGB in [0, 1]
    """Viridis at ``t`` (clipped to [0, 1]), linear between the anchors of :data:`VIRIDIS`."""
    pos = np.clip(np.asarray(t, np.float64), 0.0, 1.0) * (len(VIRIDIS) - 1)
    i0 = np.clip(np.floor(pos).astype(int), 0, len(VIRIDIS) - 2)
    frac = (pos - i0)[..., None]
    return (VIRIDIS[i0] * (1 - frac) + VIRIDIS[i0 + 1] * frac) / 255.0


def score_colours(score: np.ndarray) -> np.ndarray:
    """(N,) scores -> (N, 3) float64 RGB in [0, 1] (viridis over the scores' min..max range)."""
    score = np.asarray(score, np.float64)
    if score.size == 0:
        return np.zeros((0, 3))
    lo, hi = float(score.min()), float(score.max())
    t = (score - lo) / (hi - lo) if hi > lo else np.ones_like(score)
    return viridis(t)


def colorize_depth(depth_m: np.ndarray) -> np.ndarray:  # (H, W) float32 -> (H, W, 3) uint8
    """Viridis over 1/depth (near = yellow, far = dark purple); 0 (no depth) is black."""
    valid = depth_m > 0
    out = np.zeros((*depth_m.shape, 3), np.uint8)
    if not valid.any():
        return out
    inv = 1.0 / depth_m[valid]
    lo, hi = np.percentile(inv, 1), np.percentile(inv, 99)
    t = np.clip((inv - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    out[valid] = np.round(viridis(t) * 255.0).astype(np.uint8)
    return out


def colorize_labels(label: np.ndarray) -> np.ndarray:  # (H, W) int32 -> (H, W, 3) uint8
    """One colour per label index (``LABEL_COLORS`` cycled); -1 is black."""
    out = LABEL_COLORS[np.maximum(label, 0) % len(LABEL_COLORS)]
    out[label < 0] = 0
    return out
