"""Mesh primitives for the procedural railway scene (float64, world frame).

Every function returns a :class:`SceneMesh`; faces are counter-clockwise seen from
outside where a primitive has an outside.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from worker.synth.scene_mesh import MATERIAL_ID, SceneMesh

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

_BOX_CORNERS = np.array(
    [[x, y, z] for z in (-0.5, 0.5) for y in (-0.5, 0.5) for x in (-0.5, 0.5)], dtype=np.float64
)
# corner index = x + 2 y + 4 z (each 0/1); quads CCW from outside
_BOX_QUADS = np.array(
    [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
)
_BOX_FACES = np.concatenate([_BOX_QUADS[:, [0, 1, 2]], _BOX_QUADS[:, [0, 2, 3]]])


def mesh(vertices: ArrayLike, faces: ArrayLike, material: str | ArrayLike) -> SceneMesh:
    """SceneMesh with one material name for all faces, or an id array per face."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if isinstance(material, str):
        m = np.full(len(f), MATERIAL_ID[material], dtype=np.int64)
    else:
        m = np.asarray(material, dtype=np.int64)
    return SceneMesh(np.asarray(vertices, dtype=np.float64), f, m)


def boxes(T_world_box: ArrayLike, size: ArrayLike, material: str) -> SceneMesh:
    """Oriented boxes centred at the frames' origins.

    T_world_box: (n, 4, 4) or (4, 4); size: (3,) or (n, 3) extents along the box axes.
    """
    T = np.asarray(T_world_box, dtype=np.float64).reshape(-1, 4, 4)
    n = len(T)
    size = np.broadcast_to(np.asarray(size, dtype=np.float64), (n, 3))
    local = _BOX_CORNERS[None, :, :] * size[:, None, :]
    v = np.einsum("nij,nkj->nki", T[:, :3, :3], local) + T[:, None, :3, 3]
    f = _BOX_FACES[None, :, :] + 8 * np.arange(n)[:, None, None]
    return mesh(v.reshape(-1, 3), f, material)


def frames_from_axes(origin: ArrayLike, x_axis: ArrayLike, z_hint: ArrayLike = (0, 0, 1)) -> F64:
    """Frames (n, 4, 4) with given origins (n, 3) and x axes (n, 3), z close to z_hint."""
    o = np.atleast_2d(np.asarray(origin, dtype=np.float64))
    x = np.atleast_2d(np.asarray(x_axis, dtype=np.float64))
    x = x / np.linalg.norm(x, axis=1, keepdims=True)
    zh = np.broadcast_to(np.asarray(z_hint, dtype=np.float64), x.shape)
    y = np.cross(zh, x)
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    z = np.cross(x, y)
    T = np.zeros((len(x), 4, 4))
    T[:, :3, :3] = np.stack([x, y, z], axis=-1)
    T[:, :3, 3] = o
    T[:, 3, 3] = 1.0
    return T


def grid_faces(n_rings: int, n_prof: int, closed: bool) -> I64:
    """Faces joining n_rings consecutive rings of n_prof vertices each (quads split)."""
    m = n_prof if closed else n_prof - 1
    r = np.arange(n_rings - 1)[:, None] * n_prof
    j = np.arange(m)[None, :]
    a = r + j
    b = r + (j + 1) % n_prof
    c, d = a + n_prof, b + n_prof
    f = np.stack([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], axis=2)
    return f.reshape(-1, 3)


def sweep_rings(rings: ArrayLike, material: str | ArrayLike, closed: bool) -> SceneMesh:
    """Mesh from rings (n_rings, n_prof, 3) of a profile swept along a path.

    material may be a name or (n_prof - 1 or n_prof,) ids per profile edge.
    """
    rings = np.asarray(rings, dtype=np.float64)
    nr, npf, _ = rings.shape
    f = grid_faces(nr, npf, closed)
    if isinstance(material, str):
        return mesh(rings.reshape(-1, 3), f, material)
    per_edge = np.asarray(material, dtype=np.int64)
    m = np.repeat(np.tile(per_edge, nr - 1), 2)
    return mesh(rings.reshape(-1, 3), f, m)


def sweep(
    frames: ArrayLike, profile_yz: ArrayLike, material: str | ArrayLike, closed: bool
) -> SceneMesh:
    """Sweep a 2D profile (m, 2) given in the frames' (y, z) plane along frames (n, 4, 4)."""
    T = np.asarray(frames, dtype=np.float64)
    prof = np.asarray(profile_yz, dtype=np.float64)
    rings = (
        T[:, None, :3, 3]
        + prof[None, :, 0:1] * T[:, None, :3, 1]
        + prof[None, :, 1:2] * T[:, None, :3, 2]
    )
    return sweep_rings(rings, material, closed)


