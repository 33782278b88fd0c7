"""Scene presets of the synthetic OSDaR23 generator.

``build_scene(name, seed, length_m, **params)`` builds a deterministic procedural railway
scene (same name, seed and params -> identical arrays). ``length_m`` is the part of the
ego track a train drives (``Scene.drive_range``); the track continues ``lookahead`` metres
beyond it (what the cameras see ahead) and starts ``behind`` metres before it.

Common params: ``origin_offset`` (3,) far-origin offset added to every coordinate,
``heading`` (rad) of the ego track at its start, ``speed_mps`` (overrides the preset's),
``lookahead`` (m, default 450), ``behind`` (m, default 40), ``vegetation`` (density
factor, default 1), ``base`` (for ``stationary``: the preset it copies, default
``station``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from worker.synth import scene_builders as sb
from worker.synth.scene import Landmark, Platform, Pole, Scene, Terrain
from worker.synth.scene_mesh import SceneMesh
from worker.synth.track import AlignedTrack, Alignment, Profile, Track

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)


@dataclass
class Layout:
    """What a preset puts in the scene, before the generic assembly."""

    tracks: list[Track]
    drive_range: tuple[float, float]
    speed_mps: float
    catenary: list[tuple[int, float]] = field(default_factory=list)  # (track idx, lateral)
    pole_spacing: float = 55.0
    signals: list[tuple[int, float, float]] = field(default_factory=list)  # (idx, s, lateral)
    platforms: list[tuple[int, float, float, str, float]] = field(default_factory=list)
    shelters: list[tuple[int, float, float]] = field(default_factory=list)  # (idx, s, lateral)
    fences: list[tuple[int, float, float, float]] = field(default_factory=list)
    roads: list[float] = field(default_factory=list)  # lateral offsets from the ego track
    trees_per_100m: float = 20.0
    conifer_share: float = 0.25
    bushes_per_100m: float = 25.0
    buildings_per_100m: float = 1.0
    building_lateral: tuple[float, float] = (25.0, 140.0)
    tree_lateral: tuple[float, float] = (9.0, 110.0)
    terrain_amplitude: float = 1.2
    cess: bool = True


def _ego(
    alignment: Alignment, params: dict, rng: np.random.Generator, grade: float = 0.0
) -> AlignedTrack:
    offset = np.asarray(params.get("origin_offset", (0.0, 0.0, 0.0)), dtype=np.float64)
    heading = float(params.get("heading", rng.uniform(0.0, 2.0 * np.pi)))
    profile = Profile((0.0, 400.0, 900.0), (grade, -0.5 * grade, grade))
    return AlignedTrack(alignment, offset, heading, profile, track_id=0)


def _span(length_m: float, params: dict) -> tuple[float, float, float]:
    """(behind, lookahead, total length) of the ego track."""
    behind = float(params.get("behind", 40.0))
    ahead = float(params.get("lookahead", 450.0))
    return behind, ahead, behind + length_m + ahead


def _fire_site(rng: np.random.Generator, length_m: float, params: dict) -> Layout:
    behind, _, total = _span(length_m, params)
    straight = behind + 0.45 * length_m
    radius = float(params.get("radius", rng.uniform(550.0, 750.0)))
    al = Alignment().straight(straight).clothoid(80.0, radius, 0.06)
    al.arc(max(10.0, total - straight - 80.0))
    ego = _ego(al, params, rng, grade=0.003)
    s1 = ego.length
    return Layout(
        tracks=[ego, ego.offset(-4.0, 1)],
        drive_range=(behind, behind + length_m),
        speed_mps=9.0,
        catenary=[(0, 3.3), (1, -3.3)],
        pole_spacing=float(rng.uniform(52.0, 60.0)),
        signals=[(0, behind + 0.8 * length_m + 60.0, 3.0)],
        fences=[(0, behind, s1, 9.0)],
        roads=[-32.0],
        trees_per_100m=30.0,
        buildings_per_100m=1.5,
    )


def _station(rng: np.random.Generator, length_m: float, params: dict) -> Layout:
    behind, _, total = _span(length_m, params)
    straight = behind + length_m + 120.0
    al = (
        Alignment()
        .straight(straight)
        .clothoid(60.0, 1200.0, 0.03)
        .arc(max(10.0, total - straight - 60.0))
    )
    ego = _ego(al, params, rng)
    island = 6.0
    t1 = ego.offset(sb.PLATFORM_EDGE * 2 + island, 1)
    t2 = ego.offset(sb.PLATFORM_EDGE * 2 + island + 4.5, 2)
    p0, p1 = behind + 0.3 * length_m, behind + length_m + 110.0
    sm = 0.5 * (p0 + p1)
    return Layout(
        tracks=[ego, t1, t2],
        drive_range=(behind, behind + length_m),
        speed_mps=6.0,
        catenary=[(0, -3.3 - 7.0), (2, 3.3)],
        pole_spacing=50.0,
        signals=[(0, p1 + 40.0, -3.0)],
        platforms=[(0, p0, p1, "left", island), (0, p0, p1, "right", 7.0)],
        shelters=[
            (0, sm - 30.0, sb.PLATFORM_EDGE + 0.5 * island),
            (0, sm + 25.0, -(sb.PLATFORM_EDGE + 4.0)),
        ],
        fences=[(0, p0 - 40.0, p1 + 40.0, -(sb.PLATFORM_EDGE + 7.5))],
        roads=[-30.0],
        trees_per_100m=12.0,
        buildings_per_100m=4.0,
        building_lateral=(22.0, 120.0),
    )


def _klein_flottbek(rng: np.random.Generator, length_m: float, params: dict) -> Layout:
    behind, _, total = _span(length_m, params)
    ego = _ego(Alignment().straight(total), params, rng, grade=0.004)
    p0 = behind + 0.5 * length_m
    return Layout(
        tracks=[ego, ego.offset(4.0, 1), ego.offset(8.5, 2)],
        drive_range=(behind, behind + length_m),
        speed_mps=11.0,
        catenary=[(0, -3.3), (2, 3.3)],
        pole_spacing=60.0,
        signals=[(0, p0 + 230.0, -3.0)],
        platforms=[(0, p0, p0 + 140.0, "right", 6.0)],
        shelters=[(0, p0 + 70.0, -(sb.PLATFORM_EDGE + 3.5))],
        fences=[(0, behind, total, 12.0)],
        roads=[-28.0],
        trees_per_100m=45.0,
        conifer_share=0.15,
        buildings_per_100m=1.5,
    )


def _straight_sparse(rng: np.random.Generator, length_m: float, params: dict) -> Layout:
    behind, _, total = _span(length_m, params)
    ego = _ego(Alignment().straight(total), params, rng)
    return Layout(
        tracks=[ego],
        drive_range=(behind, behind + length_m),
        speed_mps=20.0,
        catenary=[(0, -3.3)],
        pole_spacing=max(150.0, total / 4.0),
        trees_per_100m=0.0,
        bushes_per_100m=0.0,
        buildings_per_100m=0.0,
        terrain_amplitude=0.08,
        cess=False,
    )


def _tight_curve(rng: np.random.Generator, length_m: float, params: dict) -> Layout:
    behind, _, total = _span(length_m, params)
    radius = float(params.get("radius", 190.0))
    cant = float(params.get("cant", 0.15))
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    straight = behind + 0.15 * length_m
    arc = min(radius * 2.2, max(60.0, total - straight - 240.0))
    al = Alignment().straight(straight).clothoid(70.0, side * radius, side * cant).arc(arc)
    al.clothoid(70.0, None, 0.0).straight(max(10.0, total - straight - arc - 140.0))
    ego = _ego(al, params, rng, grade=-0.005)
    return Layout(
        tracks=[ego],
        drive_range=(behind, behind + length_m),
        speed_mps=12.0,
        catenary=[(0, side * 3.3)],
        pole_spacing=40.0,
        signals=[(0, behind + length_m + 30.0, -3.0)],
        roads=[-side * 40.0],
        trees_per_100m=35.0,
        buildings_per_100m=0.7,
    )


def _switch(rng: np.random.Generator, length_m: float, params: dict) -> Layout:
    behind, _, total = _span(length_m, params)
    ego = _ego(Alignment().straight(total), params, rng)
    spacing = 4.5
    t1 = ego.offset(spacing, 1)
    r_sw, angle = 300.0, 1.0 / 9.0
    s_div = behind + 0.6 * length_m
    siding = ego.branch(s_div, r_sw, "right", 260.0, 2, turn_angle=angle)
    # crossover joining the ego track from the parallel one (a trailing switch ahead)
    shift = spacing - 2.0 * r_sw * (1.0 - np.cos(angle))
    straight = shift / np.sin(angle)
    xo = Alignment().arc(r_sw * angle, -r_sw).straight(straight).arc(r_sw * angle, r_sw)
    s_x = behind + length_m + 60.0
    start = t1.point(s_x)[0]
    crossover = AlignedTrack(xo, start, float(t1.heading(s_x)[0]), Profile(), track_id=3)
    return Layout(
        tracks=[ego, t1, siding, crossover],
        drive_range=(behind, behind + length_m),
        speed_mps=8.0,
        catenary=[(0, -3.3 - 0.0), (1, 3.3)],
        pole_spacing=55.0,
        signals=[(0, s_div - 80.0, -3.0), (2, 150.0, -3.0)],
        roads=[40.0],
        trees_per_100m=18.0,
        buildings_per_100m=1.0,
    )


PRESETS: dict[str, Callable[[np.random.Generator, float, dict], Layout]] = {
    "fire_site": _fire_site,
    "station": _station,
    "klein_flottbek": _klein_flottbek,
    "straight_sparse": _straight_sparse,
    "tight_curve": _tight_curve,
    "switch": _switch,
}
SCENE_NAMES = (*PRESETS, "stationary")


def build_scene(name: str, seed: int, length_m: float = 150.0, **params: object) -> Scene:
    """Build a preset scene deterministically from ``seed`` (see module doc for params)."""
    speed_zero = name == "stationary"
    preset = str(params.get("base", "station")) if speed_zero else name
    if preset not in PRESETS:
        raise ValueError(f"unknown scene {name!r}; known: {', '.join(SCENE_NAMES)}")
    rng = np.random.default_rng(seed)
    layout = PRESETS[preset](rng, float(length_m), params)
    scene = assemble(name, seed, layout, rng, float(params.get("vegetation", 1.0)))
    scene.speed_mps = 0.0 if speed_zero else float(params.get("speed_mps", layout.speed_mps))
    scene.origin_offset = np.asarray(params.get("origin_offset", (0.0, 0.0, 0.0)), dtype=np.float64)
    log.info(
        "scene %s seed %d: %d tracks, %d triangles, %d landmarks",
        name, seed, len(scene.tracks), len(scene.mesh.faces), len(scene.landmarks),
    )  # fmt: skip
    return scene


def _bounds(tracks: list[Track], margin: float) -> F64:
    pts = np.vstack([t.point(t.sample(5.0)) for t in tracks])
    return np.array([pts[:, :2].min(0) - margin, pts[:, :2].max(0) + margin])


def assemble(
    name: str, seed: int, lay: Layout, rng: np.random.Generator, veg: float = 1.0
) -> Scene:
    """Turn a layout into a :class:`Scene`: track bed, structures, vegetation, ground."""
    tracks = lay.tracks
    ego = tracks[0]
    bounds = _bounds(tracks, 230.0)
    terrain = Terrain(tracks, rng, amplitude=lay.terrain_amplitude, bounds_xy=bounds)
    parts: list[SceneMesh] = []
    poles: list[Pole] = []
    landmarks: list[Landmark] = []
    platforms: list[Platform] = []
    for t in tracks:
        parts += [
            sb.rails(t, 0.0, t.length),
            sb.sleepers(t, 0.0, t.length),
            sb.ballast(t, 0.0, t.length),
        ]
    if lay.cess:
        parts.append(sb.cess_path(ego, 0.0, ego.length, -3.4))
    for k, (ti, lateral) in enumerate(lay.catenary):
        t = tracks[ti]
        m, p, lm = sb.catenary(
            t, 5.0, t.length - 5.0, terrain, rng, lay.pole_spacing, lateral, prefix=f"cat{k}"
        )
        parts += m
        poles += p
        landmarks += lm
    for k, (ti, s, lateral) in enumerate(lay.signals):
        m, p, lm = sb.signal(tracks[ti], s, terrain, k, lateral)
        parts += m
        poles.append(p)
        landmarks += lm
    for k, (ti, s0, s1, side, width) in enumerate(lay.platforms):
        m, pf, lm = sb.platform(tracks[ti], s0, s1, side, k, width)
        parts += m
        platforms.append(pf)
        landmarks += lm
    for ti, s, lateral in lay.shelters:
        parts += sb.shelter(tracks[ti], s, lateral)
    for ti, s0, s1, lateral in lay.fences:
        parts += sb.fence(tracks[ti], s0, s1, lateral, terrain)
    occ = sb.Occupancy()
    for pf in platforms:
        occ.add(pf.polygon[:, :2], 3.0)
    for lateral in lay.roads:
        rt = ego.offset(lateral, -1)
        parts.append(sb.road(rt, 0.0, rt.length, terrain))
        occ.add(rt.point(rt.sample(3.0))[:, :2], 4.5)
    parts += _structures(ego, lay, rng, terrain, occ, veg)
    parts.append(sb.ground(terrain, bounds, _ground_spacing(bounds)))
    mesh = SceneMesh.concatenate(parts)
    lo = np.concatenate([bounds[0], [mesh.vertices[:, 2].min()]])
    hi = np.concatenate([bounds[1], [mesh.vertices[:, 2].max()]])
    return Scene(
        name=name, seed=seed, tracks=tracks, mesh=mesh, landmarks=landmarks, poles=poles,
        platforms=platforms, extent=np.array([lo, hi]), drive_range=lay.drive_range,
        speed_mps=lay.speed_mps,
    )  # fmt: skip


def _ground_spacing(bounds: F64, max_vertices: float = 40000.0) -> float:
    area = float(np.prod(bounds[1] - bounds[0]))
    return max(3.0, float(np.sqrt(area / max_vertices)))


def _structures(
    ego: Track,
    lay: Layout,
    rng: np.random.Generator,
    terrain: Terrain,
    occ: sb.Occupancy,
    veg: float,
) -> list[SceneMesh]:
    """Buildings, trees, conifers and bushes scattered along the ego track."""
    L = ego.length
    per = L / 100.0
    parts: list[SceneMesh] = []
    nb = round(lay.buildings_per_100m * per)
    bxy = sb.scatter(ego, 0.0, L, nb, lay.building_lateral, rng, terrain, occ, 12.0, 16.0)
    if len(bxy):
        s_near = _nearest_s(ego, bxy)
        heading = ego.heading(s_near) + rng.choice([0.0, 0.5 * np.pi], len(bxy))
        m, _ = sb.buildings(bxy, heading, terrain, rng)
        parts += m
    nt = round(lay.trees_per_100m * per * veg)
    nc = round(nt * lay.conifer_share)
    txy = sb.scatter(
        ego, 0.0, L, nt - nc, lay.tree_lateral, rng, terrain, occ, 2.5, 8.0, cluster=3.0
    )
    cxy = sb.scatter(ego, 0.0, L, nc, lay.tree_lateral, rng, terrain, occ, 2.0, 9.0, cluster=1.0)
    bu = sb.scatter(
        ego,
        0.0,
        L,
        round(lay.bushes_per_100m * per * veg),
        (6.0, 40.0),
        rng,
        terrain,
        occ,
        1.0,
        6.0,
    )
    parts += (
        sb.trees(txy, terrain, rng) + sb.conifers(cxy, terrain, rng) + sb.bushes(bu, terrain, rng)
    )
    return parts


def _nearest_s(track: Track, xy: F64) -> F64:
    s = track.sample(2.0)
    p = track.point(s)[:, :2]
    d = np.linalg.norm(xy[:, None, :] - p[None], axis=2)
    return s[np.argmin(d, axis=1)]
