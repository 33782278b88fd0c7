"""Request and response schemas of the API (separate from the tables)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from datetime import datetime
from typing import Annotated, Any, Generic, Literal, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    ValidationInfo,
    field_validator,
    model_serializer,
    model_validator,
)

from osdar_platform.catalog import BUILTIN_OBJECTS, MESH_FILE_TYPES, STRATEGIES
from osdar_platform.models import JobState

T = TypeVar("T")

BuiltinObject = Literal[BUILTIN_OBJECTS]  # type: ignore[valid-type]
Strategy = Literal[STRATEGIES]  # type: ignore[valid-type]
MeshFileType = Literal[MESH_FILE_TYPES]  # type: ignore[valid-type]
Name = Annotated[str, Field(min_length=1, max_length=200, pattern=r"^[\w .:@+-]+$")]
#: What an id of ours (a job, sequence or asset: a UUID) can be made of. Checked before any
#: lookup: a NUL or a control character must never reach the database (PostgreSQL refuses
#: NUL in text, which would be a 500), and the schema says so, so clients know.
ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
Ident = Annotated[str, Field(min_length=1, max_length=64, pattern=ID_PATTERN)]
#: An absolute POSIX path: any characters but NUL (which no file system accepts).
ABSOLUTE_PATH_PATTERN = r"^/[^\x00]*$"
CameraName = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_]+$")]


class _In(BaseModel):
    """Request bodies: unknown fields are errors, NaN/inf are refused."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Page(BaseModel, Generic[T]):
    items: list[T]
    total: int = Field(description="matching items over all pages")
    limit: int
    offset: int


class Health(BaseModel):
    status: Literal["ok", "degraded"]
    database: str
    version: str


# ---------------------------------------------------------------------------- sequences
class SequenceRegister(_In):
    """Register a sequence folder the workers can read (absolute path)."""

    path: str = Field(
        min_length=1, max_length=4096, pattern=ABSOLUTE_PATH_PATTERN,
        examples=["/data/osdar23/1_calibration_1.1"],
    )  # fmt: skip
    name: Name | None = None


class SequencePublic(BaseModel):
    id: str
    name: str
    source: Literal["path", "upload"]
    path: str
    frames: int
    first_frame: int | None = None
    last_frame: int | None = None
    cameras: list[str]
    time_span_s: float
    validation: dict[str, Any]
    state: str
    created_at: datetime

    @classmethod
    def from_row(cls, row: Any) -> SequencePublic:
        v = row.validation or {}
        return cls(
            id=row.id,
            name=row.name,
            source=row.source,
            path=row.path,
            frames=row.frames,
            first_frame=v.get("first_frame"),
            last_frame=v.get("last_frame"),
            cameras=row.cameras,
            time_span_s=row.time_span_s,
            validation=v,
            state=row.state,
            created_at=row.created_at,
        )


