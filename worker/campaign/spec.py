"""The campaign spec: a dataset as sequences x obstacles x placements x draws.

A campaign asks for many augmented sequences at once. It names the sequences, the
obstacles (today's job ``object``: a built-in class or an uploaded asset, plus the
variation seeds of a built-in), the placements (today's job ``placement`` as is, or a rule
the positions are drawn from) and how many independent draws of each rule to make. The
expansion (:func:`worker.campaign.expand.expand`) turns it into variants, deterministically:
the same spec with the same ``seed`` gives the same variants, byte for byte in their JSON.

YAML (``examples/osdar_ar_paper.yaml`` is a complete one)::

    name: station_demo
    seed: 7
    sequences:
      - path: data/synth/station          # the CLI: a sequence folder
      - id: 3f2a9c51                      # the service: a registered sequence's id
        frame_range: [0, 49]
    obstacles:
      - builtin: person
        seeds: [0, 1, 2]                  # three different persons
      - builtin: fallen_tree
        scale: 0.8
      - asset_id: a81b3c                  # an uploaded mesh
    placements:
      - zone: track                       # a rule: drawn positions
        distance_m: [30, 100]             # ahead of the train when first in view
        yaw_deg: [-180, 180]
      - zone: platform
        side: right
        sequences: [data/synth/station]   # the rule applies to these sequences only
        obstacles: [person]               # and to these obstacles only
      - explicit: {mode: track, s: 45, offset: 0.0, yaw_deg: 90}
    draws: 2                              # each rule drawn twice
    objects_per_sequence: 1
    constraints: {min_spacing_m: 5, clearance_m: 0.1}
    job: {cameras: [rgb_center, rgb_highres_center], lidar: true, strategy: auto}

JSON is the same document (``examples/campaign_rules.json``)::

    {"name": "rocks", "sequences": [{"path": "data/synth/fire_site"}],
     "obstacles": [{"builtin": "rock", "seeds": [0, 1, 2, 3]}],
     "placements": [{"zone": "gauge_edge", "distance_m": [40, 120]}]}

Zones (lateral, from the ego centreline; W is the envelope's half-width of
:class:`~worker.augmentation.gauge.GaugeOutline`, 1.775 m by default, B the ballast bed's
half-width, 1.6 m; ``side`` picks left, right or either where a zone has sides):

=============  ======================================================================
track          on the track inside the gauge: the footprint within +-W, its centre on
               the track bed
gauge_edge     at the gauge's edge: the footprint straddles +W or -W (not the centreline)
beside         beside the track: the footprint outside +-W, its centre within W + 5 m
platform       on a platform the preparation found: the footprint inside the platform
crossing       across the track: the footprint spans the centreline, its centre on the
               bed; yaw 60-120 or 240-300 deg by default (crossing either way)
=============  ======================================================================

Whatever the zone, an object never stands inside a pole, across a platform's edge or half
on the track bed (its footprint reaching over the bed's edge from the ground beside it),
keeps ``constraints.clearance_m`` from all three, and keeps ``constraints.min_spacing_m``
(footprint to footprint) from the other objects of its variant.

``distance_m`` is measured along the ego track from the train (the base frame's origin,
the front of the train) to the object when the object first comes into view: the first
frame (of the sequence's ``frame_range``) where it lies within ``view_half_angle_deg`` of
the train's heading and no farther than the rule's upper distance.

Moving obstacles: an obstacle with ``motion`` walks through its drawn (or explicit track)
position, the middle of its path::

    obstacles:
      - builtin: person
        motion: {pattern: cross, speed_mps: [1.0, 1.6], span_m: 8}   # across the track
      - builtin: cow
        motion: {pattern: along, speed_mps: [0.3, 0.8], span_m: 6}   # wandering along it

``cross`` walks across the track (the path at the drawn arc length, from offset - span/2
to offset + span/2), ``along`` along it (at the drawn offset, from s - span/2 to s +
span/2); the direction (left or right, with or against the train) and the speed are
drawn per object, ``start_s`` [low, high] seconds after the first frame. The zone's rules
hold at the path's middle; along the whole path the object keeps ``clearance_m`` from the
poles and ``min_spacing_m`` from the variant's other objects (every position of a moving
one), never walks through a platform's edge (it stays on the platform it starts on, or
off all of them) and stays on the prepared track's extent. The variant's job carries the path in
track coordinates (``motion``: :class:`~worker.augmentation.spec.MotionModel`).

Variants: for each sequence, every (draw, placement, obstacle, variation seed) in this
order is one object, where the placement applies to the sequence and the obstacle (its
``sequences`` and ``obstacles`` filters); consecutive objects are grouped
``objects_per_sequence`` at a time into one variant (the last group may be smaller).
Explicit placements are drawn once.

This module imports only pydantic and the service's request schemas, whose ``ObjectSpec``,
``Placement`` and ``GaugeOptions`` it reuses: the spec can be checked where the pipeline is
not installed. A variant is a job of the service's ``JobCreate`` format.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    field_validator,
    model_validator,
)

from service.schemas import (
    CameraName,
    GaugeOptions,
    ObjectSpec,
    Placement,
    RenderOptions,
    Strategy,
)
from worker.campaign.variant import Issue

Zone = Literal["track", "gauge_edge", "beside", "platform", "crossing"]
ZONES: tuple[str, ...] = get_args(Zone)
Side = Literal["left", "right", "either"]

#: Upper bound on the variants of one campaign (a spec error beyond it).
MAX_VARIANTS = 10_000

#: Default yaw ranges (deg, relative to the track direction) per zone.
DEFAULT_YAW_DEG: dict[str, list[tuple[float, float]]] = {
    "track": [(-180.0, 180.0)],
    "gauge_edge": [(-180.0, 180.0)],
    "beside": [(-180.0, 180.0)],
    "platform": [(-180.0, 180.0)],
    "crossing": [(60.0, 120.0), (240.0, 300.0)],
}


class _Spec(BaseModel):
    """Spec sections: unknown fields are errors, NaN/inf are refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _range(v: tuple[float, float], what: str) -> tuple[float, float]:
    if v[0] > v[1]:
        raise ValueError(f"{what} must be [low, high] with low <= high, got {list(v)}")
    return v


