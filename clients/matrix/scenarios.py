"""The matrix's axes, the sample of their combinations and the split of the seeds.

Every scenario is one combination of a level per axis. A full factorial would be thousands of
scenarios; instead each axis's levels are repeated to fill the ``n`` scenarios and shuffled per
axis (a Latin-hypercube-like sample): every level of every axis appears ``n / levels`` times,
give or take one. Resolution is weighted: 640x480 once per 12 scenarios, 320x240 twice, the rest
160x120 (the big ones are slow).

Seeds: a scenario's seed (its room, its path, its noise) is held out when ``seed % 3 == 0`` and
in the tuning set otherwise. Thresholds and training choices are made on ``tune`` only; the
``heldout`` split is what the docs report. The sample itself is drawn with a fixed generator per
split, so ``--split heldout`` always gives the same scenarios.

>>> [s.seed for s in build_matrix("heldout", 4)]
[0, 3, 6, 9]
>>> [s.seed for s in build_matrix("tune", 4)]
[1, 2, 4, 5]
>>> sorted({s.layout for s in build_matrix("heldout", 12)}) == sorted(LAYOUTS)
True
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

LAYOUTS = ("apartment", "studio", "office", "corridor", "living_large", "sparse")
PATHS = ("loop", "sparse", "wall_hug", "fast_turns", "revisit")
FOVS_DEG = (60.0, 70.0, 80.0, 90.0)
EFFECTS = ("none", "jpeg", "blur", "exposure")
POSE_ERRORS = ("exact", "noise_1cm", "noise_3cm", "drift")
OV_NOISE = ("calibrated", "harsh")
DEPTH = (True, False)
SPLITS = ("tune", "heldout", "all")

FRAMES = {"loop": 80, "sparse": 70, "wall_hug": 80, "fast_turns": 80, "revisit": 90}
"""Frames per path kind (sparse: the whole loop in 70 frames; revisit: a loop and a third)."""
DEFAULT_SCENARIOS = 12
"""Scenarios per split in the default matrix."""


@dataclass(frozen=True)
class Scenario:
    """One combination of the axes."""

    index: int
    seed: int
    layout: str
    path: str
    frames: int
    width: int
    height: int
    hfov_deg: float
    effect: str
    pose_error: str
    ov_noise: str
    depth: bool

    @property
    def split(self) -> str:
        return split_of(self.seed)

    @property
    def name(self) -> str:
        d = "d" if self.depth else "rgb"
        return (f"{self.index:02d}-{self.layout}-{self.path}-{self.width}-{self.effect}-{self.pose_error}"
                f"-{self.ov_noise}-{d}-s{self.seed}")

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "split": self.split, "name": self.name}


def split_of(seed: int) -> str:
    """``heldout`` when ``seed % 3 == 0``, else ``tune``."""
    return "heldout" if seed % 3 == 0 else "tune"


def seeds_of(split: str, n: int) -> list[int]:
    """The first ``n`` seeds of a split (``all``: both, in order)."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; choose one of {list(SPLITS)}")
    out: list[int] = []
    seed = 0
    while len(out) < n:
        if split == "all" or split_of(seed) == split:
            out.append(seed)
        seed += 1
    return out


def _column(levels: tuple[Any, ...] | list[Any], n: int, rng: np.random.Generator) -> list[Any]:
    col = [levels[i % len(levels)] for i in range(n)]
    return [col[i] for i in rng.permutation(n)]


def _resolutions(n: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    n_640 = n // 12 + (1 if n % 12 >= 8 else 0)
    n_320 = max(0, round(n / 6))
    col = [(640, 480)] * n_640 + [(320, 240)] * n_320
    col += [(160, 120)] * (n - len(col))
    return [col[i] for i in rng.permutation(n)]


def build_matrix(split: str, n: int = DEFAULT_SCENARIOS) -> list[Scenario]:
    """``n`` scenarios of ``split`` (``tune``, ``heldout`` or ``all``: both, ``n`` each)."""
    if n < 1:
        raise ValueError(f"--scenarios {n} must be >= 1")
    if split == "all":
        return [*build_matrix("heldout", n), *[
            Scenario(**{**asdict(s), "index": n + s.index}) for s in build_matrix("tune", n)]]
    seeds = seeds_of(split, n)
    rng = np.random.default_rng([SPLITS.index(split), 41])
    layout, path = _column(LAYOUTS, n, rng), _column(PATHS, n, rng)
    fov, effect = _column(FOVS_DEG, n, rng), _column(EFFECTS, n, rng)
    pose, ov = _column(POSE_ERRORS, n, rng), _column(OV_NOISE, n, rng)
    depth, res = _column(DEPTH, n, rng), _resolutions(n, rng)
    return [Scenario(index=i, seed=seeds[i], layout=layout[i], path=path[i], frames=FRAMES[path[i]],
                     width=res[i][0], height=res[i][1], hfov_deg=fov[i], effect=effect[i],
                     pose_error=pose[i], ov_noise=ov[i], depth=depth[i]) for i in range(n)]


def quick_matrix() -> list[Scenario]:
    """Two tiny scenarios (16 frames at 160x120): one with depth and exact poses, one RGB-only
    with pose noise, JPEG and the harsh OV noise. For the tests and a first look."""
    return [
        Scenario(0, 0, "apartment", "loop", 16, 160, 120, 70.0, "blur", "exact", "calibrated", True),
        Scenario(1, 3, "sparse", "revisit", 16, 160, 120, 80.0, "jpeg", "noise_1cm", "harsh", False),
    ]
