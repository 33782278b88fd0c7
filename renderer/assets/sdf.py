"""Signed-distance primitives, smooth unions and marching-cubes meshing.

An obstacle is a list of :class:`Part` s: a signed-distance function (negative inside,
metres, object frame x forward / y left / z up) with a region label and a blend radius.
:func:`mesh_parts` combines them by smooth minimum, cuts everything below the ground plane
``z = 0`` (so feet, rocks and trunks stand flat on it), samples the field on a regular grid
and meshes the zero level with ``skimage.measure.marching_cubes``. Each vertex gets the
label of the part nearest to it, from which the builders colour the regions.

Evaluation is sparse: each part is evaluated only inside its own bounding box (padded by
the blend radius and two voxels); elsewhere the field is clamped at that padding, which
marching cubes cannot tell from the true distance since only the sign and the values next
to the surface matter. Costs are proportional to the parts' volumes, not the grid's.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.measure import marching_cubes

F64 = NDArray[np.float64]
SdfFn = Callable[[F64], F64]
"""(n, 3) points -> (n,) signed distance (m), negative inside."""

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------
# primitives: each returns a function of (n, 3) points
# --------------------------------------------------------------------------------------


def sphere(center: ArrayLike, radius: float) -> SdfFn:
    """Sphere of ``radius`` around ``center`` (3,)."""
    c = np.asarray(center, dtype=np.float64)

    def f(p: F64) -> F64:
        return np.linalg.norm(p - c, axis=1) - radius

    return f


def ellipsoid(center: ArrayLike, radii: ArrayLike, R: ArrayLike | None = None) -> SdfFn:
    """Ellipsoid with semi-axes ``radii`` (3,) along the columns of rotation ``R`` (3, 3).

    Uses the first-order bound ``k0 (k0 - 1) / k1`` (Quilez): exact on the surface, a
    good approximation near it, which is all marching cubes needs.
    """
    c = np.asarray(center, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    Rm = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)

    def f(p: F64) -> F64:
        q = (p - c) @ Rm
        k0 = np.linalg.norm(q / r, axis=1)
        k1 = np.linalg.norm(q / (r * r), axis=1)
        return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)

    return f


def capsule(a: ArrayLike, b: ArrayLike, ra: float, rb: float | None = None) -> SdfFn:
    """Segment ``a`` -> ``b`` (3,) swept by a radius going linearly from ``ra`` to ``rb``.

    With ``rb`` given this is a tapered capsule (a cone between two spheres, the radius
    interpolated along the segment; close to the exact round cone while ``|ra - rb|`` is
    small against the length).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    rb = ra if rb is None else rb
    ab = b - a
    denom = max(float(ab @ ab), 1e-12)

    def f(p: F64) -> F64:
        ap = p - a
        h = np.clip(ap @ ab / denom, 0.0, 1.0)
        return np.linalg.norm(ap - h[:, None] * ab, axis=1) - (ra + (rb - ra) * h)

    return f


def rounded_box(
    center: ArrayLike, half: ArrayLike, radius: float, R: ArrayLike | None = None
) -> SdfFn:
    """Box of half extents ``half`` (3,) (rounding included) with edges rounded by
    ``radius``, axes the columns of ``R`` (3, 3)."""
    c = np.asarray(center, dtype=np.float64)
    h = np.asarray(half, dtype=np.float64) - radius
    Rm = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)

    def f(p: F64) -> F64:
        q = np.abs((p - c) @ Rm) - h
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return outside + inside - radius

    return f


def displaced(base: SdfFn, noise: Callable[[F64], F64], amplitude: float) -> SdfFn:
    """``base`` plus ``amplitude * noise(p)`` (noise in [-1, 1]): organic, irregular
    surfaces. No longer an exact distance; keep ``amplitude`` below the feature size."""

    def f(p: F64) -> F64:
        return base(p) + amplitude * noise(p)

    return f


