"""Uncertainty of a pose track and the pixel bound it puts on a placed object.

A pose track's uncertainty is kept as the information matrix (inverse covariance) of its
per-frame perturbations, sparse as the least-squares problem that produced it: frame k
owns columns ``6k .. 6k + 6``, a world rotation vector applied on the left of its
rotation, then a world position offset; further columns (nuisance parameters such as an
INS bias) may follow and are marginalised by the inversion. The covariance of two
frames' perturbations is solved from one sparse factorisation, never formed densely.

An object placed in the map near frame ``r`` and seen from frame ``i`` is off by what
the relative pose of the two frames is off (a shift of the whole trajectory and map
together moves neither): :func:`anchor_bound_px` propagates the 12 x 12 covariance of
the two frames' perturbations to the anchor's pixel and returns the radius that holds
the pixel error with ``coverage`` probability (the exact quantile of a 2-D Gaussian
error's length, :func:`gaussian_radius_quantile`).
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq
from scipy.sparse import csc_matrix, diags
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation
from scipy.special import ndtr, ndtri

F64 = NDArray[np.float64]

#: Regularisation added to the diagonal before factorising (keeps the unobservable
#: directions finite: they are bounded by the priors of the problem anyway).
RIDGE = 1e-12
#: Finite-difference steps of the pixel Jacobian: rad, m.
STEP_ROT = 1e-6
STEP_POS = 1e-4


@dataclass
class PoseInformation:
    """Sparse information matrix of a track's per-frame perturbations (module docstring).

    matrix : (m, m) with m >= 6 n_frames; scale : variance factor (>= 1) by which the
    covariance is multiplied (the solution's own consistency: its residuals' spread).
    """

    matrix: csc_matrix
    n_frames: int
    scale: float = 1.0
    _cache: dict[tuple[int, int], F64] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        m = self.matrix.shape[0]
        if self.matrix.shape != (m, m) or m < 6 * self.n_frames:
            raise ValueError(f"information matrix {self.matrix.shape} for {self.n_frames} frames")

    @cached_property
    def _lu(self) -> Callable[[F64], F64]:
        A = csc_matrix(self.matrix) + RIDGE * diags(np.ones(self.matrix.shape[0]), format="csc")
        return splu(A.tocsc()).solve

    def covariance(self, r: int, i: int) -> F64:
        """(12, 12) covariance of [dtheta_r, dp_r, dtheta_i, dp_i] (rad, m), scaled."""
        key = (r, i)
        if key not in self._cache:
            m = self.matrix.shape[0]
            cols = np.r_[6 * r : 6 * r + 6, 6 * i : 6 * i + 6]
            E = np.zeros((m, 12))
            E[cols, np.arange(12)] = 1.0
            X = self._lu(E)
            C = X[cols]
            self._cache[key] = 0.5 * (C + C.T) * self.scale
        return self._cache[key]

    def relative_covariance(self, r: int, i: int) -> F64:
        """(6, 6) covariance of frame i's perturbation minus frame r's, scaled, solved for
        the difference directly (no cancellation of two large absolute covariances)."""
        m = self.matrix.shape[0]
        D = np.zeros((m, 6))
        D[6 * i + np.arange(6), np.arange(6)] += 1.0
        D[6 * r + np.arange(6), np.arange(6)] -= 1.0
        C = D.T @ self._lu(D)
        return 0.5 * (C + C.T) * self.scale

    @classmethod
    def independent(cls, sigma_rot: float, sigma_pos: float, n: int) -> PoseInformation:
        """Frames with independent errors (sigma rad, m): a raw INS, a fitted centreline."""
        w = np.tile([sigma_rot] * 3 + [sigma_pos] * 3, n) ** -2.0
        return cls(diags(w, format="csc"), n)

    @classmethod
    def random_walk(
        cls,
        sigma_rot: float,
        sigma_pos: float,
        n: int,
        prior_rot: float = np.radians(0.5),
        prior_pos: float = 1.0,
    ) -> PoseInformation:
        """Frames chained by relative motions with independent step errors (sigma rad, m
        per step): lidar odometry; its first frame anchored within ``prior_rot`` (rad) and
        ``prior_pos`` (m), as an odometry anchored on the INS is."""
        w_step = np.array([sigma_rot] * 3 + [sigma_pos] * 3) ** -2.0
        links = np.zeros(n)
        links[:-1] += 1.0  # the step to the next frame
        links[1:] += 1.0  # the step from the previous one
        main = np.repeat(links, 6) * np.tile(w_step, n)
        main[:6] += np.array([prior_rot] * 3 + [prior_pos] * 3) ** -2.0
        off = -np.tile(w_step, max(n - 1, 0))
        # scipy-stubs types diags' diagonals as sequences of numbers, not a list of arrays
        A = diags([main, off, off], [0, 6, -6], shape=(6 * n, 6 * n), format="csc")  # type: ignore[call-overload]
        return cls(A, n)

    def to_npz_bytes(self) -> bytes:
        """The matrix and its metadata as an .npz (no pickle)."""
        A = csc_matrix(self.matrix)
        buf = io.BytesIO()
        np.savez(
            buf, data=A.data, indices=A.indices, indptr=A.indptr,
            shape=np.array(A.shape), n_frames=np.array(self.n_frames),
            scale=np.array(self.scale),
        )  # fmt: skip
        return buf.getvalue()

    @classmethod
    def from_npz_bytes(cls, data: bytes) -> PoseInformation:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            A = csc_matrix((z["data"], z["indices"], z["indptr"]), shape=tuple(z["shape"]))
            return cls(A, int(z["n_frames"]), float(z["scale"]))


def _perturbed(T: F64, d: F64) -> F64:
    """``T`` (4, 4) with a left world rotation d[:3] about its origin and offset d[3:]."""
    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(d[:3]).as_matrix() @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + d[3:]
    return out


def anchor_pixel_jacobian(
    project: Callable[[F64, F64], F64],
    T_r: F64,
    T_i: F64,
    p_obj: F64,
    project_many: Callable[[F64, F64], F64] | None = None,
) -> F64:
    """(2, 12) derivative of the anchor's pixel in frame i with respect to
    [dtheta_r, dp_r, dtheta_i, dp_i]: the anchor is held in frame r's map
    (``q = T_r^-1 p_obj``) and seen with pose ``T_i``. ``project(p_world, T_world_base)``
    returns its (2,) pixel; ``project_many(P_world (n, 3), T_world_base)`` their (n, 2)
    pixels, when given, takes all 13 in one call (a perturbed pose ``T'`` seen as the
    point ``T_i T'^-1 p_obj`` from ``T_i``)."""
    q = np.linalg.solve(T_r, np.append(p_obj, 1.0))
    steps = np.array([STEP_ROT] * 3 + [STEP_POS] * 3)
    units = [_unit(c, steps) for c in range(6)]
    p_world = [np.asarray(p_obj, np.float64)] + [(_perturbed(T_r, d) @ q)[:3] for d in units]
    if project_many is not None:
        p_h = np.append(p_obj, 1.0)
        p_world += [(T_i @ np.linalg.solve(_perturbed(T_i, d), p_h))[:3] for d in units]
        uv = np.asarray(project_many(np.stack(p_world), T_i), np.float64)
    else:
        uv = np.stack(
            [project(p, T_i) for p in p_world] + [project(p_obj, _perturbed(T_i, d)) for d in units]
        )
    J: F64 = ((uv[1:] - uv[0]) / np.concatenate([steps, steps])[:, None]).T
    return J


def _unit(c: int, steps: F64) -> F64:
    """(6,) the perturbation of coordinate ``c`` by its step."""
    d = np.zeros(6)
    d[c] = steps[c]
    return d


def anchor_bound_px(J: F64, cov: F64, coverage: float = 0.9) -> float:
    """Radius (px) holding the anchor's pixel error with probability ``coverage``: the
    (2, 12) Jacobian ``J`` propagates the (12, 12) covariance to the pixel's (2, 2) one,
    and the radius is the ``coverage`` quantile of the length of a 2-D Gaussian error with
    that covariance (:func:`gaussian_radius_quantile`)."""
    S = J @ cov @ J.T
    lam = np.linalg.eigvalsh(0.5 * (S + S.T))
    return gaussian_radius_quantile(float(lam[1]), float(lam[0]), coverage)


#: Gauss-Legendre nodes of the radius distribution's integral (exact to ~1e-10 here).
_GL_X, _GL_W = np.polynomial.legendre.leggauss(48)
_GL_SIN, _GL_COS = np.sin(0.5 * np.pi * _GL_X), np.cos(0.5 * np.pi * _GL_X)  # [-pi/2, pi/2]
_SQRT_2PI = float(np.sqrt(2.0 * np.pi))


def _radius_cdf(r: float, s1: float, s2: float) -> float:
    """P(||e|| <= r) for e ~ N(0, diag(s1^2, s2^2)), s1 >= s2 > 0: the integral over the
    major axis' coordinate x = r sin(t) of its density times P(|e2| <= r cos(t)) (smooth
    in t up to the ends, where the integrand in x has a kink)."""
    # the standard normal's density and distribution function from numpy and
    # scipy.special directly: scipy.stats' checks took 0.4 ms a call, a fifth of a
    # sequence's placement bounds
    x, y = r * _GL_SIN, r * _GL_COS
    f = np.exp(-0.5 * (x / s1) ** 2) / (_SQRT_2PI * s1) * (2.0 * ndtr(y / s2) - 1.0) * y
    return float(0.5 * np.pi * np.sum(_GL_W * f))


def gaussian_radius_quantile(lam_major: float, lam_minor: float, coverage: float = 0.9) -> float:
    """The radius holding a zero-mean 2-D Gaussian error with variances ``lam_major`` >=
    ``lam_minor`` along its principal axes (px^2) with probability ``coverage``.

    It runs from the 1-D quantile (a flat ellipse: 1.645 sigma at 90 %) to the circular
    one (2.146 sigma at 90 %); the major axis' circular radius, which over-states a flat
    ellipse's by 1.3x, is its upper end.
    """
    lam1, lam2 = max(lam_major, 0.0), max(min(lam_minor, lam_major), 0.0)
    if lam1 <= 0.0:
        return 0.0
    s1 = float(np.sqrt(lam1))
    lo = s1 * float(ndtri(0.5 * (1.0 + coverage)))  # the major axis' error alone
    hi = s1 * float(np.sqrt(-2.0 * np.log1p(-coverage)))  # a circle of the major axis' sigma
    s2 = float(np.sqrt(lam2))
    if s2 < 1e-6 * s1:
        return lo
    f_lo, f_hi = _radius_cdf(lo, s1, s2) - coverage, _radius_cdf(hi, s1, s2) - coverage
    if f_hi <= 0.0:  # a circle (to rounding)
        return hi
    if f_lo >= 0.0:
        return lo
    return float(brentq(lambda r: _radius_cdf(r, s1, s2) - coverage, lo, hi, xtol=1e-9 * hi))