# ---------------------------------------------------------------------------- assets
class AssetPublic(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: str
    name: str
    file_type: str
    size: int
    vertices: int
    faces: int
    created_at: datetime


# ---------------------------------------------------------------------------- jobs
class ObjectSpec(_In):
    """The obstacle: a built-in mesh or an uploaded asset, and its scale."""

    # exactly one source, stated in the schema too (clients generate code from it)
    model_config = ConfigDict(
        json_schema_extra={
            "oneOf": [
                {"required": ["builtin"], "properties": {"builtin": {"type": "string"},
                                                        "asset_id": {"type": "null"}}},
                {"required": ["asset_id"], "properties": {"asset_id": {"type": "string"},
                                                         "builtin": {"type": "null"}}},
            ]
        }
    )  # fmt: skip

    builtin: BuiltinObject | None = Field(None, description="built-in obstacle name")
    asset_id: str | None = Field(
        None, max_length=64, pattern=ID_PATTERN, description="id of an uploaded asset"
    )
    scale: float = Field(1.0, gt=0.0, le=100.0, description="uniform scale of the mesh")
    seed: int = Field(
        0, ge=0, le=2**31 - 1, description="variation seed of a built-in (its shape, size)"
    )

    @model_validator(mode="after")
    def _one_source(self) -> ObjectSpec:
        if (self.builtin is None) == (self.asset_id is None):
            raise ValueError("give exactly one of 'builtin' and 'asset_id'")
        if self.seed != 0 and self.builtin is None:
            raise ValueError("'seed' varies a built-in obstacle, not an uploaded asset")
        return self

    @model_serializer(mode="wrap")
    def _seed_when_set(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """``seed`` is written when it is not 0 (a job of the default variation keeps the
        spec it had before seeds existed; a campaign variant writes it the same way)."""
        out: dict[str, Any] = handler(self)
        if out.get("seed", 0) == 0:
            out.pop("seed", None)
        return out


class TrackPlacement(_In):
    """On the ego track: arc length ``s`` from the first frame's position, lateral offset
    (left positive), yaw relative to the track direction."""

    mode: Literal["track"]
    s: float = Field(ge=0.0, le=10_000.0, description="m along the ego track")
    offset: float = Field(0.0, ge=-50.0, le=50.0, description="m, left of the centreline")
    yaw_deg: float = Field(0.0, ge=-360.0, le=360.0)


class PointPlacement(_In):
    """At a point: in the world frame, or in the lidar (base) frame of ``frame_idx``."""

    mode: Literal["world", "lidar_frame"]
    xyz: tuple[float, float, float]
    yaw_deg: float = Field(0.0, ge=-360.0, le=360.0)
    frame_idx: int | None = Field(None, ge=0, description="required for mode lidar_frame")

    @model_validator(mode="after")
    def _frame_for_lidar(self) -> PointPlacement:
        if self.mode == "lidar_frame" and self.frame_idx is None:
            raise ValueError("mode 'lidar_frame' needs 'frame_idx'")
        return self


Placement = Annotated[TrackPlacement | PointPlacement, Field(discriminator="mode")]


class MotionModel(_In):
    """A moving object's path: waypoints walked at ``speed_mps`` from the first one; the
    object faces its direction of travel (plus ``yaw_deg``). Its pose is evaluated at each
    sensor's own timestamp of every frame (worker/augmentation/motion.py).

    mode : ``track``: waypoints are ``(s, offset)`` m in the track placement's coordinates
        (s from the first frame's position along the ego track, offset left +);
        ``world``: ``(x, y)`` m in the sequence's world frame (height snapped).
    path : two or more waypoints; the object walks the polyline at ``speed_mps``.
    start_s : seconds after the first frame of the range the object sets off (it waits at
        the first waypoint until then).
    end : at the last waypoint ``stop`` (stand there) or ``bounce`` (walk back, and so on).
    yaw_deg : the object's heading relative to its direction of travel (0: its +x, the
        front of the built-ins, leads).
    gait : the built-in person swings legs and arms, the built-in animals their legs, in
        step with the distance walked (renderer/assets/walk_cycle.py); other objects (and
        a person lying, crouching or sitting) are rigid.

    One model for the API's jobs, the campaigns' variants and the augmentation
    (worker/augmentation/spec.py imports it from here).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    mode: Literal["track", "world"] = "track"
    path: tuple[tuple[float, float], ...] = Field(min_length=2, max_length=256)
    speed_mps: float = Field(gt=0.0, le=50.0)
    start_s: float = Field(0.0, ge=0.0, le=3600.0)
    end: Literal["stop", "bounce"] = "stop"
    yaw_deg: float = 0.0
    gait: bool = True

    @model_validator(mode="after")
    def _finite_path(self) -> MotionModel:
        values = [v for p in self.path for v in p]
        if not all(math.isfinite(v) for v in values) or not math.isfinite(self.yaw_deg):
            raise ValueError("motion path and yaw_deg must be finite")
        length = sum(math.dist(a, b) for a, b in zip(self.path, self.path[1:], strict=False))
        if length < 1e-3:
            raise ValueError("motion path must have a length (its waypoints all coincide)")
        return self


def _needs_placement(placement: Any, info: ValidationInfo, where: str) -> Any:
    """A still object needs its placement; a moving one's ``motion`` (validated before it)
    decides its position. Skipped when the motion itself was invalid (its own error)."""
    if placement is None and "motion" in info.data and info.data["motion"] is None:
        raise ValueError(f"{where}needs a 'placement' (or a 'motion' for a moving object)")
    return placement


class SceneObjectSpec(_In):
    """One object of a multi-object job: what (``object``), where (``placement``) and, for
    a moving object, its ``motion`` (which then decides the position: the placement may
    be left out)."""

    object: ObjectSpec
    motion: MotionModel | None = None
    placement: Placement | None = Field(None, validate_default=True)

    @field_validator("placement")
    @classmethod
    def _placed(cls, v: Any, info: ValidationInfo) -> Any:
        return _needs_placement(v, info, "an object ")

    @model_serializer(mode="wrap")
    def _no_nulls(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        out: dict[str, Any] = handler(self)
        return {k: v for k, v in out.items() if v is not None}


class GaugeOptions(_In):
    """The clearance envelope of the gauge labels: the fields of
    :class:`~worker.augmentation.gauge.GaugeOutline` with its bounds; a field left out
    (None) takes the outline's default (half-width 1.575 m, margin 0.2 m, 0-4.65 m above
    the top of rail, curve widening 2.5 m^2 / R)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    half_width_m: float | None = Field(None, gt=0.0, le=5.0)
    margin_m: float | None = Field(None, ge=0.0, le=5.0)
    floor_m: float | None = Field(None, ge=-1.0, le=2.0)
    height_m: float | None = Field(None, gt=0.0, le=10.0)
    curve_widening_m2: float | None = Field(None, ge=0.0, le=50.0)

    @model_serializer(mode="wrap")
    def _no_nulls(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        out: dict[str, Any] = handler(self)
        return {k: v for k, v in out.items() if v is not None}


class RenderOptions(_In):
    scale: float = Field(1.0, gt=0.0, le=1.0, description="fraction of the real resolution")
    png_compression: int = Field(3, ge=0, le=9)
    blur: bool = True
    shadow: bool = True
    exposure_ms: float = Field(
        5.0, ge=0.0, le=100.0, description="front cameras' exposure (motion blur); 0: none"
    )
    aperture_mm: float = Field(
        4.0, ge=0.0, le=100.0, description="effective aperture diameter (defocus); 0: pinhole"
    )


Clicks = dict[CameraName, dict[str, tuple[float, float]]]
#: Where in a request body: ``("body", "objects", 1, "placement")``.
Loc = tuple[str | int, ...]


def spec_objects(spec: Mapping[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """The ``{object, placement, motion}`` entries of a stored job spec (a JobCreate's JSON
    or a campaign variant's job), either form, each with its path in the spec (``object``
    or ``objects[1].object``): what the runner and the asset checks read every object
    from."""
    many = spec.get("objects")
    if many:
        return [(f"objects[{i}].object", dict(o)) for i, o in enumerate(many)]
    return [("object", {k: spec.get(k) for k in ("object", "placement", "motion")})]


def spec_asset_ids(spec: Mapping[str, Any]) -> list[tuple[str, str]]:
    """(path in the spec, asset id) of every object of a stored job spec that is an
    uploaded asset, in the spec's order."""
    out = []
    for where, o in spec_objects(spec):
        asset_id = (o.get("object") or {}).get("asset_id")
        if asset_id is not None:
            out.append((where, str(asset_id)))
    return out


#: The most objects one job (or campaign variant) places.
MAX_JOB_OBJECTS = 32


class JobCreate(_In):
    """A job spec; checked against the sequence at submission.

    Objects: one as ``object`` + ``placement`` (+ ``motion`` for a moving one: then the
    placement may be left out), or several as ``objects``, a list of ``{object, placement,
    motion}`` (:class:`SceneObjectSpec`), each annotated on its own, hiding each other in
    the images and the lidar. A campaign's variant is a job of this very format
    (worker/campaign/variant.py). ``gauge`` sets the clearance envelope of the gauge labels.
    """

    # the two forms, stated in the schema too (clients generate code from it)
    model_config = ConfigDict(json_schema_extra={"oneOf": [
        {"required": ["object"],
         "properties": {"object": {"not": {"type": "null"}}, "objects": {"type": "null"}},
         "anyOf": [{"required": [k], "properties": {k: {"not": {"type": "null"}}}}
                   for k in ("placement", "motion")]},
        {"required": ["objects"],
         "properties": {"objects": {"type": "array"},
                        **{k: {"type": "null"} for k in ("object", "placement", "motion")}}},
    ]})  # fmt: skip

    sequence_id: Ident
    cameras: list[CameraName] = Field(
        default_factory=lambda: ["rgb_center", "rgb_highres_center"], min_length=1, max_length=8
    )
    lidar: bool = True
    # validated in this order: each field's check sees the ones before it (_one_form)
    objects: list[SceneObjectSpec] | None = Field(
        None, min_length=1, max_length=MAX_JOB_OBJECTS, description="several objects"
    )
    object: ObjectSpec | None = Field(
        None, validate_default=True, description="the one object (or give 'objects')"
    )
    motion: MotionModel | None = Field(None, description="the one object's path, if it moves")
    placement: Placement | None = Field(
        None, validate_default=True, description="where the one object stands"
    )
    gauge: GaugeOptions | None = Field(None, description="envelope of the gauge labels")
    strategy: Strategy = "auto"
    frame_range: tuple[int, int] | None = Field(
        None, description="[first, last] frame index, inclusive; default: all frames"
    )
    clicks: Clicks | None = Field(
        None, description="camera -> {frame index: [u, v]} pixel clicks of the landmark"
    )
    render: RenderOptions = Field(default_factory=RenderOptions)

    @field_validator("object", "motion", "placement")
    @classmethod
    def _one_form(cls, v: Any, info: ValidationInfo) -> Any:
        """One object (``object`` + ``placement`` / ``motion``) or ``objects``, each error
        on the field it is about. Skipped when ``objects`` itself was invalid."""
        if "objects" not in info.data:
            return v
        many, name = info.data["objects"] is not None, info.field_name
        if many and v is not None:
            raise ValueError(
                f"'{name}' given beside 'objects': give each object's object, placement "
                "and motion inside 'objects'"
            )
        if not many and name == "object" and v is None:
            raise ValueError("give 'object' (one object) or 'objects' (a list of them)")
        if not many and name == "placement" and info.data.get("object") is not None:
            return _needs_placement(v, info, "'object' ")
        return v

    @model_serializer(mode="wrap")
    def _no_unused_forms(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """The stored spec: the object form not used, and no gauge or motion, left out."""
        out: dict[str, Any] = handler(self)
        optional = ("object", "placement", "motion", "objects", "gauge")
        return {k: v for k, v in out.items() if not (k in optional and v is None)}

    def scene_objects(self) -> list[tuple[Loc, SceneObjectSpec]]:
        """Each object with where it is in the request body (``("body", "objects", 1)`` or
        ``("body",)`` for the one ``object``)."""
        if self.objects is not None:
            return [(("body", "objects", i), o) for i, o in enumerate(self.objects)]
        assert self.object is not None  # _one_form
        one = SceneObjectSpec(object=self.object, placement=self.placement, motion=self.motion)
        return [(("body",), one)]

    @field_validator("cameras")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError("cameras must not repeat")
        return v

    @field_validator("frame_range")
    @classmethod
    def _ordered(cls, v: tuple[int, int] | None) -> tuple[int, int] | None:
        if v is not None and not 0 <= v[0] <= v[1]:
            raise ValueError("frame_range must be [first, last] with 0 <= first <= last")
        return v

    @field_validator("clicks")
    @classmethod
    def _click_frames(cls, v: Clicks | None) -> Clicks | None:
        for cam, per_frame in (v or {}).items():
            if len(per_frame) > 10_000:
                raise ValueError(f"clicks[{cam}]: too many frames")
            for frame in per_frame:
                if not frame.isdigit() or len(frame) > 9:
                    raise ValueError(f"clicks[{cam}]: frame key {frame[:20]!r} is not an index")
        return v


class Progress(BaseModel):
    done: int
    total: int


class JobLinks(BaseModel):
    self: str
    events: str
    archive: str | None = None
    metrics: str | None = None
    previews: str | None = None


class JobPublic(BaseModel):
    id: str
    state: JobState
    stage: str | None
    progress: Progress
    sequence_id: str | None
    campaign_id: str | None = Field(None, description="the campaign it is a variant of")
    spec: dict[str, Any]
    attempt: int
    cancel_requested: bool
    error: str | None
    metrics: dict[str, Any] | None
    timings: dict[str, Any] | None
    previews: int = Field(description="number of preview images")
    result_available: bool
    created_at: datetime
    updated_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    links: JobLinks

    @classmethod
    def from_row(cls, job: Any) -> JobPublic:
        base = f"/v1/jobs/{job.id}"
        done = (
            job.state.value == "SUCCEEDED" and job.result_key is not None
        )  # as the result routes decide
        return cls(
            id=job.id,
            state=job.state,
            stage=job.stage,
            progress=Progress(done=job.progress_done, total=job.progress_total),
            sequence_id=job.sequence_id,
            campaign_id=getattr(job, "campaign_id", None),
            spec=job.spec,
            attempt=job.attempt,
            cancel_requested=job.cancel_requested,
            error=job.error,
            metrics=job.metrics,
            timings=job.timings,
            previews=len(job.previews or []),
            result_available=done,
            created_at=job.created_at,
            updated_at=job.updated_at,
            started_at=job.started_at,
            finished_at=job.finished_at,
            links=JobLinks(
                self=base,
                events=f"{base}/events",
                archive=f"{base}/archive" if done else None,
                metrics=f"{base}/metrics" if job.metrics is not None else None,
                previews=f"{base}/previews" if job.previews else None,
            ),
        )


class JobEventPublic(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    at: datetime
    kind: str
    message: str | None
    attempt: int
    data: dict[str, Any] | None


class Problem(BaseModel):
    """Error body of 4xx responses other than validation (422)."""

    detail: str


class ValidationProblemItem(BaseModel):
    loc: list[str | int]
    msg: str
    type: str


class ValidationProblem(BaseModel):
    detail: list[ValidationProblemItem]
