"""The obstacle library: person, rock, fallen tree, cow, horse and Indian elephant.

Each obstacle is built procedurally from signed-distance primitives (capsules, ellipsoids,
rounded boxes, noise-displaced blobs) joined by smooth unions and meshed by marching cubes
(:mod:`renderer.assets.sdf`), at real-world size, in the :class:`~renderer.mesh.ObjectMesh`
object frame: metres, x forward (the head / face / the trunk's top), y left, z up, origin
at the centre of the ground footprint (bounding box of the vertical projection), min z = 0.

Everything random (proportions inside the required size ranges, pose details, colour
schemes) is drawn from ``numpy.random.default_rng([seed, class index])``: the same
``(name, seed, detail)`` always gives the same mesh, and results are cached in-process.
``detail`` scales the grid resolution (faces grow as ``detail ** 2``; ~8k-30k faces at
1.0); ``scale`` multiplies the final size (1.0 = the real-world sizes below).

Sizes at ``scale = 1`` (also in ``mesh.meta``):

=============  =================================================================
person         height 1.60-1.90 m (``height_m``)
cow            withers 1.30-1.50 m (``withers_m``), length 2.25-2.55 m
horse          withers 1.50-1.70 m, length 2.30-2.60 m, slimmer, longer legs and neck
elephant       height 2.50-3.00 m, length 3.6-4.4 m (Indian: small ears, twin domes)
rock           largest horizontal extent 0.40-1.20 m (``size_m``), partly buried
fallen_tree    length 5-10 m along x (roots to crown), trunk diameter ~0.3-0.6 m
=============  =================================================================

Colours are per-vertex linear RGB by region (the label of the nearest primitive) with a
low-frequency brightness variation; ``reflectivity`` (lidar, 905 nm) follows the region's
brightness (``0.08 + 0.6 * luminance``), higher for retro-reflective hi-vis vests.
"""

# ruff: noqa: RUF005 (numpy vector + list offsets, not list concatenation)

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from renderer.assets.sdf import (
    Part,
    SdfMesh,
    SmoothNoise,
    displaced,
    ellipsoid,
    intersect_halfspace,
    mesh_parts,
    part_box,
    part_capsule,
    part_ellipsoid,
    part_sphere,
)
from renderer.assets.textures import detail_material
from renderer.mesh import PLAIN, Material, ObjectMesh

F64 = NDArray[np.float64]
logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------
# colours
# --------------------------------------------------------------------------------------


def srgb_to_linear(c: ArrayLike) -> F64:
    """sRGB in [0, 1] -> linear RGB (the IEC 61966-2-1 curve)."""
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _hex(h: str) -> F64:
    """'#rrggbb' (sRGB) -> linear RGB (3,)."""
    h = h.lstrip("#")
    return srgb_to_linear([int(h[i : i + 2], 16) / 255.0 for i in (0, 2, 4)])


def reflectivity_of(rgb_linear: ArrayLike) -> float:
    """Lidar reflectivity from a region's colour: ``0.08 + 0.6 * luminance``."""
    lum = float(np.asarray(rgb_linear) @ np.array([0.2126, 0.7152, 0.0722]))
    return float(np.clip(0.08 + 0.6 * lum, 0.05, 0.95))


@dataclass
class Region:
    """Appearance of one labelled region: linear RGB, reflectivity, brightness jitter."""

    rgb: F64
    reflectivity: float
    jitter: float = 0.08


def _region(hexcol: str | F64, jitter: float = 0.08, reflectivity: float | None = None) -> Region:
    rgb = _hex(hexcol) if isinstance(hexcol, str) else np.asarray(hexcol, dtype=np.float64)
    refl = reflectivity_of(rgb) if reflectivity is None else reflectivity
    return Region(rgb, refl, jitter)


def _pick(rng: np.random.Generator, options: list) -> object:
    return options[int(rng.integers(len(options)))]


# --------------------------------------------------------------------------------------
# assembling a mesh
# --------------------------------------------------------------------------------------


def _finish(
    sm: SdfMesh,
    regions: dict[str, Region],
    rng: np.random.Generator,
    name: str,
    meta: dict,
    recolor: Callable[[F64, NDArray[np.int64], list[str], F64, NDArray], None] | None = None,
    textures: dict[str, str] | None = None,
) -> ObjectMesh:
    """Colour an :class:`SdfMesh` by region and re-centre it on its ground footprint;
    ``textures`` maps regions to a procedural detail texture kind (renderer.assets.textures,
    mapped triplanarly; a face takes its first vertex's region)."""
    v = sm.vertices.copy()
    v[:, 2] -= v[:, 2].min()
    lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
    v[:, :2] -= 0.5 * (lo + hi)

    rgb_by_label = np.stack([regions[n].rgb for n in sm.label_names])
    refl_by_label = np.array([regions[n].reflectivity for n in sm.label_names])
    jit_by_label = np.array([regions[n].jitter for n in sm.label_names])
    colors = rgb_by_label[sm.labels].copy()
    refl = refl_by_label[sm.labels].copy()
    if recolor is not None:  # patches and other position-dependent colouring
        recolor(v, sm.labels, sm.label_names, colors, refl)
    size = float(np.ptp(v, axis=0).max())
    noise = SmoothNoise(rng, frequency=3.0 / max(size, 0.3), octaves=3)
    colors *= (1.0 + jit_by_label[sm.labels] * 2.0 * noise(v))[:, None]
    materials: list[Material] = []
    face_material = None
    if textures:
        tex_seed = int(rng.integers(2**31))
        kinds = sorted(set(textures.values()))
        materials = [detail_material(k, tex_seed) for k in kinds] + [PLAIN]
        by_label = np.array([kinds.index(textures[n]) if n in textures else len(kinds)
                             for n in sm.label_names])  # fmt: skip
        face_material = by_label[sm.labels[sm.faces[:, 0]]].astype(np.int32)
        meta["textures"] = {n: textures[n] for n in sm.label_names if n in textures}
    mesh = ObjectMesh(
        vertices=v,
        faces=sm.faces,
        colors=np.clip(colors, 0.0, 1.0).astype(np.float32),
        reflectivity=np.clip(refl, 0.0, 1.0).astype(np.float32),
        name=name,
        meta=meta,
        materials=materials,
        face_material=face_material,
    )
    ext = mesh.size
    meta.update(
        {
            "length_m": float(ext[0]),
            "width_m": float(ext[1]),
            "height_m": float(ext[2]),
            "faces": len(mesh.faces),
            "vertices": len(mesh.vertices),
        }
    )
    meta.setdefault("regions", list(sm.label_names))
    return mesh


