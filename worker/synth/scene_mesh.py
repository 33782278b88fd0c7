"""The synthetic scene as one triangle mesh with a material per face.

Shared by the camera simulation (moderngl) and the lidar simulation (open3d ray casting).
Vertices are float64 in the sequence's world frame (ENU, metres); the renderers subtract a
nearby origin before anything becomes float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Material:
    """Appearance of a surface for the cameras and the lidar.

    albedo: linear RGB in [0, 1]; texture: name of the procedural pattern the camera
    shader draws (``plain``, ``ballast``, ``grass``, ``wood``, ``metal``, ``concrete``,
    ``brick``, ``foliage``, ``asphalt``, ``gravel``); reflectivity: lidar return strength
    in [0, 1] at normal incidence.
    """

    name: str
    albedo: tuple[float, float, float]
    texture: str
    reflectivity: float


MATERIALS: tuple[Material, ...] = (
    Material("ground", (0.30, 0.33, 0.20), "grass", 0.25),
    Material("ballast", (0.42, 0.40, 0.37), "ballast", 0.30),
    Material("sleeper", (0.45, 0.43, 0.40), "concrete", 0.35),
    Material("rail", (0.55, 0.53, 0.50), "metal", 0.80),
    Material("pole", (0.50, 0.50, 0.50), "metal", 0.60),
    Material("platform", (0.58, 0.56, 0.52), "concrete", 0.40),
    Material("platform_edge", (0.85, 0.85, 0.80), "plain", 0.85),
    Material("fence", (0.30, 0.32, 0.30), "metal", 0.45),
    Material("foliage", (0.16, 0.28, 0.10), "foliage", 0.20),
    Material("trunk", (0.28, 0.20, 0.13), "wood", 0.25),
    Material("building", (0.55, 0.35, 0.28), "brick", 0.35),
    Material("roof", (0.25, 0.22, 0.22), "plain", 0.20),
    Material("sign", (0.95, 0.95, 0.95), "plain", 0.95),
    Material("sign_dark", (0.05, 0.05, 0.05), "plain", 0.10),
    Material("road", (0.22, 0.22, 0.23), "asphalt", 0.15),
    Material("gravel", (0.48, 0.45, 0.40), "gravel", 0.30),
)
MATERIAL_ID: dict[str, int] = {m.name: i for i, m in enumerate(MATERIALS)}


@dataclass
class SceneMesh:
    """Triangle soup of the whole scene.

    vertices: (n, 3) float64 world coordinates; faces: (m, 3) int64 vertex indices,
    counter-clockwise seen from outside; material: (m,) int64 index into MATERIALS.
    """

    vertices: F64
    faces: NDArray[np.int64]
    material: NDArray[np.int64]

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        self.material = np.asarray(self.material, dtype=np.int64).reshape(-1)
        if len(self.material) != len(self.faces):
            raise ValueError("material must have one entry per face")

    @staticmethod
    def concatenate(parts: list[SceneMesh]) -> SceneMesh:
        """One mesh from several, vertex indices offset."""
        if not parts:
            return SceneMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64))
        offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
        return SceneMesh(
            np.concatenate([p.vertices for p in parts]),
            np.concatenate([p.faces + o for p, o in zip(parts, offsets, strict=True)]),
            np.concatenate([p.material for p in parts]),
        )
