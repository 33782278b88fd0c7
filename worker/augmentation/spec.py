"""The augmentation job spec: small typed sections, defaults in one place.

One :class:`AugmentSpec` says everything the augmentation step needs besides the
sequence and its preparation: which objects, where (and how they move), which cameras,
the lidar, the frame range, the localization strategy (for the preparation), the lidar ray
origins and the render options. The CLI builds it from its flags, the service from its
``JobCreate`` JSON (:meth:`AugmentSpec.from_job_spec`).

Objects: one object as ``object`` + ``placement`` (+ ``motion``), the form every job had
so far, or several as ``objects``, a list of ``{object, placement, motion}``
(:class:`SceneObject`); :attr:`AugmentSpec.scene_objects` is the list either way. Each
object is annotated on its own (its own uid); they hide each other in the images and the
lidar.

Moving objects (``motion``, :class:`MotionModel`, the API's own model from
service/schemas.py, one for jobs, campaign variants and this spec): a path of waypoints in track
coordinates ``(s, offset)`` (as a track placement: m from the first frame's position
along the ego track, m left of it) or in world coordinates ``(x, y)``, walked at
``speed_mps`` from the first waypoint; the object faces its direction of travel (plus
``yaw_deg``). Its pose is evaluated at each sensor's own timestamp of every frame.

Lidar origins (``lidar_origins``):

- ``"single"`` (default): the OSDaR-AR paper's fallback, ONE origin for every point:
  the origin of the merged lidar (base) frame, (0, 0, 0). OSDaR23 does not publish the
  six lidars' mounting poses, and the merged frame's origin is the only point the data
  names. It lies near rail height, so rays to the ground behind an object run low: see
  the per-sensor comparison printed by scripts/bench_augment.py.
- ``"x,y,z"``: one given origin in the base frame (e.g. the roof lidar's position).
- a path to a JSON file in the ``ground_truth/lidar_origins.json`` layout
  (``[{sensor_index, translation, quaternion}, ...]``): per-sensor origins (known on
  synthetic data, or estimated).
"""

from __future__ import annotations

import base64
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_serializer,
    field_validator,
    model_validator,
)

from renderer.camera_optics import APERTURE_M, EXPOSURE_S
from service.schemas import MotionModel
from worker.augmentation.gauge import GaugeOutline
from worker.augmentation.placement import PlacementError, PlacementSpec, parse_place

#: A resolved uploaded asset: the mesh file's bytes and its file type (glb, obj, ...).
MeshFile = tuple[bytes, str]

#: The front cameras augmented by default (those of them the sequence has).
DEFAULT_CAMERAS = ("rgb_center", "rgb_highres_center")


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ObjectSource(_Section):
    """The obstacle: a built-in mesh, a mesh file, or mesh bytes with their type.

    ``name`` is the class written to the annotations (default: the built-in's name, or
    ``custom`` for meshes); ``mesh_scale`` is metres per file unit of a mesh file (None:
    the file is in metres); ``scale`` is the uniform size factor on the final object.
    """

    builtin: str | None = None
    mesh_path: str | None = None
    mesh_bytes: bytes | None = Field(None, repr=False)  # JSON: base64 (_mesh_bytes_*)
    file_type: str | None = None
    name: str | None = None
    scale: float = Field(1.0, gt=0.0, le=100.0)
    mesh_scale: float | None = Field(None, gt=0.0)
    up: str | None = None  # None: the format's own (glTF +Y, OBJ/PLY/STL +Z)
    seed: int = 0
    detail: float = Field(1.0, ge=0.05, le=4.0)
    pose: str | None = None  # built-in person: standing, walking, lying, crouching, sitting
    animation_time_s: float | None = Field(None, ge=0.0, le=3600.0)  # glTF skins / morphs

    @field_serializer("mesh_bytes", when_used="json")
    def _mesh_bytes_base64(self, v: bytes | None) -> str | None:
        """In JSON the mesh travels as base64: a job's plan record (records.py) carries
        its spec, and a worker reading the plan back must get the same spec."""
        return None if v is None else base64.b64encode(v).decode("ascii")

    @field_validator("mesh_bytes", mode="before")
    @classmethod
    def _mesh_bytes_from_base64(cls, v: Any) -> Any:
        if isinstance(v, str):
            try:
                return base64.b64decode(v, validate=True)
            except ValueError as exc:
                raise ValueError(f"mesh_bytes: not base64 ({exc})") from None
        return v

    @model_validator(mode="after")
    def _one_source(self) -> ObjectSource:
        given = [
            self.builtin is not None,
            self.mesh_path is not None,
            self.mesh_bytes is not None,
        ]
        if sum(given) != 1:
            raise ValueError("give exactly one of builtin, mesh_path, mesh_bytes")
        if self.mesh_bytes is not None and not self.file_type:
            raise ValueError("mesh_bytes need a file_type (glb, gltf, obj, ply, ...)")
        return self

    @property
    def class_name(self) -> str:
        if self.name:
            return self.name
        return self.builtin if self.builtin is not None else "custom"

    @classmethod
    def from_cli(cls, text: str, **kw: Any) -> ObjectSource:
        """``NAME`` of a built-in obstacle, or a path to a mesh file (has a suffix)."""
        p = Path(text)
        if p.suffix and (p.is_file() or "/" in text):
            return cls(mesh_path=str(p), file_type=p.suffix.lstrip(".").lower(), **kw)
        return cls(builtin=text, **kw)


