"""Seeded random choices of a scene: sizes, colours and materials drawn from its style.

Every draw goes through one `numpy` generator in a fixed order, so a scene is a pure
function of its seed and style.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypeVar

import numpy as np

from clients.sim.scenes.appearance import Colour, Material, Texture
from clients.sim.scenes.styles import SceneStyle

_T = TypeVar("_T")


def _scaled(c: Colour, factor: float) -> Colour:
    return (c[0] * factor, c[1] * factor, c[2] * factor)


class _Rand:
    def __init__(self, seed: int, style: SceneStyle) -> None:
        self.rng = np.random.default_rng(seed)
        self.style = style

    def u(self, lo: float, hi: float) -> float:
        return float(self.rng.uniform(lo, hi))

    def dim(self, nominal: float) -> float:
        j = self.style.size_jitter
        return nominal * self.u(1.0 - j, 1.0 + j)

    def pick(self, seq: Sequence[_T]) -> _T:
        return seq[int(self.rng.integers(len(seq)))]

    def chance(self, p: float) -> bool:
        return bool(self.rng.random() < p)

    def jitter(self, c: Colour, amount: float = 0.06) -> Colour:
        out = np.clip(np.asarray(c) * self.u(1 - amount, 1 + amount)
                      + self.rng.uniform(-amount, amount, 3) * 0.5, 0.02, 1.0)
        return (float(out[0]), float(out[1]), float(out[2]))

    def mat(self, colour: Colour, texture: Texture, scale: float, colour2: Colour | None = None,
            contrast: float = 0.7) -> Material:
        c = self.jitter(colour)
        c2 = colour2 if colour2 is not None else _scaled(c, contrast)
        return Material(c, c2, texture, scale * self.u(0.8, 1.25))

    def wood(self) -> Material:
        return self.mat(self.pick(self.style.wood_colours), Texture.WOOD, 0.05, contrast=0.75)

    def fabric(self) -> Material:
        tex = self.pick((Texture.FABRIC, Texture.STRIPES, Texture.FABRIC))
        return self.mat(self.pick(self.style.fabric_colours), tex, 0.06, contrast=0.7)

    def accent(self) -> Material:
        return self.mat(self.pick(self.style.accent_colours), Texture.PLAIN, 0.1)

    def appliance(self) -> Material:
        return self.mat(self.pick(self.style.appliance_colours), Texture.PLAIN, 0.08, contrast=0.9)

    def ceramic(self) -> Material:
        return self.mat((0.94, 0.94, 0.93), Texture.MARBLE, 0.3, contrast=0.85)

    def metal(self) -> Material:
        return self.mat((0.62, 0.63, 0.66), Texture.PLAIN, 0.05, contrast=0.8)

    def dark(self) -> Material:
        return self.mat((0.08, 0.08, 0.09), Texture.PLAIN, 0.05, contrast=0.6)

    def patches(self, scale: float = 0.05) -> Material:
        return self.mat(self.pick(self.style.accent_colours), Texture.PATCHES, scale, contrast=0.5)
