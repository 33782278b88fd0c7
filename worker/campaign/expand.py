"""A campaign spec expanded into variants, deterministically; and its validation.

:func:`expand` (spec, prepared sequences) -> variants; :func:`validate` -> the issues
(errors say what is impossible and what to change; warnings what was adjusted).

Determinism: every random draw comes from a generator seeded with the campaign's
``seed``, the sequence's key, and the object's place in the product (placement, draw,
obstacle, variation seed) through sha256; positions are rounded to the millimetre and
angles to the thousandth of a degree before anything is derived from them. The same spec
(and seed) on the same preparations gives the same variants, byte for byte in their JSON
(:func:`~worker.campaign.variant.dump_variants`).

A rule's position is drawn by rejection: yaw from the rule's ranges, arc length within
the rule's distance window ahead of the train at the first frame (within the platforms'
stretches for the zone ``platform``), the offset within the zone
(:meth:`~worker.campaign.placement.SequenceGeometry.zone_offsets`); a draw is kept when
nothing is in the way (:meth:`~worker.campaign.placement.SequenceGeometry.conflict`) and
the object first comes into view within the distance range. After
``constraints.max_attempts`` draws the rule is reported impossible with the reasons the
draws were refused for.
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from renderer.assets import MeshError, build_obstacle
from worker.campaign.placement import (
    Footprint,
    GeometryError,
    Placed,
    SequenceGeometry,
    rotated_extent,
)
from worker.campaign.spec import (
    CampaignSpec,
    ExplicitPlacement,
    Obstacle,
    ObstacleMotion,
    PlacementRule,
    SequenceEntry,
)
from worker.campaign.variant import (
    CampaignError,
    Issue,
    ResolvedPosition,
    Variant,
    VariantObject,
    variant_key,
)

log = logging.getLogger(__name__)

#: Level of detail the footprints are measured at: the augmentation's default (spec.py).
FOOTPRINT_DETAIL = 1.0
#: Step (m) between the positions of a moving obstacle's path checked against the poles
#: and the other objects.
PATH_STEP_M = 0.25


def _r(x: float, nd: int = 3) -> float:
    """Rounded for the JSON (and -0.0 made 0.0)."""
    return round(float(x), nd) + 0.0


def _rng(*parts: object) -> np.random.Generator:
    """A generator seeded by sha256 of the parts (stable across runs and machines)."""
    digest = hashlib.sha256("|".join(map(str, parts)).encode()).digest()
    words = [int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)]
    return np.random.default_rng(words)


def _uniform(rng: np.random.Generator, intervals: list[tuple[float, float]]) -> float:
    """A uniform draw over a union of disjoint intervals."""
    widths = np.array([b - a for a, b in intervals])
    k = int(rng.choice(len(intervals), p=widths / widths.sum())) if len(intervals) > 1 else 0
    a, b = intervals[k]
    return float(rng.uniform(a, b))


def _intersect(
    intervals: list[tuple[float, float]], bound: tuple[float, float] | None
) -> list[tuple[float, float]]:
    if bound is None:
        return intervals
    out = [(max(a, bound[0]), min(b, bound[1])) for a, b in intervals]
    return [(a, b) for a, b in out if b > a]


def footprint_of(
    obstacle: Obstacle, seed: int, footprints: Mapping[str, Footprint] | None = None
) -> Footprint:
    """The obstacle's footprint: a built-in's mesh at the augmentation's detail and the
    obstacle's scale; an asset's from ``footprints`` (its mesh at scale 1) times its scale.
    Raises ValueError for an asset whose footprint is not given."""
    if obstacle.builtin is not None:
        mesh = build_obstacle(obstacle.builtin, seed=seed, detail=FOOTPRINT_DETAIL,
                              scale=obstacle.scale)  # fmt: skip
        return Footprint.from_bounds(mesh.bounds)
    fp = (footprints or {}).get(str(obstacle.asset_id))
    if fp is None:
        raise ValueError(
            f"asset {obstacle.asset_id!r}: its footprint is unknown; pass it in "
            "`footprints` (Footprint.from_bounds of the asset's mesh bounds)"
        )
    k = obstacle.scale
    return Footprint((fp.x[0] * k, fp.x[1] * k), (fp.y[0] * k, fp.y[1] * k), fp.height * k)


@dataclass(frozen=True)
class _Item:
    """One object of the product: which placement, draw, obstacle and variation."""

    placement: int
    draw: int
    obstacle: int
    seed: int


@dataclass
class _Expansion:
    spec: CampaignSpec
    prepared: Mapping[str, Any]
    footprints: Mapping[str, Footprint] | None
    issues: list[Issue] = field(default_factory=list)
    _fp: dict[tuple[int, int], Footprint | None] = field(default_factory=dict)
    _reported: set[tuple[str, str]] = field(default_factory=set)

    def issue(self, level: str, where: str, message: str) -> None:
        if (where, message) in self._reported:
            return
        self._reported.add((where, message))
        self.issues.append(Issue(level, where, message))  # type: ignore[arg-type]

    # ---------------------------------------------------------------- the parts
    def footprint(self, oi: int, seed: int) -> Footprint | None:
        if (oi, seed) not in self._fp:
            try:
                self._fp[(oi, seed)] = footprint_of(self.spec.obstacles[oi], seed, self.footprints)
            except (MeshError, ValueError) as exc:
                self.issue("error", f"obstacles[{oi}]", str(exc))
                self._fp[(oi, seed)] = None
        return self._fp[(oi, seed)]

    def geometry(self, i: int, entry: SequenceEntry) -> tuple[Any, SequenceGeometry | None]:
        """The sequence's preparation and geometry (None when rules cannot be drawn)."""
        where = f"sequences[{i}] ({entry.label})"
        prepared = self.prepared.get(entry.key, self.prepared.get(entry.label))
        if prepared is None:
            self.issue("error", where, f"no preparation given for {entry.key!r} "
                       f"(given: {sorted(self.prepared)})")  # fmt: skip
            return None, None
        try:
            geom = SequenceGeometry.from_prepared(
                prepared, key=entry.key, label=entry.label, frame_range=entry.frame_range
            )
        except GeometryError as exc:
            rules = [p for p in self.spec.placements if isinstance(p, PlacementRule)
                     and self.spec.applies(p, entry)]  # fmt: skip
            if rules or entry.frame_range is not None:
                self.issue("error", where, str(exc))
            return prepared, None
        return prepared, geom

    def items(self, entry: SequenceEntry) -> list[_Item]:
        out: list[_Item] = []
        for draw in range(self.spec.draws):
            for pi, p in enumerate(self.spec.placements):
                if not self.spec.applies(p, entry) or (isinstance(p, ExplicitPlacement) and draw):
                    continue
                for oi, ob in enumerate(self.spec.obstacles):
                    if self.spec.places(p, ob):
                        out.extend(_Item(pi, draw, oi, s) for s in ob.variation_seeds)
        return out

    # ---------------------------------------------------------------- rules
    def rule_window(
        self, rule: PlacementRule, geom: SequenceGeometry, where: str
    ) -> list[tuple[float, float]] | None:
        """The arc-length intervals a rule draws from (None: impossible, reported)."""
        d_lo, d_hi = rule.distance_m
        ahead = geom.length - geom.s_first
        f0 = int(geom.frames[0])
        if ahead <= d_lo:
            self.issue("error", where, (
                f"distance_m {d_lo:g}-{d_hi:g} m: the prepared ego track of {geom.label} "
                f"reaches only {max(ahead, 0.0):.1f} m ahead of the train at frame {f0}: "
                "lower distance_m, or start the frame_range earlier"))  # fmt: skip
            return None
        if ahead < d_hi:
            self.issue("warning", where, (
                f"distance_m {d_lo:g}-{d_hi:g} m clipped to {d_lo:g}-{ahead:.1f} m: the "
                f"prepared ego track of {geom.label} ends there"))  # fmt: skip
        window = [(geom.s_first + d_lo, geom.s_first + min(d_hi, ahead))]
        if rule.zone != "platform":
            return window
        platforms = geom.platforms_on(rule.side)
        if not platforms:
            sides = "" if rule.side == "either" else f" on the {rule.side}"
            self.issue("error", where, (
                f"zone 'platform', but the preparation found no platform{sides} in "
                f"{geom.label}: use another zone, or restrict the rule to the sequences "
                "with platforms (`sequences:`)"))  # fmt: skip
            return None
        spans = [(max(window[0][0], p.s_range[0]), min(window[0][1], p.s_range[1]))
                 for p in platforms]  # fmt: skip
        spans = sorted((a, b) for a, b in spans if b > a)
        if not spans:
            where_pl = ", ".join(
                f"{p.s_range[0] - geom.s_first:.0f}-{p.s_range[1] - geom.s_first:.0f} m"
                for p in platforms
            )
            self.issue("error", where, (
                f"zone 'platform': no platform of {geom.label} lies {d_lo:g}-{d_hi:g} m ahead "
                f"of the train at frame {f0} (its platforms: {where_pl} ahead): change "
                "distance_m"))  # fmt: skip
            return None
        merged: list[tuple[float, float]] = []
        for a, b in spans:
            if merged and a <= merged[-1][1]:
                merged[-1] = (merged[-1][0], max(merged[-1][1], b))
            else:
                merged.append((a, b))
        return merged

    def draw_rule(
        self,
        rule: PlacementRule,
        window: list[tuple[float, float]],
        geom: SequenceGeometry,
        fp: Footprint,
        item: _Item,
        others: list[Placed],
        motion: ObstacleMotion | None = None,
    ) -> tuple[list[Placed], ResolvedPosition, dict[str, Any] | None] | Counter[str]:
        """A position (and a moving obstacle's path) by rejection (module docstring); the
        refusal reasons when none. Returns the footprints the variant's later objects keep
        away from (the position, or every position of the path), the resolved position
        and the job motion."""
        c = self.spec.constraints
        rng = _rng(self.spec.seed, geom.key, item.placement, item.draw, item.obstacle, item.seed)
        reasons: Counter[str] = Counter()
        d_lo, d_hi = rule.distance_m
        for _ in range(c.max_attempts):
            yaw_deg = _r(_uniform(rng, rule.yaw_ranges))
            s_job = _r(_uniform(rng, window) - geom.s0_job)
            s = geom.s0_job + s_job
            _, _, l_lo, l_hi = rotated_extent(fp, math.radians(yaw_deg))
            spans = _intersect(
                geom.zone_offsets(rule.zone, rule.side, (l_lo, l_hi), s, c.clearance_m),
                rule.lateral_m,
            )
            if not spans:
                reasons[f"the footprint does not fit the zone {rule.zone} there"] += 1
                continue
            offset = _r(_uniform(rng, spans))
            placed = Placed(fp, s, offset, math.radians(yaw_deg))
            why = geom.conflict(placed, clearance=c.clearance_m, others=others,
                                min_spacing=c.min_spacing_m, zone=rule.zone)  # fmt: skip
            if why is None and s_job < 0.0:
                why = "behind the sequence's first frame"
            if why is not None:
                reasons[why] += 1
                continue
            job_motion, spots = None, [placed]
            if motion is not None:
                job_motion = self.motion_job(motion, s_job, offset, rng)
                why, spots = self.path_conflict(geom, fp, job_motion, others)
                if why is not None:
                    reasons[why] += 1
                    continue
            p, heading = geom.pose(s, offset, yaw_deg)
            centre = p + np.array([0.0, 0.0, 0.5 * fp.height])
            seen = geom.first_view(centre, s, d_hi, rule.view_half_angle_deg)
            if seen is None:
                reasons["never in view within the distance range"] += 1
                continue
            if seen[1] < d_lo:
                reasons[f"first in view nearer than {d_lo:g} m (a curve hides it)"] += 1
                continue
            return spots, ResolvedPosition(
                zone=rule.zone, s_m=_r(s), s_job_m=s_job, offset_m=offset, yaw_deg=yaw_deg,
                heading_deg=_r((heading + 180.0) % 360.0 - 180.0),
                xyz_world=(_r(p[0]), _r(p[1]), _r(p[2])),
                first_view_frame=seen[0], distance_first_view_m=_r(seen[1]),
                footprint_m=(_r(fp.size[0]), _r(fp.size[1])),
            ), job_motion  # fmt: skip
        return reasons

    # ---------------------------------------------------------------- motion
    @staticmethod
    def motion_job(
        m: ObstacleMotion, s_job: float, offset: float, rng: np.random.Generator
    ) -> dict[str, Any]:
        """A moving obstacle's job ``motion``: the path through (s_job, offset), its
        direction, speed and start drawn (spec.py's module docstring)."""
        sign = 1.0 if rng.random() < 0.5 else -1.0
        half = 0.5 * m.span_m
        if m.pattern == "cross":
            a, b = (s_job, offset - sign * half), (s_job, offset + sign * half)
        else:
            a, b = (s_job - sign * half, offset), (s_job + sign * half, offset)
        return {
            "mode": "track",
            "path": [[_r(a[0]), _r(a[1])], [_r(b[0]), _r(b[1])]],
            "speed_mps": _r(rng.uniform(*m.speed_mps)),
            "start_s": _r(rng.uniform(*m.start_s)),
            "gait": m.gait,
        }

    def path_conflict(
        self, geom: SequenceGeometry, fp: Footprint, motion: dict[str, Any], others: list[Placed]
    ) -> tuple[str | None, list[Placed]]:
        """Why a moving obstacle's path may not be walked (None: it may), and its
        positions every PATH_STEP_M (what the variant's later objects keep away from)."""
        c = self.spec.constraints
        (s_a, o_a), (s_b, o_b) = motion["path"]
        length = math.hypot(s_b - s_a, o_b - o_a)
        n = max(2, math.ceil(length / PATH_STEP_M) + 1)
        yaw = math.atan2(o_b - o_a, s_b - s_a)
        spots = [
            Placed(fp, geom.s0_job + s_a + t * (s_b - s_a), o_a + t * (o_b - o_a), yaw)
            for t in np.linspace(0.0, 1.0, n)
        ]
        start_on = {pl.index for pl in geom.platforms
                    if bool(pl.contains(np.array([[spots[0].s, spots[0].offset]]))[0])}  # fmt: skip
        for sp in spots:
            lo, hi = sp.s_range()
            if lo < 0.0 or hi > geom.length:
                return f"its path leaves the prepared ego track (0..{geom.length:.0f} m)", spots
            samples = sp.samples(c.clearance_m)
            for pl in geom.platforms:  # no walking through a platform's wall
                inside = pl.contains(samples)
                if (pl.index in start_on and not inside.all()) or (
                    pl.index not in start_on and inside.any()
                ):
                    return f"its path crosses the edge of platform {pl.index}", spots
            for pole in geom.poles:
                if sp.distance_to_point(np.array([pole.s, pole.lateral])) < (
                    pole.radius + c.clearance_m
                ):
                    return f"its path crosses pole {pole.id}", spots
            for other in others:
                if sp.distance_to(other) < c.min_spacing_m:
                    return f"its path comes nearer than {c.min_spacing_m:g} m to an object", spots
        return None, spots

    # ---------------------------------------------------------------- explicit
    def explicit(
        self,
        ep: ExplicitPlacement,
        prepared: Any,
        geom: SequenceGeometry | None,
        fp: Footprint,
        others: list[Placed],
        where: str,
        warnings: list[str],
    ) -> tuple[Placed | None, ResolvedPosition] | None:
        """An explicit placement resolved against the sequence (None: impossible, reported)."""
        pl = ep.explicit
        if pl.mode == "track":
            if geom is None:
                self.issue("error", where, "a track placement needs the ego track, and the "
                           "preparation found none: use mode world or lidar_frame")  # fmt: skip
                return None
            s = geom.s0_job + pl.s
            p, heading = geom.pose(s, pl.offset, pl.yaw_deg)
            offset, yaw = pl.offset, pl.yaw_deg
        else:
            p, heading = self._point(pl, prepared, where)
            if p is None:
                return None
            if geom is None:
                return None, ResolvedPosition(
                    zone=None, s_m=None, s_job_m=None, offset_m=None, yaw_deg=_r(pl.yaw_deg),
                    heading_deg=_r(heading), xyz_world=(_r(p[0]), _r(p[1]), _r(p[2])),
                    footprint_m=(_r(fp.size[0]), _r(fp.size[1])),
                )  # fmt: skip
            s, offset, yaw = geom.track_position(p, heading)
        placed = Placed(fp, s, offset, math.radians(yaw))
        c = self.spec.constraints
        why = geom.conflict(placed, clearance=c.clearance_m, others=others,
                            min_spacing=c.min_spacing_m)  # fmt: skip
        if why is not None and (why.startswith("beyond") or why.startswith("in pole")):
            self.issue("error", where, f"the explicit placement is {why}: move it")
            return None
        if why is not None:
            warnings.append(f"{where}: the explicit placement is {why}")
            self.issue("warning", where, f"the explicit placement is {why}")
        seen = geom.first_view(p + np.array([0.0, 0.0, 0.5 * fp.height]), s, math.inf, 15.0)
        return placed, ResolvedPosition(
            zone=None, s_m=_r(s), s_job_m=_r(s - geom.s0_job), offset_m=_r(offset),
            yaw_deg=_r(yaw), heading_deg=_r((heading + 180.0) % 360.0 - 180.0),
            xyz_world=(_r(p[0]), _r(p[1]), _r(p[2])),
            first_view_frame=None if seen is None else seen[0],
            distance_first_view_m=None if seen is None else _r(seen[1]),
            footprint_m=(_r(fp.size[0]), _r(fp.size[1])),
        )  # fmt: skip

    def _point(self, pl: Any, prepared: Any, where: str) -> tuple[Any, float]:
        """World point (3,) and heading (deg) of a world or lidar_frame placement."""
        xyz = np.asarray(pl.xyz, dtype=np.float64)
        if pl.mode == "world":
            return xyz, float(pl.yaw_deg)
        track = prepared.track
        frames = (list(range(len(track.T))) if track.frame_idx is None
                  else [int(f) for f in track.frame_idx])  # fmt: skip
        if pl.frame_idx not in frames:
            self.issue("error", where, f"frame_idx {pl.frame_idx} is not a frame of the "
                       f"sequence ({frames[0]}..{frames[-1]})")  # fmt: skip
            return None, 0.0
        T = track.T[frames.index(pl.frame_idx)]
        p = T[:3, :3] @ xyz + T[:3, 3]
        return p, math.degrees(math.atan2(T[1, 0], T[0, 0])) + float(pl.yaw_deg)

    # ---------------------------------------------------------------- variants
    def run(self) -> list[Variant]:
        spec = self.spec
        base_job: dict[str, Any] = {
            "cameras": list(spec.job.cameras),
            "lidar": spec.job.lidar,
            "strategy": spec.job.strategy,
            "render": spec.job.render.model_dump(mode="json"),
        }
        if spec.job.gauge is not None:
            base_job["gauge"] = spec.job.gauge.model_dump(mode="json", exclude_none=True)
        variants: list[Variant] = []
        for i, entry in enumerate(spec.sequences):
            prepared, geom = self.geometry(i, entry)
            if prepared is None:
                continue
            windows: dict[int, list[tuple[float, float]] | None] = {}
            for pi, p in enumerate(spec.placements):
                if isinstance(p, PlacementRule) and geom is not None and spec.applies(p, entry):
                    where = f"placements[{pi}] on {entry.label}"
                    windows[pi] = self.rule_window(p, geom, where)
            items = self.items(entry)
            k = spec.objects_per_sequence
            for start in range(0, len(items), k):
                group = items[start : start + k]
                objects, warnings = self.resolve_group(group, entry, prepared, geom, windows)
                if objects is None:
                    continue
                job = {**base_job, "frame_range": None if entry.frame_range is None
                       else list(entry.frame_range)}  # fmt: skip
                if len(objects) == 1:
                    job.update(object=objects[0].object, placement=objects[0].placement)
                    if objects[0].motion is not None:
                        job["motion"] = objects[0].motion
                else:
                    job["objects"] = [
                        {"object": o.object, "placement": o.placement}
                        | ({} if o.motion is None else {"motion": o.motion})
                        for o in objects
                    ]
                n = len(variants)
                variants.append(Variant(
                    index=n, id=f"v{n:04d}", key=variant_key(entry.key, job),
                    sequence=entry.key, sequence_label=entry.label, objects=objects,
                    job=job, warnings=warnings,
                ))  # fmt: skip
        return variants

    def resolve_group(
        self,
        group: list[_Item],
        entry: SequenceEntry,
        prepared: Any,
        geom: SequenceGeometry | None,
        windows: dict[int, list[tuple[float, float]] | None],
    ) -> tuple[list[VariantObject] | None, list[str]]:
        """The objects of one variant, each keeping its distance from the ones before."""
        placed: list[Placed] = []
        objects: list[VariantObject] = []
        warnings: list[str] = []
        for item in group:
            ob = self.spec.obstacles[item.obstacle]
            p = self.spec.placements[item.placement]
            where = f"placements[{item.placement}] on {entry.label}"
            fp = self.footprint(item.obstacle, item.seed)
            if fp is None:
                return None, warnings
            job_motion: dict[str, Any] | None = None
            if isinstance(p, ExplicitPlacement):
                res = self.explicit(p, prepared, geom, fp, placed, where, warnings)
                if res is None:
                    return None, warnings
                spot, pos = res
                spots = [] if spot is None else [spot]
                placement = p.explicit.model_dump(mode="json")
                if ob.motion is not None:
                    if geom is None or spot is None or p.explicit.mode != "track":
                        self.issue("error", where, (
                            f"{ob.class_name} moves: its motion needs a track placement (mode "
                            "track) on a sequence with an ego track, or a rule"))  # fmt: skip
                        return None, warnings
                    rng = _rng(self.spec.seed, geom.key, item.placement, item.draw,
                               item.obstacle, item.seed, "motion")  # fmt: skip
                    job_motion = self.motion_job(ob.motion, p.explicit.s, p.explicit.offset, rng)
                    why, spots = self.path_conflict(geom, fp, job_motion, placed)
                    if why is not None:
                        self.issue("error", where, f"the explicit moving {ob.class_name}: {why}")
                        return None, warnings
            else:
                window = windows.get(item.placement)
                if geom is None or window is None:
                    return None, warnings
                got = self.draw_rule(p, window, geom, fp, item, placed, ob.motion)
                if isinstance(got, Counter):
                    top = ", ".join(f"{why} ({n}x)" for why, n in got.most_common(3))
                    self.issue("error", where, (
                        f"could not place {ob.class_name} (seed {item.seed}, draw {item.draw}) "
                        f"in zone {p.zone} after {self.spec.constraints.max_attempts} draws: "
                        f"{top}; widen distance_m, yaw_deg or lateral_m, or lower "
                        "min_spacing_m / objects_per_sequence"))  # fmt: skip
                    return None, warnings
                spots, pos, job_motion = got
                placement = {"mode": "track", "s": pos.s_job_m, "offset": pos.offset_m,
                             "yaw_deg": pos.yaw_deg}  # fmt: skip
            placed.extend(spots)
            objects.append(VariantObject(
                obstacle=item.obstacle, class_name=ob.class_name, variation_seed=item.seed,
                placement_index=item.placement, draw=item.draw,
                object=ob.job_object(item.seed), placement=placement, resolved=pos,
                motion=job_motion,
            ))  # fmt: skip
        return objects, warnings


