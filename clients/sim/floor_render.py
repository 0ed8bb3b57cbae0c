"""Rendering a floor of rooms (`clients.sim.scenes.floor`) with a ray caster per band.

A camera in a band (its rooms and its corridor) can only see that band's faces and the spine's
(`Floor.zone_at`), so `FloorRenderer` casts its rays against that part of the mesh alone; a
camera in the spine casts against the whole floor. With Open3D the images are the same as with
one `SceneRenderer` of the whole floor (the faces keep their relative order, so even ties
between faces resolve the same way); the torch fallback casts in coordinates centred on the part
it casts against, so a few edge pixels can differ by float32 rounding. Open3D's BVH hardly slows
down with more triangles; the torch fallback does (it tests each bundle of rays against every
triangle its cone can reach), and the bands win it about twice (docs/how-to/simulator.md,
`benchmarks/speed/sim_floor_render.py`).

>>> from clients.sim.scenes.floor import generate_floor
>>> from clients.sim.robot import default_intrinsics, look_at
>>> floor = generate_floor(0, 3)
>>> room = floor.rooms[0]
>>> eye = np.array([*(0.5 * (room.lo + room.hi)), 1.3])
>>> view = FloorRenderer(floor).render(default_intrinsics(32, 24), look_at(eye, eye + [1.0, 0, 0]), 32, 24)
>>> bool((view.depth_m > 0).all())
True
"""

from __future__ import annotations

import numpy as np

from clients.sim.raycast import RenderedView, SceneRenderer
from clients.sim.scenes import Scene
from clients.sim.scenes.floor import Floor


def _sub_scene(scene: Scene, faces: np.ndarray) -> Scene:
    """The scene with only the faces `faces` (ascending ids), vertices compacted."""
    tri = scene.triangles[faces]
    used, inverse = np.unique(tri.ravel(), return_inverse=True)
    return Scene(scene.seed, scene.style, scene.vertices[used], inverse.reshape(-1, 3).astype(np.int32),
                 scene.face_label[faces], scene.face_instance[faces], scene.instances, scene.room_min,
                 scene.room_max, scene.face_colour[faces], scene.face_colour2[faces],
                 scene.face_texture[faces], scene.face_texture_scale[faces], scene.face_normal[faces],
                 scene.light, scene.structures, scene.light_map)


class FloorRenderer:
    """`SceneRenderer`'s `render` and `cast` for a floor, one ray caster per band (built on first use)."""

    def __init__(self, floor: Floor, backend: str | None = None, device: str | None = None) -> None:
        self.floor = floor
        self.scene = floor.scene
        self._backend, self._device = backend, device
        self._by_zone: dict[int, SceneRenderer] = {}
        self._whole: SceneRenderer | None = None

    def _renderer(self, zone: int) -> SceneRenderer:
        if zone < 0:
            if self._whole is None:
                self._whole = SceneRenderer(self.scene, self._backend, self._device)
            return self._whole
        if zone not in self._by_zone:
            faces = np.flatnonzero((self.floor.face_zone == zone) | (self.floor.face_zone == -1))
            self._by_zone[zone] = SceneRenderer(_sub_scene(self.scene, faces), self._backend, self._device)
        return self._by_zone[zone]

    def prepare(self) -> FloorRenderer:
        """Build every band's caster (and the whole floor's) now, not at the first frame there."""
        for zone in range(-1, len(self.floor.band_y)):
            self._renderer(zone)
        return self

    @property
    def backend(self) -> str:
        return self._renderer(-1).backend

    def render(self, K: np.ndarray, world_from_cam: np.ndarray, width: int, height: int) -> RenderedView:
        """As `SceneRenderer.render`, casting against the camera's band only."""
        zone = self.floor.zone_at(np.asarray(world_from_cam, dtype=np.float64)[:2, 3])
        return self._renderer(zone).render(K, world_from_cam, width, height)

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As `SceneRenderer.cast`, against the whole floor (rays from anywhere)."""
        return self._renderer(-1).cast(origins, dirs)
