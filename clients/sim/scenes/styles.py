"""Scene styles: room sizes, palettes, textures, light and furniture mix of a family of scenes.

>>> sorted(STYLES)
['apartment', 'corridor', 'living_large', 'office', 'sparse', 'studio']
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from clients.sim.scenes.appearance import Colour, Texture


@dataclass(frozen=True)
class SceneStyle:
    """Parameters of a family of scenes: sizes, palettes, textures, light and furniture mix."""

    name: str
    room_x_m: tuple[float, float]          # interior size along x, metres (min, max)
    room_y_m: tuple[float, float]          # interior size along y
    ceiling_m: tuple[float, float]         # ceiling height
    notch_prob: float                      # probability of an L-shaped room (block in a corner)
    n_zones: tuple[int, int]               # how many furniture zones per room (min, max)
    zone_weights: dict[str, float]         # relative frequency of each zone
    n_windows: tuple[int, int]
    n_clutter: tuple[int, int]             # free-standing objects in the middle (min, max)
    wall_colours: tuple[Colour, ...]
    wall_textures: tuple[tuple[Texture, float], ...]   # (kind, scale_m)
    floor_colours: tuple[tuple[Colour, Colour], ...]   # (colour, colour2)
    floor_textures: tuple[tuple[Texture, float], ...]
    wood_colours: tuple[Colour, ...]
    fabric_colours: tuple[Colour, ...]
    accent_colours: tuple[Colour, ...]
    appliance_colours: tuple[Colour, ...]
    ceiling_colour: Colour
    light_colour: Colour
    light_diffuse: tuple[float, float]
    ambient: tuple[float, float]
    size_jitter: float                     # relative random scaling of furniture dimensions
    layout: str = "room"                   # "room": one room; "corridor": rooms off a corridor


STYLES: dict[str, SceneStyle] = {
    # Training style: warm, wooden, smallish rooms, rectangular.
    "apartment": SceneStyle(
        name="apartment",
        room_x_m=(4.6, 7.0), room_y_m=(3.8, 5.6), ceiling_m=(2.45, 2.75),
        notch_prob=0.0, n_zones=(3, 4),
        zone_weights={"living": 1.0, "dining": 1.0, "bedroom": 1.0, "kitchen": 1.0,
                      "bathroom": 0.8, "office": 0.8},
        n_windows=(1, 2), n_clutter=(1, 3),
        wall_colours=((0.86, 0.80, 0.70), (0.80, 0.76, 0.66), (0.90, 0.86, 0.78),
                      (0.74, 0.78, 0.70), (0.84, 0.72, 0.62)),
        wall_textures=((Texture.PLAIN, 0.25), (Texture.STRIPES, 0.12), (Texture.FABRIC, 0.08)),
        floor_colours=(((0.55, 0.38, 0.22), (0.42, 0.28, 0.16)), ((0.62, 0.46, 0.30), (0.50, 0.36, 0.22)),
                       ((0.70, 0.66, 0.58), (0.56, 0.52, 0.46))),
        floor_textures=((Texture.WOOD, 0.18), (Texture.TILES, 0.40), (Texture.CHECKER, 0.35)),
        wood_colours=((0.55, 0.36, 0.20), (0.65, 0.47, 0.28), (0.42, 0.27, 0.15), (0.72, 0.58, 0.40)),
        fabric_colours=((0.62, 0.30, 0.22), (0.35, 0.45, 0.30), (0.70, 0.62, 0.45), (0.45, 0.35, 0.50),
                        (0.75, 0.55, 0.35)),
        accent_colours=((0.80, 0.30, 0.20), (0.85, 0.70, 0.25), (0.30, 0.50, 0.35), (0.55, 0.30, 0.45)),
        appliance_colours=((0.92, 0.92, 0.90), (0.85, 0.85, 0.82)),
        ceiling_colour=(0.93, 0.91, 0.86),
        light_colour=(1.0, 0.92, 0.80),
        light_diffuse=(0.60, 0.80), ambient=(0.35, 0.45),
        size_jitter=0.10,
    ),
    # Unseen style: cool, bright and saturated, big rooms, often L-shaped, marble and concrete.
    "studio": SceneStyle(
        name="studio",
        room_x_m=(6.0, 8.5), room_y_m=(4.8, 6.8), ceiling_m=(2.9, 3.3),
        notch_prob=0.6, n_zones=(3, 5),
        zone_weights={"living": 1.2, "dining": 0.8, "bedroom": 0.7, "kitchen": 1.0,
                      "bathroom": 0.6, "office": 1.2},
        n_windows=(2, 3), n_clutter=(2, 4),
        wall_colours=((0.92, 0.93, 0.95), (0.70, 0.72, 0.75), (0.55, 0.65, 0.75), (0.88, 0.88, 0.82)),
        wall_textures=((Texture.MARBLE, 0.60), (Texture.TILES, 0.55), (Texture.PLAIN, 0.40)),
        floor_colours=(((0.35, 0.36, 0.38), (0.20, 0.21, 0.22)), ((0.85, 0.85, 0.84), (0.60, 0.60, 0.62)),
                       ((0.20, 0.22, 0.30), (0.40, 0.42, 0.50))),
        floor_textures=((Texture.MARBLE, 0.80), (Texture.CHECKER, 0.60), (Texture.FABRIC, 0.10)),
        wood_colours=((0.85, 0.82, 0.75), (0.20, 0.20, 0.22), (0.90, 0.90, 0.92), (0.60, 0.30, 0.20)),
        fabric_colours=((0.10, 0.45, 0.70), (0.85, 0.20, 0.25), (0.95, 0.75, 0.10), (0.20, 0.65, 0.45),
                        (0.30, 0.30, 0.35)),
        accent_colours=((0.10, 0.60, 0.85), (0.95, 0.40, 0.10), (0.60, 0.20, 0.80), (0.20, 0.80, 0.50)),
        appliance_colours=((0.75, 0.77, 0.80), (0.25, 0.25, 0.28)),
        ceiling_colour=(0.96, 0.97, 1.00),
        light_colour=(0.85, 0.93, 1.05),
        light_diffuse=(0.70, 0.95), ambient=(0.25, 0.35),
        size_jitter=0.18,
    ),
}

_APARTMENT, _STUDIO = STYLES["apartment"], STYLES["studio"]
STYLES.update({
    # Open-plan office: rows of desks with monitors and chairs, chairs along a wall, grey and blue.
    "office": replace(
        _STUDIO, name="office", room_x_m=(7.5, 9.5), room_y_m=(6.0, 7.5), ceiling_m=(2.7, 3.0),
        notch_prob=0.0, n_zones=(2, 3), zone_weights={"desk_rows": 3.0, "office": 1.0, "dining": 0.6},
        n_windows=(2, 3), n_clutter=(0, 2),
        wall_colours=((0.90, 0.90, 0.88), (0.78, 0.80, 0.82), (0.85, 0.86, 0.80)),
        wall_textures=((Texture.PLAIN, 0.40), (Texture.FABRIC, 0.08)),
        floor_colours=(((0.40, 0.42, 0.46), (0.30, 0.32, 0.36)), ((0.55, 0.52, 0.48), (0.45, 0.42, 0.38))),
        floor_textures=((Texture.FABRIC, 0.10), (Texture.TILES, 0.60)),
        light_colour=(1.0, 1.0, 1.0), light_diffuse=(0.75, 0.95), ambient=(0.35, 0.45),
    ),
    # Two or three rooms off a corridor along one side; doorways in the corridor's wall.
    "corridor": replace(
        _APARTMENT, name="corridor", room_x_m=(8.0, 10.0), room_y_m=(5.4, 6.6), ceiling_m=(2.5, 2.7),
        notch_prob=0.0, n_zones=(3, 4),
        zone_weights={"living": 1.0, "dining": 1.0, "bedroom": 1.0, "office": 1.0, "kitchen": 0.5},
        n_windows=(1, 2), n_clutter=(0, 1), layout="corridor",
    ),
    # A large living room, 8-10 m: far walls, small objects at many depths.
    "living_large": replace(
        _APARTMENT, name="living_large", room_x_m=(8.0, 10.0), room_y_m=(6.0, 8.0), ceiling_m=(2.6, 3.0),
        notch_prob=0.3, n_zones=(3, 4), zone_weights={"living": 3.0, "dining": 1.5, "office": 0.8,
                                                      "kitchen": 0.8},
        n_windows=(2, 3), n_clutter=(3, 5),
    ),
    # A sparsely furnished room: one or two zones, bare walls, little clutter.
    "sparse": replace(
        _APARTMENT, name="sparse", room_x_m=(5.0, 7.0), room_y_m=(4.0, 6.0), ceiling_m=(2.5, 2.8),
        notch_prob=0.0, n_zones=(1, 2), zone_weights={"dining": 1.0, "office": 1.0, "living": 0.5},
        n_windows=(1, 1), n_clutter=(0, 1),
    ),
})
"""Named scene styles. `apartment` is the training style; `studio` is held out (unseen). The
others are held-out layouts of the scenario matrix (docs/how-to/scenario-matrix.md)."""
