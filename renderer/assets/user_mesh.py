"""User meshes: glTF / GLB, OBJ and PLY uploads turned into an :class:`ObjectMesh`.

Untrusted input (RELIABILITY.md): the bytes are parsed with an explicit file type (never
guessed, never read from a path), glTF files may not reference anything outside
themselves (``uri`` s other than ``data:`` URIs are refused before trimesh sees them),
vertex and face counts are capped from the headers *before* parsing where the format
says them (PLY, glTF accessors, OBJ line counts) and again after, and every failure is a
:class:`MeshError` (a ``ValueError``) saying what is wrong. Cap the upload's byte size
where it is received (the service streams it with a limit).

Geometry: the file's ``up`` axis becomes +z (glTF files are +Y up by convention, with
their front towards +Z: pass ``up="y"``, which maps +Z to the object's forward +x); then
the mesh is scaled (``scale`` given) or assumed to be in metres (a warning if its size is
implausible, < 0.05 m or > 50 m), and re-centred so that the origin is the ground-contact
centre: min z = 0, x and y the centre of the footprint (the bounding box of the vertical
projection). Closed meshes with inward faces are flipped.

Colours: per-vertex colours of the file when present (face colours averaged to the
vertices), else the texture sampled at the vertices' UVs, else the material's base
colour, else grey; 8-bit sRGB values are converted to linear RGB. Lidar reflectivity
follows the colour (``0.08 + 0.6 * luminance``), as in the built-in library.
"""

from __future__ import annotations

import io
import json
import logging
import re
import struct

import numpy as np
import trimesh
from numpy.typing import NDArray

from renderer.assets.obstacles import reflectivity_of, srgb_to_linear
from renderer.mesh import ObjectMesh

logger = logging.getLogger(__name__)

FILE_TYPES = ("glb", "gltf", "obj", "ply")
DEFAULT_SRGB = 0.58
"""Grey (sRGB) of meshes without colours."""
PLAUSIBLE_SIZE_M = (0.05, 50.0)

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


def load_user_mesh(
    data: bytes,
    file_type: str,
    *,
    scale: float | None = None,
    up: str = "z",
    max_vertices: int = 500_000,
    max_faces: int = 1_000_000,
    name: str = "custom",
) -> ObjectMesh:
    """Parse an uploaded mesh into an :class:`ObjectMesh` standing on the ground.

    Parameters
    ----------
    data : the file's bytes (a GLB, a self-contained glTF JSON, an OBJ or a PLY).
    file_type : ``glb``, ``gltf``, ``obj`` or ``ply`` (a leading dot and case ignored).
    scale : metres per file unit; None = the file is in metres.
    up : the file's up axis, one of ``z``, ``y``, ``x``, ``-z``, ``-y``, ``-x``.
    max_vertices, max_faces : caps on the whole mesh (all parts of a scene together).
    name : the object's class name for the annotations.

    Returns
    -------
    ObjectMesh in the object frame (x forward, y left, z up, origin at the
    ground-contact centre); meta records the source type, the original extent, the
    colour source and the scale.

    Raises
    ------
    MeshError : unknown type, unparsable bytes, external references, over the caps,
        empty, non-finite, bad scale or up axis.
    """
    ft = _check_arguments(data, file_type, scale, up)
    data = bytes(data)
    _precheck(data, ft, max_vertices, max_faces)
    v, f, rgb, sources = _merged_parts(_parse(data, ft), ft)
    _check_merged(v, f, max_vertices, max_faces)
    v = v @ _UP[up].T
    extent_file = np.ptp(v, axis=0)
    v = _to_metres(v, extent_file, scale, name)
    v = _on_the_ground(v)
    tm = trimesh.Trimesh(v, f, process=False)
    flipped = False
    if tm.is_watertight and tm.volume < 0.0:
        f = f[:, ::-1].copy()
        flipped = True
    elif not tm.is_watertight:
        logger.info("%s: mesh is not closed; face orientation taken as given", name)

    refl = np.array([reflectivity_of(c) for c in rgb], dtype=np.float32)
    meta = {
        "class": name,
        "source": ft,
        "scale": 1.0 if scale is None else float(scale),
        "up": up,
        "file_extent": [float(x) for x in extent_file],
        "color_source": "+".join(sorted(sources)),
        "flipped": flipped,
        "watertight": bool(tm.is_watertight),
    }
    mesh = ObjectMesh(v, f, rgb.astype(np.float32), refl, name, meta)
    ext = mesh.size
    meta.update({"length_m": float(ext[0]), "width_m": float(ext[1]), "height_m": float(ext[2])})
    logger.info("user mesh %s (%s): %d vertices, %d faces, size %s m", name, ft, len(v), len(f),
                np.round(ext, 3).tolist())  # fmt: skip
    return mesh


