"""The frame's own sharpness near an object, measured from its real step edges.

A rendered object with a lens model's blur is sharper or softer than the real pixels
around it whenever the real camera (optics, demosaicing, compression, focus) differs from
the model. :func:`estimate_blur_sigma` measures the Gaussian blur of the frame's step
edges around the object, so the composite can give the object that blur.

What is measured: the standard deviation of the frame's edge spread, as the pixels hold
it, so a pixel's own integration (a 1-px box, variance 1/12 px^2) is part of it: a scene
blurred by a Gaussian of ``s`` px and integrated over the pixels reads
``sqrt(s^2 + 1/12)``.

Method (Zhuo & Sim 2011, "Defocus map estimation from a single image", Pattern
Recognition 44(9), the re-blur gradient ratio): a step edge blurred by a Gaussian of
sigma, differentiated with a derivative-of-Gaussian of ``DERIV_SIGMA_PX`` (sd), has the
gradient peak ``A / sqrt(2 pi (sigma^2 + sd^2))``; re-blurred by ``REBLUR_SIGMA_PX``
(s0) first, ``A / sqrt(2 pi (sigma^2 + sd^2 + s0^2))``. Their ratio R gives

    sigma^2 = s0^2 / (R^2 - 1) - sd^2,

independent of the edge's contrast and direction. Per window (luma, 8-bit):

1. candidate pixels: Canny (non-maximum suppression and hysteresis) on the
   derivative-of-Gaussian gradient itself, so its thresholds are in the units they are
   computed in: the high one ``CANNY_HIGH`` times the gradient's noise std (from the
   window's pixel noise, Immerkaer's estimate over at most ``NOISE_MAX_PIXELS``) and at
   least the peak of a ``MIN_CONTRAST`` step blurred to ``MAX_SIGMA_PX``; outside the
   excluded pixels (the object grown by ``EXCLUDE_GROW_PX``) and away from the window's
   border; of those
   across the motion (step 4, tested first), at most ``MAX_CANDIDATES`` (an even stride
   through them: a cap taken before the direction test left a large textured window
   with too few edges across a vertical motion, and the lens model's blur instead);
2. only *isolated step edges* among them (:func:`renderer.sensor_noise.step_profiles`:
   a profile along the gradient of +-``STEP_HALF_PX`` with flat ends at least
   ``MIN_CONTRAST`` apart and no fall-back): texture (ballast, vegetation), noise and
   thin lines have the far side of their profile within reach and read sharper than the
   camera's blur; they are left out instead of outvoted;
3. both gradient magnitudes at the edge's sub-pixel peak: a Gaussian profile's logarithm
   is a parabola, so the vertex of the parabola through the pixel and its two
   neighbours along the gradient's main axis is the exact peak wherever the edge lies
   between pixels (the pixel's own value under-reads the narrower profile more, and
   small blurs would read larger);
4. only edges whose gradient direction is within 60 degrees of perpendicular to
   ``motion_uv`` (when given): their profile is not smeared by the motion blur the
   composite applies separately (no double blur);
5. the median of the per-edge sigma^2 (clipped at 0) over at least ``MIN_EDGE_PIXELS``.

A window larger than ``BLUR_MAX_PIXELS`` (a fallen tree 30 m ahead of rgb_highres_center:
2.6 Mpx) is measured on every k-th band of ``BLUR_BAND_ROWS`` rows (k the smallest that
brings it under the cap), the bands stacked and the rows near their joins left out like
the object: the same median from a third of the pixels, whose candidates are capped at
``MAX_CANDIDATES`` anyway.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
from numpy.typing import NDArray

from renderer.sensor_noise import band_rows, robust_sigma, step_profiles

log = logging.getLogger(__name__)

DERIV_SIGMA_PX = 1.0
REBLUR_SIGMA_PX = 1.5
CANNY_HIGH = 6.0
CANNY_LOW = 3.0
MIN_CONTRAST = 20.0
EXCLUDE_GROW_PX = 6
MIN_EDGE_PIXELS = 40
MAX_SIGMA_PX = 3.0
MAX_CANDIDATES = 4000
#: Pixels the window's noise level (the Canny thresholds) is read from at most.
NOISE_MAX_PIXELS = 300_000
#: A larger window is measured on every k-th band of BLUR_BAND_ROWS rows (module doc).
BLUR_MAX_PIXELS = 1_000_000
BLUR_BAND_ROWS = 96
#: Rows each side of a join of two bands left out, grown by EXCLUDE_GROW_PX: the filters
#: (re-blur and gradient, 10 px) and the profiles (9 px) of an edge stay inside its band.
JOIN_PX = 6
STEP_HALF_PX = 6.0
STRAIGHT_PX = 3.0
STRAIGHT_TOL_PX = 0.5
_BORDER_PX = 8
_CANNY_SCALE = 16.0  # gradient units -> int16 for cv2.Canny


F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


def _dog_kernels(sigma: float) -> tuple[F32, F32]:
    """(Gaussian, derivative-of-Gaussian) 1-D kernels of ``sigma`` px, the derivative
    with a unit response to a unit ramp."""
    k = int(2 * np.ceil(4.0 * sigma) + 1)
    x = np.arange(k, dtype=np.float64) - k // 2
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    dg = -x / sigma**2 * g
    dg -= dg.mean()
    dg /= -np.sum(x * dg)
    return g.astype(np.float32), dg.astype(np.float32)


def _gradient(img: F32, sigma: float) -> tuple[F32, F32]:
    """(d/du, d/dv) (H, W) of ``G_sigma * img`` (H, W) by Gaussian-derivative filters (px).
    The magnitude is read only where it is needed (:func:`subpixel_peak`)."""
    g, dg = _dog_kernels(sigma)
    rep = cv2.BORDER_REPLICATE
    gx = np.asarray(cv2.sepFilter2D(img, cv2.CV_32F, dg, g, borderType=rep), np.float32)
    gy = np.asarray(cv2.sepFilter2D(img, cv2.CV_32F, g, dg, borderType=rep), np.float32)
    return gx, gy


def _gradient_noise_gain(sigma: float) -> float:
    """Std of one gradient component of unit white noise (the filters' L2 norms)."""
    g, dg = _dog_kernels(sigma)
    return float(np.sqrt(np.sum(g.astype(np.float64) ** 2) * np.sum(dg.astype(np.float64) ** 2)))


def candidate_pixels(
    gray: F32,
    gx: F32,
    gy: F32,
    exclude: NDArray[np.bool_] | None,
    noise_rows: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """Edge candidates of a luma window (module docstring, step 1): Canny on ``gx``, ``gy``
    (the window's gradient at ``DERIV_SIGMA_PX``); the pixel noise read on the rows
    ``noise_rows`` (default all: stacked bands leave their joins out)."""
    mask = None
    if noise_rows is not None:
        mask = np.repeat(np.asarray(noise_rows, bool)[:, None], gray.shape[1], axis=1)
    pixel_noise = robust_sigma(gray, mask, max_pixels=NOISE_MAX_PIXELS)
    pixel_noise = pixel_noise if np.isfinite(pixel_noise) else 0.0
    noise = pixel_noise * _gradient_noise_gain(DERIV_SIGMA_PX)
    weakest = MIN_CONTRAST / np.sqrt(2.0 * np.pi * (MAX_SIGMA_PX**2 + DERIV_SIGMA_PX**2))
    hi = max(CANNY_HIGH * noise, weakest)
    lo = max(CANNY_LOW * noise, 0.5 * weakest)
    dx = np.clip(np.round(gx * _CANNY_SCALE), -32767, 32767).astype(np.int16)
    dy = np.clip(np.round(gy * _CANNY_SCALE), -32767, 32767).astype(np.int16)
    edges = cv2.Canny(dx, dy, lo * _CANNY_SCALE, hi * _CANNY_SCALE, L2gradient=True)
    keep = np.zeros(gray.shape, bool)
    b = _BORDER_PX
    keep[b:-b, b:-b] = True
    if exclude is not None:
        k = 2 * EXCLUDE_GROW_PX + 1
        grown = cv2.dilate(exclude.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        keep &= ~grown
    return np.asarray(edges, bool) & keep


def subpixel_peak(
    gx: F32,
    gy: F32,
    vs: NDArray[np.intp],
    us: NDArray[np.intp],
    horizontal: NDArray[np.bool_],
) -> F64:
    """(n,) peak of the gradient magnitude ``|(gx, gy)|`` (H, W each) through pixels
    (vs, us) along u (``horizontal``) or v: the vertex of the parabola through the
    logarithms of the pixel and its two neighbours (exact for a Gaussian profile); NaN
    where the three are not concave. The magnitude (float32, as ``np.hypot`` of the whole
    images gives it) is computed at those 3n pixels only."""
    du = horizontal.astype(np.intp)
    dv = 1 - du
    eps = 1e-6

    def log_mag(v: NDArray[np.intp], u: NDArray[np.intp]) -> F64:
        return np.log(np.maximum(np.hypot(gx[v, u], gy[v, u]).astype(np.float64), eps))

    c = log_mag(vs, us)
    a = log_mag(vs - dv, us - du)
    b = log_mag(vs + dv, us + du)
    curv = a - 2.0 * c + b
    with np.errstate(divide="ignore", invalid="ignore"):
        off = 0.5 * (a - b) / curv
        peak = c - 0.25 * (a - b) * off
    ok = (curv < 0) & (np.abs(off) <= 1.0)
    return np.where(ok, np.exp(peak), np.nan)


def straight_steps(gray: F32, points: F64, normals: F64) -> NDArray[np.intp]:
    """Indices of ``points`` (n, 2) (u, v) that are straight isolated step edges across
    their unit ``normals`` (n, 2) (module docstring, step 2): the profile through the
    point and those through the points ``STRAIGHT_PX`` to either side along the edge are
    all steps (:func:`renderer.sensor_noise.step_profiles`), crossing their midpoint
    within ``STRAIGHT_TOL_PX`` of one another."""
    n = len(points)
    tangent = np.stack([-normals[:, 1], normals[:, 0]], 1)
    shifted = [points, points + STRAIGHT_PX * tangent, points - STRAIGHT_PX * tangent]
    t, idx, env = step_profiles(
        gray, np.concatenate(shifted), np.concatenate([normals] * 3), STEP_HALF_PX, MIN_CONTRAST
    )
    mid = np.full(3 * n, np.nan)
    if len(idx):
        first = np.argmax(env >= 0.5, axis=1)  # env is monotone, 0 -> 1
        k = np.clip(first, 1, len(t) - 1)
        e0, e1 = env[np.arange(len(idx)), k - 1], env[np.arange(len(idx)), k]
        mid[idx] = t[k - 1] + (0.5 - e0) / np.maximum(e1 - e0, 1e-9) * (t[k] - t[k - 1])
    c, a, b = mid[:n], mid[n : 2 * n], mid[2 * n :]
    with np.errstate(invalid="ignore"):
        ok = (np.abs(a - c) <= STRAIGHT_TOL_PX) & (np.abs(b - c) <= STRAIGHT_TOL_PX)
    return np.flatnonzero(ok)


def estimate_blur_sigma(
    frame_rgb: NDArray[np.uint8],
    window: tuple[int, int, int, int],
    exclude: NDArray[np.bool_] | None = None,
    motion_uv: tuple[float, float] | None = None,
) -> float | None:
    """Edge spread sigma (px, pixel integration included) of the frame's isolated step
    edges in ``window`` (u0, v0, u1, v1), without the ``exclude`` pixels (a mask of the
    window's shape: the object), only edges across ``motion_uv`` (px, the image motion)
    when given (module docstring). None: fewer than ``MIN_EDGE_PIXELS`` such edges."""
    u0, v0, u1, v1 = window
    sub = np.asarray(frame_rgb)[v0:v1, u0:u1]
    if sub.shape[0] < 3 * _BORDER_PX or sub.shape[1] < 3 * _BORDER_PX:
        return None
    rows = band_rows(v1 - v0, u1 - u0, BLUR_MAX_PIXELS, BLUR_BAND_ROWS)
    noise_rows = None
    if len(rows) < v1 - v0:  # a large window: its bands stacked, no edge read near a join
        sub = sub[rows]
        exclude = (np.zeros(sub.shape[:2], bool) if exclude is None
                   else np.asarray(exclude, bool)[rows])  # fmt: skip
        noise_rows = np.ones(len(rows), bool)
        for j in np.flatnonzero(np.diff(rows) > 1):
            exclude[max(j - JOIN_PX + 1, 0) : j + JOIN_PX + 1] = True
            noise_rows[max(j - 1, 0) : j + 3] = False  # the noise operator's 3 x 3
    gray = cv2.cvtColor(np.ascontiguousarray(sub), cv2.COLOR_RGB2GRAY).astype(np.float32)
    gx, gy = _gradient(gray, DERIV_SIGMA_PX)
    vs, us = np.nonzero(candidate_pixels(gray, gx, gy, exclude, noise_rows))
    ex, ey = gx[vs, us].astype(np.float64), gy[vs, us].astype(np.float64)
    mag = np.maximum(np.hypot(ex, ey), 1e-9)
    normals = np.stack([ex / mag, ey / mag], 1)
    if motion_uv is not None and np.hypot(*motion_uv) >= 0.5:
        d = np.asarray(motion_uv, np.float64) / np.hypot(*motion_uv)
        across = np.abs(normals @ d) < 0.5
        vs, us, normals = vs[across], us[across], normals[across]
    if len(vs) > MAX_CANDIDATES:  # the cap after the direction test: it bounds the work
        pick = np.linspace(0, len(vs) - 1, MAX_CANDIDATES).astype(np.intp)
        vs, us, normals = vs[pick], us[pick], normals[pick]
    if len(vs) < MIN_EDGE_PIXELS:
        return None
    pts = np.stack([us, vs], 1).astype(np.float64)
    steps = straight_steps(gray, pts, normals)
    if len(steps) < MIN_EDGE_PIXELS:
        log.debug("frame blur: %d step edges of %d candidates", len(steps), len(vs))
        return None
    vs, us, normals = vs[steps], us[steps], normals[steps]
    re = np.asarray(
        cv2.GaussianBlur(gray, (0, 0), REBLUR_SIGMA_PX, borderType=cv2.BORDER_REPLICATE),
        np.float32,
    )
    gx2, gy2 = _gradient(re, DERIV_SIGMA_PX)
    horizontal = np.abs(normals[:, 0]) >= np.abs(normals[:, 1])
    p1 = subpixel_peak(gx, gy, vs, us, horizontal)
    p2 = subpixel_peak(gx2, gy2, vs, us, horizontal)
    R2 = (p1 / p2) ** 2
    R2 = R2[np.isfinite(R2)]
    if len(R2) < MIN_EDGE_PIXELS:
        return None
    s0, sd = REBLUR_SIGMA_PX, DERIV_SIGMA_PX
    s2 = np.where(R2 > 1.0, s0**2 / np.maximum(R2 - 1.0, 1e-9) - sd**2, np.inf)
    sigma = float(np.sqrt(max(float(np.median(s2)), 0.0)))
    log.debug("frame blur: %d step edges, sigma %.2f px", len(R2), sigma)
    return min(sigma, MAX_SIGMA_PX)
