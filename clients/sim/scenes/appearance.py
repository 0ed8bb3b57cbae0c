"""Appearance of scene surfaces: procedural texture kinds, materials and the room light.

The ray caster (`clients.sim.raycast`) turns a face's material into colour at the hit point
and shades it with the scene's `Light`.

>>> Material((0.5, 0.5, 0.5), (0.4, 0.4, 0.4)).texture is Texture.PLAIN
True
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np


class Texture(IntEnum):
    """Procedural texture kinds, evaluated per hit point by the renderer."""

    PLAIN = 0      # base colour with faint noise (still enough for stereo matching)
    CHECKER = 1    # two-colour checker board (floor tiles)
    STRIPES = 2    # two-colour stripes (wallpaper, fabric)
    WOOD = 3       # wood grain bands distorted by noise
    FABRIC = 4     # fine two-scale noise weave
    TILES = 5      # square tiles with grout lines (colour2 = grout)
    MARBLE = 6     # veins from turbulent noise
    PATCHES = 7    # cells of random colours (book spines, paintings)
    SKY = 8        # bright gradient seen through a window; not lit (emissive)


@dataclass(frozen=True)
class Material:
    """Appearance of a part: colours are linear RGB in [0, 1]."""

    colour: tuple[float, float, float]
    colour2: tuple[float, float, float]
    texture: Texture = Texture.PLAIN
    scale_m: float = 0.2  # texture period, metres


@dataclass(frozen=True)
class Light:
    """One point light plus ambient term (Lambert shading)."""

    position: np.ndarray  # (3,) world metres
    colour: np.ndarray    # (3,) RGB multiplier
    diffuse: float        # diffuse strength at distance `falloff_m`
    ambient: float        # ambient strength
    falloff_m: float      # distance at which the diffuse term halves


Colour = tuple[float, float, float]
