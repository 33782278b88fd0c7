"""Checks that need the pipeline, called by the API at request time (lazy imports).

:func:`inspect_sequence` opens (and so validates) an OSDaR23 folder and summarises it;
:func:`inspect_mesh` loads an uploaded mesh with an explicit file type and counts it.
Both raise :class:`InspectionError` (a ValueError) with a message a user can act on.
"""

from __future__ import annotations

import io
import json
import threading
import warnings
from pathlib import Path
from typing import Any

_warn_lock = threading.Lock()  # warnings.catch_warnings is process-global


class InspectionError(ValueError):
    """The sequence or mesh is unusable; the message says why."""


def inspect_sequence(folder: str | Path) -> dict[str, Any]:
    """Summary of a sequence folder: name, frames, first/last frame, frame indices,
    cameras, lidar stream, time span, warnings."""
    # The API calls this at request time; its start must not import the pipeline. Measured
    # over `import service.app` (0.65 s, 90 MiB max RSS), median of 7 runs:
    # lazy: worker.osdar.sequence (numpy, the OSDaR23 reader) adds 0.38 s and 98 MiB.
    from worker.osdar.errors import SequenceError
    from worker.osdar.sequence import Sequence
    from worker.osdar.summary import summarize

    folder = Path(folder)
    if not folder.is_dir():
        raise InspectionError(f"{folder}: not a folder")
    with _warn_lock, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            summary = summarize(folder)
            frame_indices = [int(i) for i in Sequence.open(folder).frame_indices]
        except (SequenceError, OSError, ValueError, KeyError) as exc:
            raise InspectionError(f"not a valid OSDaR23 sequence: {exc}") from exc
        except Exception as exc:  # the reader on hostile input: wrong JSON types, nesting
            # Found by scripts/reliability/hostile_uploads.py: labels whose "frames" is a
            # list (AttributeError) or 100k nested arrays (RecursionError) were a 500.
            name = type(exc).__name__
            raise InspectionError(
                f"not a valid OSDaR23 sequence: unreadable ({name}: {str(exc)[:300]})"
            ) from exc
    summary["frame_indices"] = frame_indices
    summary["warnings"] = sorted({str(w.message) for w in caught})[:50]
    plain: dict[str, Any] = json.loads(json.dumps(summary, default=str))  # JSON types only
    return plain


def inspect_mesh(
    path: str | Path, file_type: str, *, max_vertices: int, max_faces: int
) -> dict[str, Any]:
    """Load a mesh of ``file_type`` from ``path``; vertex/face counts and extents.

    glTF files must be self-contained (no external ``uri``); counts are capped.
    """
    path = Path(path)
    data = path.read_bytes()
    if file_type == "gltf":
        try:
            doc = json.loads(data)
        except ValueError as exc:
            raise InspectionError(f"gltf: not JSON ({exc})") from exc
        for section in ("buffers", "images"):
            for item in doc.get(section, []) if isinstance(doc, dict) else []:
                uri = item.get("uri", "") if isinstance(item, dict) else ""
                if uri and not uri.startswith("data:"):
                    raise InspectionError(f"gltf: external uri {uri[:80]!r} refused")
    # lazy: trimesh (and numpy) add 0.42 s and 82 MiB max RSS to the API's start, median of 7.
    import trimesh

    try:
        loaded = trimesh.load(io.BytesIO(data), file_type=file_type, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for malformed input
        raise InspectionError(
            f"{file_type}: could not be read ({type(exc).__name__}: {exc})"
        ) from exc
    if not isinstance(loaded, trimesh.Trimesh):  # force="mesh" makes one
        raise InspectionError(f"{file_type}: not a triangle mesh ({type(loaded).__name__})")
    vertices, faces = len(loaded.vertices), len(loaded.faces)
    if vertices == 0 or faces == 0:
        raise InspectionError(f"{file_type}: the mesh has no triangles")
    if vertices > max_vertices or faces > max_faces:
        raise InspectionError(
            f"mesh too large: {vertices} vertices / {faces} faces "
            f"(limits {max_vertices} / {max_faces})"
        )
    extents = [float(x) for x in loaded.extents]
    return {"vertices": vertices, "faces": faces, "extents": extents}
