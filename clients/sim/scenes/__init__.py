"""Procedural indoor scenes for the simulated robot (client side, ground truth lives here).

A scene is one room (rectangular, or L-shaped when a structural block fills a corner; or a floor
of rooms, `floor`) built from axis-aligned boxes, cylinders and spheres. Every triangle carries a
class label (index into `CLASS_NAMES`), an instance id and a material (base colour, second colour,
procedural texture kind and scale) that the ray caster (`clients.sim.raycast`) turns into colour
at the hit point.

Furniture comes in functional *zones* (living, dining, bedroom, kitchen, bathroom, office), each
a set of objects placed against walls or in the room's middle. Placement rejects any candidate
whose bounding box touches another object's box (a 1 cm gap is kept; an object resting on
another one, e.g. a pillow on a bed, touches only the part it rests on) and any candidate that
would cut the free floor into pieces, so a robot can always drive around the room.

World frame: metres, right-handed, +z up; the room interior is `[room_min, room_max]` with
`room_min = (0, 0, 0)`.

Modules, each importing only the ones above it (none imports this package's `__init__`):

- `vocabulary`: `SCANNET20`, `CLASS_NAMES`, `LABEL_OF`, `NON_BLOCKING_CLASSES`
- `appearance`: `Texture`, `Material`, `Light`, `Colour`
- `styles`: `SceneStyle`, `STYLES`
- `scene`: the output container, `Scene` and its `Instance`s
- `primitives`: mesh pieces (`_Part`: box, cylinder, ellipsoid) and local-frame `_Object`s
- `rand`: `_Rand`, the seeded draws of sizes, colours and materials from a style
- `furniture`: object builders (sofa, bed, kitchen run, window, ...)
- `placement`: `_Placer`, wall / middle placement with collision and free-floor checks
- `zones`: functional zones (anchor + extras) and free-standing clutter
- `generate`: `generate_scene`, which assembles the room into a `Scene`; `generate_room`, a room of
  a given size with an open `Doorway` (for floors)
- `floor`: `generate_floor`, 2-30 rooms joined by doorways and corridors, merged into one `Scene`
  (imported from `clients.sim.scenes.floor`, not re-exported here)

Names with a leading underscore are internal to this package; the public ones are re-exported
here (`from clients.sim.scenes import generate_scene, Scene, CLASS_NAMES, ...`).

>>> scene = generate_scene(3, "apartment")
>>> scene.vertices.shape[1], scene.triangles.shape[1]
(3, 3)
>>> bool((scene.face_label >= 0).all() and (scene.face_label < len(CLASS_NAMES)).all())
True
"""

from clients.sim.scenes.appearance import Colour, Light, Material, Texture
from clients.sim.scenes.generate import generate_room, generate_scene, room_wall_boxes
from clients.sim.scenes.placement import placed_reserve
from clients.sim.scenes.scene import Doorway, Instance, LightMap, Scene
from clients.sim.scenes.styles import STYLES, SceneStyle
from clients.sim.scenes.vocabulary import (
    CLASS_NAMES,
    EXTRA_CLASSES,
    LABEL_OF,
    NON_BLOCKING_CLASSES,
    SCANNET20,
)

__all__ = [
    "CLASS_NAMES",
    "EXTRA_CLASSES",
    "LABEL_OF",
    "NON_BLOCKING_CLASSES",
    "SCANNET20",
    "STYLES",
    "Colour",
    "Doorway",
    "Instance",
    "Light",
    "LightMap",
    "Material",
    "Scene",
    "SceneStyle",
    "Texture",
    "generate_room",
    "generate_scene",
    "placed_reserve",
    "room_wall_boxes",
]
