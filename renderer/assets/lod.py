"""Levels of detail: quadric decimation and the face budget from the projected size.

:func:`simplify` decimates an :class:`~renderer.mesh.ObjectMesh` with open3d's quadric
error metric and carries colours and reflectivity over from the nearest original vertex.

:func:`choose_detail` turns the object's projected height (pixels) into a face budget.
The rule follows from the geometry of a silhouette: with F faces spread over a surface
of size H (m), edges are ~H / sqrt(F) long and the chord error on a curved outline of
radius ~H is ~edge^2 / (8 H) ~ H / (8 F); in pixels, with h = fx H / Z the projected
height, the outline moves by ~h / (8 F). Keeping that under a tolerance gives a budget
*linear* in the projected height, ``F = FACES_PER_PX * h``; scripts/bench_lod.py measures
the constant on the six obstacles (the faces at which the silhouette at 80 m in
rgb_highres_center, fx = 7268 px, first moves by more than 1 px) and checks the linearity
at other distances.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from renderer.mesh import ObjectMesh

F64 = NDArray[np.float64]
logger = logging.getLogger(__name__)

FACES_PER_PX = 16.0
"""Face budget per pixel of projected height. scripts/bench_lod.py (fx 7268, 20-160 m,
three views) measured 5-15.5 faces/px for person, rock, cow, horse and elephant (one
rock outlier at 19 within the benchmark's sqrt(2) face steps): the silhouette then stays
within one pixel (Hausdorff <= 1.5 px) of the full mesh's. The fallen tree's foliage
needs ~12k faces whatever the distance: ``meta["lod_faces_per_px"]``."""
MIN_FACES = 200
"""Never fewer faces: below this the shapes lose their parts (legs, trunk, head)."""
MAX_FACES = 60_000
"""Budget cap; the library's meshes have fewer at detail 1."""


def choose_detail(projected_height_px: float, faces_per_px: float = FACES_PER_PX) -> int:
    """Face budget for an object whose image height is ``projected_height_px``.

    ``clip(ceil(faces_per_px * h), MIN_FACES, MAX_FACES)``; objects whose outline is
    mostly fine detail carry their own constant in ``mesh.meta["lod_faces_per_px"]``
    (the fallen tree's foliage: pass it as ``faces_per_px``). Pass the result to
    :func:`simplify` (which leaves meshes with fewer faces untouched). An object 1.8 m
    tall at 80 m in rgb_highres_center (164 px) gets 2624 faces, an elephant at 3 m the
    cap. Non-finite or non-positive heights (behind the camera) give ``MIN_FACES``.
    """
    h = float(projected_height_px)
    if not np.isfinite(h) or h <= 0.0:
        return MIN_FACES
    return int(np.clip(np.ceil(faces_per_px * h), MIN_FACES, MAX_FACES))


def simplify(mesh: ObjectMesh, target_faces: int) -> ObjectMesh:
    """Quadric-error decimation to about ``target_faces`` faces, colours kept.

    Parameters
    ----------
    mesh : the full mesh (not modified).
    target_faces : wanted face count (>= 4); a mesh with no more faces is returned as a
        copy unchanged.

    Returns
    -------
    ObjectMesh with <= ~target_faces faces; colours and reflectivity of each new vertex
    from the nearest original vertex; meta copied with ``lod_faces`` set. A mesh with
    UVs (textured) is returned as a copy, undecimated; materials without UVs (plain,
    triplanar procedural textures) are kept, each new face taking the material of the
    original vertex nearest to its first vertex.
    """
    target = max(int(target_faces), 4)
    if len(mesh.faces) <= target or mesh.uv is not None:
        # Textured meshes keep their geometry: decimation would tear the UV seams, and
        # their detail is in the texture (mipmapped), not in the face count.
        return mesh.with_vertices(mesh.vertices.copy())
    o3m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices),
        o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)),
    )
    out = o3m.simplify_quadric_decimation(target_number_of_triangles=target)
    out.remove_degenerate_triangles()
    out.remove_unreferenced_vertices()
    v = np.asarray(out.vertices, dtype=np.float64)
    f = np.asarray(out.triangles, dtype=np.int64)
    _, nearest = cKDTree(mesh.vertices).query(v)
    meta = dict(mesh.meta)
    meta["lod_faces"] = len(f)
    logger.debug("simplify %s: %d -> %d faces", mesh.name, len(mesh.faces), len(f))
    # materials (no UVs here: plain or triplanar) carried over like the colours, each
    # new face taking the material of its first vertex's nearest original vertex
    fm = None
    if mesh.materials:
        vm = np.zeros(len(mesh.vertices), np.int32)
        vm[mesh.faces[:, 0]] = mesh.surface[1]
        fm = vm[nearest[f[:, 0]]]
    return ObjectMesh(v, f, mesh.colors[nearest], mesh.reflectivity[nearest], mesh.name, meta,
                      materials=list(mesh.materials), face_material=fm)  # fmt: skip