def _check_arguments(data: object, file_type: str, scale: float | None, up: str) -> str:
    """The normalised file type; MeshError for a bad type, up axis, scale or empty data."""
    ft = str(file_type).lower().lstrip(".")
    if ft not in FILE_TYPES:
        raise MeshError(f"unsupported mesh type {file_type!r}; use one of {FILE_TYPES}")
    if up not in _UP:
        raise MeshError(f"up must be one of {sorted(_UP)}, got {up!r}")
    if scale is not None and not (np.isfinite(scale) and scale > 0.0):
        raise MeshError(f"scale must be a positive number, got {scale}")
    if not isinstance(data, bytes | bytearray | memoryview) or len(data) == 0:
        raise MeshError("empty upload")
    return ft


def _parse(data: bytes, ft: str) -> list[trimesh.Trimesh]:
    """The triangle meshes of the file (trimesh, as a scene); MeshError on any failure."""
    try:
        loaded = trimesh.load(io.BytesIO(data), file_type=ft, force="scene", process=False)
        geoms = _scene_meshes(loaded)
    except MeshError:
        raise
    except Exception as e:  # trimesh raises many types on bad input
        raise MeshError(f"could not parse the {ft} data: {type(e).__name__}: {e}") from e
    if not geoms:
        raise MeshError(f"the {ft} file contains no triangle mesh")
    return geoms


def _merged_parts(
    geoms: list[trimesh.Trimesh], ft: str
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64], set[str]]:
    """All non-empty parts as one mesh: vertices, faces, vertex colours (linear RGB) and
    where the colours came from."""
    verts, faces, colors, sources = [], [], [], set()
    offset = 0
    for g in geoms:
        v = np.asarray(g.vertices, dtype=np.float64)
        f = np.asarray(g.faces, dtype=np.int64).reshape(-1, 3)
        if len(v) == 0 or len(f) == 0:
            continue
        c, src = _vertex_colors(g)
        sources.add(src)
        verts.append(v)
        faces.append(f + offset)
        colors.append(c)
        offset += len(v)
    if not faces:
        raise MeshError(f"the {ft} file has no faces (a point cloud or an empty mesh)")
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(colors), sources


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


def _precheck(data: bytes, ft: str, max_vertices: int, max_faces: int) -> None:
    """Refuse external references and over-cap counts from the headers."""
    if ft in ("glb", "gltf"):
        _check_gltf(_gltf_json(data, ft), max_vertices, max_faces)
    elif ft == "ply":
        head = data[: min(len(data), 64 * 1024)]
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or end < 0:
            raise MeshError("not a PLY file (no 'ply' magic or no end_header)")
        text = head[:end].decode("ascii", errors="replace")
        counts = dict(re.findall(r"element\s+(\w+)\s+(\d+)", text))
        nv, nf = int(counts.get("vertex", 0)), int(counts.get("face", 0))
        _check_counts(nv, nf, max_vertices, max_faces)
    elif ft == "obj":
        nv = data.count(b"\nv ") + data.startswith(b"v ")
        nf = data.count(b"\nf ") + data.startswith(b"f ")
        _check_counts(nv, nf, max_vertices, max_faces)
        if re.search(rb"(?m)^\s*(mtllib|map_\w+)\s", data):
            logger.info("OBJ references material/texture files: they are not loaded")


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


def _check_gltf(doc: dict, max_vertices: int, max_faces: int) -> None:
    """Refuse external ``uri`` s (buffers, images) and over-cap accessor counts."""
    for kind in ("buffers", "images"):
        for i, item in enumerate(doc.get(kind) or []):
            uri = item.get("uri") if isinstance(item, dict) else None
            if uri is not None and not str(uri).startswith("data:"):
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


def _vertex_colors(g: trimesh.Trimesh) -> tuple[NDArray[np.float64], str]:
    """Linear RGB (n, 3) per vertex and where it came from."""
    n = len(g.vertices)
    vis = g.visual
    try:
        if vis is not None and vis.kind in ("vertex", "face"):
            c = np.asarray(vis.vertex_colors, dtype=np.float64)[:, :3] / 255.0
            if len(c) == n:
                return srgb_to_linear(c), vis.kind
        if vis is not None and vis.kind == "texture":
            mat = getattr(vis, "material", None)
            uv = getattr(vis, "uv", None)
            if uv is not None and len(uv) == n:
                c = np.asarray(vis.to_color().vertex_colors, dtype=np.float64)[:, :3] / 255.0
                if len(c) == n:
                    return srgb_to_linear(c), "texture"
            if mat is not None and getattr(mat, "main_color", None) is not None:
                c = np.asarray(mat.main_color, dtype=np.float64)[:3] / 255.0
                return np.tile(srgb_to_linear(c), (n, 1)), "material"
    except Exception as e:  # colour is a nicety: never fail the mesh for it
        logger.warning("could not read the mesh colours (%s): using grey", e)
    return np.tile(srgb_to_linear([DEFAULT_SRGB] * 3), (n, 1)), "default"