class PlacementModel(_Section):
    """A placement (see :mod:`worker.augmentation.placement`); ``mode`` track, world or
    lidar (``lidar_frame`` is accepted for lidar)."""

    mode: Literal["track", "world", "lidar"] = "track"
    s: float = 40.0
    offset: float = 0.0
    yaw_deg: float = 90.0
    xyz: tuple[float, float, float | None] | None = None
    frame_idx: int | None = None

    @field_validator("mode", mode="before")
    @classmethod
    def _alias(cls, v: Any) -> Any:
        return "lidar" if v == "lidar_frame" else v

    @model_validator(mode="after")
    def _complete(self) -> PlacementModel:
        if self.mode != "track" and self.xyz is None:
            raise ValueError(f"placement mode {self.mode} needs xyz")
        if self.mode == "lidar" and self.frame_idx is None:
            raise ValueError("placement mode lidar needs frame_idx")
        vals = [self.s, self.offset, self.yaw_deg, *(v for v in (self.xyz or ()) if v is not None)]
        if not all(np.isfinite(vals)):
            raise ValueError("placement values must be finite")
        return self

    def to_spec(self) -> PlacementSpec:
        return PlacementSpec(
            mode=self.mode,
            s=self.s,
            offset=self.offset,
            yaw_deg=self.yaw_deg,
            xyz=self.xyz,
            frame_idx=self.frame_idx,
        )

    @classmethod
    def from_spec(cls, p: PlacementSpec) -> PlacementModel:
        return cls(
            mode=p.mode, s=p.s, offset=p.offset, yaw_deg=p.yaw_deg, xyz=p.xyz, frame_idx=p.frame_idx
        )

    @classmethod
    def parse(cls, text: str) -> PlacementModel:
        """The CLI's ``--place`` string (raises :class:`PlacementError`)."""
        return cls.from_spec(parse_place(text))


class SceneObject(_Section):
    """One object of a job: what (``object``), where (``placement``) and, for a moving
    object, its ``motion`` (which then decides the position; the placement is not used)."""

    object: ObjectSource
    placement: PlacementModel = Field(default_factory=PlacementModel)
    motion: MotionModel | None = None


class RenderSpec(_Section):
    """Render and composite options.

    png_compression : zlib level of the rows of the augmented PNGs that the objects change
        (the rows around them keep the input's compressed bytes where the input is 8-bit
        RGB and not interlaced: worker/osdar/png_splice.py). The level the input used
        cannot be read back from a PNG, so the default is 1 (fast); the I/O floor uses the
        same for its whole re-encode.
    blur, lab_match, shadow_strength : see :func:`renderer.composite.composite`.
    pixel_offset : shift the object by the calibration point's mean residual per camera
        (needs clicks in the preparation), compensating a constant calibration error.
    antialias : the renderer's ``auto``, ``none`` or ``ssaa<s>``.
    sun : ``ephemeris`` (the sun's direction at the sequence's place and time) or
        ``default`` (renderer.lighting's DEFAULT_SUN_DIR_WORLD, the synthetic scenes' sun).
    scale : the job's fraction of the real resolution; the augmentation always works at
        the input images' resolution (kept for the service's spec; see from_job_spec).
    exposure_ms, aperture_mm : the front cameras' exposure (the object's motion blur: its
        image motion over the exposure) and effective aperture diameter (its defocus at
        its distance, a lens focused at infinity; the frame's measured blur is never
        undercut by it). OSDaR23 publishes neither: the defaults are assumptions; 0 turns
        either off (the synthetic generator's cameras: pinholes at the frame's instant,
        ``meta.json``'s ``camera_optics``).
    lidar_noise : the object's lidar points get their sensor's range noise and dropout,
        measured per frame on the real points around the object
        (:func:`renderer.lidar_noise.measure_lidar_noise`); False: exactly on the
        object's surface, none dropped. On by default: on the synthetic sequences (six
        scenes, 12 scene/seed pairs, four frames each, every sensor) the estimate is
        0.83-1.20x the sensors' true range noise and the object points scatter
        0.95-1.18x it (tests/augmentation/test_frame.py).
    """

    png_compression: int = Field(1, ge=0, le=9)
    blur: bool = True
    lab_match: bool = True
    shadow_strength: float = Field(0.6, ge=0.0, le=1.0)
    pixel_offset: bool = False
    antialias: str = "auto"
    sun: Literal["ephemeris", "default"] = "ephemeris"
    scale: float = Field(1.0, gt=0.0, le=1.0)
    exposure_ms: float = Field(1000.0 * EXPOSURE_S, ge=0.0, le=100.0)
    aperture_mm: float = Field(1000.0 * APERTURE_M, ge=0.0, le=100.0)
    lidar_noise: bool = True


