"""Class vocabulary of the simulated scenes: label ids, class names, what a robot may drive over.

>>> CLASS_NAMES[:20] == SCANNET20 and CLASS_NAMES[LABEL_OF["rug"]] == "rug"
True
"""

from __future__ import annotations

SCANNET20: tuple[str, ...] = (
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf",
    "picture", "counter", "desk", "curtain", "refrigerator", "shower curtain", "toilet", "sink",
    "bathtub", "otherfurniture",
)
"""The 20 ScanNet benchmark classes, in the benchmark's order (label ids 0..19)."""

EXTRA_CLASSES: tuple[str, ...] = (
    "ceiling", "lamp", "plant", "monitor", "pillow", "rug", "television", "mirror", "clock",
    "vase", "towel", "trash can",
)
"""Classes outside the ScanNet-20 set (open vocabulary); label ids 20.. in this order."""

CLASS_NAMES: tuple[str, ...] = SCANNET20 + EXTRA_CLASSES
"""Label id -> class name. The ScanNet-20 classes come first, in the same order."""

LABEL_OF: dict[str, int] = {name: i for i, name in enumerate(CLASS_NAMES)}
"""Class name -> label id."""

NON_BLOCKING_CLASSES: frozenset[str] = frozenset({"rug"})
"""Classes a robot may drive over (all other instances are obstacles for trajectories)."""