def _scale_z_x(sm: SdfMesh, sx: float, syz: float) -> SdfMesh:
    """Stretch a mesh: x by ``sx``, y and z by ``syz`` (orientation is kept)."""
    v = sm.vertices * np.array([sx, syz, syz])
    return SdfMesh(v, sm.faces, sm.labels, sm.label_names, sm.voxel * min(sx, syz))


def _fit_size(sm: SdfMesh, length: float, withers: float, window: tuple[float, float]) -> SdfMesh:
    """Stretch a quadruped to ``length`` (x extent) and ``withers`` (top of the back over
    the shoulders: the highest vertex with x in ``window``, metres before scaling)."""
    v = sm.vertices
    x = v[:, 0]
    w0 = float(v[(x >= window[0]) & (x <= window[1]), 2].max() - v[:, 2].min())
    return _scale_z_x(sm, length / float(np.ptp(x)), withers / w0)


def _max_faces(detail: float) -> int:
    """Face budget of a library mesh: 30k at detail 1, growing as detail^2."""
    return int(30_000 * detail**2)


def _yaw(deg: float) -> F64:
    return Rotation.from_euler("z", deg, degrees=True).as_matrix()


def _rot(seq: str, deg: ArrayLike) -> F64:
    return Rotation.from_euler(seq, deg, degrees=True).as_matrix()


# --------------------------------------------------------------------------------------
# person
# --------------------------------------------------------------------------------------

SKIN_TONES = ["#f1c27d", "#e0ac69", "#c68642", "#8d5524", "#ffdbac", "#5c3a21", "#d9a066"]
HAIR = ["#2b1b0e", "#3b2414", "#6a4e2e", "#a67b4b", "#111111", "#8a8a8a", "#d8c07a"]
SHIRTS = ["#2a4d8f", "#8f2a2a", "#e6e6e6", "#2f6b3a", "#d9b44a", "#444444", "#7a4f9a",
          "#c0392b", "#1f1f1f", "#5d8aa8"]  # fmt: skip
TROUSERS = ["#1f2a44", "#2b2b2b", "#4a4a3a", "#5b4636", "#3a5a8c", "#6b6b6b", "#8b7d5b"]
SHOES = ["#1a1a1a", "#3b2a1d", "#e8e8e8", "#55524e"]
HIVIS = ["#f6ff00", "#ff7a00"]


PERSON_POSES = ("standing", "walking", "lying", "crouching", "sitting")
"""Poses of the built-in person (``pose`` of :func:`build_obstacle`)."""

# Segment lengths and joint heights as fractions of the stature H (standing; close to
# Drillis & Contini's body segment proportions, the eye at 0.936 H).
_HIP, _KNEE, _ANKLE, _SHOULDER, _HEAD_C = 0.50, 0.275, 0.045, 0.805, 0.934
_THIGH, _SHANK = _HIP - _KNEE, _KNEE - _ANKLE
_UPPER_ARM, _FOREARM, _HAND = 0.185, 0.15, 0.045
# Lying on the back across the object frame: body up (+z) -> +y, front (+x) -> +z.
_R_LIE_BACK = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


@dataclass
class _PersonPose:
    """Joint angles (deg): trunk lean forward; per side (left, right) hip flexion (knee
    forward), knee flexion, shoulder flexion (arm forward), elbow flexion; pelvis height
    (fraction of H; None: the lower foot stands on the ground)."""

    lean: float
    hip: tuple[float, float]
    knee: tuple[float, float]
    shoulder: tuple[float, float]
    elbow: tuple[float, float]
    pelvis: float | None = None


def _person_pose(pose: str, rng: np.random.Generator) -> _PersonPose:
    u = rng.uniform
    if pose == "standing":
        st, sw = u(-4, 4), u(-6, 6)
        return _PersonPose(u(-2, 3), (st, -st), (u(0, 4), u(0, 4)), (-sw, sw),
                           (u(5, 15), u(5, 15)))  # fmt: skip
    if pose == "walking":
        st, sw = u(15, 24), u(14, 24)
        lead = 1.0 if rng.random() < 0.5 else -1.0
        return _PersonPose(u(2, 6), (lead * st, -lead * st), (u(2, 8), u(8, 20)),
                           (-lead * sw, lead * sw), (u(10, 25), u(10, 25)))  # fmt: skip
    if pose == "crouching":  # deep squat: knees up, feet under the hips
        f = u(100, 120)
        hips = (f, f + u(-8, 8))
        pelvis = u(0.20, 0.26)
        return _PersonPose(u(25, 40), hips, _knees_to_ground(hips, pelvis, behind=True),
                           (u(35, 65), u(35, 65)), (u(20, 45), u(20, 45)), pelvis)  # fmt: skip
    if pose == "sitting":  # on the ground, knees raised, feet in front
        f = u(100, 130)
        hips = (f, f + u(-15, 10))
        pelvis = 0.048
        hands_back = rng.random() < 0.4
        sh = (u(-40, -25), u(-40, -25)) if hands_back else (u(30, 55), u(30, 55))
        return _PersonPose(u(-12, 5), hips, _knees_to_ground(hips, pelvis, behind=False), sh,
                           (u(5, 15), u(5, 15)) if hands_back else (u(25, 50), u(25, 50)),
                           pelvis)  # fmt: skip
    if pose == "lying":
        spread = u(2, 8)
        return _PersonPose(0.0, (spread, -spread * u(0.5, 1.0)), (u(0, 10), u(0, 25)),
                           (u(-8, 8), u(-8, 8)), (u(0, 20), u(0, 20)))  # fmt: skip
    raise ValueError(f"unknown person pose {pose!r}; known: {PERSON_POSES}")


def _knees_to_ground(hips: tuple[float, float], pelvis: float, behind: bool) -> tuple[float, float]:
    """Knee flexions (deg) that put the ankles on the ground (ankle height) for these hip
    flexions and pelvis height (fractions of H); the foot behind or in front of the knee."""
    out = []
    for f in hips:
        knee_z = pelvis - _THIGH * np.cos(np.radians(f))
        c = float(np.clip((knee_z - _ANKLE) / _SHANK, -1.0, 1.0))
        shank = -np.degrees(np.arccos(c)) if behind else np.degrees(np.arccos(c))
        out.append(float(f - shank))
    return out[0], out[1]


def _dir_xz(angle_deg: float) -> F64:
    """Unit vector down (-z) turned forward (+x) by ``angle_deg``."""
    a = np.radians(angle_deg)
    return np.array([np.sin(a), 0.0, -np.cos(a)])


