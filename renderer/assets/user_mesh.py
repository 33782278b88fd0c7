"""User meshes: glTF / GLB, OBJ (+ MTL and textures in an archive), PLY, STL and OFF uploads
turned into an :class:`ObjectMesh`.

Untrusted input (RELIABILITY.md): the bytes are parsed with an explicit file type (never
guessed, never read from a path), glTF files may not reference anything outside
themselves (``uri`` s other than ``data:`` URIs are refused before anything is parsed)
unless they come in an archive, vertex and face counts are capped from the headers
*before* parsing where the format says them (PLY, STL, glTF accessors, OBJ line counts)
and again after, texture images are capped in pixels, and every failure is a
:class:`MeshError` (a ``ValueError``) saying what is wrong. Cap the upload's byte size
where it is received (the service streams it with a limit).

Archives (``zip``, ``tar``, ``tar.gz`` / ``tgz``): an OBJ with its MTL and texture
images (or a glTF with its .bin and images, or any single mesh file) uploaded together.
The archive is extracted by :func:`osdar_platform.archive_safety.extract_archive` (no
absolute or ``..`` paths, no links, size and ratio caps) into a temporary folder that is
removed afterwards; it must hold exactly one mesh file, and the files it references are
read only from inside that folder (a reference leaving it is a MeshError).

Geometry: each format's own convention is the default (``up=None``): glTF / GLB are +Y
up with their front towards +Z (the glTF specification), mapped to the object frame's
+z up and +x forward; OBJ, PLY and STL have no convention and are taken as +Z up with
+x forward (``DEFAULT_UP``). ``up`` overrides it. Units: metres (glTF by its
specification; the others by assumption, with a warning when the size is implausible,
< 0.05 m or > 50 m) unless ``scale`` (metres per file unit) is given. Then the mesh is
re-centred so that the origin is the ground-contact centre: min z = 0, x and y the
centre of the footprint (the bounding box of the vertical projection). Closed meshes
with inward faces are flipped.

glTF content (:mod:`renderer.assets.gltf_reader`): node hierarchy, skins and morph
targets posed at rest or at ``animation_time_s`` of an animation; materials as
:class:`~renderer.mesh.Material` (base colour factor and texture, normal map, metallic /
roughness, alpha mask) rendered per pixel by the renderer. OBJ / PLY / STL through
trimesh: OBJ UVs and the MTL's diffuse colour and ``map_Kd`` texture (``map_bump`` /
``norm`` normal maps when present), PLY / OBJ per-vertex colours.

Colours: vertex colours (COLOR_0, PLY colours, face colours averaged) multiply the
material; 8-bit sRGB values are converted to linear RGB. Lidar reflectivity per vertex
follows the albedo at the vertex (vertex colour x base colour x texture at its UV):
``0.08 + 0.6 * luminance``, as in the built-in library.
"""

from __future__ import annotations

import io
import json
import logging
import re
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import trimesh
from numpy.typing import NDArray

from osdar_platform.archive_safety import ArchiveLimits, UnsafeArchive, extract_archive
from renderer.assets.gltf_reader import GltfError, Resolver, decode_image, read_gltf
from renderer.assets.obstacles import srgb_to_linear
from renderer.mesh import Material, ObjectMesh

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
MESH_TYPES = ("glb", "gltf", "obj", "ply", "stl", "off")
ARCHIVE_TYPES = ("zip", "tar", "tar.gz", "tgz")
FILE_TYPES = MESH_TYPES + ARCHIVE_TYPES
DEFAULT_UP = {"glb": "y", "gltf": "y", "obj": "z", "ply": "z", "stl": "z", "off": "z"}
"""The up axis assumed for each format when ``up`` is not given."""
DEFAULT_SRGB = 0.58
"""Grey (sRGB) of meshes without colours."""
PLAUSIBLE_SIZE_M = (0.05, 50.0)
ARCHIVE_LIMITS = ArchiveLimits(max_members=2_000, max_total_bytes=512 * 1024**2)

# Rotations taking the file's up axis to +z (proper rotations, det +1).
_UP: dict[str, NDArray[np.float64]] = {
    "z": np.eye(3),
    "-z": np.diag([1.0, -1.0, -1.0]),
    "y": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),  # +Z front -> +x
    "-y": np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
    "x": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
    "-x": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]),
}


