"""Triangle meshes of virtual objects and of the scene proxies, as the renderers take them.

An ``ObjectMesh`` lives in its own object frame: metres, x forward (the object's front),
y left, z up, origin at the centre of its ground contact (so placing it is choosing
T_world_obj with the origin on the surface below). Colours are per vertex, linear RGB in
[0, 1]; ``reflectivity`` is the lidar return strength per vertex in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass
class ObjectMesh:
    """A virtual obstacle.

    vertices : (n, 3) float64, object frame; faces : (m, 3) int64, counter-clockwise seen
    from outside; colors : (n, 3) float32 linear RGB; reflectivity : (n,) float32;
    name : class name (``person``, ``cow``, ...), used for annotations.
    """

    vertices: F64
    faces: NDArray[np.int64]
    colors: NDArray[np.float32]
    reflectivity: NDArray[np.float32]
    name: str = "object"
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        n = len(self.vertices)
        self.colors = np.asarray(self.colors, dtype=np.float32).reshape(n, 3)
        self.reflectivity = np.asarray(self.reflectivity, dtype=np.float32).reshape(n)
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= n):
            raise ValueError(f"{self.name}: face indices out of range")
        if not np.all(np.isfinite(self.vertices)):
            raise ValueError(f"{self.name}: non-finite vertices")

    @property
    def bounds(self) -> F64:
        """(2, 3) min and max corner in the object frame."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @property
    def size(self) -> F64:
        """(3,) extent along x, y, z (m)."""
        b = self.bounds
        return b[1] - b[0]


@dataclass
class ProxyMesh:
    """Depth-only stand-ins of the real scene (track boxes, ground and platform planes,
    pole boxes): vertices (n, 3) float64 in the world frame, faces (m, 3) int64."""

    vertices: F64
    faces: NDArray[np.int64]

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)

    @staticmethod
    def concatenate(parts: list[ProxyMesh]) -> ProxyMesh:
        if not parts:
            return ProxyMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
        offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
        return ProxyMesh(
            np.concatenate([p.vertices for p in parts]),
            np.concatenate([p.faces + o for p, o in zip(parts, offsets, strict=True)]),
        )