def build_person(rng: np.random.Generator, detail: float, pose: str | None = None) -> ObjectMesh:
    """An adult of stature 1.60-1.90 m, facing +x, in one of ``PERSON_POSES`` (default
    standing): varied build, skin, hair and clothes (and a hi-vis vest now and then).

    Lying: on the back with the body along the object's y axis (head at +y), so a
    placement that puts the object's x along the track lays the person across the rails.
    Crouching and sitting (on the ground, knees up) keep the feet on the ground.
    """
    pose = pose or "standing"
    pose_rng = np.random.default_rng(rng.integers(2**62))  # the same person in every pose
    H = rng.uniform(1.60, 1.90)
    build = rng.uniform(0.88, 1.18)  # girth
    w = 0.5 * H * build  # half-widths scale with build, heights with H
    long_sleeves = rng.random() < 0.6
    hivis = rng.random() < 0.25
    shorts = rng.random() < 0.15
    pp = _person_pose(pose, pose_rng)

    P = np.array([0.0, 0.0, _pelvis_height(pp, H)])
    Rt = _rot("y", pp.lean)  # trunk: +z leans towards +x

    def trunk(x: float, y: float, z: float) -> F64:
        """A point given in the standing body (z in fractions of H above the hips)."""
        return P + Rt @ np.array([x, y, z])

    top = "vest" if hivis else "shirt"
    parts, hc = _person_head_torso(trunk, Rt, H, w, top, rng)
    parts += _person_legs(P, pp, H, w, shorts)
    parts += _person_arms(trunk, Rt, pp, pose, H, w, top, long_sleeves)

    eye = hc + Rt @ np.array([0.045 * H, 0.0, 0.0])
    if pose == "lying":  # turned, then lifted clear of the ground cut (re-grounded later)
        parts = [_turned(p, _R_LIE_BACK, np.zeros(3)) for p in parts]
        lift = np.array([0.0, 0.0, -min(float(p.lo[2]) for p in parts)])
        parts = [_turned(p, np.eye(3), lift) for p in parts]
        eye = _R_LIE_BACK @ eye + lift
    voxel = 0.016 / detail
    sm = mesh_parts(parts, voxel)
    skin, regions = _person_regions(rng)
    z0 = float(sm.vertices[:, 2].min())
    meta = {"class": "person", "osdar_class": "person", "voxel_m": voxel, "pose": pose,
            "variant": "hivis" if hivis else "casual", "skin": skin, "stature_m": H,
            "build": build, "eye_height_m": float(eye[2] - z0),
            "eye_height_standing_m": _HEAD_C * H}  # fmt: skip
    detail_of = {"skin": "skin", "hair": "fur", "shirt": "cloth", "vest": "cloth",
                 "trousers": "cloth", "shoes": "stone"}  # fmt: skip
    return _finish(sm, regions, rng, "person", meta, textures=detail_of)


def _pelvis_height(pp: _PersonPose, H: float) -> float:
    """Pelvis height (m): from the pose, or with the lower ankle on the ground."""
    if pp.pelvis is not None:
        return pp.pelvis * H
    ankles_below_hip = [
        _THIGH * H * _dir_xz(pp.hip[i]) + _SHANK * H * _dir_xz(pp.hip[i] - pp.knee[i])
        for i in (0, 1)
    ]
    return _ANKLE * H - min(float(a[2]) for a in ankles_below_hip)


def _person_head_torso(
    trunk: Callable[[float, float, float], F64],
    Rt: F64,
    H: float,
    w: float,
    top: str,
    rng: np.random.Generator,
) -> tuple[list[Part], F64]:
    """Head, hair, neck and torso (chest and abdomen in ``top``, pelvis in trousers);
    returns the parts and the head's centre (3,)."""
    parts: list[Part] = []
    hc = trunk(0.0, 0.0, (_HEAD_C - _HIP) * H)
    parts.append(part_ellipsoid(hc, [0.057 * H, 0.046 * H, 0.066 * H], "skin", R=Rt))
    parts.append(part_ellipsoid(hc + Rt @ [0.012 * H, 0, -0.035 * H],
                                [0.05 * H, 0.04 * H, 0.03 * H], "skin", 0.02, R=Rt))  # fmt: skip
    hair_r = np.array([0.058 * rng.uniform(1.0, 1.1), 0.048 * rng.uniform(1.0, 1.05), 0.06]) * H
    parts.append(part_ellipsoid(hc + Rt @ [-0.018 * H, 0, 0.006 * H], hair_r, "hair", 0.01,
                                R=Rt))  # fmt: skip
    parts.append(part_capsule(trunk(0, 0, 0.30 * H), trunk(0.004 * H, 0, 0.385 * H), 0.032 * H,
                              0.028 * H, "skin", 0.02))  # fmt: skip
    parts.append(part_ellipsoid(trunk(0, 0, 0.225 * H), [0.13 * w, 0.235 * w, 0.105 * H], top,
                                0.04, R=Rt))  # fmt: skip
    parts.append(part_ellipsoid(trunk(0.005 * H, 0, 0.10 * H), [0.125 * w, 0.20 * w, 0.09 * H],
                                top, 0.05, R=Rt))  # fmt: skip
    parts.append(part_ellipsoid(trunk(0, 0, 0.015 * H), [0.12 * w, 0.205 * w, 0.06 * H],
                                "trousers", 0.04, R=Rt))  # fmt: skip
    return parts, hc


def _person_legs(P: F64, pp: _PersonPose, H: float, w: float, shorts: bool) -> list[Part]:
    """Thighs, shanks and shoes (hips on the pelvis ``P``, not leaning with the trunk)."""
    parts: list[Part] = []
    for i, side in enumerate((1.0, -1.0)):
        hip = P + np.array([0.0, side * 0.105 * w, 0.0])
        knee = hip + _THIGH * H * _dir_xz(pp.hip[i]) + [0, -side * 0.005 * w, 0]
        shank_dir = _dir_xz(pp.hip[i] - pp.knee[i])
        ankle = knee + _SHANK * H * shank_dir + [0, -side * 0.005 * w, 0]
        lower = "skin" if shorts else "trousers"
        parts.append(part_capsule(hip, knee, 0.075 * w, 0.052 * w, "trousers", 0.03))
        parts.append(part_capsule(knee, ankle, 0.05 * w, 0.036 * w, lower, 0.02))
        # the foot flat on the ground unless the shank tilts a lot (lying: along it)
        tilt = pp.hip[i] - pp.knee[i]
        foot_tilt = tilt if abs(tilt) > 30.0 else 0.0
        Rf = _rot("y", -foot_tilt)
        parts.append(part_box(ankle + Rf @ [0.04 * H, 0, -0.025 * H],
                              [0.075 * H, 0.028 * H, 0.024 * H], 0.018 * H, "shoes", 0.02,
                              R=Rf))  # fmt: skip
    return parts


