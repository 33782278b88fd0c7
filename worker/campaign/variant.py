"""What a campaign expands into: variants, each one job of today's format with the
objects' resolved positions, and the issues a validation reports.

A variant's ``job`` holds today's job fields (``object``, ``placement``, ``cameras``,
``lidar``, ``strategy``, ``frame_range``, ``render``, and ``motion`` for a moving
obstacle) without ``sequence_id`` (:meth:`Variant.job_spec` adds it). A variant of
several objects carries ``objects`` (a list of ``{object, placement[, motion]}``) in place
of ``object`` and ``placement``: the augmentation's multi-object job
(:class:`~worker.augmentation.spec.AugmentSpec`, ``objects``).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict


class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ResolvedPosition(_Out):
    """Where an object stands, resolved against the sequence's preparation.

    zone : the rule's zone (None: an explicit placement).
    s_m : arc length on the prepared ego centreline (m from its start; None without one).
    s_job_m : the same from the sequence's first frame (the job's track placement ``s``).
    offset_m : lateral offset from the ego centreline (m, left +).
    yaw_deg : relative to the track direction; heading_deg : in the world frame (from
        East, counter-clockwise).
    xyz_world : the nominal point (world ENU, m) before the render snaps it onto the
        scene's surface (track bed, platform, ground).
    first_view_frame, distance_first_view_m : the frame the object first comes into view
        and its distance along the track from the train then (rules; None otherwise).
    footprint_m : (length, width) of the object's bounding box on the ground.
    """

    zone: str | None
    s_m: float | None
    s_job_m: float | None
    offset_m: float | None
    yaw_deg: float
    heading_deg: float
    xyz_world: tuple[float, float, float]
    first_view_frame: int | None = None
    distance_first_view_m: float | None = None
    footprint_m: tuple[float, float]


class VariantObject(_Out):
    """One object of a variant: its obstacle (index into the spec's ``obstacles``, class,
    variation seed), today's job ``object`` and ``placement``, the resolved position, and
    the placement it was drawn from (index into the spec's ``placements``) and the draw;
    a moving obstacle's job ``motion`` (the path in track coordinates, the speed)."""

    obstacle: int
    class_name: str
    variation_seed: int
    placement_index: int
    draw: int
    object: dict[str, Any]
    placement: dict[str, Any]
    resolved: ResolvedPosition
    motion: dict[str, Any] | None = None


class Variant(_Out):
    """One augmented sequence to make (module docstring).

    index : 0-based over the campaign; id : ``v<index>``; key : a digest of what the
    variant makes (sequence, objects, job), the same for the same variant in any campaign.
    """

    index: int
    id: str
    key: str
    sequence: str
    sequence_label: str
    objects: list[VariantObject]
    job: dict[str, Any]
    warnings: list[str] = []

    def job_spec(self, sequence_id: str | None = None) -> dict[str, Any]:
        """Today's job spec (``JobCreate`` JSON) with ``sequence_id`` (default: the
        variant's sequence key, a registered id in a service campaign)."""
        return {"sequence_id": sequence_id or self.sequence, **self.job}


def variant_key(sequence: str, job: dict[str, Any]) -> str:
    """sha256 (hex, 16 digits) of the canonical JSON of a variant's sequence and job."""
    text = json.dumps({"sequence": sequence, "job": job}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def dump_variants(variants: list[Variant]) -> str:
    """The variants as canonical JSON (sorted keys): same variants, same bytes."""
    return json.dumps([v.model_dump(mode="json") for v in variants], sort_keys=True, indent=1)


@dataclass(frozen=True)
class Issue:
    """A problem of a spec against its sequences: ``where`` names the spec's part (e.g.
    ``placements[1] on station``), ``message`` says what is wrong and what to do."""

    level: Literal["error", "warning"]
    where: str
    message: str

    def __str__(self) -> str:
        return f"{self.level}: {self.where}: {self.message}"

    def to_json(self) -> dict[str, str]:
        return {"level": self.level, "where": self.where, "message": self.message}


class CampaignError(ValueError):
    """A campaign that cannot be expanded; ``issues`` lists every problem found."""

    def __init__(self, issues: list[Issue]) -> None:
        self.issues = issues
        errors = [i for i in issues if i.level == "error"]
        head = f"{len(errors)} error(s) in the campaign"
        super().__init__(head + ":\n" + "\n".join(f"  {i}" for i in errors))


__all__ = [
    "CampaignError",
    "Issue",
    "ResolvedPosition",
    "Variant",
    "VariantObject",
    "dump_variants",
    "variant_key",
]
