"""The scene container: a labelled triangle mesh of one room, its object instances and light.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from clients.sim.scenes.appearance import Light
from clients.sim.scenes.vocabulary import NON_BLOCKING_CLASSES


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
        self, n_points: int, seed: int = 0, exclude_labels: tuple[int, ...] = ()
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample points uniformly by area on the surfaces.

        Returns xyz (P, 3) float32, label (P,) int32, instance (P,) int32.
        """
        if n_points < 1:
            raise ValueError(f"n_points {n_points} out of range 1..")
        areas = self.face_areas()
        if exclude_labels:
            areas = np.where(np.isin(self.face_label, exclude_labels), 0.0, areas)
        rng = np.random.default_rng(seed)
        face = rng.choice(len(areas), size=n_points, p=areas / areas.sum())
        r1, r2 = rng.random(n_points), rng.random(n_points)
        s = np.sqrt(r1)
        bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)  # (P, 3)
        tri = self.vertices.astype(np.float64)[self.triangles[face]]  # (P, 3, 3)
        xyz = np.einsum("pk,pkd->pd", bary, tri)
        return xyz.astype(np.float32), self.face_label[face].copy(), self.face_instance[face].copy()