def _person_arms(
    trunk: Callable[[float, float, float], F64],
    Rt: F64,
    pp: _PersonPose,
    pose: str,
    H: float,
    w: float,
    top: str,
    long_sleeves: bool,
) -> list[Part]:
    """Arms: shoulder flexion forward, slight abduction, elbow flexion forward."""
    parts: list[Part] = []
    for i, side in enumerate((1.0, -1.0)):
        sh = trunk(0.0, side * 0.255 * w, (_SHOULDER - _HIP) * H)
        abd = np.radians(6.0)
        d1 = Rt @ _dir_xz(pp.shoulder[i]) if pose != "sitting" else _dir_xz(pp.shoulder[i])
        d1 = d1 + np.array([0.0, side * np.sin(abd), 0.0])
        d1 /= np.linalg.norm(d1)
        d2 = _rot("y", -pp.elbow[i]) @ d1  # forearm turned forward (towards +x)
        elbow = sh + _UPPER_ARM * H * d1
        wrist = elbow + _FOREARM * H * d2
        hand = wrist + _HAND * H * d2
        parts.append(part_capsule(sh, elbow, 0.048 * w, 0.04 * w, top, 0.03))
        fore = top if long_sleeves else "skin"
        parts.append(part_capsule(elbow, wrist, 0.04 * w, 0.032 * w, fore, 0.015))
        parts.append(part_capsule(wrist, hand, 0.03 * w, 0.024 * w, "skin", 0.015))
    return parts


def _person_regions(rng: np.random.Generator) -> tuple[object, dict[str, Region]]:
    """The skin tone picked and the colour regions: skin, hair, clothes, shoes."""
    skin = _pick(rng, SKIN_TONES)
    regions = {
        "skin": _region(_vary(rng, skin, 0.06), 0.04),
        "hair": _region(_vary(rng, _pick(rng, HAIR), 0.1), 0.05),
        "shirt": _region(_vary(rng, _pick(rng, SHIRTS), 0.15), 0.06),
        "vest": _region(_pick(rng, HIVIS), 0.03, reflectivity=0.95),
        "trousers": _region(_vary(rng, _pick(rng, TROUSERS), 0.15), 0.06),
        "shoes": _region(_pick(rng, SHOES), 0.04),
    }
    return skin, regions


def _turned(p: Part, R: F64, t: F64) -> Part:
    """A part moved by x -> R x + t (its box: the moved box's bounds)."""
    f0 = p.sdf

    def f(x: F64) -> F64:
        return f0((x - t) @ R)  # (x - t) @ R == R^T (x - t): back in the part's frame

    corners = np.array([[a, b, c] for a in (p.lo[0], p.hi[0]) for b in (p.lo[1], p.hi[1])
                        for c in (p.lo[2], p.hi[2])]) @ R.T + t  # fmt: skip
    return Part(f, corners.min(axis=0), corners.max(axis=0), p.label, p.blend)


def _vary(rng: np.random.Generator, hexcol: str, amount: float) -> F64:
    """A colour (linear) with its brightness and tint jittered by up to ``amount``."""
    c = _hex(hexcol) if isinstance(hexcol, str) else np.asarray(hexcol)
    gain = rng.uniform(1.0 - amount, 1.0 + amount)
    tint = rng.uniform(1.0 - 0.4 * amount, 1.0 + 0.4 * amount, size=3)
    return np.clip(c * gain * tint, 0.0, 1.0)


# --------------------------------------------------------------------------------------
# quadrupeds
# --------------------------------------------------------------------------------------


def _patches(rng: np.random.Generator, freq: float, label_ids: list[int], color: F64,
             refl: float, threshold: float) -> Callable:  # fmt: skip
    """Recolour callback: ``color`` where a smooth noise exceeds ``threshold``."""
    noise = SmoothNoise(rng, frequency=freq, octaves=2, waves=5)

    def recolor(v: F64, labels: NDArray, names: list[str], colors: F64, r: NDArray) -> None:
        on = np.isin(labels, label_ids) & (noise(v) > threshold)
        colors[on] = color
        r[on] = refl

    return recolor


def _leg(parts: list[Part], top: F64, knee: F64, foot: F64, r: tuple[float, float, float],
         label: str, hoof: str, hoof_r: ArrayLike) -> None:  # fmt: skip
    parts.append(part_capsule(top, knee, r[0], r[1], label, 0.05))
    parts.append(part_capsule(knee, foot, r[1], r[2], label, 0.03))
    parts.append(part_ellipsoid(foot + [0.02, 0, -foot[2] + 0.5 * hoof_r[2]], hoof_r, hoof, 0.02))


COW_SCHEMES = {
    "holstein": ("#1b1b1b", "#f2f2f0", 0.05),  # base, patch colour, patch threshold
    "brown_white": ("#7a4424", "#efe9df", 0.35),
    "red_brown": ("#8a3f1d", "#d9c3a5", 0.8),
    "black": ("#1e1c1a", "#efe9df", 0.9),
    "grey_zebu": ("#bdb8ae", "#8c877f", 0.55),
}