class MeshError(ValueError):
    """An uploaded mesh that cannot be used; the message says why."""


@dataclass
class _Part:
    """One piece of the file before merging: positions in the file frame."""

    positions: F64
    faces: NDArray[np.int64]
    material: Material
    normals: F64 | None = None
    uv: F64 | None = None  # glTF convention (v = 0 at the image top)
    tangents: F64 | None = None
    colors: F64 | None = None  # (n, 3) linear
    source: str = "default"


@dataclass
class _Merged:
    v: F64
    f: NDArray[np.int64]
    normals: F64
    uv: F64 | None
    tangents: F64 | None
    colors: F64
    materials: list[Material]
    face_material: NDArray[np.int32]
    sources: set[str] = field(default_factory=set)


def load_user_mesh(
    data: bytes,
    file_type: str,
    *,
    scale: float | None = None,
    up: str | None = None,
    max_vertices: int = 500_000,
    max_faces: int = 1_000_000,
    name: str = "custom",
    animation_time_s: float | None = None,
    animation: int | str | None = None,
) -> ObjectMesh:
    """Parse an uploaded mesh (or archive) into an :class:`ObjectMesh` standing on the ground.

    Parameters
    ----------
    data : the file's bytes (a GLB, a self-contained glTF JSON, an OBJ, a PLY, an STL,
        or a zip / tar / tar.gz archive holding one mesh file and what it references).
    file_type : one of ``FILE_TYPES`` (a leading dot and case ignored).
    scale : metres per file unit; None = the file is in metres.
    up : the file's up axis, one of ``z``, ``y``, ``x``, ``-z``, ``-y``, ``-x``; None =
        the format's convention (``DEFAULT_UP``: glTF +Y, others +Z).
    max_vertices, max_faces : caps on the whole mesh (all parts of a scene together).
    name : the object's class name for the annotations.
    animation_time_s : glTF only: pose skins and morph targets at this time (s) of the
        animation (looped over its duration); None = rest pose.
    animation : glTF only: which animation (index or name), default the first.

    Returns
    -------
    ObjectMesh in the object frame (x forward, y left, z up, origin at the
    ground-contact centre), with UVs, normals, tangents and materials; meta records the
    source type, the original extent, the colour source, the scale, the up axis and the
    pose (animation, time, skinned / morphed primitives).

    Raises
    ------
    MeshError : unknown type, unparsable bytes, external references, over the caps,
        empty, non-finite, bad scale or up axis, unsafe archive.
    """
    ft = _check_arguments(data, file_type, scale, up)
    data = bytes(data)
    if ft in ARCHIVE_TYPES:
        return _load_archive(data, ft, scale=scale, up=up, max_vertices=max_vertices,
                             max_faces=max_faces, name=name, animation_time_s=animation_time_s,
                             animation=animation)  # fmt: skip
    return _load(data, ft, None, scale=scale, up=up, max_vertices=max_vertices,
                 max_faces=max_faces, name=name, animation_time_s=animation_time_s,
                 animation=animation)  # fmt: skip


