"""The augmentation's plan and chunk records as typed, versioned files: no pickle.

A job's plan and its chunks' records cross process and storage boundaries (the object
store, the pool's plan file). Pickle there would let anyone who can write to the bucket run
code on every worker; here a record is one ``.npz`` (``allow_pickle=False``) holding a JSON
header and the numeric arrays:

- the header names the record's ``format`` (``osdar-ar.plan``, ``osdar-ar.chunk``) and
  its ``version`` (:data:`VERSION`), and holds the value tree;
- in the tree, dataclasses and pydantic models appear by name and are rebuilt only from
  :data:`ALLOWED` (a dataclass from exactly its ``__init__`` fields, so its own checks
  run again; a pydantic model through ``model_validate``); arrays are references to
  ``.npz`` members; dict keys keep their type (frame numbers are ints).

Reading checks all of it: another format or version, an unknown type, a missing or extra
field, an object array or a malformed file raise :class:`RecordFormatError` naming the
record and what is wrong, never a misread plan.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ValidationError

from geometry.camera import CameraModel
from renderer.lidar_cast import LidarNoise
from renderer.lighting import Lighting
from renderer.mesh import Material, ObjectMesh, ProxyMesh
from worker.augmentation.annotations import CameraView, FrameAnnotation
from worker.augmentation.frame import CameraRecord, ChunkResult, FrameRecord, ObjectFrame
from worker.augmentation.gauge import GaugeLabel
from worker.augmentation.plan import Plan, PlannedObject
from worker.augmentation.spec import AugmentSpec

#: Version of the record layout; a record of another version is refused. Bumped whenever
#: a stored type's fields change.
VERSION = 5
PLAN_FORMAT = "osdar-ar.plan"
CHUNK_FORMAT = "osdar-ar.chunk"
_HEADER = "__header__"

#: The only types a record can rebuild.
ALLOWED: dict[str, type] = {
    t.__name__: t
    for t in (
        Plan,
        PlannedObject,
        AugmentSpec,
        CameraModel,
        ObjectMesh,
        Material,
        ProxyMesh,
        Lighting,
        GaugeLabel,
        LidarNoise,
        ChunkResult,
        FrameRecord,
        ObjectFrame,
        CameraRecord,
        FrameAnnotation,
        CameraView,
    )
}


class RecordFormatError(ValueError):
    """A stored record this code cannot read as what it should be."""


def dump_record(obj: Any, fmt: str) -> bytes:
    """``obj`` as a record of format ``fmt`` (bytes of an ``.npz``)."""
    arrays: list[np.ndarray] = []
    header = {"format": fmt, "version": VERSION, "tree": _encode(obj, arrays)}
    buf = io.BytesIO()
    members = {f"a{i}": a for i, a in enumerate(arrays)}
    members[_HEADER] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    np.savez(buf, allow_pickle=False, **members)
    return buf.getvalue()


def load_record(data: bytes, fmt: str, what: str = "record") -> Any:
    """The object in ``data``, which must be a record of format ``fmt`` and this
    :data:`VERSION`; ``what`` names it in errors (e.g. its store key)."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            members = {k: z[k] for k in z.files}
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as exc:
        raise RecordFormatError(f"{what}: not a readable record ({exc})") from None
    if _HEADER not in members:
        raise RecordFormatError(f"{what}: no header: not an osdar-ar record")
    try:
        header = json.loads(members.pop(_HEADER).tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordFormatError(f"{what}: unreadable header ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != fmt:
        got = header.get("format") if isinstance(header, dict) else None
        raise RecordFormatError(f"{what}: format {got!r}, expected {fmt!r}")
    if header.get("version") != VERSION:
        raise RecordFormatError(
            f"{what}: {fmt} version {header.get('version')!r}; this worker reads version "
            f"{VERSION} (written by another release: re-run the job)"
        )
    try:
        return _decode(header.get("tree"), members)
    except RecordFormatError as exc:
        raise RecordFormatError(f"{what}: {exc}") from None


def dump_plan(plan: Plan) -> bytes:
    return dump_record(plan, PLAN_FORMAT)


def load_plan(data: bytes, what: str = "plan") -> Plan:
    plan = load_record(data, PLAN_FORMAT, what)
    if not isinstance(plan, Plan):
        raise RecordFormatError(f"{what}: holds a {type(plan).__name__}, not a Plan")
    return plan


def read_plan(path: str | Path) -> Plan:
    return load_plan(Path(path).read_bytes(), str(path))


def dump_chunk(result: ChunkResult) -> bytes:
    return dump_record(result, CHUNK_FORMAT)


def load_chunk(data: bytes, what: str = "chunk record") -> ChunkResult:
    result = load_record(data, CHUNK_FORMAT, what)
    if not isinstance(result, ChunkResult):
        raise RecordFormatError(f"{what}: holds a {type(result).__name__}, not a ChunkResult")
    return result


# ---------------------------------------------------------------------------- the tree
def _encode(obj: Any, arrays: list[np.ndarray]) -> Any:
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, np.integer)) and not isinstance(obj, np.bool_):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else {"float": repr(v)}
    if isinstance(obj, np.ndarray):
        if obj.dtype == object:
            raise TypeError("object arrays cannot be stored")
        arrays.append(np.ascontiguousarray(obj))
        return {"array": len(arrays) - 1}
    if isinstance(obj, Path):
        return {"path": str(obj)}
    if isinstance(obj, bytes):
        arrays.append(np.frombuffer(obj, dtype=np.uint8))
        return {"bytes": len(arrays) - 1}
    if isinstance(obj, tuple):
        return {"tuple": [_encode(v, arrays) for v in obj]}
    if isinstance(obj, list):
        return [_encode(v, arrays) for v in obj]
    if isinstance(obj, dict):
        return {"dict": [[_encode(k, arrays), _encode(v, arrays)] for k, v in obj.items()]}
    name = type(obj).__name__
    if ALLOWED.get(name) is not type(obj):
        raise TypeError(f"{name} is not a storable record type")
    if isinstance(obj, BaseModel):
        return {"model": name, "data": obj.model_dump(mode="json")}
    fields = {f.name: _encode(getattr(obj, f.name), arrays) for f in _init_fields(type(obj))}
    return {"dataclass": name, "fields": fields}


