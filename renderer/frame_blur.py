"""The frame's own sharpness near an object, measured from its real edges.

A rendered object with a lens model's blur is sharper or softer than the real pixels
around it whenever the real camera (optics, demosaicing, compression, focus) differs from
the model. :func:`estimate_blur_sigma` measures the Gaussian blur of the frame's strong
edges around the object, so the composite can give the object that blur.

Method (Zhuo & Sim 2011, "Defocus map estimation from a single image", Pattern
Recognition 44(9), the re-blur gradient ratio): a step edge blurred by a Gaussian of
sigma, differentiated with a derivative-of-Gaussian of ``DERIV_SIGMA_PX`` (sd), has the
gradient peak ``A / sqrt(2 pi (sigma^2 + sd^2))``; re-blurred by ``REBLUR_SIGMA_PX``
(s0) first, ``A / sqrt(2 pi (sigma^2 + sd^2 + s0^2))``. Their ratio R gives

    sigma^2 = s0^2 / (R^2 - 1) - sd^2,

independent of the edge's contrast and direction. Per window (luma, 8-bit):

1. edge pixels: Canny edges (thresholds from the window's noise: ``CANNY_LOW`` /
   ``CANNY_HIGH`` times the gradient magnitude's median absolute deviation, at least
   ``MIN_CONTRAST`` levels) outside the excluded pixels (the object grown by
   ``EXCLUDE_GROW_PX``) and away from the window's border;
2. both gradient magnitudes are taken as their maximum in the pixel's 3 x 3 neighbourhood
   (the peak lies within half a pixel of a Canny pixel);
3. only edges whose gradient direction is within 60 degrees of perpendicular to
   ``motion_uv`` (when given): their profile is not smeared by the motion blur the
   composite applies separately (no double blur);
4. the median of the per-pixel sigmas (clipped at 0) over at least ``MIN_EDGE_PIXELS``.

What is measured is the blur of *step* edges; thin lines and texture read sharper, and
the median keeps them a minority where the frame has real object outlines. Pixel
integration (a 1-px box, variance 1/12 px^2) is part of the measured blur.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

DERIV_SIGMA_PX = 1.0
REBLUR_SIGMA_PX = 1.5
CANNY_LOW = 6.0
CANNY_HIGH = 12.0
MIN_CONTRAST = 20.0
EXCLUDE_GROW_PX = 6
MIN_EDGE_PIXELS = 40
MAX_SIGMA_PX = 8.0
_BORDER_PX = 8


F32 = NDArray[np.float32]


def _gradient_magnitude(img: F32, sigma: float) -> tuple[F32, F32, F32]:
    """(|grad|, d/du, d/dv) of ``G_sigma * img`` by Gaussian-derivative filters (px)."""
    k = int(2 * np.ceil(4.0 * sigma) + 1)
    x = np.arange(k, dtype=np.float64) - k // 2
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    dg = -x / sigma**2 * g
    dg -= dg.mean()
    dg /= -np.sum(x * dg)  # unit response to a unit ramp
    g32, dg32 = g.astype(np.float32), dg.astype(np.float32)
    rep = cv2.BORDER_REPLICATE
    gx = np.asarray(cv2.sepFilter2D(img, cv2.CV_32F, dg32, g32, borderType=rep), np.float32)
    gy = np.asarray(cv2.sepFilter2D(img, cv2.CV_32F, g32, dg32, borderType=rep), np.float32)
    return np.hypot(gx, gy).astype(np.float32), gx, gy


def edge_pixels(
    gray: NDArray[np.float32], mag: NDArray[np.float32], exclude: NDArray[np.bool_] | None
) -> NDArray[np.bool_]:
    """Strong step-edge pixels of a luma window (module docstring, step 1); ``mag``: its
    gradient magnitude at ``DERIV_SIGMA_PX``."""
    mad = float(np.median(np.abs(mag - np.median(mag))))
    lo = max(CANNY_LOW * mad, MIN_CONTRAST / 4.0)
    hi = max(CANNY_HIGH * mad, MIN_CONTRAST / 2.0)
    g8 = np.clip(np.round(gray), 0, 255).astype(np.uint8)
    edges = cv2.Canny(g8, lo, hi, L2gradient=True).astype(bool) & (mag >= hi / 8.0)
    keep = np.zeros_like(edges)
    b = _BORDER_PX
    keep[b:-b, b:-b] = True
    if exclude is not None:
        k = 2 * EXCLUDE_GROW_PX + 1
        grown = cv2.dilate(exclude.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        keep &= ~grown
    return edges & keep


def estimate_blur_sigma(
    frame_rgb: NDArray[np.uint8],
    window: tuple[int, int, int, int],
    exclude: NDArray[np.bool_] | None = None,
    motion_uv: tuple[float, float] | None = None,
) -> float | None:
    """Gaussian blur sigma (px) of the frame's step edges in ``window`` (u0, v0, u1, v1),
    without the ``exclude`` pixels (a mask of the window's shape: the object), only
    edges across ``motion_uv`` (px, the image motion) when given. None: fewer than
    ``MIN_EDGE_PIXELS`` edge pixels."""
    u0, v0, u1, v1 = window
    sub = np.asarray(frame_rgb)[v0:v1, u0:u1]
    if sub.shape[0] < 3 * _BORDER_PX or sub.shape[1] < 3 * _BORDER_PX:
        return None
    gray = cv2.cvtColor(np.ascontiguousarray(sub), cv2.COLOR_RGB2GRAY).astype(np.float32)
    m1, gx, gy = _gradient_magnitude(gray, DERIV_SIGMA_PX)
    edges = edge_pixels(gray, m1, exclude)
    if edges.sum() < MIN_EDGE_PIXELS:
        return None
    re = np.asarray(
        cv2.GaussianBlur(gray, (0, 0), REBLUR_SIGMA_PX, borderType=cv2.BORDER_REPLICATE),
        np.float32,
    )
    m2, _, _ = _gradient_magnitude(re, DERIV_SIGMA_PX)
    k3 = np.ones((3, 3), np.uint8)
    p1, p2 = cv2.dilate(m1, k3)[edges], cv2.dilate(m2, k3)[edges]
    if motion_uv is not None and np.hypot(*motion_uv) >= 0.5:
        d = np.asarray(motion_uv, np.float64) / np.hypot(*motion_uv)
        cos = np.abs(gx[edges] * d[0] + gy[edges] * d[1]) / np.maximum(m1[edges], 1e-9)
        across = cos < 0.5
        p1, p2 = p1[across], p2[across]
        if len(p1) < MIN_EDGE_PIXELS:
            return None
    R2 = (p1 / np.maximum(p2, 1e-9)) ** 2
    s0, sd = REBLUR_SIGMA_PX, DERIV_SIGMA_PX
    with np.errstate(divide="ignore"):
        s2 = np.where(R2 > 1.0, s0**2 / np.maximum(R2 - 1.0, 1e-9) - sd**2, np.inf)
    sigma = float(np.sqrt(max(float(np.median(s2)), 0.0)))
    log.debug("frame blur: %d edge pixels, sigma %.2f px", len(p1), sigma)
    return min(sigma, MAX_SIGMA_PX)
