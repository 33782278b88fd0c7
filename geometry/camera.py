"""The one camera model of osdar-ar: OSDaR23 pinhole + Brown-Conrady distortion.

Frames (../shared/design/OSDAR23.md):
- ``base``: the merged lidar frame, x forward, y left, z up (metres);
- ``cam``: the camera's non-optical frame, aligned like base; ``T_base_cam`` is the
  OpenLABEL ``pose_wrt_parent`` of the camera (camera -> base);
- ``opt``: the optical frame, x right, y down, z forward:
  ``p_opt = (-p_cam.y, -p_cam.z, p_cam.x)``.

Pixels follow OpenCV: integer coordinates at pixel centres, u to the right, v down.
Distortion [k1, k2, p1, p2, k3] acts on normalised optical coordinates (x, y) = (X/Z, Y/Z):

    r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

The radial map r -> r radial(r) is only invertible up to its first turning point
``r_valid`` (where d(r radial)/dr = 0); beyond it the lens model folds back. Points
projecting beyond ``r_valid`` are flagged invalid, never wrapped onto the image.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import map_coordinates

from geometry.transforms import invert_T, openlabel_pose_to_T, transform_points

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

# p_opt = R_OPT_CAM @ p_cam
R_OPT_CAM: F64 = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
T_CAM_OPT: F64 = np.eye(4)
T_CAM_OPT[:3, :3] = R_OPT_CAM.T


@dataclass(frozen=True)
class CameraTolerances:
    """Numerical tolerances of the camera model, in one place."""

    # Points closer than this along the optical axis (m) are "at or behind" the camera.
    min_depth_m: float = 1e-3
    # Undistortion: Newton stops below this residual in normalised coordinates
    # (1e-12 ~ 5e-9 px at f = 4600 px).
    undistort_tol: float = 1e-12
    undistort_max_iter: int = 50
    # A solution whose residual stays above this is declared invalid (~5e-4 px).
    undistort_accept: float = 1e-7
    # Largest normalised radius ever considered (tan 85 deg): beyond, a pinhole is meaningless.
    max_radius: float = 11.43


TOL = CameraTolerances()


@dataclass(frozen=True)
class RenderSetup:
    """An undistorted pinhole image that covers a distorted camera image, and the remap.

    ``cv2.remap(pinhole_img, map_x, map_y, cv2.INTER_LINEAR)`` gives the distorted image;
    pixels without a valid source have map values -1 (and come out as the border value).

    K: (3, 3) pinhole intrinsics of the render; width, height: its size in pixels;
    map_x, map_y: (H, W) float32 over the *distorted* image.
    """

    K: F64
    width: int
    height: int
    map_x: NDArray[np.float32] = field(repr=False)
    map_y: NDArray[np.float32] = field(repr=False)


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A calibrated camera of a sequence.

    Attributes
    ----------
    name : stream name, e.g. ``rgb_center``.
    width, height : image size in pixels (of this possibly scaled image).
    K : (3, 3) intrinsics [fx 0 cx; 0 fy cy; 0 0 1].
    dist : (5,) Brown-Conrady [k1, k2, p1, p2, k3].
    T_base_cam : (4, 4) pose of the non-optical camera frame in the base (lidar) frame.
    scale : this image's size relative to the sensor's real resolution.
    """

    name: str
    width: int
    height: int
    K: F64
    dist: F64
    T_base_cam: F64
    scale: float = 1.0

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        T = np.asarray(self.T_base_cam, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"camera {self.name}: K must be a finite (3,3) with fx, fy > 0")
        if dist.shape != (5,) or not np.all(np.isfinite(dist)):
            raise ValueError(f"camera {self.name}: dist must be 5 finite [k1,k2,p1,p2,k3]")
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"camera {self.name}: T_base_cam must be a finite (4,4)")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name}: width and height must be positive")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "T_base_cam", T)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_openlabel(
        cls, name: str, stream: dict[str, Any], T_base_cam: ArrayLike
    ) -> CameraModel:
        """Camera from an OpenLABEL stream (with ``intrinsics_pinhole``) and its pose.

        ``camera_matrix`` is 3x4 row-major [fx 0 cx 0; 0 fy cy 0; 0 0 1 0].
        """
        try:
            intr = stream["stream_properties"]["intrinsics_pinhole"]
            m = np.asarray(intr["camera_matrix"], dtype=np.float64)
            dist = np.asarray(intr.get("distortion_coeffs", [0.0] * 5), dtype=np.float64)
            width, height = int(intr["width_px"]), int(intr["height_px"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"stream {name}: no usable intrinsics_pinhole ({exc})") from exc
        if m.size != 12:
            raise ValueError(f"stream {name}: camera_matrix must have 12 values, got {m.size}")
        if dist.size < 5:
            dist = np.concatenate([dist, np.zeros(5 - dist.size)])
        T = np.asarray(T_base_cam, dtype=np.float64)
        return cls(name, width, height, m.reshape(3, 4)[:, :3], dist[:5], T)

    def scaled(self, s: float) -> CameraModel:
        """The same camera for an image resized by ``s`` (sizes rounded), see :meth:`resized`."""
        if not s > 0:
            raise ValueError(f"scale must be > 0, got {s}")
        return self.resized(max(1, round(self.width * s)), max(1, round(self.height * s)))

    def resized(self, width: int, height: int) -> CameraModel:
        """The same camera for its image resized to exactly ``width`` x ``height``.

        Pixel centres stay exact: u' = (u + 0.5) * sx - 0.5 with sx = W'/W and sy = H'/H
        taken separately, so that a resize with rounded sizes inverts exactly.
        """
        if width <= 0 or height <= 0:
            raise ValueError(f"size must be positive, got {width} x {height}")
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return CameraModel(self.name, width, height, K, self.dist, self.T_base_cam, self.scale * sx)

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON form (round-trips through ``from_json``)."""
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "T_base_cam": self.T_base_cam.tolist(),
            "scale": self.scale,
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> CameraModel:
        return cls(
            d["name"],
            int(d["width"]),
            int(d["height"]),
            d["K"],
            d["dist"],
            d["T_base_cam"],
            float(d.get("scale", 1.0)),
        )

    # ------------------------------------------------------------------ frames
    @cached_property
    def T_base_opt(self) -> F64:
        """(4, 4) pose of the optical frame in the base frame."""
        return self.T_base_cam @ T_CAM_OPT

    @cached_property
    def T_opt_base(self) -> F64:
        """(4, 4) base -> optical."""
        return invert_T(self.T_base_opt)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    # ------------------------------------------------------------------ distortion
    @cached_property
    def r_valid(self) -> float:
        """Largest normalised radius where the radial distortion is still monotonic."""
        return valid_radius(self.dist)

    def distort(self, xy: ArrayLike) -> F64:
        """Normalised undistorted (n, 2) -> normalised distorted (n, 2)."""
        return distort_normalized(np.asarray(xy, dtype=np.float64), self.dist)

    def undistort(self, xy_d: ArrayLike) -> tuple[F64, NDArray[np.bool_]]:
        """Normalised distorted (n, 2) -> (undistorted (n, 2), valid (n,)).

        Invalid where the distorted point lies beyond the lens model's fold (no preimage
        within ``r_valid``) or the iteration does not converge; those rows are NaN.
        """
        return undistort_normalized(np.asarray(xy_d, dtype=np.float64), self.dist, self.r_valid)

    # ------------------------------------------------------------------ projection
    def project_optical(self, p_opt: ArrayLike) -> tuple[F64, NDArray[np.bool_]]:
        """Points (n, 3) in the optical frame -> (uv (n, 2) distorted pixels, valid (n,)).

        Invalid (uv NaN): at or behind the camera (z < min depth), non-finite, or beyond
        the distortion model's valid radius. Nothing is ever divided by ~0.
        """
        p = np.asarray(p_opt, dtype=np.float64).reshape(-1, 3)
        z = p[:, 2]
        valid = np.isfinite(p).all(axis=1) & (z > TOL.min_depth_m)
        xy = np.full((len(p), 2), np.nan)
        xy[valid] = p[valid, :2] / z[valid, None]
        r = np.hypot(xy[:, 0], xy[:, 1])
        valid &= r <= min(self.r_valid, TOL.max_radius)
        uv = np.full((len(p), 2), np.nan)
        if np.any(valid):
            xy_d = self.distort(xy[valid])
            uv[valid] = xy_d @ self.K[:2, :2].T + self.K[:2, 2]
        return uv, valid

    def project(self, p_base: ArrayLike) -> tuple[F64, NDArray[np.bool_]]:
        """Points (n, 3) in the base (lidar) frame -> (uv (n, 2), valid (n,))."""
        p = np.asarray(p_base, dtype=np.float64).reshape(-1, 3)
        return self.project_optical(transform_points(self.T_opt_base, p))

    def project_world(
        self, p_world: ArrayLike, T_world_base: ArrayLike
    ) -> tuple[F64, NDArray[np.bool_]]:
        """Points (n, 3) in the world frame seen from vehicle pose ``T_world_base`` (4, 4)."""
        T_opt_world = self.T_opt_base @ invert_T(np.asarray(T_world_base, dtype=np.float64))
        p = np.asarray(p_world, dtype=np.float64).reshape(-1, 3)
        return self.project_optical(transform_points(T_opt_world, p))

    def in_image(self, uv: ArrayLike, margin: float = 0.0) -> NDArray[np.bool_]:
        """(n,) mask of pixels inside [-0.5, W-0.5) x [-0.5, H-0.5) shrunk by ``margin``."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return (
                (uv[:, 0] >= -0.5 + margin)
                & (uv[:, 0] < self.width - 0.5 - margin)
                & (uv[:, 1] >= -0.5 + margin)
                & (uv[:, 1] < self.height - 0.5 - margin)
            )

    def pixel_to_normalized(self, uv: ArrayLike) -> F64:
        """Distorted pixels (n, 2) -> normalised distorted coordinates (n, 2)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        y = (uv[:, 1] - self.cy) / self.fy
        x = (uv[:, 0] - self.cx - self.K[0, 1] * y) / self.fx
        return np.stack([x, y], axis=1)

    def unproject(self, uv: ArrayLike) -> tuple[F64, NDArray[np.bool_]]:
        """Distorted pixels (n, 2) -> (unit rays (n, 3) in the optical frame, valid (n,))."""
        xy, valid = self.undistort(self.pixel_to_normalized(uv))
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        return rays, valid

    def unproject_depth(self, uv: ArrayLike, depth: ArrayLike) -> tuple[F64, NDArray[np.bool_]]:
        """Pixels (n, 2) and optical z-depths (n,) -> (points (n, 3) in base, valid (n,))."""
        xy, valid = self.undistort(self.pixel_to_normalized(uv))
        z = np.asarray(depth, dtype=np.float64).reshape(-1)
        p_opt = np.concatenate([xy * z[:, None], z[:, None]], axis=1)
        return transform_points(self.T_base_opt, p_opt), valid & np.isfinite(z)

    # ------------------------------------------------------------------ rendering
    def render_setup(self, margin_px: float = 2.0) -> RenderSetup:
        """Undistorted pinhole covering this (distorted) image plus a margin, and its remap.

        The pinhole keeps fx, fy; its extent is that of the undistorted image border
        (clamped at ``r_valid``) plus ``margin_px`` on each side. Cached per model.
        """
        return _render_setup(self, float(margin_px))


# ---------------------------------------------------------------------- free functions
def distort_normalized(xy: F64, dist: F64) -> F64:
    """Apply Brown-Conrady distortion to normalised coordinates (n, 2) -> (n, 2)."""
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def valid_radius(dist: ArrayLike) -> float:
    """First r > 0 where d/dr [r (1 + k1 r^2 + k2 r^4 + k3 r^6)] = 0, else ``max_radius``.

    With u = r^2 the derivative is 1 + 3 k1 u + 5 k2 u^2 + 7 k3 u^3: the smallest positive
    real root u0 of that cubic gives r_valid = sqrt(u0).
    """
    k1, k2, _, _, k3 = (float(c) for c in np.asarray(dist, dtype=np.float64))
    coeffs = np.array([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0])
    # Drop leading zeros so np.roots sees the true degree.
    nz = np.flatnonzero(np.abs(coeffs) > 0)
    roots = np.roots(coeffs[nz[0] :]) if nz[0] < 3 else np.array([])
    real = roots[np.abs(roots.imag) < 1e-12].real
    pos = real[real > 0]
    if len(pos) == 0:
        return TOL.max_radius
    return float(min(np.sqrt(pos.min()), TOL.max_radius))


def _radial_forward(r: F64, k1: float, k2: float, k3: float) -> tuple[F64, F64]:
    """r -> (r radial(r), d/dr of it)."""
    r2 = r * r
    f = r * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
    df = 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))
    return f, df


def _invert_radial(rd: F64, k1: float, k2: float, k3: float, r_max: float) -> F64:
    """Solve r radial(r) = rd for r in [0, r_max] (monotonic there): safeguarded Newton."""
    lo = np.zeros_like(rd)
    hi = np.full_like(rd, r_max)
    r = np.clip(rd, 0.0, r_max)
    for _ in range(TOL.undistort_max_iter):
        f, df = _radial_forward(r, k1, k2, k3)
        res = f - rd
        lo = np.where(res < 0, r, lo)
        hi = np.where(res > 0, r, hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = r - res / df
        bad = ~np.isfinite(step) | (step <= lo) | (step >= hi)
        r_new = np.where(bad, 0.5 * (lo + hi), step)
        if np.all(np.abs(r_new - r) < TOL.undistort_tol):
            r = r_new
            break
        r = r_new
    return r


def undistort_normalized(
    xy_d: F64, dist: F64, r_valid: float | None = None
) -> tuple[F64, NDArray[np.bool_]]:
    """Invert Brown-Conrady on normalised coordinates (n, 2) -> ((n, 2), valid (n,)).

    The radial part is inverted exactly within the monotonic range [0, r_valid]
    (safeguarded Newton), then a 2-D Newton step with the analytic Jacobian absorbs the
    tangential terms. Rows without a preimage inside the valid radius are NaN / invalid.
    """
    dist = np.asarray(dist, dtype=np.float64)
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    r_max = valid_radius(dist) if r_valid is None else float(r_valid)
    xy_d = np.asarray(xy_d, dtype=np.float64).reshape(-1, 2)
    finite = np.isfinite(xy_d).all(axis=1)
    rd = np.hypot(xy_d[:, 0], xy_d[:, 1])
    rd_max, _ = _radial_forward(np.array([r_max]), k1, k2, k3)
    valid = finite & (rd <= rd_max[0])
    out = np.full_like(xy_d, np.nan)
    if not np.any(valid):
        return out, valid
    rdv = rd[valid]
    r = _invert_radial(rdv, k1, k2, k3, r_max)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(rdv > 0, r / rdv, 1.0)
    xy = xy_d[valid] * ratio[:, None]
    if p1 != 0.0 or p2 != 0.0:
        xy = _newton_full(xy, xy_d[valid], dist)
    resid = np.abs(distort_normalized(xy, dist) - xy_d[valid]).max(axis=1)
    ok = np.isfinite(resid) & (resid < TOL.undistort_accept)
    ok &= np.hypot(xy[:, 0], xy[:, 1]) <= r_max * (1 + 1e-9)
    idx = np.flatnonzero(valid)
    out[idx[ok]] = xy[ok]
    valid[idx[~ok]] = False
    return out, valid


def _newton_full(xy: F64, xy_d: F64, dist: F64) -> F64:
    """2-D Newton on the full distortion (radial + tangential), from a good start."""
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    for _ in range(TOL.undistort_max_iter):
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        drad = k1 + r2 * (2.0 * k2 + r2 * 3.0 * k3)  # d radial / d r2
        res = distort_normalized(xy, dist) - xy_d
        j11 = radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        j21 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        j22 = radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
        det = j11 * j22 - j12 * j21
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = (j22 * res[:, 0] - j12 * res[:, 1]) / det
            dy = (-j21 * res[:, 0] + j11 * res[:, 1]) / det
        xy = xy - np.stack([dx, dy], axis=1)
        if np.nanmax(np.abs(res)) < TOL.undistort_tol:
            break
    return xy


#: (width, height, K bytes, dist bytes, margin) of a camera's render setup
_CameraKey = tuple[int, int, bytes, bytes, float]
_SETUP_CACHE: dict[_CameraKey, RenderSetup] = {}


def _camera_key(cam: CameraModel, margin: float) -> _CameraKey:
    return (cam.width, cam.height, cam.K.tobytes(), cam.dist.tobytes(), margin)


def _render_setup(cam: CameraModel, margin_px: float) -> RenderSetup:
    key = _camera_key(cam, margin_px)
    hit = _SETUP_CACHE.get(key)
    if hit is not None:
        return hit
    # Undistorted extent of the image border, sampled densely (the extreme can lie
    # between corners for strong distortion).
    n = 512
    us = np.linspace(-0.5, cam.width - 0.5, n)
    vs = np.linspace(-0.5, cam.height - 0.5, n)
    border = np.concatenate(
        [
            np.stack([us, np.full(n, -0.5)], 1),
            np.stack([us, np.full(n, cam.height - 0.5)], 1),
            np.stack([np.full(n, -0.5), vs], 1),
            np.stack([np.full(n, cam.width - 0.5), vs], 1),
        ]
    )
    xy_d = cam.pixel_to_normalized(border)
    xy, ok = cam.undistort(xy_d)
    if not np.all(ok):
        # Beyond the fold: clamp the border direction to the valid radius.
        r_lim = cam.r_valid
        dirs = xy_d[~ok] / np.maximum(np.hypot(xy_d[~ok, 0], xy_d[~ok, 1]), 1e-12)[:, None]
        xy[~ok] = dirs * r_lim
        log.warning(
            "camera %s: %d border samples lie beyond the distortion fold (r_valid=%.4f)",
            cam.name,
            int((~ok).sum()),
            r_lim,
        )
    fx, fy = cam.fx, cam.fy
    u_min = fx * xy[:, 0].min() - margin_px
    u_max = fx * xy[:, 0].max() + margin_px
    v_min = fy * xy[:, 1].min() - margin_px
    v_max = fy * xy[:, 1].max() + margin_px
    width = int(np.ceil(u_max - u_min)) + 1
    height = int(np.ceil(v_max - v_min)) + 1
    K = np.array([[fx, 0.0, -u_min], [0.0, fy, -v_min], [0.0, 0.0, 1.0]])
    # Map: for each distorted pixel, its position in the pinhole render.
    pu, pv = _pinhole_map(cam, K)
    setup = RenderSetup(
        K=K,
        width=width,
        height=height,
        map_x=pu,
        map_y=pv,
    )
    _SETUP_CACHE[key] = setup
    return setup


def _pinhole_map(
    cam: CameraModel, K_render: F64, step: int = 4
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """For every distorted pixel (H, W), its (u, v) in the pinhole render (-1: none).

    The map is smooth, so it is solved exactly on a grid every ``step`` pixels and
    interpolated bilinearly (error < 1e-3 px for the real OSDaR23 lenses); pixels next to
    an invalid node (the distortion fold) are solved exactly.
    """

    H, W = cam.height, cam.width
    gu = np.arange(0, W - 1 + step, step, dtype=np.float64)
    gv = np.arange(0, H - 1 + step, step, dtype=np.float64)
    GU, GV = np.meshgrid(gu, gv)
    nodes = np.stack([GU.ravel(), GV.ravel()], axis=1)
    xy, ok = cam.undistort(cam.pixel_to_normalized(nodes))
    node_u = (xy[:, 0] * K_render[0, 0] + K_render[0, 2]).reshape(GU.shape)
    node_v = (xy[:, 1] * K_render[1, 1] + K_render[1, 2]).reshape(GU.shape)
    node_ok = ok.reshape(GU.shape)
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    coords = np.stack([vv / step, uu / step])
    fill_u = np.where(node_ok, node_u, 0.0)
    fill_v = np.where(node_ok, node_v, 0.0)
    pu = map_coordinates(fill_u, coords, order=1, mode="nearest")
    pv = map_coordinates(fill_v, coords, order=1, mode="nearest")
    all_ok = map_coordinates(node_ok.astype(np.float64), coords, order=1, mode="nearest")
    exact = all_ok < 1.0 - 1e-9
    if np.any(exact):
        uv = np.stack([uu[exact], vv[exact]], axis=1)
        xy_e, ok_e = cam.undistort(cam.pixel_to_normalized(uv))
        pu[exact] = np.where(ok_e, xy_e[:, 0] * K_render[0, 0] + K_render[0, 2], -1.0)
        pv[exact] = np.where(ok_e, xy_e[:, 1] * K_render[1, 1] + K_render[1, 2], -1.0)
    return pu.astype(np.float32), pv.astype(np.float32)


def gl_projection(K: ArrayLike, width: int, height: int, near: float, far: float) -> F64:
    """OpenGL projection (4, 4) for points in the optical frame (x right, y down, z fwd).

    clip = P @ [x, y, z, 1] with w_clip = z. Pixel centres follow OpenCV: pixel u covers
    NDC x in [-1 + 2u/W, -1 + 2(u+1)/W], so u = fx x/z + cx maps to
    x_ndc = (2 (u + 0.5)) / W - 1. Image row v maps to framebuffer row v counted from the
    bottom, so the rows that ``glReadPixels`` / moderngl's ``fbo.read()`` return are image
    rows top to bottom with no flip. This mirrors the image vertically relative to a usual
    GL camera, so triangle winding appears reversed: disable face culling or set
    ``ctx.front_face = "cw"``. Depth: z = near -> -1, z = far -> +1 (use LESS).

    Upload to a GLSL ``mat4`` with ``P.T.astype("f4").tobytes()`` (column-major).
    """
    K = np.asarray(K, dtype=np.float64)
    if not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    fx, s, cx = K[0]
    _, fy, cy = K[1]
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * fx / width
    P[0, 1] = 2.0 * s / width
    P[0, 2] = (2.0 * cx + 1.0) / width - 1.0
    P[1, 1] = 2.0 * fy / height
    P[1, 2] = (2.0 * cy + 1.0) / height - 1.0
    P[2, 2] = (far + near) / (far - near)
    P[2, 3] = -2.0 * far * near / (far - near)
    P[3, 2] = 1.0
    return P


def gl_projection_reversed_z(K: ArrayLike, width: int, height: int, near: float) -> F64:
    """:func:`gl_projection` with a reversed, infinite depth: clip z = ``near``, so that
    with ``glClipControl(GL_LOWER_LEFT, GL_ZERO_TO_ONE)`` the window depth is ``near / z``
    (1 at the near plane, 0 at infinity; use GREATER, clear to 0). Near-plane clipping
    stays (z_clip <= w); nothing is clipped far away. x and y as :func:`gl_projection`.
    """
    if not near > 0:
        raise ValueError(f"need near > 0, got {near}")
    P = gl_projection(K, width, height, near, 2.0 * near)
    P[2] = [0.0, 0.0, 0.0, near]
    return P


def load_cameras(
    labels_raw: dict[str, Any], names: list[str] | None = None
) -> dict[str, CameraModel]:
    """All cameras with pinhole intrinsics of an OpenLABEL dict (or those in ``names``).

    The camera pose is its coordinate system's ``pose_wrt_parent`` composed up to the root
    (``base``): T_base_cam. Quaternions are normalised on input.
    """
    ol = labels_raw.get("openlabel", labels_raw)
    streams = ol.get("streams", {})
    css = ol.get("coordinate_systems", {})
    out: dict[str, CameraModel] = {}
    for name, stream in streams.items():
        if names is not None and name not in names:
            continue
        if stream.get("type") != "camera":
            continue
        if "intrinsics_pinhole" not in stream.get("stream_properties", {}):
            continue
        out[name] = CameraModel.from_openlabel(name, stream, T_root_cs(css, name))
    if names is not None:
        missing = sorted(set(names) - set(out))
        if missing:
            raise ValueError(f"cameras not in the labels' streams: {', '.join(missing)}")
    return out


def T_root_cs(coordinate_systems: dict[str, Any], name: str) -> F64:
    """Pose (4, 4) of coordinate system ``name`` in the root frame (composing parents)."""
    T = np.eye(4)
    seen: set[str] = set()
    cur = name
    while True:
        if cur in seen:
            raise ValueError(f"coordinate system {name}: cycle in parents at {cur}")
        seen.add(cur)
        cs = coordinate_systems.get(cur)
        if cs is None:
            raise ValueError(f"coordinate system {cur!r} is not defined")
        parent = cs.get("parent", "")
        if not parent:
            return T
        pose = cs.get("pose_wrt_parent")
        if pose is None:
            raise ValueError(f"coordinate system {cur}: no pose_wrt_parent")
        try:
            T = openlabel_pose_to_T(pose) @ T
        except ValueError as exc:
            raise ValueError(f"coordinate system {cur}: {exc}") from exc
        cur = parent
