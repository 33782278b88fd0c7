"""The preparation config: small typed sections, defaults in one place.

One :class:`PrepareConfig` describes a preparation run completely (together with the
sequence's content and the clicks file, it is what the cached artifact is keyed by, see
:func:`PrepareConfig.config_hash`). Stages never receive the whole config: small factories
(``registration_kwargs``, :meth:`PlaneConfig`, ...) hand them plain arguments.

A job spec overrides a section with a partial dict, e.g.
``PrepareConfig.model_validate({"strategy": "rails", "registration": {"voxel_size": 0.2}})``.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from osdar_platform.catalog import STRATEGY_NAMES


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RegistrationConfig(_Section):
    """The merged cloud (registration.py)."""

    voxel_size: float = Field(0.10, gt=0.0, le=2.0)  # m, final cloud: the speed/accuracy knob
    max_range: float = Field(80.0, gt=0.0)  # m from the base origin
    pre_voxel_size: float | None = Field(None, gt=0.0)  # m, pre-registration (default 2.5 x)
    frame_step: int = Field(4, ge=1)  # every k-th frame for the final cloud (10 Hz overlaps)
    lateral_limit: float | None = Field(30.0, gt=0.0)  # m, |y| in the base frame kept
    pre_frame_step: int = Field(4, ge=1)  # every k-th frame for the pre-registration
    #: m, |y| in the base frame kept for the pre-registration: its cloud serves only to find
    #: the ego track along the driven stretch (the rail heads near each pose, and ahead as
    #: far as the track stays within this band), not the neighbours or the scene.
    pre_lateral_limit: float | None = Field(10.0, gt=0.0)
    pre_poses: Literal["odometry", "ins"] = "odometry"  # poses of the pre-registration

    @model_validator(mode="after")
    def _derived(self) -> RegistrationConfig:
        # Derived default filled in one place (kiss-icp style): the pre-registration only
        # feeds the rail extraction, a coarser cloud is enough.
        if self.pre_voxel_size is None:
            object.__setattr__(self, "pre_voxel_size", min(2.0, 2.5 * self.voxel_size))
        return self


class RailsConfig(_Section):
    """Rail / centreline extraction (tracks.py): backend and its segmentation options."""

    backend: Literal["geometric", "image"] = "geometric"
    options: dict[str, Any] = Field(default_factory=dict)


class LocalizationConfig(_Section):
    """Options passed to the strategies (``LocalizationInput.options``)."""

    options: dict[str, Any] = Field(default_factory=dict)


class LidarAlignmentConfig(_Section):
    """Per-lidar corrections of the merged clouds (lidar_alignment.py)."""

    #: Estimate them and apply those beyond the estimate's own error before odometry
    #: (docs/method.md, "Lidar alignment").
    enabled: bool = True
    frames: int = Field(8, ge=2)  # frames they are estimated on (alternate ones: 2 halves)


class PlaneConfig(_Section):
    """Ground and platform planes near the track (RANSAC, open3d ``segment_plane``)."""

    segment_length: float = Field(40.0, gt=1.0)  # m of track per piece of plane
    corridor: float = Field(14.0, gt=0.0)  # m either side of the centreline considered
    height_band: tuple[float, float] = (-3.0, 2.0)  # m relative to the rail top kept
    distance_threshold: float = Field(0.06, gt=0.0)  # m, RANSAC inlier distance
    ransac_iterations: int = Field(400, ge=10)
    ransac_probability: float = Field(0.9999, gt=0.0, lt=1.0)  # stop early when this sure
    max_planes: int = Field(4, ge=1)  # per segment
    min_points: int = Field(200, ge=3)  # inliers of an accepted plane (per component)
    max_tilt_deg: float = Field(12.0, gt=0.0, lt=90.0)  # from horizontal
    cell_size: float = Field(0.5, gt=0.0)  # m, grid of the connected components / outline
    outline_step: float = Field(2.0, gt=0.0)  # m of arc length per outline vertex
    ground_height: tuple[float, float] = (-1.2, 0.1)  # m rel. rail top: track bed
    platform_height: tuple[float, float] = (0.35, 1.4)  # m rel. rail top: platform top
    platform_min_lateral: float = Field(1.2, ge=0.0)  # m, platform edge beyond this
    max_points: int = Field(60_000, ge=1000)  # per segment (random subset above this)


class PoleConfig(_Section):
    """Poles by DBSCAN (open3d ``cluster_dbscan``) over tall thin vertical structures."""

    corridor: float = Field(20.0, gt=0.0)  # m either side of the centreline
    height_band: tuple[float, float] = (0.5, 12.0)  # m rel. rail top of candidate points
    column_cell: float = Field(0.25, gt=0.0)  # m, xy cell of the vertical-extent filter
    min_column_extent: float = Field(1.5, gt=0.0)  # m of z extent for a "tall" cell
    eps: float = Field(0.45, gt=0.0)  # m, DBSCAN neighbourhood
    min_cluster_points: int = Field(8, ge=2)  # DBSCAN core size
    min_height: float = Field(2.5, gt=0.0)  # m vertical extent of a pole
    max_radius: float = Field(0.45, gt=0.0)  # m horizontal radius of a pole
    min_points: int = Field(15, ge=3)


class CalibrationConfig(_Section):
    """The calibration point (clicked landmark, or proposed pole tops)."""

    search_radius_px: float = Field(30.0, gt=0.0)  # neighbourhood of a click (full res. px)
    seed_frames: int = Field(6, ge=1)  # clicked views that seed the candidate points
    #: m: refine the chosen point among every frame's points within this radius at full
    #: density (registration.points_near); 0 keeps the registered cloud's point.
    dense_radius_m: float = Field(0.5, ge=0.0)
    auto: bool = True  # propose pole tops when there are no clicks
    auto_proposals: int = Field(3, ge=1)  # pole tops listed
    auto_min_depth: float = Field(3.0, gt=0.0)  # m, in front of the camera
    auto_max_depth: float = Field(120.0, gt=0.0)  # m
    auto_margin_px: float = Field(20.0, ge=0.0)  # full-resolution px from the image border


class PrepareConfig(_Section):
    """Everything a preparation run depends on besides the sequence and the clicks."""

    strategy: str = "auto"
    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)
    rails: RailsConfig = Field(default_factory=RailsConfig)
    localization: LocalizationConfig = Field(default_factory=LocalizationConfig)
    lidar_alignment: LidarAlignmentConfig = Field(default_factory=LidarAlignmentConfig)
    planes: PlaneConfig = Field(default_factory=PlaneConfig)
    poles: PoleConfig = Field(default_factory=PoleConfig)
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)

    @model_validator(mode="after")
    def _check_strategy(self) -> PrepareConfig:
        if self.strategy not in STRATEGY_NAMES:
            raise ValueError(
                f"unknown strategy {self.strategy!r}; known: {', '.join(STRATEGY_NAMES)}"
            )
        return self

    def with_overrides(self, **sections: Any) -> PrepareConfig:
        """A copy with fields or partial sections replaced (validated again)."""
        data = self.model_dump()
        for key, value in sections.items():
            if isinstance(value, dict) and isinstance(data.get(key), dict):
                data[key] = {**data[key], **value}
            else:
                data[key] = value
        return PrepareConfig.model_validate(data)

    def config_hash(self) -> str:
        """sha256 hex of the canonical JSON of every field (derived defaults included)."""
        text = json.dumps(self.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()

    def registration_kwargs(self, final: bool = True) -> dict[str, Any]:
        """Arguments of ``register_clouds`` for the final or the pre-registration."""
        r = self.registration
        voxel = r.voxel_size if final else r.pre_voxel_size
        lateral = r.lateral_limit if final else r.pre_lateral_limit
        return {
            "voxel_size": float(voxel),
            "max_range": float(r.max_range),
            "lateral_limit": None if lateral is None else float(lateral),
        }