def _decode(node: Any, arrays: dict[str, np.ndarray]) -> Any:
    if node is None or isinstance(node, (bool, int, float, str)):
        return node
    if isinstance(node, list):
        return [_decode(v, arrays) for v in node]
    if not isinstance(node, dict) or len(node) not in (1, 2):
        raise RecordFormatError(f"malformed value {str(node)[:80]!r}")
    if "array" in node:
        a = arrays.get(f"a{node['array']}")
        if a is None:
            raise RecordFormatError(f"array {node['array']!r} missing")
        return a
    if "bytes" in node:
        b = arrays.get(f"a{node['bytes']}")
        if b is None or b.dtype != np.uint8:
            raise RecordFormatError(f"bytes {node['bytes']!r} missing")
        return b.tobytes()
    if "float" in node:
        return float(node["float"])
    if "path" in node:
        return Path(str(node["path"]))
    if "tuple" in node:
        return tuple(_decode(v, arrays) for v in node["tuple"])
    if "dict" in node:
        return {_hashable(_decode(k, arrays)): _decode(v, arrays) for k, v in node["dict"]}
    if "model" in node:
        cls = _allowed(node["model"])
        try:
            return cls.model_validate(node.get("data"))  # type: ignore[attr-defined]
        except ValidationError as exc:
            raise RecordFormatError(f"{node['model']}: {exc}") from None
    if "dataclass" in node:
        cls = _allowed(node["dataclass"])
        fields = node.get("fields")
        want = {f.name for f in _init_fields(cls)}
        if not isinstance(fields, dict) or set(fields) != want:
            got = set(fields) if isinstance(fields, dict) else set()
            raise RecordFormatError(
                f"{cls.__name__}: fields missing {sorted(want - got)}, unknown {sorted(got - want)}"
            )
        try:
            return cls(**{k: _decode(v, arrays) for k, v in fields.items()})
        except (TypeError, ValueError) as exc:
            raise RecordFormatError(f"{cls.__name__}: {exc}") from None
    raise RecordFormatError(f"malformed value {str(node)[:80]!r}")


def _allowed(name: Any) -> type:
    cls = ALLOWED.get(str(name))
    if cls is None:
        raise RecordFormatError(f"type {name!r} is not a record type")
    return cls


def _init_fields(cls: type) -> list[dataclasses.Field[Any]]:
    return [f for f in dataclasses.fields(cls) if f.init]


def _hashable(key: Any) -> Any:
    if isinstance(key, list):
        raise RecordFormatError("a list cannot be a dict key")
    return key
