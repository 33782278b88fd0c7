"""OSDaR23 labels files (ASAM OpenLABEL 1.0.0): typed view plus the raw dict.

:class:`Labels` parses what the project needs (coordinate systems, streams, frames and
their file uris, objects) into dataclasses and keeps the whole JSON document in ``raw``,
so that a sequence written back is lossless: ``load -> dump -> load`` gives equal dicts.
Timestamps keep their exact strings (file names are built from them) next to a float64.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from jsonschema import Draft7Validator
from numpy.typing import NDArray

from geometry.transforms import openlabel_pose_to_T
from osdar_platform.shared_data import openlabel_schema_path
from worker.osdar.errors import SequenceError, atomic_write_bytes

logger = logging.getLogger(__name__)


@dataclass
class CoordinateSystem:
    """One entry of ``openlabel.coordinate_systems``.

    Attributes
    ----------
    name, parent, type : str
        As in the file (``parent`` is ``""`` for the root).
    T_parent_cs : ndarray
        (4, 4) float64 pose of this system in its parent (maps cs points to the parent);
        identity when the file gives no ``pose_wrt_parent``.
    """

    name: str
    parent: str
    type: str
    T_parent_cs: NDArray[np.float64]


@dataclass
class Stream:
    """One entry of ``openlabel.streams``.

    Attributes
    ----------
    name, type, uri : str
        e.g. ``rgb_center``, ``camera``, ``rgb_center``.
    intrinsics : dict or None
        The raw ``stream_properties.intrinsics_pinhole`` (cameras only).
    """

    name: str
    type: str
    uri: str
    intrinsics: dict | None = None


@dataclass
class FrameStream:
    """One stream's file in one frame.

    Attributes
    ----------
    uri : str
        Path relative to the sequence folder, starting with ``/``.
    timestamp_str : str
        The sensor's timestamp exactly as in the file.
    timestamp : float
        The same as float64 UNIX seconds.
    """

    uri: str
    timestamp_str: str
    timestamp: float


@dataclass
class Frame:
    """One frame of ``openlabel.frames``.

    Attributes
    ----------
    index : int
        Frame number (the file counter).
    timestamp_str, timestamp : str, float
        ``frame_properties.timestamp`` as written and as float64.
    streams : dict of str to FrameStream
        Stream name -> its file in this frame.
    """

    index: int
    timestamp_str: str
    timestamp: float
    streams: dict[str, FrameStream] = field(default_factory=dict)


@dataclass
class ObjectInfo:
    """One entry of ``openlabel.objects`` (uuid, name such as ``track0001``, class)."""

    uuid: str
    name: str
    type: str


@dataclass
class Labels:
    """A parsed OpenLABEL file.

    Attributes
    ----------
    raw : dict
        The whole JSON document, unchanged.
    coordinate_systems, streams, objects : dict
        Name (uuid for objects) -> typed entry.
    frames : list of Frame
        Sorted by index.
    path : Path or None
        The file it was read from.
    """

    raw: dict[str, Any]
    coordinate_systems: dict[str, CoordinateSystem]
    streams: dict[str, Stream]
    frames: list[Frame]
    objects: dict[str, ObjectInfo]
    path: Path | None = None

    @property
    def openlabel(self) -> dict[str, Any]:
        """``raw["openlabel"]``."""
        return self.raw["openlabel"]

    def frame(self, index: int) -> Frame:
        """The frame with this index (KeyError if absent)."""
        for f in self.frames:
            if f.index == index:
                return f
        raise KeyError(f"no frame {index} in the labels")

    def frame_objects(self, frame_index: int) -> dict[str, dict[str, Any]]:
        """Object uuid -> raw ``object_data`` dict of that frame ({} when it has none)."""
        frame = self.openlabel.get("frames", {}).get(str(frame_index), {})
        return {uuid: obj.get("object_data", {}) for uuid, obj in frame.get("objects", {}).items()}


# ---------------------------------------------------------------------------------------
# parsing
# ---------------------------------------------------------------------------------------


def load_labels(path: str | Path) -> Labels:
    """Read and parse an OpenLABEL labels file.

    Raises
    ------
    SequenceError
        Missing or unreadable file, invalid JSON, or contents this module cannot use.
    """
    path = Path(path)
    try:
        raw = json.loads(path.read_bytes())
    except OSError as e:
        raise SequenceError(path, f"cannot read labels file: {e.strerror or e}") from e
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SequenceError(path, f"labels file is not valid JSON: {e}") from e
    return parse_labels(raw, path)


def parse_labels(raw: dict[str, Any], path: str | Path | None = None) -> Labels:
    """Typed view of an OpenLABEL document (``raw`` is kept as is, not copied).

    Parameters
    ----------
    raw : dict
        The JSON document, ``{"openlabel": {...}}``.
    path : str or Path, optional
        Named in errors.
    """
    where = Path(path) if path is not None else Path("<labels>")
    if not isinstance(raw, dict) or not isinstance(raw.get("openlabel"), dict):
        raise SequenceError(where, "not an OpenLABEL file: no top-level 'openlabel' object")
    ol = raw["openlabel"]
    return Labels(
        raw=raw,
        coordinate_systems={
            name: _parse_cs(where, name, cs)
            for name, cs in ol.get("coordinate_systems", {}).items()
        },
        streams={name: _parse_stream(name, s) for name, s in ol.get("streams", {}).items()},
        frames=sorted(
            (_parse_frame(where, key, fr) for key, fr in ol.get("frames", {}).items()),
            key=lambda f: f.index,
        ),
        objects={
            uuid: ObjectInfo(uuid, str(o.get("name", "")), str(o.get("type", "")))
            for uuid, o in ol.get("objects", {}).items()
        },
        path=Path(path) if path is not None else None,
    )


def _parse_cs(where: Path, name: str, cs: dict[str, Any]) -> CoordinateSystem:
    pose = cs.get("pose_wrt_parent")
    return CoordinateSystem(
        name=name,
        parent=str(cs.get("parent", "")),
        type=str(cs.get("type", "")),
        T_parent_cs=np.eye(4) if pose is None else pose_to_matrix(pose, where, name),
    )


def pose_to_matrix(
    pose: dict[str, Any], where: str | Path = "<labels>", name: str = "?"
) -> NDArray[np.float64]:
    """(4, 4) float64 matrix of an OpenLABEL pose.

    Parameters
    ----------
    pose : dict
        ``{"translation": [x, y, z], "quaternion": [x, y, z, w]}`` (quaternion normalised
        here) or ``{"matrix4x4": [16 values, row-major]}``.
    where, name : str
        File and coordinate system named in errors.

    Raises
    ------
    SequenceError
        Missing, non-finite or degenerate values.
    """
    try:
        return openlabel_pose_to_T(pose)
    except ValueError as e:
        raise SequenceError(where, f"coordinate system {name!r}: bad pose_wrt_parent: {e}") from e


def _check_finite(where: str | Path, name: str, what: str, values: NDArray) -> None:
    if not np.all(np.isfinite(values)):
        raise SequenceError(where, f"coordinate system {name!r}: non-finite {what} {values}")


def _parse_stream(name: str, s: dict[str, Any]) -> Stream:
    props = s.get("stream_properties") or {}
    return Stream(
        name=name,
        type=str(s.get("type", "")),
        uri=str(s.get("uri", "")),
        intrinsics=props.get("intrinsics_pinhole"),
    )


def _timestamp(where: Path, what: str, value: Any) -> tuple[str, float]:
    """(exact string, float64) of a timestamp given as a string or a number."""
    text = value if isinstance(value, str) else repr(value)
    try:
        number = float(text)
    except (TypeError, ValueError) as e:
        raise SequenceError(where, f"{what}: timestamp {value!r} is not a number") from e
    if not math.isfinite(number):
        raise SequenceError(where, f"{what}: timestamp {value!r} is not finite")
    return text, number


def _parse_frame(where: Path, key: str, fr: dict[str, Any]) -> Frame:
    try:
        index = int(key)
    except ValueError as e:
        raise SequenceError(where, f"frame key {key!r} is not an integer") from e
    props = fr.get("frame_properties") or {}
    ts = props.get("timestamp")
    ts_str, ts_val = _timestamp(where, f"frame {key}", ts) if ts is not None else ("", math.nan)
    streams = {}
    for name, s in (props.get("streams") or {}).items():
        uri = s.get("uri")
        if not isinstance(uri, str) or not uri:
            raise SequenceError(where, f"frame {key}, stream {name!r}: no uri")
        sync = ((s.get("stream_properties") or {}).get("sync") or {}).get("timestamp")
        if sync is None:
            s_str, s_val = ts_str, ts_val
        else:
            s_str, s_val = _timestamp(where, f"frame {key}, stream {name!r}", sync)
        streams[name] = FrameStream(uri, s_str, s_val)
    return Frame(index, ts_str, ts_val, streams)


# ---------------------------------------------------------------------------------------
# writing and validation
# ---------------------------------------------------------------------------------------


def frame_intervals(frames: list[int]) -> list[dict[str, int]]:
    """Contiguous runs of frame counters as OpenLABEL ``frame_intervals``."""
    out: list[dict[str, int]] = []
    for f in sorted(int(x) for x in frames):
        if out and f == out[-1]["frame_end"] + 1:
            out[-1]["frame_end"] = f
        elif not out or f > out[-1]["frame_end"]:
            out.append({"frame_start": f, "frame_end": f})
    return out


def encode_labels(labels_raw: dict[str, Any]) -> bytes:
    """The bytes :func:`dump_labels` writes: compact JSON like OSDaR23's, newline at the end."""
    text = json.dumps(labels_raw, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    return (text + "\n").encode("utf-8")


def dump_labels(labels_raw: dict[str, Any], path: str | Path) -> Path:
    """Write an OpenLABEL document atomically, formatted like OSDaR23's files.

    OSDaR23 writes compact JSON (no indentation, ``","`` and ``":"`` separators) with a
    final newline; floats are written as Python's shortest repr, so a number such as
    ``-0.0000243881`` comes back as ``-2.43881e-05``: equal values, other bytes.

    Raises
    ------
    ValueError
        NaN or infinite numbers (not valid JSON).
    """
    return atomic_write_bytes(path, encode_labels(labels_raw))


@lru_cache(maxsize=1)
def _schema_validator(schema_path: str) -> Any:

    schema = json.loads(Path(schema_path).read_text(encoding="utf-8"))
    return Draft7Validator(schema)


def validate_openlabel(raw: dict[str, Any], schema_path: str | Path | None = None) -> list[str]:
    """Validate an OpenLABEL document against the ASAM OpenLABEL 1.0.0 JSON schema.

    Parameters
    ----------
    raw : dict
        The document.
    schema_path : str or Path, optional
        Default :func:`osdar_platform.shared_data.openlabel_schema_path` (``../shared`` or
        ``$OSDAR_AR_SHARED``).

    Returns
    -------
    list of str
        One ``"<json path>: <message>"`` per violation; ``[]`` when valid or when the
        schema file is not reachable (logged).
    """
    schema_path = Path(schema_path) if schema_path is not None else openlabel_schema_path()
    if not schema_path.is_file():
        logger.info("OpenLABEL schema %s not found: validation skipped", schema_path)
        return []
    validator = _schema_validator(str(schema_path))
    errors = sorted(validator.iter_errors(raw), key=lambda e: list(map(str, e.absolute_path)))
    return [f"/{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in errors]