def _load(
    data: bytes,
    ft: str,
    resolve: Resolver | None,
    *,
    scale: float | None,
    up: str | None,
    max_vertices: int,
    max_faces: int,
    name: str,
    animation_time_s: float | None,
    animation: int | str | None,
) -> ObjectMesh:
    up_axis = DEFAULT_UP[ft] if up is None else up
    _precheck(data, ft, max_vertices, max_faces, external_ok=resolve is not None)
    pose: dict = {}
    if ft in ("glb", "gltf"):
        try:
            scene = read_gltf(data, ft, animation_time_s=animation_time_s, animation=animation,
                              resolve=resolve)  # fmt: skip
        except GltfError as e:
            raise MeshError(str(e)) from e
        parts = [_Part(p.positions, p.faces, p.material, p.normals, p.uv, p.tangents,
                       None if p.colors is None else p.colors[:, :3], _gltf_source(p))
                 for p in scene.primitives]  # fmt: skip
        pose = scene.info
    else:
        if animation_time_s is not None:
            logger.warning("%s: animation_time_s applies to glTF only; ignored for %s", name, ft)
        parts = [_part_of(g) for g in _parse(data, ft, resolve)]
    m = _merge(parts, ft)
    _check_merged(m.v, m.f, max_vertices, max_faces)
    R = _UP[up_axis]
    v = m.v @ R.T
    normals = m.normals @ R.T
    tangents = m.tangents
    if tangents is not None:
        tangents = np.concatenate([tangents[:, :3] @ R.T, tangents[:, 3:]], axis=1)
    extent_file = np.ptp(v, axis=0)
    v = _to_metres(v, extent_file, scale, name)
    v = _on_the_ground(v)
    f = m.f
    tm = trimesh.Trimesh(v, f, process=False)
    flipped = False
    if tm.is_watertight and tm.volume < 0.0:
        f = f[:, ::-1].copy()
        normals = -normals
        flipped = True
    elif not tm.is_watertight:
        logger.info("%s: mesh is not closed; face orientation taken as given", name)
    if m.uv is not None and tangents is None and any(x.normal_texture is not None
                                                     for x in m.materials):  # fmt: skip
        tangents = compute_tangents(v, f, normals, m.uv)

    refl = _reflectivity(m)
    meta = {
        "class": name,
        "source": ft,
        "scale": 1.0 if scale is None else float(scale),
        "up": up_axis,
        "file_extent": [float(x) for x in extent_file],
        "color_source": "+".join(sorted(m.sources)),
        "flipped": flipped,
        "watertight": bool(tm.is_watertight),
        "textured": any(x.textured for x in m.materials),
        "materials": [x.name for x in m.materials],
    }
    if pose:
        meta["pose"] = {k: v for k, v in pose.items() if v is not None}
    mesh = ObjectMesh(v, f, m.colors.astype(np.float32), refl, name, meta, uv=m.uv,
                      normals=normals, tangents=tangents, materials=m.materials,
                      face_material=m.face_material)  # fmt: skip
    ext = mesh.size
    meta.update({"length_m": float(ext[0]), "width_m": float(ext[1]), "height_m": float(ext[2])})
    logger.info("user mesh %s (%s): %d vertices, %d faces, size %s m", name, ft, len(v), len(f),
                np.round(ext, 3).tolist())  # fmt: skip
    return mesh


def _gltf_source(p: object) -> str:
    """Where a glTF primitive's colour comes from: vertex (COLOR_0), texture or material."""
    if getattr(p, "colors", None) is not None:
        return "vertex"
    mat = getattr(p, "material", None)
    return "texture" if getattr(mat, "base_color_texture", None) is not None else "material"


def _load_archive(data: bytes, kind: str, **kw: object) -> ObjectMesh:
    """Extract safely, find the one mesh file, load it with references inside the folder."""
    with tempfile.TemporaryDirectory(prefix="osdar_mesh_") as tmp:
        arc = Path(tmp) / f"upload.{kind}"
        arc.write_bytes(data)
        try:
            res = extract_archive(arc, Path(tmp) / "x", ARCHIVE_LIMITS)
        except UnsafeArchive as e:
            raise MeshError(f"archive refused: {e}") from e
        root = res.dest.resolve()
        meshes = sorted(p for p in root.rglob("*") if p.is_file()
                        and p.suffix.lower().lstrip(".") in MESH_TYPES)  # fmt: skip
        if len(meshes) != 1:
            found = [str(p.relative_to(root)) for p in meshes][:10]
            raise MeshError(f"the archive must hold exactly one mesh file ({', '.join(MESH_TYPES)}"
                            f"), found {len(meshes)}: {found}")  # fmt: skip
        path = meshes[0]
        ft = path.suffix.lower().lstrip(".")
        logger.info("archive %s: mesh %s (%d members)", kind, path.relative_to(root), res.members)
        return _load(path.read_bytes(), ft, _folder_resolver(root, path.parent), **kw)  # type: ignore[arg-type]