def intersect_halfspace(base: SdfFn, normal: ArrayLike, offset: float) -> SdfFn:
    """``base`` cut by the half-space ``normal . p <= offset`` (a flat facet)."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)

    def f(p: F64) -> F64:
        return np.maximum(base(p), p @ n - offset)

    return f


class SmoothNoise:
    """Smooth 3D noise in [-1, 1]: a sum of random plane waves.

    Parameters
    ----------
    rng : generator the wave directions, frequencies and phases are drawn from.
    frequency : mean spatial frequency (cycles per metre).
    octaves : number of wave groups, each twice the frequency and half the amplitude of
        the previous.
    waves : plane waves per octave.
    """

    def __init__(
        self, rng: np.random.Generator, frequency: float, octaves: int = 3, waves: int = 6
    ) -> None:
        k, amp, ph = [], [], []
        for o in range(octaves):
            d = rng.normal(size=(waves, 3))
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            fr = frequency * 2.0**o * rng.uniform(0.7, 1.3, size=waves)
            k.append(2.0 * np.pi * d * fr[:, None])
            amp.append(np.full(waves, 0.5**o))
            ph.append(rng.uniform(0.0, 2.0 * np.pi, size=waves))
        self.k = np.concatenate(k)
        self.amp = np.concatenate(amp)
        self.amp /= self.amp.sum() * 0.45  # typical |value| ~0.5, rarely beyond 1
        self.phase = np.concatenate(ph)

    def __call__(self, p: F64) -> F64:
        """(n, 3) points -> (n,) values, clipped to [-1, 1]."""
        return np.clip(np.sin(p @ self.k.T + self.phase) @ self.amp, -1.0, 1.0)


# --------------------------------------------------------------------------------------
# parts and meshing
# --------------------------------------------------------------------------------------


@dataclass
class Part:
    """One primitive of an obstacle.

    Attributes
    ----------
    sdf : the signed distance function.
    lo, hi : (3,) corners of a box that contains the part (its zero level set).
    label : region name (``skin``, ``shirt``, ``horn`` ...), used for colours.
    blend : smooth-minimum radius (m) with which it joins the parts before it.
    """

    sdf: SdfFn
    lo: F64
    hi: F64
    label: str
    blend: float = 0.0


def part_sphere(center: ArrayLike, radius: float, label: str, blend: float = 0.0) -> Part:
    """A :func:`sphere` as a :class:`Part`."""
    c = np.asarray(center, dtype=np.float64)
    return Part(sphere(c, radius), c - radius, c + radius, label, blend)


def part_ellipsoid(
    center: ArrayLike,
    radii: ArrayLike,
    label: str,
    blend: float = 0.0,
    R: ArrayLike | None = None,
    pad: float = 0.0,
) -> Part:
    """An :func:`ellipsoid` as a :class:`Part`; ``pad`` enlarges the box (for noise)."""
    c = np.asarray(center, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    Rm = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)
    ext = np.abs(Rm) @ r + pad  # box of the rotated ellipsoid (conservative)
    return Part(ellipsoid(c, r, Rm), c - ext, c + ext, label, blend)


def part_capsule(
    a: ArrayLike, b: ArrayLike, ra: float, rb: float | None, label: str, blend: float = 0.0
) -> Part:
    """A :func:`capsule` as a :class:`Part`."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    r = max(ra, ra if rb is None else rb)
    return Part(capsule(a, b, ra, rb), np.minimum(a, b) - r, np.maximum(a, b) + r, label, blend)


def part_box(
    center: ArrayLike,
    half: ArrayLike,
    radius: float,
    label: str,
    blend: float = 0.0,
    R: ArrayLike | None = None,
) -> Part:
    """A :func:`rounded_box` as a :class:`Part`."""
    c = np.asarray(center, dtype=np.float64)
    h = np.asarray(half, dtype=np.float64)
    Rm = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)
    ext = np.abs(Rm) @ h
    return Part(rounded_box(c, h, radius, Rm), c - ext, c + ext, label, blend)


def smin(a: F64, b: F64, k: float) -> F64:
    """Polynomial smooth minimum of two distance arrays with blend radius ``k`` (m)."""
    if k <= 0.0:
        return np.minimum(a, b)
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


@dataclass
class SdfMesh:
    """Output of :func:`mesh_parts`.

    vertices : (n, 3) float64; faces : (m, 3) int64, counter-clockwise seen from outside;
    labels : (n,) int64 index into ``label_names``; label_names : region names;
    voxel : the grid spacing used (m).
    """

    vertices: F64
    faces: NDArray[np.int64]
    labels: NDArray[np.int64]
    label_names: list[str]
    voxel: float = 0.0


def mesh_parts(
    parts: Sequence[Part], voxel: float, ground_cut: bool = True, max_faces: int | None = None
) -> SdfMesh:
    """Smooth union of ``parts`` meshed by marching cubes.

    Parameters
    ----------
    parts : the primitives, joined in order (``smin`` with each part's ``blend``).
    voxel : grid spacing (m); faces scale roughly as area / voxel^2.
    ground_cut : intersect with ``z >= 0`` (flat contact with the ground).
    max_faces : if the mesh has more faces, it is meshed again once with the voxel
        enlarged by ``sqrt(faces / (0.95 * max_faces))``.

    Returns
    -------
    SdfMesh, closed and oriented outward (the sign is checked and fixed).
    """
    if not parts:
        raise ValueError("no parts to mesh")
    out = _mesh_parts(parts, voxel, ground_cut)
    if max_faces is not None and len(out.faces) > max_faces:
        grow = float(np.sqrt(len(out.faces) / (0.95 * max_faces)))
        logger.debug("%d faces > %d: voxel x %.3f", len(out.faces), max_faces, grow)
        out = _mesh_parts(parts, voxel * grow, ground_cut)
        out.voxel = voxel * grow
    return out


