"""A walk cycle for the built-in person: legs and arms swing with the distance walked.

The person of :func:`renderer.assets.obstacles.build_person` is one closed mesh (no
skeleton), built facing +x with its feet on z = 0 and its origin under its centre. The
cycle poses it by linear blend skinning with weights read off the rest pose's geometry
(the builder's proportions, relative to the height H):

- each leg (vertices below the hips, 0.50 H, within the hips' width) turns about its hip
  joint around the body's y axis, and its shank (below the knee, 0.275 H) also flexes
  about the knee;
- each arm (vertices at the shoulders' width, 0.40-0.83 H) turns about its shoulder,
  opposite to the leg of its side;
- after posing, the body is lowered so that the lower foot stands on the ground again.

Weights blend over a few centimetres (smoothstep) at the hips and the armpits, so the
surface stays closed. The phase advances one full cycle (two steps) per
``STRIDE_PER_HEIGHT * H`` metres walked (about 1.4 m for a 1.75 m person, a normal gait).
Amplitudes: legs +-22 deg at the hip, up to 35 deg at the knee, arms +-18 deg.

The quadrupeds (cow, horse, elephant: :func:`quadruped_walk_pose`) swing their legs in
diagonal pairs (left fore with right hind), +-18 deg about a joint 0.15 H above the belly,
one cycle per ``STRIDE_PER_LENGTH`` body lengths. A leg is what stands below the belly
(the lowest point between the fore and hind legs) within its foot's column; the tail and
an elephant's trunk, outside the columns, stay as built. :func:`gait_pose` picks the
cycle by the mesh's class.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.typing import NDArray

from renderer.mesh import ObjectMesh

F64 = NDArray[np.float64]

#: One full cycle (left and right step) per this many body heights walked.
STRIDE_PER_HEIGHT = 0.8
#: A quadruped's full cycle per this many body lengths walked.
STRIDE_PER_LENGTH = 0.6
QUADRUPED_SWING_DEG = 18.0
#: The classes with a walk cycle.
WALKERS = ("person", "cow", "horse", "elephant")
LEG_SWING_DEG = 22.0
KNEE_FLEX_DEG = 35.0
ARM_SWING_DEG = 18.0

# Proportions of build_person (fractions of the height).
_HIP_Z = 0.50
_KNEE_Z = 0.275
_SHOULDER_Z = 0.805
_ARM_Z = (0.38, 0.83)


def gait_phase(distance_m: float, height_m: float) -> float:
    """The cycle's phase (rad) after ``distance_m`` walked by a person ``height_m`` tall."""
    stride = STRIDE_PER_HEIGHT * max(float(height_m), 0.1)
    return 2.0 * math.pi * float(distance_m) / stride


def _smoothstep(e0: float, e1: float, x: F64) -> F64:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _rot_y(angle: F64) -> NDArray[np.float64]:
    """(n,) angles -> (n, 3, 3) rotations about +y (a positive angle moves +z towards +x)."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((len(angle), 3, 3))
    R[:, 0, 0] = c
    R[:, 0, 2] = s
    R[:, 1, 1] = 1.0
    R[:, 2, 0] = -s
    R[:, 2, 2] = c
    return R


def _turn(p: F64, pivot: F64, angle: F64) -> F64:
    """Points (n, 3) turned about +y through pivots (n, 3) by angles (n,)."""
    return np.einsum("nij,nj->ni", _rot_y(angle), p - pivot) + pivot


def walk_pose(mesh: ObjectMesh, phase: float) -> ObjectMesh:
    """The person ``mesh`` (rest pose, facing +x) posed at ``phase`` (rad) of the cycle.

    Returns a new ObjectMesh (same faces, colours, reflectivity; meta gains
    ``gait_phase``). A foot forward is a leg turned by a negative angle about +y.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    H = float(v[:, 2].max() - v[:, 2].min())
    z = (v[:, 2] - v[:, 2].min()) / max(H, 1e-6)
    y = v[:, 1]
    band = (z > 0.6) & (z < 0.78)
    y_max = float(np.abs(y[band]).max()) if np.any(band) else 0.15 * H
    side = np.where(y >= 0.0, 1.0, -1.0)  # +1: the left side (y left of +x)

    # legs: below the hips, within the hips' width
    w_leg = _smoothstep(_HIP_Z, _HIP_Z - 0.05, z) * _smoothstep(
        0.70 * y_max, 0.60 * y_max, np.abs(y)
    )
    w_knee = _smoothstep(_KNEE_Z + 0.03, _KNEE_Z - 0.03, z) * w_leg
    # arms: beside the chest, from the hands to the shoulders
    w_arm = (
        _smoothstep(0.70 * y_max, 0.80 * y_max, np.abs(y))
        * _smoothstep(_ARM_Z[0] - 0.04, _ARM_Z[0], z)
        * _smoothstep(_ARM_Z[1], _ARM_Z[1] - 0.04, z)
    )

    sw = math.sin(phase)
    leg_fwd = np.radians(LEG_SWING_DEG) * sw * side  # the left leg leads at phase pi/2
    # the knee flexes while the leg swings forward (first half of its own swing)
    flex = np.radians(KNEE_FLEX_DEG) * np.maximum(0.0, np.cos(phase) * side)
    arm_fwd = -np.radians(ARM_SWING_DEG) * sw * side  # opposite to the leg of its side

    hip = np.column_stack([np.zeros(len(v)), side * 0.6 * y_max, np.full(len(v), _HIP_Z * H)])
    knee = np.column_stack([np.zeros(len(v)), side * 0.6 * y_max, np.full(len(v), _KNEE_Z * H)])
    shoulder = np.column_stack(
        [np.zeros(len(v)), side * 0.85 * y_max, np.full(len(v), _SHOULDER_Z * H)]
    )
    p = v.copy()
    # shank about the knee (backwards: the foot goes to -x), then the leg about the hip
    p = _turn(p, knee, flex * w_knee)
    p = _turn(p, hip, -leg_fwd * w_leg)
    p = _turn(p, shoulder, -arm_fwd * w_arm)
    p[:, 2] -= p[:, 2].min() - v[:, 2].min()  # the lower foot back on the ground
    meta = dict(mesh.meta)
    meta["gait_phase"] = float(phase)
    posed = dataclasses.replace(mesh, vertices=p, meta=meta)
    if getattr(posed, "normals", None) is not None:  # rest-pose normals: recomputed
        posed.normals = None
    return posed