def build_cow(rng: np.random.Generator, detail: float) -> ObjectMesh:
    """A standing cow: barrel, hump, legs, dewlap, udder, head, ears, optional horns,
    tail; black-and-white or brown patches. Withers 1.30-1.50 m, length 2.25-2.55 m."""
    withers = rng.uniform(1.30, 1.50)
    length = rng.uniform(2.25, 2.55)
    horns = rng.random() < 0.5
    head_down = rng.uniform(-0.1, 0.12)
    p: list[Part] = []
    p.append(part_ellipsoid([0, 0, 1.0], [0.78, 0.31, 0.35], "hide"))
    p.append(part_ellipsoid([0.45, 0, 1.13], [0.36, 0.25, 0.27], "hide", 0.12))
    p.append(part_ellipsoid([-0.55, 0, 1.08], [0.36, 0.29, 0.30], "hide", 0.12))
    p.append(part_ellipsoid([0.62, 0, 0.92], [0.25, 0.26, 0.3], "hide", 0.1))  # chest
    neck_end = np.array([0.98, 0, 1.06 - head_down])
    p.append(part_capsule([0.55, 0, 1.12], neck_end, 0.22, 0.15, "hide", 0.08))
    p.append(part_ellipsoid([0.82, 0, 0.86 - 0.5 * head_down], [0.2, 0.07, 0.17], "hide", 0.06))
    muzzle = neck_end + [0.30, 0, -0.28]
    p.append(part_capsule(neck_end, muzzle, 0.13, 0.095, "head", 0.05))
    p.append(part_ellipsoid(muzzle + [0.02, 0, -0.01], [0.085, 0.095, 0.085], "muzzle", 0.03))
    for s in (1.0, -1.0):
        p.append(part_ellipsoid(neck_end + [-0.02, s * 0.17, 0.03], [0.045, 0.11, 0.05], "head",
                                0.02, R=_rot("x", s * 15)))  # fmt: skip
        if horns:
            h0, h1 = neck_end + [0.02, s * 0.08, 0.1], neck_end + [0.06, s * 0.22, 0.2]
            p.append(part_capsule(h0, h1, 0.035, 0.018, "horn", 0.02))
        # legs: front, then hind with a thigh
        _leg(p, np.array([0.5, s * 0.17, 0.88]), np.array([0.52, s * 0.17, 0.45]),
             np.array([0.52, s * 0.16, 0.08]), (0.1, 0.065, 0.055), "leg", "hoof",
             [0.075, 0.06, 0.05])  # fmt: skip
        p.append(part_ellipsoid([-0.55, s * 0.17, 0.88], [0.24, 0.13, 0.26], "hide", 0.08))
        _leg(p, np.array([-0.6, s * 0.17, 0.8]), np.array([-0.68, s * 0.17, 0.45]),
             np.array([-0.62, s * 0.16, 0.08]), (0.085, 0.06, 0.052), "leg", "hoof",
             [0.075, 0.06, 0.05])  # fmt: skip
    p.append(part_ellipsoid([-0.38, 0, 0.64], [0.15, 0.13, 0.1], "udder", 0.05))
    p.append(part_capsule([-0.9, 0, 1.3], [-0.95, 0, 0.58], 0.04, 0.03, "hide", 0.03))
    p.append(part_ellipsoid([-0.95, 0, 0.52], [0.05, 0.05, 0.1], "tail_tuft", 0.02))

    voxel = 0.026 / detail
    sm = mesh_parts(p, voxel)
    sm = _fit_size(sm, length, withers, (0.25, 0.65))

    scheme = str(_pick(rng, list(COW_SCHEMES)))
    base_hex, patch_hex, thr = COW_SCHEMES[scheme]
    base, patch = _vary(rng, base_hex, 0.12), _vary(rng, patch_hex, 0.06)
    thr = thr + rng.uniform(-0.15, 0.15)  # more or less of the patch colour
    regions = {
        "hide": _region(base, 0.06), "leg": _region(base, 0.06), "head": _region(base, 0.06),
        "muzzle": _region("#c98f86" if scheme == "holstein" else "#3a2a24", 0.05),
        "udder": _region("#e3a9a0", 0.04), "hoof": _region("#2a2420", 0.03),
        "horn": _region("#d8cdb0", 0.05), "tail_tuft": _region("#1a1816", 0.04),
    }  # fmt: skip
    ids = [sm.label_names.index(n) for n in ("hide", "leg", "head") if n in sm.label_names]
    pc = patch
    recolor = _patches(rng, rng.uniform(1.2, 2.2), ids, pc, reflectivity_of(pc), thr)
    meta = {"class": "cow", "osdar_class": "animal", "voxel_m": voxel, "variant": scheme,
            "withers_m": withers, "horns": horns}  # fmt: skip
    return _finish(sm, regions, rng, "cow", meta, recolor,
                   textures={"hide": "fur", "leg": "fur", "head": "fur", "udder": "skin",
                             "muzzle": "skin", "horn": "stone", "hoof": "stone"})  # fmt: skip


HORSE_COATS = {
    "bay": ("#6b3a1e", "#151110"),  # body, mane/tail/lower legs
    "chestnut": ("#8c4a22", "#7a3d18"),
    "black": ("#1a1715", "#0f0d0c"),
    "grey": ("#b9b6b0", "#8f8b85"),
    "dun": ("#b08d57", "#2a211a"),
    "white": ("#e4e0d8", "#cfc9be"),
}