class SequenceEntry(_Spec):
    """One sequence: a registered sequence (``id``, the service) or a folder (``path``,
    the CLI), optionally a frame range (inclusive frame indices, as in a job spec)."""

    id: str | None = Field(None, min_length=1, max_length=64)
    path: str | None = Field(None, min_length=1, max_length=4096)
    name: str | None = Field(None, min_length=1, max_length=200, description="label")
    frame_range: tuple[int, int] | None = None

    @model_validator(mode="after")
    def _one_ref(self) -> SequenceEntry:
        if (self.id is None) == (self.path is None):
            raise ValueError("give exactly one of 'id' and 'path'")
        if self.frame_range is not None and not 0 <= self.frame_range[0] <= self.frame_range[1]:
            raise ValueError("frame_range must be [first, last] with 0 <= first <= last")
        return self

    @property
    def key(self) -> str:
        """What the prepared sequences are looked up by: the id or the path."""
        return self.id if self.id is not None else str(self.path)

    @property
    def label(self) -> str:
        if self.name:
            return self.name
        return self.id if self.id is not None else Path(str(self.path)).name


class ObstacleMotion(_Spec):
    """How an obstacle moves (module docstring): ``pattern`` cross or along the track
    through its position, a path ``span_m`` long walked at a speed drawn from
    ``speed_mps`` [low, high], setting off ``start_s`` [low, high] s after the first frame;
    ``gait``: the built-in person swings legs and arms."""

    pattern: Literal["cross", "along"] = "cross"
    speed_mps: tuple[float, float] = (1.0, 1.6)
    span_m: float = Field(8.0, gt=0.0, le=500.0)
    start_s: tuple[float, float] = (0.0, 0.0)
    gait: bool = True

    @field_validator("speed_mps")
    @classmethod
    def _speed(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] <= 0.0 or v[1] > 50.0:
            raise ValueError("speed_mps must lie within (0, 50] m/s")
        return _range(v, "speed_mps")

    @field_validator("start_s")
    @classmethod
    def _start(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] < 0.0 or v[1] > 3600.0:
            raise ValueError("start_s must lie within [0, 3600] s")
        return _range(v, "start_s")