def quadruped_phase(distance_m: float, length_m: float) -> float:
    """The cycle's phase (rad) after ``distance_m`` walked by an animal ``length_m`` long."""
    stride = STRIDE_PER_LENGTH * max(float(length_m), 0.1)
    return 2.0 * math.pi * float(distance_m) / stride


def quadruped_walk_pose(mesh: ObjectMesh, phase: float) -> ObjectMesh:
    """A quadruped ``mesh`` (rest pose, facing +x, feet on its lowest z) posed at ``phase``
    (rad) of its cycle (module docstring). Returns a new ObjectMesh."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    z0 = float(v[:, 2].min())
    H = float(v[:, 2].max() - z0)
    z = v[:, 2] - z0
    feet = z < 0.06 * H
    if not np.any(feet):
        return mesh
    fx = v[feet, 0]
    split = 0.5 * (fx.min() + fx.max())
    fore, hind = fx[fx > split], fx[fx <= split]
    if len(fore) == 0 or len(hind) == 0:
        return mesh
    margin = 0.25 * max(np.ptp(fore), np.ptp(hind)) + 0.02 * H
    between = (v[:, 0] > hind.max() + margin) & (v[:, 0] < fore.min() - margin)
    belly = float(z[between].min()) if np.any(between) else 0.5 * H
    pivot_z = z0 + belly + 0.15 * H
    w_z = _smoothstep(belly + 0.04 * H, belly - 0.02 * H, z)
    side = np.where(v[:, 1] >= 0.0, 1.0, -1.0)
    p = v.copy()
    sw = math.radians(QUADRUPED_SWING_DEG) * math.sin(phase)
    for cols, sign_fore in ((fore, 1.0), (hind, -1.0)):
        in_col = (v[:, 0] >= cols.min() - margin) & (v[:, 0] <= cols.max() + margin)
        w = w_z * in_col
        if not np.any(w > 0):
            continue
        x_joint = 0.5 * (cols.min() + cols.max())
        pivot = np.column_stack([np.full(len(v), x_joint), v[:, 1], np.full(len(v), pivot_z)])
        # diagonal pairs: left fore and right hind lead together
        fwd = sw * side * sign_fore
        p = _turn(p, pivot, -fwd * w)
    p[:, 2] -= p[:, 2].min() - z0
    meta = dict(mesh.meta)
    meta["gait_phase"] = float(phase)
    posed = dataclasses.replace(mesh, vertices=p, meta=meta)
    if getattr(posed, "normals", None) is not None:
        posed.normals = None
    return posed


def gait_phase_of(mesh: ObjectMesh, distance_m: float) -> float:
    """The phase (rad) of ``mesh``'s cycle after ``distance_m`` walked (by its class)."""
    if mesh.meta.get("class") == "person":
        return gait_phase(distance_m, float(mesh.size[2]))
    return quadruped_phase(distance_m, float(mesh.size[0]))


def gait_pose(mesh: ObjectMesh, phase: float) -> ObjectMesh:
    """``mesh`` posed at ``phase`` of its class's cycle (the rest mesh for other classes)."""
    cls = mesh.meta.get("class")
    if cls == "person":
        return walk_pose(mesh, phase)
    if cls in WALKERS:
        return quadruped_walk_pose(mesh, phase)
    return mesh


__all__ = [
    "STRIDE_PER_HEIGHT",
    "STRIDE_PER_LENGTH",
    "WALKERS",
    "gait_phase",
    "gait_phase_of",
    "gait_pose",
    "quadruped_phase",
    "quadruped_walk_pose",
    "walk_pose",
]