def build_horse(rng: np.random.Generator, detail: float) -> ObjectMesh:
    """A standing horse: slimmer than the cow, longer legs and raised neck, mane and
    tail. Withers 1.50-1.70 m, length 2.30-2.60 m."""
    withers = rng.uniform(1.50, 1.70)
    length = rng.uniform(2.30, 2.60)
    neck_up = rng.uniform(-0.08, 0.08)
    p: list[Part] = []
    p.append(part_ellipsoid([0, 0, 1.22], [0.68, 0.26, 0.29], "coat"))
    p.append(part_ellipsoid([0.42, 0, 1.33], [0.3, 0.2, 0.26], "coat", 0.1))
    p.append(part_ellipsoid([-0.5, 0, 1.28], [0.34, 0.27, 0.29], "coat", 0.1))
    p.append(part_ellipsoid([0.62, 0, 1.2], [0.2, 0.23, 0.28], "coat", 0.08))
    n0 = np.array([0.62, 0, 1.38])
    n1 = np.array([1.02, 0, 1.86 + neck_up])
    p.append(part_capsule(n0, n1, 0.19, 0.115, "coat", 0.08))
    nose = n1 + [0.33, 0, -0.36]
    p.append(part_capsule(n1 + [0.0, 0, 0.04], nose, 0.11, 0.07, "coat", 0.05))
    p.append(part_ellipsoid(nose + [-0.01, 0, -0.01], [0.07, 0.065, 0.075], "muzzle", 0.03))
    # mane along the top of the neck: offset perpendicular to the neck, towards back-up
    ax = (n1 - n0) / np.linalg.norm(n1 - n0)
    perp = np.array([-ax[2], 0.0, ax[0]])
    p.append(part_capsule(n0 + perp * 0.16 + [-0.05, 0, 0], n1 + perp * 0.09 + [0.02, 0, 0.05],
                          0.05, 0.04, "mane", 0.02))  # fmt: skip
    p.append(part_ellipsoid(n1 + [0.07, 0, 0.1], [0.08, 0.04, 0.04], "mane", 0.02))  # forelock
    for s in (1.0, -1.0):
        p.append(part_capsule(n1 + [-0.01, s * 0.055, 0.1], n1 + [-0.03, s * 0.07, 0.22], 0.03,
                              0.014, "coat", 0.02))  # ears  # fmt: skip
        p.append(part_capsule([0.5, s * 0.14, 1.05], [0.52, s * 0.14, 0.55], 0.08, 0.05, "coat",
                              0.05))  # fmt: skip
        p.append(part_capsule([0.52, s * 0.14, 0.55], [0.53, s * 0.135, 0.1], 0.042, 0.038,
                              "lower_leg", 0.02))  # fmt: skip
        p.append(part_sphere([0.53, s * 0.135, 0.13], 0.048, "lower_leg", 0.02))
        p.append(part_ellipsoid([0.56, s * 0.135, 0.04], [0.065, 0.055, 0.045], "hoof", 0.02))
        p.append(part_ellipsoid([-0.5, s * 0.15, 1.06], [0.24, 0.12, 0.26], "coat", 0.08))
        p.append(part_capsule([-0.56, s * 0.15, 1.0], [-0.66, s * 0.14, 0.56], 0.09, 0.05,
                              "coat", 0.05))  # fmt: skip
        p.append(part_capsule([-0.66, s * 0.14, 0.56], [-0.6, s * 0.135, 0.1], 0.042, 0.038,
                              "lower_leg", 0.02))  # fmt: skip
        p.append(part_sphere([-0.6, s * 0.135, 0.13], 0.048, "lower_leg", 0.02))
        p.append(part_ellipsoid([-0.57, s * 0.135, 0.04], [0.065, 0.055, 0.045], "hoof", 0.02))
    p.append(part_capsule([-0.8, 0, 1.48], [-0.9, 0, 1.3], 0.07, 0.065, "mane", 0.04))
    p.append(part_capsule([-0.9, 0, 1.3], [-0.93, 0, 0.72], 0.065, 0.05, "mane", 0.02))

    voxel = 0.024 / detail
    sm = mesh_parts(p, voxel)
    sm = _fit_size(sm, length, withers, (0.2, 0.5))
    coat = str(_pick(rng, list(HORSE_COATS)))
    body, dark = (_vary(rng, c, 0.12) for c in HORSE_COATS[coat])
    white_socks = rng.random() < 0.3
    regions = {
        "coat": _region(body, 0.05), "mane": _region(dark, 0.04),
        "lower_leg": _region("#e8e4dc" if white_socks else dark, 0.04),
        "muzzle": _region("#2a2422", 0.04), "hoof": _region("#2b2622", 0.03),
    }  # fmt: skip
    meta = {"class": "horse", "osdar_class": "animal", "voxel_m": voxel, "variant": coat,
            "withers_m": withers}  # fmt: skip
    return _finish(sm, regions, rng, "horse", meta,
                   textures={"coat": "fur", "mane": "fur", "lower_leg": "fur", "muzzle": "skin",
                             "hoof": "stone"})  # fmt: skip


def build_elephant(rng: np.random.Generator, detail: float) -> ObjectMesh:
    """An Indian (Asian) elephant: big body with an arched back, column legs, twin-domed
    head, small ears, long trunk, optional tusks, tail; grey. Height 2.5-3.0 m."""
    height = rng.uniform(2.5, 3.0)
    tusks = rng.random() < 0.5
    curl = rng.uniform(0.0, 0.25)
    p: list[Part] = []
    p.append(part_ellipsoid([0, 0, 1.85], [1.45, 0.78, 0.8], "skin"))
    p.append(part_ellipsoid([0.15, 0, 2.0], [0.9, 0.62, 0.75], "skin", 0.25))  # arched back
    p.append(part_ellipsoid([-0.9, 0, 1.85], [0.6, 0.68, 0.7], "skin", 0.2))  # rump
    hc = np.array([1.55, 0, 2.15])
    p.append(part_ellipsoid(hc, [0.5, 0.45, 0.52], "skin", 0.2))
    for s in (1.0, -1.0):
        p.append(part_sphere(hc + [-0.05, s * 0.16, 0.32], 0.3, "skin", 0.12))  # twin domes
        # ears: flat flaps against the side of the head, slightly open
        p.append(part_ellipsoid(hc + [-0.38, s * 0.52, -0.1], [0.36, 0.07, 0.46], "ear", 0.04,
                                R=_yaw(s * 14.0)))  # fmt: skip
        if tusks:
            p.append(part_capsule(hc + [0.3, s * 0.2, -0.42], hc + [0.72, s * 0.26, -0.72], 0.08,
                                  0.05, "tusk", 0.03))  # fmt: skip
        for x, r0 in ((0.85, 0.29), (-0.9, 0.3)):
            p.append(part_capsule([x, s * 0.42, 1.6], [x + 0.03, s * 0.42, 0.25], r0, 0.24,
                                  "skin", 0.12))  # fmt: skip
            p.append(part_ellipsoid([x + 0.05, s * 0.42, 0.1], [0.27, 0.26, 0.16], "foot", 0.06))
    # trunk: a tapering chain hanging from the face, the tip curled forward by `curl`
    pts = np.array(
        [hc + [0.38, 0, -0.05], hc + [0.55, 0, -0.6], hc + [0.6, 0, -1.2],
         hc + [0.62 + curl, 0, -1.7], hc + [0.75 + 1.5 * curl, 0, -1.95 + 1.2 * curl]]
    )  # fmt: skip
    radii = [0.22, 0.17, 0.13, 0.1, 0.075]
    for i in range(len(pts) - 1):
        p.append(part_capsule(pts[i], pts[i + 1], radii[i], radii[i + 1], "skin", 0.06))
    p.append(part_capsule([-1.35, 0, 2.15], [-1.5, 0, 1.3], 0.07, 0.05, "skin", 0.05))
    p.append(part_ellipsoid([-1.5, 0, 1.22], [0.06, 0.06, 0.12], "tail_tuft", 0.03))

    voxel = 0.06 / detail
    sm = mesh_parts(p, voxel)
    s_all = height / float(np.ptp(sm.vertices[:, 2]))
    sm = _scale_z_x(sm, s_all, s_all)
    grey = _vary(rng, str(_pick(rng, ["#6f6a66", "#7d7771", "#5f5a57", "#8a807a", "#7a6656"])),
                 0.1)  # fmt: skip
    regions = {
        "skin": _region(grey, 0.08), "ear": _region(0.85 * grey, 0.1),
        "foot": _region("#5a5450", 0.05), "tusk": _region("#e9e0c8", 0.03),
        "tail_tuft": _region("#222020", 0.03),
    }  # fmt: skip
    meta = {"class": "elephant", "osdar_class": "animal", "voxel_m": voxel,
            "variant": "tusker" if tusks else "tuskless"}  # fmt: skip
    ear_id = [sm.label_names.index("ear")]
    pink = _hex("#b59a8e")  # the depigmented, mottled ear edges of Asian elephants
    recolor = _patches(rng, 4.0, ear_id, pink, reflectivity_of(pink), 0.3)
    return _finish(sm, regions, rng, "elephant", meta, recolor,
                   textures={"skin": "stone", "ear": "skin", "foot": "stone", "tusk": "skin",
                             "tail_tuft": "fur"})  # wrinkled hide: the stone grain  # fmt: skip