class Obstacle(ObjectSpec):
    """An obstacle: today's job ``object`` (``builtin`` class or ``asset_id``, ``scale``),
    for a built-in its variation seeds (one obstacle per seed; default [0]), and how it
    moves (``motion``; None: it stands still)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    seeds: list[Annotated[int, Field(ge=0, le=2**31 - 1)]] | None = Field(
        None, min_length=1, max_length=1000, description="variation seeds of a built-in"
    )
    motion: ObstacleMotion | None = None

    @model_validator(mode="after")
    def _seeds_for_builtins(self) -> Obstacle:
        if "seed" in self.model_fields_set:
            raise ValueError("an obstacle's variation seeds are 'seeds', a list (e.g. [0, 1])")
        if self.seeds is not None and self.builtin is None:
            raise ValueError("'seeds' vary built-in obstacles only, not an uploaded asset")
        if self.seeds is not None and len(set(self.seeds)) != len(self.seeds):
            raise ValueError("seeds must not repeat")
        return self

    @property
    def variation_seeds(self) -> list[int]:
        return list(self.seeds) if self.seeds is not None else [0]

    @property
    def class_name(self) -> str:
        """The class written to the annotations (an asset: ``asset:<id>`` here)."""
        return str(self.builtin) if self.builtin is not None else f"asset:{self.asset_id}"

    def job_object(self, seed: int) -> dict[str, Any]:
        """Today's job ``object`` for one variation (the service's ``ObjectSpec``). The
        variation seed is written as ``seed`` when it is not 0, as ObjectSpec writes it."""
        out: dict[str, Any] = (
            {"builtin": self.builtin} if self.builtin is not None else {"asset_id": self.asset_id}
        )
        out["scale"] = self.scale
        if seed != 0:
            out["seed"] = seed
        return out


class ExplicitPlacement(_Spec):
    """Today's job placement, as is: ``{mode: track, s, offset, yaw_deg}`` or
    ``{mode: world | lidar_frame, xyz, yaw_deg, frame_idx}``."""

    explicit: Placement
    sequences: list[str] | None = Field(
        None, min_length=1, description="keys or names of the sequences it applies to"
    )
    obstacles: list[str] | None = Field(
        None, min_length=1, description="classes or asset ids of the obstacles it applies to"
    )


class PlacementRule(_Spec):
    """Positions drawn from a zone (module docstring).

    distance_m : [near, far] m along the track from the train when the object first comes
        into view.
    yaw_deg : yaw ranges (deg, relative to the track direction: 0 faces along the direction
        of travel, 90 faces left); one [low, high] pair or a list of them (a range is picked
        with probability in proportion to its width). Default: per zone (DEFAULT_YAW_DEG).
    side : left, right or either (zones with sides: gauge_edge, beside, platform).
    lateral_m : narrows the zone: [low, high] m of the object centre's offset (left +).
    view_half_angle_deg : the cameras' horizontal half field of view for "in view" (the
        front cameras of OSDaR23 have about 15 deg).
    sequences : keys or names of the sequences it applies to (default: all).
    obstacles : built-in classes or asset ids of the obstacles it applies to (default: all).
    """

    zone: Zone = "track"
    distance_m: tuple[float, float] = (30.0, 200.0)
    yaw_deg: list[tuple[float, float]] | None = Field(None, min_length=1, max_length=16)
    side: Side = "either"
    lateral_m: tuple[float, float] | None = None
    view_half_angle_deg: float = Field(15.0, gt=0.0, lt=90.0)
    sequences: list[str] | None = Field(None, min_length=1)
    obstacles: list[str] | None = Field(None, min_length=1)

    @field_validator("distance_m")
    @classmethod
    def _distance(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] < 0.0 or v[1] > 5000.0:
            raise ValueError("distance_m must lie within [0, 5000] m")
        return _range(v, "distance_m")

    @field_validator("lateral_m")
    @classmethod
    def _lateral(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and (v[0] < -50.0 or v[1] > 50.0):
            raise ValueError("lateral_m must lie within [-50, 50] m (a job's offset range)")
        return None if v is None else _range(v, "lateral_m")

    @field_validator("yaw_deg", mode="before")
    @classmethod
    def _one_pair(cls, v: Any) -> Any:
        if (
            isinstance(v, (list, tuple))
            and len(v) == 2
            and all(isinstance(x, (int, float)) for x in v)
        ):
            return [v]
        return v

    @field_validator("yaw_deg")
    @classmethod
    def _yaw(cls, v: list[tuple[float, float]] | None) -> list[tuple[float, float]] | None:
        for r in v or []:
            _range(r, "yaw_deg")
            if r[0] < -360.0 or r[1] > 360.0:
                raise ValueError("yaw_deg ranges must lie within [-360, 360]")
        return v

    @property
    def yaw_ranges(self) -> list[tuple[float, float]]:
        return list(self.yaw_deg) if self.yaw_deg is not None else DEFAULT_YAW_DEG[self.zone]


def _placement_kind(v: Any) -> str:
    if isinstance(v, dict):
        return "explicit" if "explicit" in v else "rule"
    return "explicit" if isinstance(v, ExplicitPlacement) else "rule"


PlacementEntry = Annotated[
    Annotated[ExplicitPlacement, Tag("explicit")] | Annotated[PlacementRule, Tag("rule")],
    Discriminator(_placement_kind),
]


def _default_placements() -> list[ExplicitPlacement | PlacementRule]:
    return [PlacementRule()]


class Constraints(_Spec):
    """What every drawn position keeps: ``min_spacing_m`` footprint to footprint between
    the objects of a variant, ``clearance_m`` to poles, platform edges and the track bed's
    edge; ``max_attempts`` draws per object before the rule is reported impossible."""

    min_spacing_m: float = Field(5.0, ge=0.0, le=1000.0)
    clearance_m: float = Field(0.1, ge=0.0, le=10.0)
    max_attempts: int = Field(400, ge=1, le=100_000)


class JobOptions(_Spec):
    """The job fields shared by every variant (as in today's job spec); ``gauge`` sets the
    envelope of the gauge labels (e.g. ``{margin_m: 0.3}``)."""

    cameras: list[CameraName] = Field(
        default_factory=lambda: ["rgb_center", "rgb_highres_center"], min_length=1, max_length=8
    )
    lidar: bool = True
    strategy: Strategy = "auto"
    render: RenderOptions = Field(default_factory=RenderOptions)
    gauge: GaugeOptions | None = None

    @field_validator("cameras")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError("cameras must not repeat")
        return v


class CampaignSpec(_Spec):
    """A campaign (module docstring)."""

    name: str = Field(min_length=1, max_length=200, pattern=r"^[\w .:@+-]+$")
    seed: int = Field(0, ge=0, le=2**63 - 1)
    sequences: list[SequenceEntry] = Field(min_length=1, max_length=1000)
    obstacles: list[Obstacle] = Field(min_length=1, max_length=1000)
    placements: list[PlacementEntry] = Field(
        default_factory=_default_placements, min_length=1, max_length=1000
    )
    draws: int = Field(1, ge=1, le=1000)
    objects_per_sequence: int = Field(1, ge=1, le=32)
    constraints: Constraints = Field(default_factory=Constraints)
    job: JobOptions = Field(default_factory=JobOptions)

    @model_validator(mode="after")
    def _consistent(self) -> CampaignSpec:
        keys = [s.key for s in self.sequences]
        if len(set(keys)) != len(keys):
            raise ValueError("sequences must not repeat (same id or path twice)")
        known = set(keys) | {s.label for s in self.sequences}
        classes = {o.builtin or str(o.asset_id) for o in self.obstacles}
        for i, p in enumerate(self.placements):
            unknown = sorted(set(p.sequences or []) - known)
            if unknown:
                raise ValueError(
                    f"placements[{i}].sequences: {unknown} name no sequence of the campaign "
                    f"(its sequences: {sorted(known)})"
                )
            unknown = sorted(set(p.obstacles or []) - classes)
            if unknown:
                raise ValueError(
                    f"placements[{i}].obstacles: {unknown} name no obstacle of the campaign "
                    f"(its obstacles: {sorted(classes)})"
                )
        n = self.object_count()
        if -(-n // self.objects_per_sequence) > MAX_VARIANTS:
            raise ValueError(f"the campaign expands into more than {MAX_VARIANTS} variants")
        return self

    def applies(self, placement: ExplicitPlacement | PlacementRule, seq: SequenceEntry) -> bool:
        """Whether a placement applies to a sequence (its ``sequences`` filter)."""
        return placement.sequences is None or bool({seq.key, seq.label} & set(placement.sequences))

    def places(self, placement: ExplicitPlacement | PlacementRule, obstacle: Obstacle) -> bool:
        """Whether a placement applies to an obstacle (its ``obstacles`` filter)."""
        name = obstacle.builtin or str(obstacle.asset_id)
        return placement.obstacles is None or name in placement.obstacles

    def object_count(self) -> int:
        """Objects over all sequences (before grouping into variants)."""
        total = 0
        for seq in self.sequences:
            for p in self.placements:
                if self.applies(p, seq):
                    n = sum(len(o.variation_seeds) for o in self.obstacles if self.places(p, o))
                    total += n * (1 if isinstance(p, ExplicitPlacement) else self.draws)
        return total


def _where(loc: tuple[int | str, ...]) -> str:
    """pydantic's error location as a path: ``placements[0].zone`` (the tag pydantic puts
    after a placement's index, rule or explicit, dropped)."""
    out = ""
    for i, part in enumerate(loc):
        if isinstance(part, int):
            out += f"[{part}]"
        elif i == 2 and loc[0] == "placements":
            continue
        else:
            out += f".{part}" if out else str(part)
    return out or "(the spec)"


def spec_issues(data: Any) -> tuple[CampaignSpec | None, list[Issue]]:
    """A spec mapping validated: the spec (None when invalid) and every error as an
    :class:`~worker.campaign.variant.Issue` whose ``where`` is the field's path."""
    try:
        return CampaignSpec.model_validate(data), []
    except ValidationError as exc:
        return None, [
            Issue("error", _where(tuple(e["loc"])), e["msg"].removeprefix("Value error, "))
            for e in exc.errors()
        ]


def parse_spec(text: str, *, fmt: Literal["yaml", "json"] = "yaml") -> CampaignSpec:
    """A spec from YAML or JSON text (pydantic's ValidationError when it is invalid)."""
    data = json.loads(text) if fmt == "json" else yaml.safe_load(text)
    if not isinstance(data, dict):
        raise ValueError("a campaign spec is a mapping (name, sequences, obstacles, ...)")
    return CampaignSpec.model_validate(data)


def load_spec(path: str | Path) -> CampaignSpec:
    """A spec file: ``.json`` is read as JSON, anything else as YAML."""
    p = Path(path)
    return parse_spec(p.read_text(), fmt="json" if p.suffix.lower() == ".json" else "yaml")


__all__ = [
    "DEFAULT_YAW_DEG",
    "MAX_VARIANTS",
    "ZONES",
    "CampaignSpec",
    "Constraints",
    "ExplicitPlacement",
    "GaugeOptions",
    "JobOptions",
    "Obstacle",
    "ObstacleMotion",
    "PlacementEntry",
    "PlacementRule",
    "SequenceEntry",
    "Zone",
    "load_spec",
    "parse_spec",
    "spec_issues",
]