def _mesh_parts(parts: Sequence[Part], voxel: float, ground_cut: bool) -> SdfMesh:
    if voxel <= 0.0:
        raise ValueError(f"voxel must be positive, got {voxel}")
    max_blend = max(p.blend for p in parts)
    pad = 2.0 * voxel + max_blend
    lo = np.min([p.lo for p in parts], axis=0) - pad
    hi = np.max([p.hi for p in parts], axis=0) + pad
    if ground_cut:
        lo[2] = -2.0 * voxel
    # z = 0 must fall between two samples (no vertex exactly on a grid node).
    lo[2] = np.floor(lo[2] / voxel) * voxel - 0.5 * voxel
    shape = np.ceil((hi - lo) / voxel).astype(int) + 1
    if np.prod(shape) > 60e6:
        raise ValueError(f"grid {tuple(shape)} too large: raise the voxel size")
    field = np.full(tuple(shape), pad, dtype=np.float64)

    for part in parts:
        i0 = np.clip(np.floor((part.lo - pad - lo) / voxel).astype(int), 0, shape - 1)
        i1 = np.clip(np.ceil((part.hi + pad - lo) / voxel).astype(int) + 1, 1, shape)
        axes = [lo[d] + voxel * np.arange(i0[d], i1[d]) for d in range(3)]
        gx, gy, gz = np.meshgrid(*axes, indexing="ij")
        pts = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
        d = np.minimum(part.sdf(pts).reshape(gx.shape), pad)
        block = field[i0[0] : i1[0], i0[1] : i1[1], i0[2] : i1[2]]
        field[i0[0] : i1[0], i0[1] : i1[1], i0[2] : i1[2]] = smin(block, d, part.blend)

    if ground_cut:
        z = lo[2] + voxel * np.arange(shape[2])
        field = np.maximum(field, -z[None, None, :])
    # closed surface: the border of the grid is outside
    field[[0, -1], :, :] = pad
    field[:, [0, -1], :] = pad
    field[:, :, [0, -1]] = pad
    if field.min() >= 0.0:
        raise ValueError("the parts enclose no volume at this voxel size")

    verts, faces, _, _ = marching_cubes(field, level=0.0, spacing=(voxel,) * 3)
    verts = verts.astype(np.float64) + lo
    faces = faces.astype(np.int64)
    verts, faces = drop_small_components(verts, faces)
    if _signed_volume(verts, faces) < 0.0:
        faces = faces[:, ::-1].copy()

    names = sorted({p.label for p in parts})
    label_id = np.array([names.index(p.label) for p in parts])
    dist = np.stack([p.sdf(verts) for p in parts], axis=1)
    labels = label_id[np.argmin(dist, axis=1)]
    logger.debug(
        "sdf mesh: grid %s, voxel %.4f m, %d vertices, %d faces",
        tuple(shape),
        voxel,
        len(verts),
        len(faces),
    )
    return SdfMesh(verts, faces, labels.astype(np.int64), names, voxel)


def drop_small_components(
    verts: F64, faces: NDArray[np.int64], min_fraction: float = 0.01
) -> tuple[F64, NDArray[np.int64]]:
    """Remove connected pieces with fewer than ``min_fraction`` of the faces (noise
    bubbles inside foliage, crumbs of thin parts below the grid resolution)."""
    n = len(verts)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    n_comp, comp = connected_components(graph, directed=False)
    if n_comp == 1:
        return verts, faces
    face_comp = comp[faces[:, 0]]
    sizes = np.bincount(face_comp, minlength=n_comp)
    keep_face = sizes[face_comp] >= min_fraction * len(faces)
    faces = faces[keep_face]
    used = np.zeros(n, dtype=bool)
    used[faces.ravel()] = True
    new_index = np.cumsum(used) - 1
    logger.debug("dropped %d small pieces", int((sizes < min_fraction * len(faces)).sum()))
    return verts[used], new_index[faces]


def _signed_volume(v: F64, f: NDArray[np.int64]) -> float:
    """Volume enclosed by a closed triangle mesh (positive if oriented outward)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