# --------------------------------------------------------------------------------------
# rock and fallen tree
# --------------------------------------------------------------------------------------


def build_rock(rng: np.random.Generator, detail: float) -> ObjectMesh:
    """An irregular boulder: a noise-displaced ellipsoid with a few fracture facets, partly
    buried; grey-brown. Largest extent 0.40-1.20 m."""
    D = rng.uniform(0.45, 1.15)
    r = 0.5 * D * np.array([1.0, rng.uniform(0.6, 0.9), rng.uniform(0.45, 0.7)])
    c = np.array([0.0, 0.0, r[2] * rng.uniform(0.55, 0.8)])
    R = _yaw(rng.uniform(0, 180))
    noise = SmoothNoise(rng, frequency=1.6 / D, octaves=3)
    f = displaced(ellipsoid(c, r, R), noise, 0.1 * D)
    for _ in range(int(rng.integers(3, 6))):
        n = rng.normal(size=3)
        n[2] = abs(n[2]) * 0.6
        n /= np.linalg.norm(n)
        f = intersect_halfspace(f, n, float(n @ c + rng.uniform(0.55, 0.8) * (np.abs(n) @ r)))
    ext = np.abs(R) @ r + 0.12 * D
    part = Part(f, c - ext, c + ext, "rock")
    voxel = D / 48.0 / detail
    sm = mesh_parts([part], voxel)
    size = rng.uniform(0.4, 1.2)  # largest horizontal extent
    s = size / float(np.ptp(sm.vertices[:, :2], axis=0).max())
    sm = _scale_z_x(sm, s, s)
    tone = str(_pick(rng, ["#7b756c", "#8a8177", "#6e6a63", "#8c7f6a", "#5f5b55"]))
    regions = {"rock": _region(tone, 0.14)}
    lichen = _hex(str(_pick(rng, ["#9a9a6a", "#59604a", "#a89f8c"])))
    recolor = _patches(rng, 4.0 / D, [0], lichen, reflectivity_of(lichen), 0.55)
    meta = {"class": "rock", "osdar_class": "obstacle", "voxel_m": voxel * s, "variant": tone}
    mesh = _finish(sm, regions, rng, "rock", meta, recolor, textures={"rock": "stone"})
    mesh.meta["size_m"] = float(max(mesh.meta["length_m"], mesh.meta["width_m"]))
    return mesh


def build_fallen_tree(rng: np.random.Generator, detail: float) -> ObjectMesh:
    """A fallen tree lying along x (root end at -x): tapering, slightly bent trunk, broken
    roots, branches with foliage clumps. Length 5-10 m."""
    length = rng.uniform(5.0, 10.0)  # the whole tree, roots and crown included
    L = (length - 1.9) / 1.03  # the trunk (the crown and roots add ~0.03 L + 1.9 m)
    r0 = rng.uniform(0.15, 0.3)
    dead = rng.random() < 0.3
    p: list[Part] = []
    # trunk in 4 bent segments, resting on the ground (slightly sunk)
    xs = np.linspace(-0.5 * L, 0.45 * L, 5)
    radii = r0 * np.linspace(1.0, 0.45, 5)
    ys = np.concatenate([[0.0], np.cumsum(rng.normal(0.0, 0.04 * L, 4))])
    zs = radii * 0.9 + np.concatenate([[0.0], np.abs(rng.normal(0.0, 0.01 * L, 4))])
    axis = np.stack([xs, ys, zs], axis=1)
    for i in range(4):
        p.append(part_capsule(axis[i], axis[i + 1], radii[i], radii[i + 1], "bark", 0.05))
    # root end: flare and broken roots
    p.append(part_ellipsoid(axis[0] + [0.1 * r0, 0, 0.1 * r0], [0.6 * r0, 1.4 * r0, 1.4 * r0],
                            "bark", 0.1))  # fmt: skip
    for k in range(int(rng.integers(4, 7))):
        ang = 2 * np.pi * k / 6 + rng.uniform(-0.3, 0.3)
        d = np.array([-rng.uniform(0.3, 0.8), np.cos(ang), np.sin(ang)])
        d /= np.linalg.norm(d)
        p.append(part_capsule(axis[0], axis[0] + d * r0 * rng.uniform(2.5, 4.5), 0.45 * r0,
                              0.15 * r0 + 0.02, "roots", 0.05))  # fmt: skip
    # branches: up or sideways, leaning towards the top (+x); foliage at their ends
    n_br = int(rng.integers(6, 11))
    foliage_noise = SmoothNoise(rng, frequency=2.2, octaves=2)
    for _ in range(n_br):
        t = rng.uniform(0.3, 0.95)
        seg = min(int(t * 4), 3)
        u = t * 4 - seg
        base = axis[seg] * (1 - u) + axis[seg + 1] * u
        rb = radii[seg] * (1 - u) + radii[seg + 1] * u
        ang = rng.uniform(-100, 100)  # around x from straight up; no branch into the ground
        lean = rng.uniform(25, 60)
        d = _rot("x", ang) @ _rot("y", -(90 - lean)) @ np.array([1.0, 0.0, 0.0])
        d[2] = max(d[2], 0.1)
        d /= np.linalg.norm(d)
        blen = rng.uniform(0.8, 2.2) * (0.6 + 0.05 * L)
        tip = base + d * blen
        rbr = max(0.4 * rb, 0.085)
        p.append(part_capsule(base, tip, rbr, max(0.5 * rbr, 0.065), "bark", 0.06))
        if rng.random() < 0.6:  # a twig off the branch
            d2 = _rot("z", rng.uniform(-50, 50)) @ d
            mid = base + 0.55 * blen * d
            p.append(part_capsule(mid, mid + d2 * 0.5 * blen, max(0.6 * rbr, 0.07), 0.06,
                                  "bark", 0.03))  # fmt: skip
        rc = rng.uniform(0.35, 0.75) * (0.7 + 0.04 * L)
        clump = ellipsoid(tip, [rc * 1.2, rc, rc * 0.8], _yaw(rng.uniform(0, 180)))
        ext = np.array([1.2, 1.2, 1.2]) * rc + 0.2
        p.append(Part(displaced(clump, foliage_noise, 0.1), tip - ext, tip + ext, "foliage", 0.15))
    # crown at the top end
    top = axis[-1] + [0.4, 0, 0.3]
    rc = 0.8 + 0.06 * L
    clump = ellipsoid(top, [rc * 1.3, rc, rc * 0.75])
    ext = np.array([1.3, 1.0, 0.75]) * rc + 0.2
    p.append(Part(displaced(clump, foliage_noise, 0.18), top - ext, top + ext, "foliage", 0.15))
    p.append(part_capsule(axis[-1], top, radii[-1], 0.05, "bark", 0.05))

    sm = mesh_parts(p, 0.07 / detail, max_faces=_max_faces(detail))
    voxel = sm.voxel
    sm = _scale_z_x(sm, length / float(np.ptp(sm.vertices[:, 0])), 1.0)
    leaf = str(_pick(rng, ["#9c6b2f", "#7a5a2a"] if dead else ["#3f6b24", "#4d7a2c", "#2f5a1e"]))
    regions = {
        "bark": _region(str(_pick(rng, ["#5a4632", "#6b5a48", "#4a3b2c"])), 0.1),
        "roots": _region("#4b3a2a", 0.1),
        "foliage": _region(leaf, 0.15, reflectivity=0.35),
    }
    meta = {"class": "fallen_tree", "osdar_class": "obstacle", "voxel_m": voxel,
            "variant": "dead" if dead else "green", "trunk_diameter_m": 2 * r0,
            "lod_faces_per_px": 170.0}  # foliage outline: see renderer.assets.lod  # fmt: skip
    return _finish(sm, regions, rng, "fallen_tree", meta,
                   textures={"bark": "bark", "roots": "bark", "foliage": "fur"})  # fmt: skip