def _folder_resolver(root: Path, base: Path) -> Resolver:
    """Bytes of a file referenced relative to ``base``, only inside ``root``."""

    def resolve(name: str) -> bytes:
        rel = unquote(str(name)).replace("\\", "/")
        if "\x00" in rel or rel.startswith("/") or re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", rel):
            raise MeshError(f"reference {name[:80]!r} is not a relative path inside the upload")
        p = (base / rel).resolve()
        if not p.is_relative_to(root) or not p.is_file():
            # OBJ exporters often write absolute or foreign paths: try the bare file name.
            alt = (base / Path(rel).name).resolve()
            if alt.is_relative_to(root) and alt.is_file():
                return alt.read_bytes()
            raise MeshError(f"reference {name[:80]!r} is not a file inside the upload")
        return p.read_bytes()

    return resolve


class _TrimeshResolver(trimesh.resolvers.Resolver):
    """trimesh's resolver interface over :func:`_folder_resolver`. trimesh catches the
    errors of material and texture look-ups, so refusals are also kept in ``failures``
    and raised after parsing."""

    def __init__(self, resolve: Resolver) -> None:
        self._resolve = resolve
        self.failures: list[MeshError] = []

    def get(self, name: str) -> bytes:
        try:
            return self._resolve(name)
        except MeshError as e:
            self.failures.append(e)
            raise

    def keys(self) -> list[str]:
        return []

    def write(self, name: str, data: object) -> None:  # never used for loading
        raise MeshError("writing is not allowed")

    def namespaced(self, namespace: str) -> _TrimeshResolver:
        return _TrimeshResolver(lambda n: self._resolve(f"{namespace}/{n}"))


def _check_arguments(data: object, file_type: str, scale: float | None, up: str | None) -> str:
    """The normalised file type; MeshError for a bad type, up axis, scale or empty data."""
    ft = str(file_type).lower().lstrip(".")
    if ft not in FILE_TYPES:
        raise MeshError(f"unsupported mesh type {file_type!r}; use one of {FILE_TYPES}")
    if up is not None and up not in _UP:
        raise MeshError(f"up must be one of {sorted(_UP)}, got {up!r}")
    if scale is not None and not (np.isfinite(scale) and scale > 0.0):
        raise MeshError(f"scale must be a positive number, got {scale}")
    if not isinstance(data, bytes | bytearray | memoryview) or len(data) == 0:
        raise MeshError("empty upload")
    return ft


def _parse(data: bytes, ft: str, resolve: Resolver | None) -> list[trimesh.Trimesh]:
    """The triangle meshes of an OBJ / PLY / STL (trimesh, as a scene); MeshError on any
    failure. Without ``resolve`` an OBJ's material library is not read."""
    try:
        resolver = _TrimeshResolver(resolve) if resolve is not None else None
        kw: dict = {"resolver": resolver} if resolver is not None else {}
        if ft == "obj" and resolve is None:
            kw["skip_materials"] = True
        loaded = trimesh.load(io.BytesIO(data), file_type=ft, force="scene", process=False, **kw)
        if resolver is not None and resolver.failures:
            raise resolver.failures[0]
        geoms = _scene_meshes(loaded)
    except MeshError:
        raise
    except Exception as e:  # trimesh raises many types on bad input
        raise MeshError(f"could not parse the {ft} data: {type(e).__name__}: {e}") from e
    if not geoms:
        raise MeshError(f"the {ft} file contains no triangle mesh")
    return geoms


def _merge(parts: list[_Part], ft: str) -> _Merged:
    """All non-empty parts as one mesh (materials deduplicated by identity)."""
    parts = [p for p in parts if len(p.positions) and len(p.faces)]
    if not parts:
        raise MeshError(f"the {ft} file has no faces (a point cloud or an empty mesh)")
    mats: list[Material] = []
    verts, faces, nrms, uvs, tans, cols, fms = [], [], [], [], [], [], []
    any_uv = any(p.uv is not None for p in parts)
    any_tan = any(p.tangents is not None for p in parts)
    offset = 0
    sources = set()
    for p in parts:
        n = len(p.positions)
        if not any(p.material is m for m in mats):
            mats.append(p.material)
        k = next(i for i, m in enumerate(mats) if m is p.material)
        verts.append(p.positions)
        faces.append(p.faces + offset)
        nrms.append(p.normals if p.normals is not None else welded_normals(p.positions, p.faces))
        uvs.append(p.uv if p.uv is not None else np.zeros((n, 2)))
        tans.append(p.tangents if p.tangents is not None else np.tile([1.0, 0, 0, 1.0], (n, 1)))
        cols.append(p.colors if p.colors is not None else np.ones((n, 3)))
        fms.append(np.full(len(p.faces), k, np.int32))
        sources.add(p.source)
        offset += n
    return _Merged(
        np.concatenate(verts), np.concatenate(faces), np.concatenate(nrms),
        np.concatenate(uvs) if any_uv else None, np.concatenate(tans) if any_tan else None,
        np.concatenate(cols), mats, np.concatenate(fms), sources,
    )  # fmt: skip


