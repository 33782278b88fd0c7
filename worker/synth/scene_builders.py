"""Builders for the parts of the procedural railway scene.

Each builder returns mesh parts (and ground-truth records where it makes any). Track-side
geometry is expressed in the track's frames (:meth:`Track.frame_at`): rails, sleepers and
the ballast top follow the cant; structures beside the track use the uncanted frame.
Heights are relative to top of rail (the base frame's z = 0).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from worker.synth import scene_prims as sp
from worker.synth.scene import FORMATION_DEPTH, Landmark, Platform, Pole, Terrain
from worker.synth.scene_mesh import MATERIAL_ID, SceneMesh
from worker.synth.track import RAIL_HEAD_SPACING, Track

F64 = NDArray[np.float64]

# Simplified UIC 60 rail profile (y, z) about the rail-head centre, top of rail at z = 0.
RAIL_PROFILE = np.array(
    [[0.034, 0.0], [-0.034, 0.0], [-0.036, -0.045], [-0.009, -0.060], [-0.075, -0.160],
     [-0.075, -0.172], [0.075, -0.172], [0.075, -0.160], [0.009, -0.060], [0.036, -0.045]]
)  # fmt: skip
SLEEPER_TOP = -0.175  # rail height 0.172 + pad
SLEEPER_SIZE = (0.28, 2.6, 0.20)  # along track, across, height
SLEEPER_SPACING = 0.6
BALLAST_CRIB = -0.20  # ballast surface between the sleepers (rail head ~0.2 m above)
CONTACT_WIRE_HEIGHT = 5.5
PLATFORM_EDGE = 1.72  # platform edge from the track centre (m), German standard for 0.76 m


def _canted_rings(track: Track, s: F64, prof_yz: F64) -> F64:
    T = track.frame_at(s, canted=True)
    return (
        T[:, None, :3, 3]
        + prof_yz[None, :, 0:1] * T[:, None, :3, 1]
        + prof_yz[None, :, 1:2] * T[:, None, :3, 2]
    )


def adaptive_samples(track: Track, s0: float, s1: float, max_step: float, sagitta: float) -> F64:
    """Arc lengths from s0 to s1 spaced so that chords deviate < sagitta (m) from the curve."""
    s = track.sample(1.0, s0, s1)
    k = np.abs(track.curvature(s)) + 1e-9
    step = np.clip(np.sqrt(8.0 * sagitta / k), 1.0, max_step)
    u = np.concatenate([[0.0], np.cumsum(np.diff(s) / step[:-1])])
    n = max(2, int(np.ceil(u[-1])) + 1)
    return np.interp(np.linspace(0.0, u[-1], n), u, s)


def rails(track: Track, s0: float, s1: float, max_step: float = 4.0) -> SceneMesh:
    """Both rails of a track between arc lengths s0 and s1 (chord error < 3 mm)."""
    s = adaptive_samples(track, s0, s1, max_step, 0.003)
    T = track.frame_at(s)
    parts = []
    for sign in (1.0, -1.0):
        prof = RAIL_PROFILE + np.array([sign * 0.5 * RAIL_HEAD_SPACING, 0.0])
        parts.append(sp.sweep(T, prof, "rail", closed=True))
    return SceneMesh.concatenate(parts)


def sleepers(track: Track, s0: float, s1: float, spacing: float = SLEEPER_SPACING) -> SceneMesh:
    """Concrete sleepers every ``spacing`` metres, tops at SLEEPER_TOP."""
    s = np.arange(s0, s1, spacing)
    T = track.frame_at(s)
    T[:, :3, 3] += (SLEEPER_TOP - 0.5 * SLEEPER_SIZE[2]) * T[:, :3, 2]
    return sp.boxes(T, SLEEPER_SIZE, "sleeper")


def ballast(track: Track, s0: float, s1: float, max_step: float = 5.0) -> SceneMesh:
    """Ballast bed: canted top between the shoulders, slopes down to below the formation."""
    s = adaptive_samples(track, s0, s1, max_step, 0.01)
    top = np.array([[1.95, -0.16], [1.45, BALLAST_CRIB], [-1.45, BALLAST_CRIB], [-1.95, -0.16]])
    top_r = _canted_rings(track, s, top)
    toe = np.array([[3.0, -FORMATION_DEPTH - 0.08], [-3.0, -FORMATION_DEPTH - 0.08]])
    T = track.frame_at(s, canted=False)
    toe_r = (
        T[:, None, :3, 3]
        + toe[None, :, 0:1] * T[:, None, :3, 1]
        + toe[None, :, 1:2] * T[:, None, :3, 2]
    )
    rings = np.concatenate([toe_r[:, :1], top_r, toe_r[:, 1:]], axis=1)
    return sp.sweep_rings(rings, "ballast", closed=False)


def cess_path(track: Track, s0: float, s1: float, lateral: float, width: float = 1.0) -> SceneMesh:
    """Gravel walkway beside the track at lateral offset (centre), on the formation."""
    s = track.sample(4.0, s0, s1)
    z = -FORMATION_DEPTH + 0.06
    a = track.lateral_point(s, lateral + 0.5 * width, z)
    b = track.lateral_point(s, lateral - 0.5 * width, z)
    return sp.quad_strip(a, b, "gravel")


def ground(terrain: Terrain, bounds_xy: F64, spacing: float, far: float = 6000.0) -> SceneMesh:
    """Terrain grid over bounds_xy (2, 2) and a coarse, slightly lower far ground."""
    (x0, y0), (x1, y1) = bounds_xy
    nx = int(np.ceil((x1 - x0) / spacing)) + 1
    ny = int(np.ceil((y1 - y0) / spacing)) + 1
    xs, ys = np.linspace(x0, x1, nx), np.linspace(y0, y1, ny)
    gx, gy = np.meshgrid(xs, ys)  # (ny, nx)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    v = np.column_stack([xy, terrain.height(xy)])
    fine = sp.mesh(v, sp.grid_faces(ny, nx, closed=False)[:, ::-1], "ground")
    c = 0.5 * (bounds_xy[0] + bounds_xy[1])
    n = 61
    fx, fy = np.meshgrid(np.linspace(-far, far, n) + c[0], np.linspace(-far, far, n) + c[1])
    fxy = np.column_stack([fx.ravel(), fy.ravel()])
    fz = terrain.base_level(fxy) - 0.5
    coarse = sp.mesh(
        np.column_stack([fxy, fz]), sp.grid_faces(n, n, closed=False)[:, ::-1], "ground"
    )
    return SceneMesh.concatenate([fine, coarse])


def _wire(points: F64, size: float = 0.025) -> SceneMesh:
    d = np.gradient(points, axis=0)
    T = sp.frames_from_axes(points, d)
    h = 0.5 * size
    prof = np.array([[h, -h], [h, h], [-h, h], [-h, -h]])
    return sp.sweep(T, prof, "pole", closed=True)


def catenary(
    track: Track,
    s0: float,
    s1: float,
    terrain: Terrain,
    rng: np.random.Generator,
    spacing: float = 55.0,
    lateral: float = -3.3,
    height: float = 7.6,
    prefix: str = "cat",
) -> tuple[list[SceneMesh], list[Pole], list[Landmark]]:
    """Catenary poles with cantilevers, contact and messenger wire along a track.

    lateral < 0 puts the poles on the right of the track.
    """
    n = max(2, int((s1 - s0) / spacing) + 1)
    s = s0 + np.arange(n) * spacing + rng.uniform(-3.0, 3.0, n)
    s = np.clip(s, s0, s1)
    base_xy = track.lateral_point(s, lateral, 0.0)
    gz = terrain.height(base_xy[:, :2])
    base = np.column_stack([base_xy[:, :2], gz - 0.3])
    top = base + np.array([0.0, 0.0, height + 0.3])
    parts = [sp.cylinders(base, top, 0.17, 0.12, "pole", sides=8)]
    sgn = -np.sign(lateral)
    stagger = np.where(np.arange(n) % 2 == 0, 0.25, -0.25)
    arm_a = track.lateral_point(s, lateral + sgn * 0.12, 6.3)
    arm_b = track.lateral_point(s, stagger, 6.3)
    stay_a = track.lateral_point(s, lateral + sgn * 0.12, 7.2)
    parts.append(sp.cylinders(arm_a, arm_b, 0.03, 0.03, "pole", sides=5))
    parts.append(sp.cylinders(stay_a, arm_b + np.array([0, 0, 0.4]), 0.025, 0.025, "pole", sides=5))
    parts.append(sp.cylinders(arm_b, arm_b - np.array([0, 0, 0.8]), 0.015, 0.015, "pole", sides=4))
    # wires: contact wire zig-zags between the registration points, messenger sags
    ss = track.sample(5.0, s[0], s[-1])
    lat = np.interp(ss, s, stagger)
    parts.append(_wire(track.lateral_point(ss, lat, CONTACT_WIRE_HEIGHT), 0.025))
    u = np.interp(ss, s, np.arange(n)) % 1.0
    parts.append(_wire(track.lateral_point(ss, lat, 6.7 - 1.0 * u * (1 - u)), 0.02))
    poles, landmarks = [], []
    for i in range(n):
        pid = f"{prefix}_{i:03d}"
        poles.append(Pole(pid, "catenary_pole", base[i], height + 0.3, 0.17))
        landmarks.append(Landmark(f"{pid}_top", "pole_top", top[i].copy()))
    return parts, poles, landmarks


def signal(
    track: Track, s: float, terrain: Terrain, idx: int, lateral: float = -3.0, height: float = 5.0
) -> tuple[list[SceneMesh], Pole, list[Landmark]]:
    """Signal pole with a signal head and a white sign board facing approaching trains.

    The board's four front corners and its centre are landmarks.
    """
    p = track.lateral_point(s, lateral, 0.0)[0]
    gz = float(terrain.height(p[None, :2])[0])
    base = np.array([p[0], p[1], gz - 0.3])
    top = np.array([p[0], p[1], p[2] + height])
    radius = 0.08
    parts = [sp.cylinders(base, top, radius, radius, "pole", sides=8)]
    T = track.frame_at(s, canted=False)[0]
    R = T[:3, :3]
    x = R[:, 0]

    def at(dx: float, dy: float, z: float) -> np.ndarray:
        return np.array([p[0], p[1], p[2] + z]) + dx * x + dy * R[:, 1]

    Th = np.eye(4)
    Th[:3, :3] = R
    Th[:3, 3] = at(-(radius + 0.12), 0.0, height - 0.55)
    parts.append(sp.boxes(Th, (0.2, 0.45, 1.1), "sign_dark"))
    lamp = Th.copy()
    lamp[:3, 3] = at(-(radius + 0.225), 0.0, height - 0.35)
    parts.append(sp.boxes(lamp, (0.01, 0.16, 0.16), "sign"))
    w, h, t, zc = 0.5, 0.6, 0.03, 2.8
    Tb = Th.copy()
    Tb[:3, 3] = at(-(radius + 0.01 + 0.5 * t), 0.0, zc)
    parts.append(sp.boxes(Tb, (t, w, h), "sign"))
    # a dark band across the board makes it a recognisable sign (and tests orientation)
    Ts = Th.copy()
    Ts[:3, 3] = at(-(radius + 0.01 + t + 0.002), 0.0, zc)
    parts.append(sp.boxes(Ts, (0.004, w * 0.98, h / 3.0), "sign_dark"))
    fx = -(radius + 0.01 + t)
    pid = f"sig_{idx:03d}"
    lms = [
        Landmark(f"{pid}_board_{name}", "sign_corner", at(fx, dy, zc + dz))
        for name, dy, dz in (("tl", 0.5 * w, 0.5 * h), ("tr", -0.5 * w, 0.5 * h),
                             ("br", -0.5 * w, -0.5 * h), ("bl", 0.5 * w, -0.5 * h))
    ]  # fmt: skip
    lms.append(Landmark(f"{pid}_board_center", "sign_center", at(fx - 0.006, 0.0, zc + h / 3.0)))
    lms.append(Landmark(f"{pid}_top", "pole_top", top.copy()))
    return parts, Pole(pid, "signal_pole", base, float(top[2] - base[2]), radius), lms


def platform(
    track: Track,
    s0: float,
    s1: float,
    side: str,
    idx: int,
    width: float = 7.0,
    height: float = 0.76,
) -> tuple[list[SceneMesh], Platform, list[Landmark]]:
    """A platform beside a track (top ``height`` above top of rail) with a white edge line."""
    sg = 1.0 if side == "left" else -1.0
    s = track.sample(2.0, s0, s1)
    T = track.frame_at(s, canted=False)
    e, b = PLATFORM_EDGE, PLATFORM_EDGE + width
    zb = -FORMATION_DEPTH - 0.3
    prof = np.array([[e, zb], [e, height], [b, height], [b, zb]]) * np.array([sg, 1.0])
    if sg < 0:
        prof = prof[::-1]
    body = sp.sweep(T, prof, "platform", closed=True)
    rings = body.vertices.reshape(len(s), 4, 3)
    caps = [sp.polygon_cap(rings[0], "platform", flip=True), sp.polygon_cap(rings[-1], "platform")]
    line = np.array([[e + 0.05, height + 0.004], [e + 0.30, height + 0.004]]) * np.array([sg, 1.0])
    if sg > 0:
        line = line[::-1]
    edge = sp.sweep(T, line, "platform_edge", closed=False)
    near = track.lateral_point(s, sg * e, height)
    far = track.lateral_point(s, sg * b, height)
    poly = np.vstack([near, far[::-1]]) if sg < 0 else np.vstack([far, near[::-1]])
    pid = f"platform_{idx}"
    lms = [
        Landmark(f"{pid}_corner_start", "platform_corner", near[0].copy()),
        Landmark(f"{pid}_corner_end", "platform_corner", near[-1].copy()),
    ]
    return [body, *caps, edge], Platform(pid, poly, height, track.track_id), lms


def shelter(track: Track, s: float, lateral: float, height: float = 0.76) -> list[SceneMesh]:
    """A platform shelter: four posts and a flat roof, centred at (s, lateral)."""
    T = track.frame_at(s, canted=False)[0]
    R, p = T[:3, :3], T[:3, 3]
    posts = []
    for dx in (-4.0, 4.0):
        for dy in (-1.0, 1.0):
            a = p + dx * R[:, 0] + (lateral + dy) * R[:, 1] + np.array([0, 0, height])
            posts.append((a, a + np.array([0, 0, 2.8])))
    a, b = np.array([x[0] for x in posts]), np.array([x[1] for x in posts])
    parts = [sp.cylinders(a, b, 0.06, 0.06, "pole", sides=6)]
    Tr = T.copy()
    Tr[:3, 3] = p + lateral * R[:, 1] + np.array([0, 0, height + 2.9])
    parts.append(sp.boxes(Tr, (9.0, 3.0, 0.15), "roof"))
    return parts


def fence(
    track: Track, s0: float, s1: float, lateral: float, terrain: Terrain, height: float = 1.6
) -> list[SceneMesh]:
    """Posts every 2.5 m and three horizontal bars at a lateral offset."""
    s = track.sample(2.5, s0, s1)
    g = track.lateral_point(s, lateral, 0.0)
    gz = terrain.height(g[:, :2])
    base = np.column_stack([g[:, :2], gz - 0.2])
    top = base + np.array([0.0, 0.0, height + 0.2])
    parts = [sp.cylinders(base, top, 0.035, 0.035, "fence", sides=4)]
    for h in (0.25, 0.9, height):
        parts.append(_wire(np.column_stack([g[:, :2], gz + h]), 0.03))
    for p in parts[1:]:
        p.material[:] = MATERIAL_ID["fence"]
    return parts


def trees(xy: F64, terrain: Terrain, rng: np.random.Generator) -> list[SceneMesh]:
    """Deciduous trees at world xy (n, 2): trunk plus 2-3 noisy foliage blobs."""
    n = len(xy)
    if n == 0:
        return []
    gz = terrain.height(xy)
    h_trunk = rng.uniform(1.8, 4.5, n)
    r_crown = rng.uniform(1.6, 4.0, n)
    base = np.column_stack([xy, gz - 0.2])
    top = base + np.column_stack([np.zeros((n, 2)), h_trunk + r_crown])
    parts = [sp.cylinders(base, top, rng.uniform(0.12, 0.3, n), 0.08, "trunk", sides=6)]
    k = rng.integers(2, 4, n)
    idx = np.repeat(np.arange(n), k)
    off = rng.normal(0.0, 0.45, (len(idx), 3)) * r_crown[idx, None]
    c = np.column_stack([xy[idx], gz[idx] + h_trunk[idx] + r_crown[idx]]) + off
    r = r_crown[idx, None] * rng.uniform(0.6, 1.0, (len(idx), 1)) * np.array([1.0, 1.0, 1.15])
    parts.append(sp.blobs(c, r, rng, "foliage", noise=0.22, subdiv=1))
    return parts


def conifers(xy: F64, terrain: Terrain, rng: np.random.Generator) -> list[SceneMesh]:
    """Conifers at xy (n, 2): tall narrow noisy blobs on a short trunk."""
    n = len(xy)
    if n == 0:
        return []
    gz = terrain.height(xy)
    h = rng.uniform(8.0, 16.0, n)
    r = h * rng.uniform(0.16, 0.22, n)
    base = np.column_stack([xy, gz - 0.2])
    parts = [
        sp.cylinders(
            base, base + np.column_stack([np.zeros((n, 2)), h]), 0.2, 0.05, "trunk", sides=5
        )
    ]
    c = base + np.column_stack([np.zeros((n, 2)), 1.2 + 0.45 * h])
    parts.append(
        sp.blobs(c, np.column_stack([r, r, 0.5 * h]), rng, "foliage", noise=0.15, subdiv=1)
    )
    return parts


def bushes(xy: F64, terrain: Terrain, rng: np.random.Generator) -> list[SceneMesh]:
    """Low flattened foliage blobs at xy (n, 2)."""
    if len(xy) == 0:
        return []
    gz = terrain.height(xy)
    r = rng.uniform(0.5, 1.6, len(xy))
    c = np.column_stack([xy, gz + 0.25 * r])
    return [
        sp.blobs(
            c,
            np.column_stack([r, r * rng.uniform(0.7, 1.3, len(r)), 0.7 * r]),
            rng,
            "foliage",
            0.3,
            1,
        )
    ]


def buildings(
    xy: F64, heading: F64, terrain: Terrain, rng: np.random.Generator
) -> tuple[list[SceneMesh], F64]:
    """Gable-roofed houses at xy (n, 2) with their long side along heading (n,).

    Returns (parts, footprint radii (n,)).
    """
    n = len(xy)
    if n == 0:
        return [], np.zeros(0)
    L = rng.uniform(9.0, 22.0, n)
    W = rng.uniform(7.0, 13.0, n)
    H = rng.uniform(3.5, 12.0, n)
    roof_h = rng.uniform(1.5, 4.5, n)
    gz = terrain.height(xy)
    x = np.column_stack([np.cos(heading), np.sin(heading), np.zeros(n)])
    Tw = sp.frames_from_axes(np.column_stack([xy, gz + 0.5 * H - 0.5]), x)
    parts = [sp.boxes(Tw, np.column_stack([L, W, H + 1.0]), "building")]
    # roof prism: eaves (4) and ridge (2), overhang 0.4 m
    lx, ly = 0.5 * L + 0.4, 0.5 * W + 0.4
    zero = np.zeros(n)
    loc = np.stack(
        [np.stack(a, -1) for a in (
            (-lx, -ly, zero), (lx, -ly, zero), (lx, ly, zero), (-lx, ly, zero),
            (-lx, zero, roof_h), (lx, zero, roof_h))],
        axis=1,
    )  # fmt: skip
    R = Tw[:, :3, :3]
    org = np.column_stack([xy, gz + H - 0.5])
    v = np.einsum("nij,nkj->nki", R, loc) + org[:, None, :]
    f_roof = np.array([[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5]])
    f_gable = np.array([[1, 2, 5], [3, 0, 4]])
    off = 6 * np.arange(n)[:, None, None]
    parts.append(sp.mesh(v.reshape(-1, 3), (f_roof[None] + off).reshape(-1, 3), "roof"))
    parts.append(sp.mesh(v.reshape(-1, 3), (f_gable[None] + off).reshape(-1, 3), "building"))
    return parts, 0.5 * np.hypot(L, W)


def road(track: Track, s0: float, s1: float, terrain: Terrain, width: float = 6.0) -> SceneMesh:
    """Asphalt ribbon along a (usually offset) track, draped on the terrain."""
    s = track.sample(4.0, s0, s1)
    a = track.lateral_point(s, 0.5 * width, 0.0)
    b = track.lateral_point(s, -0.5 * width, 0.0)
    a[:, 2] = terrain.height(a[:, :2]) + 0.12
    b[:, 2] = terrain.height(b[:, :2]) + 0.12
    return sp.quad_strip(a, b, "road")


class Occupancy:
    """Circles already taken (xy, radius), to keep scattered objects apart."""

    def __init__(self) -> None:
        self.xy = np.zeros((0, 2))
        self.r = np.zeros(0)

    def add(self, xy: F64, r: F64 | float) -> None:
        xy = np.atleast_2d(xy)
        self.xy = np.vstack([self.xy, xy])
        self.r = np.concatenate([self.r, np.broadcast_to(np.asarray(r, np.float64), (len(xy),))])

    def free(self, xy: F64, r: F64 | float) -> NDArray[np.bool_]:
        xy = np.atleast_2d(xy)
        r = np.broadcast_to(np.asarray(r, np.float64), (len(xy),))
        if len(self.xy) == 0:
            return np.ones(len(xy), bool)
        ok = np.ones(len(xy), bool)
        for i0 in range(0, len(xy), 512):
            d = np.linalg.norm(xy[i0 : i0 + 512, None, :] - self.xy[None], axis=2)
            ok[i0 : i0 + 512] = np.all(d > r[i0 : i0 + 512, None] + self.r[None], axis=1)
        return ok


def scatter(
    track: Track,
    s0: float,
    s1: float,
    count: int,
    lateral: tuple[float, float],
    rng: np.random.Generator,
    terrain: Terrain,
    occupancy: Occupancy,
    radius: float,
    min_track_distance: float,
    both_sides: bool = True,
    cluster: float = 0.0,
) -> F64:
    """Random positions (k, 2) beside a track, clear of tracks and occupied circles.

    lateral: (min, max) distance from the track; cluster > 0 groups the samples around
    that many centres per 100 m (tree lines and copses rather than uniform noise).
    """
    if count <= 0:
        return np.zeros((0, 2))
    n = 3 * count
    if cluster > 0:
        k = max(1, int(cluster * (s1 - s0) / 100.0))
        cs = rng.uniform(s0, s1, k)
        cl = rng.uniform(*lateral, k) * (rng.choice([-1.0, 1.0], k) if both_sides else 1.0)
        j = rng.integers(0, k, n)
        s = cs[j] + rng.normal(0, 15.0, n)
        lat = cl[j] + rng.normal(0, 0.25 * (lateral[1] - lateral[0]) + 2.0, n)
    else:
        s = rng.uniform(s0, s1, n)
        lat = rng.uniform(*lateral, n) * (rng.choice([-1.0, 1.0], n) if both_sides else 1.0)
    s = np.clip(s, 0.0, track.length)
    xy = track.lateral_point(s, lat, 0.0)[:, :2]
    d, _ = terrain.track_distance(xy)
    keep = np.flatnonzero(d > min_track_distance)
    out = []
    for i in keep:
        if occupancy.free(xy[i], radius)[0]:
            occupancy.add(xy[i], radius)
            out.append(xy[i])
            if len(out) == count:
                break
    return np.array(out).reshape(-1, 2)