# --------------------------------------------------------------------------------------
# registry
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ObstacleSpec:
    """A library entry: its builder and the size ranges it guarantees at scale 1.

    ranges : {meta key: (min, max)} in metres, e.g. ``{"height_m": (1.6, 1.9)}``.
    """

    name: str
    builder: Callable[..., ObjectMesh]
    ranges: dict[str, tuple[float, float]]
    poses: tuple[str, ...] = ("standing",)


OBSTACLES: dict[str, ObstacleSpec] = {
    s.name: s
    for s in (
        ObstacleSpec("person", build_person, {"stature_m": (1.6, 1.9)}, PERSON_POSES),
        ObstacleSpec("rock", build_rock, {"size_m": (0.4, 1.2)}),
        ObstacleSpec("fallen_tree", build_fallen_tree, {"length_m": (5.0, 10.0)}),
        ObstacleSpec("cow", build_cow, {"withers_m": (1.3, 1.5), "length_m": (2.2, 2.6)}),
        ObstacleSpec("horse", build_horse, {"withers_m": (1.5, 1.7), "length_m": (2.3, 2.6)}),
        ObstacleSpec("elephant", build_elephant, {"height_m": (2.5, 3.0), "length_m": (3.4, 4.6)}),
    )
}
"""The six built-in obstacles by name."""

_ALIASES = {"tree": "fallen_tree", "indian_elephant": "elephant", "human": "person"}


@lru_cache(maxsize=32)
def _build_cached(name: str, seed: int, detail: float, pose: str | None) -> ObjectMesh:
    spec = OBSTACLES[name]
    rng = np.random.default_rng([int(seed) & (2**63 - 1), list(OBSTACLES).index(name)])
    mesh = spec.builder(rng, detail, pose) if len(spec.poses) > 1 else spec.builder(rng, detail)
    mesh.meta.update({"seed": int(seed), "detail": float(detail)})
    mesh.meta.setdefault("pose", "standing")
    logger.info(
        "built %s seed %d detail %.2f: %d faces, size %s m",
        name,
        seed,
        detail,
        len(mesh.faces),
        np.round(mesh.size, 2).tolist(),
    )
    return mesh


def build_obstacle(
    name: str, *, seed: int = 0, detail: float = 1.0, scale: float = 1.0, pose: str | None = None
) -> ObjectMesh:
    """Build (or fetch from the in-process cache) one obstacle of the library.

    Parameters
    ----------
    name : one of ``OBSTACLES`` (``person``, ``rock``, ``fallen_tree``, ``cow``,
        ``horse``, ``elephant``; aliases ``tree``, ``indian_elephant``, ``human``).
    seed : everything random (size within the range, pose, colours) follows from it.
    detail : grid resolution factor, 0.2-3; faces grow as ``detail ** 2``.
    scale : uniform factor on the final size (1 = real-world size).
    pose : the person's pose, one of ``PERSON_POSES`` (default standing); the animals,
        the rock and the tree have only ``standing`` (or None).

    Returns
    -------
    ObjectMesh (a private copy: callers may modify it), meta with ``height_m``,
    ``length_m``, ``width_m`` (and ``withers_m`` for cow and horse) after scaling.
    """
    key = _ALIASES.get(name.lower(), name.lower())
    if key not in OBSTACLES:
        raise ValueError(f"unknown obstacle {name!r}; known: {sorted(OBSTACLES)}")
    if not 0.05 <= detail <= 4.0:
        raise ValueError(f"detail must be in [0.05, 4], got {detail}")
    if not (np.isfinite(scale) and scale > 0.0):
        raise ValueError(f"scale must be positive, got {scale}")
    poses = OBSTACLES[key].poses
    if pose is not None and pose not in poses:
        raise ValueError(f"{key} has no pose {pose!r}; its poses: {list(poses)}")
    base = _build_cached(key, int(seed), round(float(detail), 4), pose)
    mesh = base.with_vertices(base.vertices * scale)
    mesh.meta = copy.deepcopy(base.meta)
    for k in ("length_m", "width_m", "height_m", "withers_m", "trunk_diameter_m", "size_m",
              "stature_m", "eye_height_m", "eye_height_standing_m"):  # fmt: skip
        if k in mesh.meta:
            mesh.meta[k] = float(mesh.meta[k] * scale)
    mesh.meta["scale"] = float(scale)
    return mesh
