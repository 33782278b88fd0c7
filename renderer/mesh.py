"""Triangle meshes of virtual objects and of the scene proxies, as the renderers take them.

An ``ObjectMesh`` lives in its own object frame: metres, x forward (the object's front),
y left, z up, origin at the centre of its ground contact (so placing it is choosing
T_world_obj with the origin on the surface below). Colours are per vertex, linear RGB in
[0, 1]; ``reflectivity`` is the lidar return strength per vertex in [0, 1].

Surfaces: every face belongs to a :class:`Material` (``face_material``; none given: one
plain material). The renderer's fragment shader computes, per pixel, the albedo as
vertex colour x ``base_color`` x the base-colour texture (sRGB-decoded, mipmapped),
sampled at the vertex-interpolated ``uv`` or, for ``triplanar_m`` materials (procedural
textures of meshes without UVs), at the object-space position seen along the three axes.
A normal map (tangent space, ``tangents`` (n, 4) with the bitangent sign in w) bends the
shading normal; ``roughness`` and ``metallic`` (glTF metallic-roughness) add a specular
lobe (see :mod:`renderer.lighting`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]


@dataclass
class Material:
    """A surface of a group of faces (glTF metallic-roughness, reduced).

    base_color : (4,) linear RGBA factor (multiplies the texture and the vertex colour).
    base_color_texture : (h, w, 4) uint8 sRGB-encoded RGBA (row 0 = the image's top,
        glTF convention: v = 0 at the top) or None.
    normal_texture : (h, w, 3) uint8 tangent-space normal map or None; ``normal_scale``
        scales its x, y.
    roughness, metallic : glTF factors in [0, 1]; ``metallic_roughness_texture`` (h, w,
        3) uint8, linear, G = roughness, B = metallic (multiplied by the factors) or None.
    alpha_cutoff : fragments with base alpha below it are discarded (glTF alphaMode
        MASK); None: opaque.
    triplanar_m : map the textures from the object-space position with this period (m)
        instead of the UVs (meshes without UVs); None: UV mapping.
    specular : False = the plain Lambertian model of the built-in library (no specular
        lobe, whatever ``roughness``).
    """

    name: str = "default"
    base_color: F64 = field(default_factory=lambda: np.ones(4))
    base_color_texture: U8 | None = None
    normal_texture: U8 | None = None
    normal_scale: float = 1.0
    roughness: float = 1.0
    metallic: float = 0.0
    metallic_roughness_texture: U8 | None = None
    alpha_cutoff: float | None = None
    triplanar_m: float | None = None
    specular: bool = True

    def __post_init__(self) -> None:
        self.base_color = np.asarray(self.base_color, dtype=np.float64).reshape(-1)
        if len(self.base_color) == 3:
            self.base_color = np.append(self.base_color, 1.0)
        if self.base_color.shape != (4,):
            raise ValueError(f"material {self.name}: base_color must have 3 or 4 values")
        for k in ("base_color_texture", "normal_texture", "metallic_roughness_texture"):
            t = getattr(self, k)
            if t is None:
                continue
            t = np.asarray(t)
            if t.dtype != np.uint8 or t.ndim != 3 or t.shape[2] not in (3, 4) or 0 in t.shape:
                raise ValueError(f"material {self.name}: {k} must be (h, w, 3|4) uint8")
            setattr(self, k, np.ascontiguousarray(t))
        self.roughness = float(np.clip(self.roughness, 0.0, 1.0))
        self.metallic = float(np.clip(self.metallic, 0.0, 1.0))

    @property
    def textured(self) -> bool:
        return self.base_color_texture is not None or self.normal_texture is not None


PLAIN = Material(name="plain", specular=False)
"""The material of meshes that give none: vertex colours, Lambertian."""


@dataclass
class ObjectMesh:
    """A virtual obstacle.

    vertices : (n, 3) float64, object frame; faces : (m, 3) int64, counter-clockwise seen
    from outside; colors : (n, 3) float32 linear RGB; reflectivity : (n,) float32;
    name : class name (``person``, ``cow``, ...), used for annotations.
    normals : (n, 3) float32 unit shading normals or None (then the renderer averages
        the face normals).
    uv : (n, 2) float32 texture coordinates (glTF convention: v down the image) or None.
    tangents : (n, 4) float32 unit tangents (xyz) and bitangent sign (w) or None.
    materials : the surfaces; face_material : (m,) int32 index into it (None: all faces
        use materials[0], or :data:`PLAIN` when there is none).
    """

    vertices: F64
    faces: NDArray[np.int64]
    colors: NDArray[np.float32]
    reflectivity: NDArray[np.float32]
    name: str = "object"
    meta: dict = field(default_factory=dict)
    uv: NDArray[np.float32] | None = None
    normals: NDArray[np.float32] | None = None
    tangents: NDArray[np.float32] | None = None
    materials: list[Material] = field(default_factory=list)
    face_material: NDArray[np.int32] | None = None

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
        if self.uv is not None:
            self.uv = np.asarray(self.uv, dtype=np.float32).reshape(n, 2)
        if self.normals is not None:
            self.normals = np.asarray(self.normals, dtype=np.float32).reshape(n, 3)
        if self.tangents is not None:
            self.tangents = np.asarray(self.tangents, dtype=np.float32).reshape(n, 4)
        if self.face_material is not None:
            fm = np.asarray(self.face_material, dtype=np.int32).reshape(len(self.faces))
            if len(fm) and (fm.min() < 0 or fm.max() >= max(len(self.materials), 1)):
                raise ValueError(f"{self.name}: face_material out of range")
            self.face_material = fm

    @property
    def surface(self) -> tuple[list[Material], NDArray[np.int32]]:
        """(materials, (m,) material index per face), never empty."""
        mats = self.materials or [PLAIN]
        fm = self.face_material
        return mats, (np.zeros(len(self.faces), np.int32) if fm is None else fm)

    @property
    def textured(self) -> bool:
        return any(m.textured for m in self.materials)

    def with_vertices(self, vertices: F64) -> ObjectMesh:
        """A copy with new vertex positions (same count, e.g. uniformly scaled; normals
        and tangents kept), colours and surfaces shared."""
        return ObjectMesh(
            vertices, self.faces.copy(), self.colors.copy(), self.reflectivity.copy(),
            self.name, dict(self.meta), self.uv, self.normals, self.tangents,
            list(self.materials), self.face_material,
        )  # fmt: skip

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
