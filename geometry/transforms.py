"""Rigid transforms and quaternions on float64 arrays.

Conventions (see ../shared/design/ARCHITECTURE.md):
- quaternions are [x, y, z, w] (scalar last), as in OpenLABEL and scipy;
- ``T_a_b`` is the (4, 4) pose of frame b in frame a: ``p_a = T_a_b @ [p_b, 1]``;
- points are (n, 3) float64.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

F64 = NDArray[np.float64]

# Below this norm a quaternion carries no rotation we could trust.
_MIN_QUAT_NORM = 1e-6


def normalize_quat(q_xyzw: ArrayLike) -> F64:
    """Normalise quaternion(s) and fix the sign so that w >= 0.

    Parameters
    ----------
    q_xyzw : (4,) or (n, 4) quaternions [x, y, z, w], any non-zero norm.

    Returns
    -------
    (4,) or (n, 4) float64 unit quaternions with w >= 0.
    """
    q = np.asarray(q_xyzw, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternion must have 4 components [x, y, z, w], got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("quaternion has non-finite components")
    norm: F64 = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm < _MIN_QUAT_NORM):
        raise ValueError(f"quaternion norm {float(norm.min()):.3g} is too small to normalise")
    q = q / norm
    sign: F64 = np.where(q[..., 3:4] < 0.0, -1.0, 1.0)
    return q * sign


def quat_to_matrix(q_xyzw: ArrayLike) -> F64:
    """(4,) or (n, 4) quaternion [x, y, z, w] -> (3, 3) or (n, 3, 3) rotation matrix."""
    R: F64 = Rotation.from_quat(normalize_quat(q_xyzw)).as_matrix()
    return R


def matrix_to_quat(R: ArrayLike) -> F64:
    """(3, 3) or (n, 3, 3) rotation matrix -> [x, y, z, w] with w >= 0."""
    return normalize_quat(Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat())


def make_T(R: ArrayLike, t: ArrayLike) -> F64:
    """Build a (4, 4) rigid transform from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def pose_to_T(translation: ArrayLike, q_xyzw: ArrayLike) -> F64:
    """OpenLABEL ``pose_wrt_parent`` (translation [x,y,z], quaternion [x,y,z,w]) -> (4, 4)."""
    return make_T(quat_to_matrix(q_xyzw), translation)


def openlabel_pose_to_T(pose: dict[str, Any]) -> F64:
    """OpenLABEL ``pose_wrt_parent`` -> (4, 4): ``{"translation", "quaternion" [x,y,z,w]}``
    (quaternion normalised) or ``{"matrix4x4": 16 values, row-major}``.

    Raises ValueError (with the reason) on missing, malformed or non-finite values.
    """
    try:
        if "matrix4x4" in pose:
            T = np.asarray(pose["matrix4x4"], dtype=np.float64).reshape(4, 4)
            if not np.all(np.isfinite(T)):
                raise ValueError("non-finite matrix4x4")
            return T
        t = np.asarray(pose["translation"], dtype=np.float64).reshape(3)
        q = np.asarray(pose["quaternion"], dtype=np.float64).reshape(4)
    except (KeyError, TypeError) as exc:
        raise ValueError(f"bad pose: {exc!r}") from exc
    if not np.all(np.isfinite(t)):
        raise ValueError("non-finite translation")
    if not np.all(np.isfinite(q)):
        raise ValueError("non-finite quaternion")
    if np.linalg.norm(q) < _MIN_QUAT_NORM:
        raise ValueError("zero quaternion")
    return pose_to_T(t, q)


def T_to_pose(T: ArrayLike) -> tuple[F64, F64]:
    """(4, 4) -> (translation (3,), quaternion [x, y, z, w] (4,))."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, 3].copy(), matrix_to_quat(T[:3, :3])


def invert_T(T: ArrayLike) -> F64:
    """Inverse of a rigid transform (4, 4) or a stack (n, 4, 4), without a general inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def transform_points(T_a_b: ArrayLike, p_b: ArrayLike) -> F64:
    """Map points (n, 3) from frame b to frame a with ``T_a_b`` (4, 4)."""
    T = np.asarray(T_a_b, dtype=np.float64)
    p = np.asarray(p_b, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be (n, 3), got {p.shape}")
    out = p @ T[:3, :3].T
    out += T[:3, 3]  # in place: a second (n, 3) array would cost more than the product
    return out


def rotation_angle(R: ArrayLike) -> F64 | np.float64:
    """Angle (rad) of rotation matrices (3, 3) (a scalar) or (n, 3, 3) ((n,)), robust near
    0 and pi."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).magnitude()