def expand_with_issues(
    spec: CampaignSpec,
    prepared_by_sequence: Mapping[str, Any],
    *,
    footprints: Mapping[str, Footprint] | None = None,
) -> tuple[list[Variant], list[Issue]]:
    """The variants that could be made and every issue found (errors and warnings)."""
    exp = _Expansion(spec, prepared_by_sequence, footprints)
    variants = exp.run()
    for issue in exp.issues:
        log.log(logging.ERROR if issue.level == "error" else logging.WARNING, "campaign %s: %s",
                spec.name, issue)  # fmt: skip
    return variants, exp.issues


def validate(
    spec: CampaignSpec,
    prepared_by_sequence: Mapping[str, Any],
    *,
    footprints: Mapping[str, Footprint] | None = None,
) -> list[Issue]:
    """Every issue of the spec against its sequences' preparations (empty: all good)."""
    return expand_with_issues(spec, prepared_by_sequence, footprints=footprints)[1]


def expand(
    spec: CampaignSpec,
    prepared_by_sequence: Mapping[str, Any],
    *,
    footprints: Mapping[str, Footprint] | None = None,
) -> list[Variant]:
    """The campaign's variants (module docstring).

    Parameters
    ----------
    spec : the campaign.
    prepared_by_sequence : each sequence's PreparedSequence, keyed by the entry's ``id``
        or ``path`` (or its ``name``).
    footprints : asset id -> Footprint of the asset's mesh (for rules on uploaded assets).

    Raises
    ------
    CampaignError : with every issue, when any is an error.
    """
    variants, issues = expand_with_issues(spec, prepared_by_sequence, footprints=footprints)
    if any(i.level == "error" for i in issues):
        raise CampaignError(issues)
    return variants


__all__ = ["FOOTPRINT_DETAIL", "expand", "expand_with_issues", "footprint_of", "validate"]