class AugmentSpec(_Section):
    """Everything the augmentation step needs besides the sequence (module docstring)."""

    object: ObjectSource | None = None
    placement: PlacementModel = Field(default_factory=PlacementModel)
    motion: MotionModel | None = None
    #: several objects (give either ``object`` or ``objects``)
    objects: tuple[SceneObject, ...] = Field(default=(), max_length=32)
    cameras: tuple[str, ...] | None = None  # None: DEFAULT_CAMERAS the sequence has
    lidar: bool = True
    frame_range: tuple[int, int] | None = None  # inclusive frame indices
    strategy: str = "auto"
    lidar_origins: str = "single"
    clicks: dict[str, Any] | None = None  # Clicks.to_json() layout, for the preparation
    render: RenderSpec = Field(default_factory=RenderSpec)
    #: the clearance envelope of the gauge labels (worker/augmentation/gauge.py)
    gauge: GaugeOutline = Field(default_factory=GaugeOutline)

    @model_validator(mode="before")
    @classmethod
    def _one_of_objects(cls, data: Any) -> Any:
        """``objects`` of one object is the single-object form (one spelling per job:
        readers of ``object`` / ``placement``, e.g. the evaluation, see it)."""
        if isinstance(data, dict) and data.get("object") is None:
            objs: Any = data.get("objects") or ()
            if len(objs) == 1:
                one = objs[0]
                one = one.model_dump() if isinstance(one, SceneObject) else dict(one)
                data = {k: v for k, v in data.items() if k != "objects"}
                data.update(object=one.get("object"), placement=one.get("placement") or {},
                            motion=one.get("motion"))  # fmt: skip
        return data

    @model_validator(mode="after")
    def _objects(self) -> AugmentSpec:
        if (self.object is None) == (not self.objects):
            raise ValueError("give exactly one of 'object' (one object) and 'objects' (a list)")
        return self

    @property
    def scene_objects(self) -> list[SceneObject]:
        """The objects of the job: ``objects``, or the one ``object`` with its placement."""
        if self.objects:
            return list(self.objects)
        assert self.object is not None
        return [SceneObject(object=self.object, placement=self.placement, motion=self.motion)]

    @field_validator("frame_range")
    @classmethod
    def _ordered(cls, v: tuple[int, int] | None) -> tuple[int, int] | None:
        if v is not None and v[0] > v[1]:
            raise ValueError("frame_range must be [first, last] with first <= last")
        return v

    @field_validator("lidar_origins")
    @classmethod
    def _origins(cls, v: str) -> str:
        if v == "single" or _parse_point(v) is not None or v.endswith(".json"):
            return v
        raise ValueError(
            f"lidar_origins must be 'single', 'x,y,z' or a lidar_origins .json path, got {v!r}"
        )

    def camera_names(self, available: list[str]) -> list[str]:
        """The cameras to augment: the requested ones (all must exist) or the default
        front cameras the sequence has. Raises ValueError naming a missing camera."""
        if self.cameras is None:
            chosen = [c for c in DEFAULT_CAMERAS if c in available]
            if not chosen:
                raise ValueError(
                    f"the sequence has none of the default cameras {', '.join(DEFAULT_CAMERAS)} "
                    f"(it has: {', '.join(available) or 'none'}): pass --cameras"
                )
            return chosen
        missing = [c for c in self.cameras if c not in available]
        if missing:
            raise ValueError(
                f"camera(s) {', '.join(missing)} not in the sequence "
                f"(it has: {', '.join(available) or 'none'})"
            )
        return list(self.cameras)

    def origins_value(self) -> str | tuple[float, float, float]:
        """``"single"``, a point (3,) or a JSON path (as the string)."""
        p = _parse_point(self.lidar_origins)
        return p if p is not None else self.lidar_origins

    @classmethod
    def from_job_spec(
        cls,
        d: dict[str, Any],
        *,
        assets: Mapping[str, MeshFile] | None = None,
    ) -> AugmentSpec:
        """From the service's ``JobCreate`` JSON (service/schemas.py).

        Every object's ``asset_id`` must be resolved by the caller (the asset store, the
        owner checked): ``assets`` maps each asset id to its mesh bytes and file type
        (``service.schemas.spec_asset_ids`` lists them). ``render.shadow`` false sets
        the shadow strength to 0; ``clicks`` ({camera: {frame: [u, v]}}) become the
        preparation's clicks of a landmark named ``job``; ``gauge`` (GaugeOutline's
        fields) sets the envelope of the gauge labels; ``objects`` / ``motion``: several
        objects, moving ones (module docstring).
        """
        if d.get("objects"):
            if d.get("object") is not None:
                raise ValueError("give either 'object' or 'objects', not both")
            objects = tuple(
                _scene_object(o, f"objects[{i}]", assets or {}) for i, o in enumerate(d["objects"])
            )
            one: dict[str, Any] = {"object": None, "objects": objects}
        else:
            only = _scene_object(d, "", assets or {})
            one = {"object": only.object, "placement": only.placement, "motion": only.motion}
        render = dict(d.get("render") or {})
        shadow = render.pop("shadow", True)
        render_spec = RenderSpec(
            png_compression=int(render.get("png_compression", 3)),
            blur=bool(render.get("blur", True)),
            shadow_strength=0.6 if shadow else 0.0,
            scale=float(render.get("scale", 1.0)),
            **{k: float(render[k]) for k in ("exposure_ms", "aperture_mm") if k in render},
        )
        clicks = d.get("clicks")
        fr = d.get("frame_range")
        gauge = GaugeOutline.model_validate(d["gauge"]) if d.get("gauge") else GaugeOutline()
        return cls(
            **one,
            gauge=gauge,
            cameras=tuple(d["cameras"]) if d.get("cameras") else None,
            lidar=bool(d.get("lidar", True)),
            frame_range=None if fr is None else (int(fr[0]), int(fr[1])),
            strategy=str(d.get("strategy", "auto")),
            clicks=None if not clicks else {"landmark": "job", "clicks": clicks},
            render=render_spec,
        )


