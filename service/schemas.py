"""Request and response schemas of the API (separate from the tables)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Generic, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

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

    @model_validator(mode="after")
    def _one_source(self) -> ObjectSpec:
        if (self.builtin is None) == (self.asset_id is None):
            raise ValueError("give exactly one of 'builtin' and 'asset_id'")
        return self


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


class RenderOptions(_In):
    scale: float = Field(1.0, gt=0.0, le=1.0, description="fraction of the real resolution")
    png_compression: int = Field(3, ge=0, le=9)
    blur: bool = True
    shadow: bool = True


Clicks = dict[CameraName, dict[str, tuple[float, float]]]


class JobCreate(_In):
    """A job spec; checked against the sequence at submission."""

    sequence_id: Ident
    cameras: list[CameraName] = Field(
        default_factory=lambda: ["rgb_center", "rgb_highres_center"], min_length=1, max_length=8
    )
    lidar: bool = True
    object: ObjectSpec
    placement: Placement
    strategy: Strategy = "auto"
    frame_range: tuple[int, int] | None = Field(
        None, description="[first, last] frame index, inclusive; default: all frames"
    )
    clicks: Clicks | None = Field(
        None, description="camera -> {frame index: [u, v]} pixel clicks of the landmark"
    )
    render: RenderOptions = Field(default_factory=RenderOptions)

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