def _reflectivity(m: _Merged) -> NDArray[np.float32]:
    """``0.08 + 0.6 * luminance`` of the albedo at each vertex (texture at its UV)."""
    alb = m.colors.copy()
    vm = np.zeros(len(m.v), np.int64)
    vm[m.f[:, 0]] = m.face_material
    for k, mat in enumerate(m.materials):
        sel = vm == k
        alb[sel] *= mat.base_color[:3]
        tex = mat.base_color_texture
        if tex is not None and m.uv is not None and mat.triplanar_m is None:
            h, w = tex.shape[:2]
            uv = np.mod(m.uv[sel], 1.0)
            px = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
            py = np.clip((uv[:, 1] * h).astype(int), 0, h - 1)
            alb[sel] *= srgb_to_linear(tex[py, px, :3] / 255.0)
    lum = alb @ np.array([0.2126, 0.7152, 0.0722])
    return np.clip(0.08 + 0.6 * lum, 0.05, 0.95).astype(np.float32)


CREASE_COS = 0.8
"""Faces meeting at more than acos(0.8) = 36.9 deg are not smoothed together (the
shader's own hard-edge test uses the same angle)."""


def welded_normals(v: F64, f: NDArray[np.int64], crease_cos: float = CREASE_COS) -> F64:
    """(n, 3) area-weighted vertex normals, smoothed across vertices at the same position
    (UV seams do not show as shading seams) but not across creases: each face corner
    sums the faces around its position whose normal is within the crease angle of its
    own face's; a vertex averages its corners."""
    q = np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0)
    key = np.round(q / max(float(np.ptp(q, axis=0).max()), 1e-9) * 2**20).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    tri = q[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # area-weighted
    fu = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    m = len(f)
    corner_face = np.repeat(np.arange(m), 3)
    group = inv[f.reshape(-1)]
    order = np.argsort(group, kind="stable")
    g_sorted = group[order]
    starts = np.searchsorted(g_sorted, g_sorted, side="left")
    counts = np.searchsorted(g_sorted, g_sorted, side="right") - starts
    # every (corner, other corner of its position) pair
    rep = np.repeat(np.arange(len(order)), counts)
    within = np.arange(len(rep)) - np.repeat(np.cumsum(counts) - counts, counts)
    i = order[rep]
    j = order[starts[rep] + within]
    fi, fj = corner_face[i], corner_face[j]
    close = np.einsum("ij,ij->i", fu[fi], fu[fj]) > crease_cos
    corner_n = np.zeros((3 * m, 3))
    np.add.at(corner_n, i[close], fn[fj[close]])
    out = np.zeros_like(q)
    np.add.at(out, f.reshape(-1), corner_n)
    nrm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.where(nrm > 1e-20, out / np.maximum(nrm, 1e-30), np.array([0.0, 0.0, 1.0]))


def compute_tangents(v: F64, f: NDArray[np.int64], n: F64, uv: F64) -> F64:
    """(n, 4) per-vertex tangents from the UV gradients (Lengyel's method, as MikkTSpace
    without its splitting rules): the tangent follows +u; w makes ``cross(n, t) * w``
    (the glTF bitangent, the normal map's green axis) point up the image, i.e. towards
    decreasing v of a glTF-convention uv (v = 0 at the image top)."""
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    w0, w1, w2 = uv[f[:, 0]], uv[f[:, 1]], uv[f[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    d1, d2 = w1 - w0, w2 - w0
    r = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(r) > 1e-20
    inv = np.where(ok, 1.0 / np.where(ok, r, 1.0), 0.0)
    sdir = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * inv[:, None]
    tdir = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * inv[:, None]
    T = np.zeros_like(v)
    B = np.zeros_like(v)
    for k in range(3):
        np.add.at(T, f[:, k], sdir)
        np.add.at(B, f[:, k], tdir)
    t = T - n * np.einsum("ij,ij->i", n, T)[:, None]
    tn = np.linalg.norm(t, axis=1, keepdims=True)
    fallback = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    t = np.where(tn > 1e-12, t / np.maximum(tn, 1e-30), fallback)
    w = np.where(np.einsum("ij,ij->i", np.cross(n, t), B) > 0.0, -1.0, 1.0)
    return np.concatenate([t, w[:, None]], axis=1)


def _check_merged(
    v: NDArray[np.float64], f: NDArray[np.int64], max_vertices: int, max_faces: int
) -> None:
    """The caps again (on what was parsed), finite vertices, faces within range."""
    if len(v) > max_vertices:
        raise MeshError(f"{len(v)} vertices, more than the cap of {max_vertices}")
    if len(f) > max_faces:
        raise MeshError(f"{len(f)} faces, more than the cap of {max_faces}")
    if not np.all(np.isfinite(v)):
        raise MeshError(f"{int((~np.isfinite(v)).any(axis=1).sum())} vertices are NaN or inf")
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError("face indices out of range")


def _to_metres(
    v: NDArray[np.float64], extent_file: NDArray[np.float64], scale: float | None, name: str
) -> NDArray[np.float64]:
    """Scaled by ``scale``, or taken as metres (with a warning when the size is implausible)."""
    if scale is not None:
        return v * scale
    size = float(extent_file.max())
    if not PLAUSIBLE_SIZE_M[0] <= size <= PLAUSIBLE_SIZE_M[1]:
        logger.warning(
            "%s: largest extent %.4g m is implausible for an obstacle (%.2g-%.0f m): "
            "wrong units? pass scale (e.g. 0.01 for cm, 0.001 for mm)",
            name,
            size,
            *PLAUSIBLE_SIZE_M,
        )
    return v


def _on_the_ground(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Re-centred in place: min z = 0, x and y at the centre of the footprint."""
    if float(np.ptp(v, axis=0).max()) <= 0.0:
        raise MeshError("the mesh is degenerate (all vertices at one point)")
    v[:, 2] -= v[:, 2].min()
    v[:, :2] -= 0.5 * (v[:, :2].min(axis=0) + v[:, :2].max(axis=0))
    return v


# --------------------------------------------------------------------------------------
# checks before parsing
# --------------------------------------------------------------------------------------


def _precheck(data: bytes, ft: str, max_vertices: int, max_faces: int, *,
              external_ok: bool = False) -> None:  # fmt: skip
    """Refuse external references (unless in an archive) and over-cap counts from the
    headers."""
    if ft in ("glb", "gltf"):
        _check_gltf(_gltf_json(data, ft), max_vertices, max_faces, external_ok)
    elif ft == "ply":
        head = data[: min(len(data), 64 * 1024)]
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or end < 0:
            raise MeshError("not a PLY file (no 'ply' magic or no end_header)")
        text = head[:end].decode("ascii", errors="replace")
        counts = dict(re.findall(r"element\s+(\w+)\s+(\d+)", text))
        nv, nf = int(counts.get("vertex", 0)), int(counts.get("face", 0))
        _check_counts(nv, nf, max_vertices, max_faces)
    elif ft == "stl":
        if data[:5].lower() == b"solid" and b"facet" in data[:4096]:
            nf = data.count(b"facet normal")
        elif len(data) >= 84:
            nf = struct.unpack_from("<I", data, 80)[0]
            if 84 + 50 * nf != len(data):
                raise MeshError(f"binary STL header says {nf} triangles, the size does not match")
        else:
            raise MeshError("not an STL file (too short)")
        _check_counts(3 * nf, nf, max_vertices, max_faces)
    elif ft == "off":
        m = re.match(rb"\s*OFF\s+(\d+)\s+(\d+)", data[:4096])
        if m is None:
            raise MeshError("not an OFF file (no 'OFF' header with vertex and face counts)")
        _check_counts(int(m.group(1)), int(m.group(2)), max_vertices, max_faces)
    elif ft == "obj":
        nv = data.count(b"\nv ") + data.startswith(b"v ")
        nf = data.count(b"\nf ") + data.startswith(b"f ")
        _check_counts(nv, nf, max_vertices, max_faces)
        if not external_ok and re.search(rb"(?m)^\s*(mtllib|map_\w+)\s", data):
            logger.info("OBJ references material/texture files: upload an archive (.zip, "
                        ".tar.gz) with the .obj, .mtl and images to have them loaded")  # fmt: skip


def _check_counts(nv: int, nf: int, max_vertices: int, max_faces: int) -> None:
    if nv > max_vertices:
        raise MeshError(f"{nv} vertices, more than the cap of {max_vertices}")
    if nf > max_faces:
        raise MeshError(f"{nf} faces, more than the cap of {max_faces}")


def _gltf_json(data: bytes, ft: str) -> dict:
    """The JSON document of a glTF or GLB."""
    try:
        if ft == "glb":
            if len(data) < 20 or data[:4] != b"glTF":
                raise MeshError("not a GLB file (no 'glTF' magic)")
            version, length = struct.unpack_from("<II", data, 4)
            if version != 2:
                raise MeshError(f"GLB version {version}; only glTF 2.0 is supported")
            if length > len(data):
                raise MeshError(f"GLB header says {length} bytes, the upload has {len(data)}")
            clen, ctype = struct.unpack_from("<II", data, 12)
            if ctype != 0x4E4F534A or 20 + clen > len(data):
                raise MeshError("GLB first chunk is not a valid JSON chunk")
            doc = json.loads(data[20 : 20 + clen].decode("utf-8"))
        else:
            doc = json.loads(data.decode("utf-8"))
    except MeshError:
        raise
    except (ValueError, UnicodeDecodeError, struct.error) as e:
        raise MeshError(f"invalid {ft} JSON: {e}") from e
    if not isinstance(doc, dict):
        raise MeshError(f"invalid {ft}: the JSON document is not an object")
    return doc


def _check_gltf(doc: dict, max_vertices: int, max_faces: int, external_ok: bool = False) -> None:
    """Refuse external ``uri`` s (buffers, images; allowed in archives, where they are
    resolved inside the upload) and over-cap accessor counts."""
    for kind in ("buffers", "images"):
        for i, item in enumerate(doc.get(kind) or []):
            uri = item.get("uri") if isinstance(item, dict) else None
            if uri is not None and not str(uri).startswith("data:") and not external_ok:
                raise MeshError(
                    f"glTF {kind}[{i}] references an external resource {str(uri)[:80]!r}: "
                    "only self-contained files (GLB or data: URIs) are accepted"
                )
    accessors = doc.get("accessors") or []

    def count(i: object) -> int:
        if isinstance(i, int) and 0 <= i < len(accessors) and isinstance(accessors[i], dict):
            return int(accessors[i].get("count", 0))
        return 0

    nv = nf = 0
    for mesh in doc.get("meshes") or []:
        for prim in (mesh or {}).get("primitives") or []:
            if not isinstance(prim, dict):
                continue
            n = count((prim.get("attributes") or {}).get("POSITION"))
            nv += n
            nf += (count(prim["indices"]) if "indices" in prim else n) // 3
    _check_counts(nv, nf, max_vertices, max_faces)


# --------------------------------------------------------------------------------------
# geometry and colours
# --------------------------------------------------------------------------------------


def _scene_meshes(loaded: object) -> list[trimesh.Trimesh]:
    """Every triangle mesh of a loaded scene, with its node transform applied."""
    if isinstance(loaded, trimesh.Trimesh):
        return [loaded]
    if not isinstance(loaded, trimesh.Scene):
        return []
    out = []
    for node in loaded.graph.nodes_geometry:
        T, gname = loaded.graph[node]
        g = loaded.geometry.get(gname)
        if isinstance(g, trimesh.Trimesh) and len(g.faces):
            g = g.copy()
            g.apply_transform(T)
            out.append(g)
    return out


def _image_rgba(img: object, what: str) -> NDArray[np.uint8] | None:
    """A trimesh material image (PIL) as (h, w, 4) uint8, capped like glTF images."""
    if img is None:
        return None
    buf = io.BytesIO()
    try:
        img.save(buf, format="PNG")  # type: ignore[attr-defined]
    except Exception as e:  # PIL raises many types
        logger.warning("%s: unreadable texture (%s): ignored", what, e)
        return None
    try:
        return decode_image(buf.getvalue(), what)
    except GltfError as e:
        raise MeshError(str(e)) from e


def _material_of(g: trimesh.Trimesh) -> tuple[Material, F64 | None, str]:
    """The surface of a trimesh geometry: (material, uv in the glTF convention or None,
    colour source)."""
    vis = g.visual
    n = len(g.vertices)
    if vis is None or vis.kind != "texture":
        return Material(name="vertex", specular=False), None, "default"
    mat = getattr(vis, "material", None)
    uv = getattr(vis, "uv", None)
    uv = None if uv is None or len(uv) != n else np.asarray(uv, np.float64)
    if uv is not None:
        uv = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)  # trimesh: v up -> glTF: v down
    if isinstance(mat, trimesh.visual.material.SimpleMaterial):
        diffuse = np.asarray(mat.diffuse, np.float64)[:4] / 255.0
        tex = _image_rgba(mat.image, "map_Kd") if uv is not None else None
        if tex is not None:
            diffuse = np.ones(4)  # MTL: map_Kd replaces Kd in most viewers
        base = np.concatenate([srgb_to_linear(diffuse[:3]), diffuse[3:4]])
        name = str(getattr(mat, "name", None) or "mtl")
        src = "texture" if tex is not None else "material"
        return (Material(name=name, base_color=base, base_color_texture=tex, roughness=0.8,
                         metallic=0.0), uv, src)  # fmt: skip
    if isinstance(mat, trimesh.visual.material.PBRMaterial):
        f = mat.baseColorFactor
        base = np.ones(4) if f is None else np.asarray(f, np.float64) / 255.0
        base[:3] = srgb_to_linear(base[:3]) if f is not None else base[:3]
        tex = _image_rgba(mat.baseColorTexture, "baseColorTexture") if uv is not None else None
        ntex = _image_rgba(mat.normalTexture, "normalTexture") if uv is not None else None
        return (Material(name=str(mat.name or "pbr"), base_color=base, base_color_texture=tex,
                         normal_texture=None if ntex is None else ntex[..., :3],
                         roughness=1.0 if mat.roughnessFactor is None else mat.roughnessFactor,
                         metallic=0.0 if mat.metallicFactor is None else mat.metallicFactor),
                uv, "texture" if tex is not None else "material")  # fmt: skip
    return Material(name="texture-visual"), uv, "default"


def _part_of(g: trimesh.Trimesh) -> _Part:
    """A trimesh geometry as a part: positions, faces, material, UVs, vertex colours."""
    v = np.asarray(g.vertices, dtype=np.float64)
    f = np.asarray(g.faces, dtype=np.int64).reshape(-1, 3)
    mat, uv, src = _material_of(g)
    colors = None
    if src == "default":
        c, src = _vertex_colors(g)
        colors = c
    return _Part(v, f, mat, None, uv, None, colors, src)


def _vertex_colors(g: trimesh.Trimesh) -> tuple[NDArray[np.float64], str]:
    """Linear RGB (n, 3) per vertex and where it came from."""
    n = len(g.vertices)
    vis = g.visual
    try:
        if vis is not None and vis.kind in ("vertex", "face"):
            c = np.asarray(vis.vertex_colors, dtype=np.float64)[:, :3] / 255.0
            if len(c) == n:
                return srgb_to_linear(c), vis.kind
    except Exception as e:  # colour is a nicety: never fail the mesh for it
        logger.warning("could not read the mesh colours (%s): using grey", e)
    return np.tile(srgb_to_linear([DEFAULT_SRGB] * 3), (n, 1)), "default"