def _scene_object(d: dict[str, Any], where: str, assets: Mapping[str, MeshFile]) -> SceneObject:
    """A job spec's ``{object, placement, motion}`` (``where`` names it in errors)."""
    at = f"{where}: " if where else ""
    obj = d.get("object") or {}
    if obj.get("builtin") is not None:
        source = ObjectSource(
            builtin=obj["builtin"],
            scale=float(obj.get("scale", 1.0)),
            seed=int(obj.get("seed", 0)),  # a campaign's variation seed
        )
    elif obj.get("asset_id") is not None:
        if obj["asset_id"] not in assets:
            raise ValueError(f"{at}object asset {obj['asset_id']!r} was not resolved (assets)")
        mesh_bytes, file_type = assets[obj["asset_id"]]
        source = ObjectSource(
            mesh_bytes=mesh_bytes, file_type=file_type, scale=float(obj.get("scale", 1.0))
        )
    else:
        raise ValueError(f"{at}object needs 'builtin' or 'asset_id'")
    pl = dict(d.get("placement") or {"mode": "track"})
    if pl.get("mode", "track") == "track":
        pl.setdefault("yaw_deg", 0.0)  # JobCreate's default
    motion = d.get("motion")
    return SceneObject(
        object=source,
        placement=PlacementModel.model_validate(pl),
        motion=None if motion is None else MotionModel.model_validate(motion),
    )


def _parse_point(text: str) -> tuple[float, float, float] | None:
    parts = text.split(",")
    if len(parts) != 3:
        return None
    try:
        p = tuple(float(x) for x in parts)
    except ValueError:
        return None
    return p if all(np.isfinite(p)) else None  # type: ignore[return-value]


__all__ = [
    "DEFAULT_CAMERAS",
    "AugmentSpec",
    "MeshFile",
    "MotionModel",
    "ObjectSource",
    "PlacementError",
    "PlacementModel",
    "RenderSpec",
    "SceneObject",
]