# --------------------------------------------------------------------------------------
# silhouettes (for the LOD benchmark and tests)
# --------------------------------------------------------------------------------------


def view_camera(yaw_deg: float, distance: float, cam_height: float = 2.5) -> F64:
    """T_cam_obj (4, 4) of a level pinhole camera (optical: x right, y down, z forward)
    ``distance`` m from the object origin, looking at it horizontally from azimuth
    ``yaw_deg`` (0 = in front of the object, on its +x axis; 90 = on its left side)."""
    a = np.deg2rad(yaw_deg)
    c = np.array([distance * np.cos(a), distance * np.sin(a), cam_height])
    z = -np.array([np.cos(a), np.sin(a), 0.0])  # forward, horizontal
    x = np.cross(z, [0.0, 0.0, 1.0])  # right
    y = np.cross(z, x)  # down
    R_obj_cam = np.stack([x, y, z], axis=1)
    T = np.eye(4)
    T[:3, :3] = R_obj_cam.T
    T[:3, 3] = -R_obj_cam.T @ c
    return T


def project(vertices: F64, T_cam_obj: F64, fx: float) -> F64:
    """Pinhole projection (n, 2) in pixels, principal point at the origin."""
    p = vertices @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    return fx * p[:, :2] / p[:, 2:3]


def rasterize(uv: F64, faces: NDArray[np.int64], origin: F64, shape: tuple[int, int]) -> NDArray:
    """Silhouette mask (h, w) bool of triangles ``uv[faces]`` (pixels), the pixel (0, 0)
    at ``origin`` (2,). Sub-pixel vertex positions (1/256 px)."""
    shift = 8
    mask = np.zeros(shape, dtype=np.uint8)
    tri = np.round((uv[faces] - origin) * (1 << shift)).astype(np.int32)
    for t in tri:
        cv2.fillConvexPoly(mask, t, 1, lineType=cv2.LINE_8, shift=shift)
    return mask.astype(bool)


def mask_change(a: NDArray, b: NDArray) -> dict[str, float]:
    """How two silhouettes differ: IoU, differing pixels, and the largest distance (px)
    of a pixel of one mask's outline to the other's outline (symmetric Hausdorff)."""
    inter = np.logical_and(a, b).sum()
    union = np.logical_or(a, b).sum()
    xor = int(np.logical_xor(a, b).sum())

    def outline(m: NDArray) -> NDArray:
        m8 = m.astype(np.uint8)
        return (m8 - cv2.erode(m8, np.ones((3, 3), np.uint8))).astype(bool)

    def dist_to(m: NDArray) -> NDArray:
        return cv2.distanceTransform((~outline(m)).astype(np.uint8), cv2.DIST_L2, 5)

    oa, ob = outline(a), outline(b)
    h = 0.0
    if oa.any() and ob.any():
        h = float(max(dist_to(b)[oa].max(), dist_to(a)[ob].max()))
    return {"iou": float(inter / max(union, 1)), "xor_px": xor, "hausdorff_px": h}