def cylinders(
    p0: ArrayLike, p1: ArrayLike, r0: ArrayLike, r1: ArrayLike, material: str, sides: int = 8
) -> SceneMesh:
    """Tapered closed cylinders from p0 (n, 3) to p1 (n, 3), radii r0, r1 (n,) or scalar."""
    p0 = np.atleast_2d(np.asarray(p0, dtype=np.float64))
    p1 = np.atleast_2d(np.asarray(p1, dtype=np.float64))
    n = len(p0)
    r0 = np.broadcast_to(np.asarray(r0, dtype=np.float64), (n,))
    r1 = np.broadcast_to(np.asarray(r1, dtype=np.float64), (n,))
    ax = p1 - p0
    ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    hint = np.where(np.abs(ax[:, 2:3]) > 0.9, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    u = np.cross(ax, hint)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(ax, u)
    a = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    circ = np.cos(a)[None, :, None] * u[:, None, :] + np.sin(a)[None, :, None] * w[:, None, :]
    bottom = p0[:, None, :] + r0[:, None, None] * circ
    top = p1[:, None, :] + r1[:, None, None] * circ
    v = np.concatenate([bottom, top, p0[:, None, :], p1[:, None, :]], axis=1)  # (n, 2s+2, 3)
    side = grid_faces(2, sides, closed=True)
    j = np.arange(sides)
    cap0 = np.stack([np.full(sides, 2 * sides), (j + 1) % sides, j], -1)
    cap1 = np.stack([np.full(sides, 2 * sides + 1), sides + j, sides + (j + 1) % sides], -1)
    f1 = np.concatenate([side, cap0, cap1])
    f = f1[None] + (2 * sides + 2) * np.arange(n)[:, None, None]
    return mesh(v.reshape(-1, 3), f.reshape(-1, 3), material)


@lru_cache(maxsize=4)
def icosphere(subdiv: int) -> tuple[F64, I64]:
    """Unit icosphere (vertices (n, 3), faces (m, 3)) with ``subdiv`` subdivisions."""
    t = (1.0 + 5**0.5) / 2.0
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
         [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]  # fmt: skip
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]  # fmt: skip
    verts = np.array(v, dtype=np.float64)
    faces = np.array(f, dtype=np.int64)
    for _ in range(subdiv):
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        key = np.sort(edges, axis=1)
        uniq, inv = np.unique(key, axis=0, return_inverse=True)
        mids = 0.5 * (verts[uniq[:, 0]] + verts[uniq[:, 1]])
        idx = len(verts) + inv.reshape(3, -1).T  # (m, 3): mid of 01, 12, 20
        verts = np.vstack([verts, mids])
        a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
        ab, bc, ca = idx[:, 0], idx[:, 1], idx[:, 2]
        faces = np.concatenate(
            [np.stack(x, -1) for x in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))]
        )
    verts /= np.linalg.norm(verts, axis=1, keepdims=True)
    return verts, faces


def blobs(
    centers: ArrayLike, radii: ArrayLike, rng: np.random.Generator, material: str,
    noise: float = 0.25, subdiv: int = 1,
) -> SceneMesh:  # fmt: skip
    """Noisy ellipsoids (foliage, bushes): centres (n, 3), radii (n, 3)."""
    c = np.atleast_2d(np.asarray(centers, dtype=np.float64))
    r = np.atleast_2d(np.asarray(radii, dtype=np.float64))
    v0, f0 = icosphere(subdiv)
    n = len(c)
    jitter = 1.0 + noise * rng.uniform(-1.0, 1.0, size=(n, len(v0), 1))
    v = c[:, None, :] + v0[None] * r[:, None, :] * jitter
    f = f0[None] + len(v0) * np.arange(n)[:, None, None]
    return mesh(v.reshape(-1, 3), f.reshape(-1, 3), material)


def quad_strip(left: ArrayLike, right: ArrayLike, material: str) -> SceneMesh:
    """Ribbon between two polylines (n, 3) (e.g. a road), faces up if left is on the left."""
    pts = np.stack([np.asarray(right, np.float64), np.asarray(left, np.float64)], axis=1)
    return sweep_rings(pts, material, closed=False)


def polygon_cap(ring: ArrayLike, material: str, flip: bool = False) -> SceneMesh:
    """Fan triangulation of a convex planar polygon (m, 3)."""
    ring = np.asarray(ring, dtype=np.float64)
    m = len(ring)
    j = np.arange(1, m - 1)
    f = np.stack([np.zeros(m - 2, np.int64), j, j + 1], -1)
    if flip:
        f = f[:, ::-1]
    return mesh(ring, f, material)
