"""The scene container: a labelled triangle mesh of one room (or of a floor of rooms), its object
instances and light(s), and the `Doorway` of a floor's room.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from clients.sim.scenes.appearance import Light
from clients.sim.scenes.vocabulary import NON_BLOCKING_CLASSES


@dataclass(frozen=True)
class Doorway:
    """An open doorway in one of a room's long walls (a floor's rooms open onto a corridor): on
    the wall at y = 0 (`wall` 0) or at y = size_y (`wall` 2), centred at x = `centre_x` (room
    frame), `width_m` wide and `height_m` high."""

    wall: int
    centre_x: float
    width_m: float = 1.1
    height_m: float = 2.1

    def check(self, size: np.ndarray) -> None:
        """ValueError unless the doorway fits the room of interior `size` (x, y, height)."""
        if self.wall not in (0, 2):
            raise ValueError(f"doorway wall {self.wall} must be 0 (y = 0) or 2 (y = size_y)")
        if not 0.8 <= self.width_m <= 2.0 or not 1.9 <= self.height_m <= float(size[2]) - 0.1:
            raise ValueError(f"doorway {self.width_m} x {self.height_m} m out of range "
                             f"(width 0.8..2, height 1.9..{float(size[2]) - 0.1:.2f})")
        margin = self.width_m / 2 + 0.3
        if not margin <= self.centre_x <= float(size[0]) - margin:
            raise ValueError(f"doorway centre_x {self.centre_x} must keep {margin:.2f} m from the "
                             f"room's corners (x in 0..{float(size[0])})")


@dataclass
class LightMap:
    """The lights of a floor and which one shades a point: `lights[ids[i, j]]` for the world xy in
    cell (i, j) of a grid (`cell_m` cells from `origin`); points off the grid take the nearest cell."""

    lights: list[Light]
    origin: np.ndarray  # (2,) world xy of cell (0, 0)'s corner
    cell_m: float
    ids: np.ndarray     # (nx, ny) int16 index into lights

    def lookup(self, xy: np.ndarray) -> np.ndarray:
        """(N,) int64 light index for world points xy (N, 2+) (extra columns ignored)."""
        g = np.floor((np.asarray(xy)[:, :2] - self.origin) / self.cell_m).astype(np.int64)
        i = np.clip(g[:, 0], 0, self.ids.shape[0] - 1)
        j = np.clip(g[:, 1], 0, self.ids.shape[1] - 1)
        return self.ids[i, j].astype(np.int64)


@dataclass
class Instance:
    """One object in the scene (pieces of room structure are not instances)."""

    instance_id: int
    class_name: str
    label: int                # index into CLASS_NAMES
    aabb_min: np.ndarray      # (3,) world metres
    aabb_max: np.ndarray      # (3,)
    centroid: np.ndarray      # (3,) area-weighted centroid of its surface
    support_id: int = -1      # instance it rests on or hangs from, -1 for floor or wall
    part_aabbs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))  # (P, 2, 3) min/max

    @property
    def blocks_robot(self) -> bool:
        """Whether a driving robot must keep clear of this object's footprint."""
        return self.class_name not in NON_BLOCKING_CLASSES


@dataclass
class Scene:
    """A labelled triangle mesh of one room plus what the renderer needs for textures."""

    seed: int
    style: str
    vertices: np.ndarray        # (V, 3) float32 world metres, +z up
    triangles: np.ndarray       # (F, 3) int32
    face_label: np.ndarray      # (F,) int32 index into CLASS_NAMES
    face_instance: np.ndarray   # (F,) int32 instance id, -1 for room structure
    instances: list[Instance]
    room_min: np.ndarray        # (3,) float64 interior bounds
    room_max: np.ndarray        # (3,)
    face_colour: np.ndarray     # (F, 3) float32 base colour, linear RGB in [0, 1]
    face_colour2: np.ndarray    # (F, 3) float32 second colour of the texture
    face_texture: np.ndarray    # (F,) int8 Texture kind
    face_texture_scale: np.ndarray  # (F,) float32 texture period, metres
    face_normal: np.ndarray     # (F, 3) float32 unit normal (winding order; renderer flips it)
    light: Light
    structures: list[tuple[np.ndarray, np.ndarray]]  # AABBs (min, max) of structural blocks
    light_map: LightMap | None = None  # a floor's lights (then `light` is the first room's)

    @property
    def num_faces(self) -> int:
        return int(self.triangles.shape[0])

    def obstacle_aabbs(self) -> np.ndarray:
        """(N, 2, 3) boxes a robot must keep clear of: blocking instances and structure."""
        boxes = [np.stack([i.aabb_min, i.aabb_max]) for i in self.instances if i.blocks_robot]
        boxes += [np.stack([lo, hi]) for lo, hi in self.structures]
        if not boxes:
            return np.zeros((0, 2, 3))
        return np.stack(boxes).astype(np.float64)

    def face_areas(self) -> np.ndarray:
        """(F,) float64 triangle areas, square metres."""
        v = self.vertices.astype(np.float64)[self.triangles]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    def sample_surface(
        self, n_points: int, seed: int = 0, exclude_labels: tuple[int, ...] = (),
        only_labels: tuple[int, ...] = (),
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample points uniformly by area on the surfaces (only those of ``only_labels`` when given;
        never those of ``exclude_labels``).

        Returns xyz (P, 3) float32, label (P,) int32, instance (P,) int32.
        """
        if n_points < 1:
            raise ValueError(f"n_points {n_points} out of range 1..")
        areas = self.face_areas()
        if exclude_labels:
            areas = np.where(np.isin(self.face_label, exclude_labels), 0.0, areas)
        if only_labels:
            areas = np.where(np.isin(self.face_label, only_labels), areas, 0.0)
        if not areas.sum() > 0:
            raise ValueError(f"no surface to sample (only_labels {only_labels}, "
                             f"exclude_labels {exclude_labels})")
        rng = np.random.default_rng(seed)
        face = rng.choice(len(areas), size=n_points, p=areas / areas.sum())
        r1, r2 = rng.random(n_points), rng.random(n_points)
        s = np.sqrt(r1)
        bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)  # (P, 3)
        tri = self.vertices.astype(np.float64)[self.triangles[face]]  # (P, 3, 3)
        xyz = np.einsum("pk,pkd->pd", bary, tri)
        return xyz.astype(np.float32), self.face_label[face].copy(), self.face_instance[face].copy()
