"""The camera's own noise: measured in a frame, given to the rendered object.

A rendered object is noise-free; the real pixels around it are not, and a detector can
learn that tell. :func:`estimate_noise` measures the frame's noise per channel as a
function of intensity (sensor noise grows with the signal: shot noise) in flat regions
near the object; :func:`add_noise` draws noise of that level for the object's pixels.

Estimator (Immerkaer 1996, robust form): the 3 x 3 operator
``N = [[1, -2, 1], [-2, 4, -2], [1, -2, 1]]`` (the difference of two Laplacians) cancels
constant and linear image structure; on white noise of std sigma its response has std
6 sigma. Per pixel of the window (8-bit sRGB values, the frame's own encoding):

1. ``r = |N * I|`` and the local level ``m`` = 5 x 5 mean of ``I``;
2. *flat* pixels: the gradient magnitude of the 3 x 3-smoothed channel below its
   ``FLAT_PERCENTILE`` percentile in the window (edges and strong texture left out);
   pixels of the object (and their 2 px surround) are excluded;
3. per intensity bin (``BIN_EDGES``, 8-bit levels), with at least ``MIN_BIN_SAMPLES``
   flat pixels: ``sigma = 1.4826 * median(r) / 6`` (the median makes the texture that
   is left a minority that does not count). Bins without enough samples take the value
   of the nearest bins (linear interpolation in the level, constant beyond the ends).

A window larger than ``MAX_PIXELS`` (a large object near the camera: 1.5 Mpx around a
fallen tree 30 m ahead of rgb_highres_center) is measured on every k-th band of
``BAND_ROWS`` rows only (k the smallest that brings it under the cap), each band's edge
rows left out like the object's surround: the same statistics from a few hundred
thousand pixels at a fraction of the filters' cost.

What is not modelled: the noise's spatial correlation (demosaicing and compression make
real noise somewhat blotchy; the object gets white noise of the measured per-pixel
level) and the correlation between channels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

BIN_EDGES = np.array([0, 24, 48, 80, 112, 144, 176, 208, 256], np.float64)
MIN_BIN_SAMPLES = 150
MIN_SAMPLES = 400
#: Pixels of a window measured in full; above, every k-th band of BAND_ROWS rows.
MAX_PIXELS = 300_000
BAND_ROWS = 32
FLAT_PERCENTILE = 50.0
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_MAD_TO_SIGMA = 1.4826 / 6.0


@dataclass(frozen=True)
class NoiseProfile:
    """Noise std (8-bit units) per channel at intensity levels.

    levels : (k,) bin centres (8-bit values); sigma : (3, k) std per channel there;
    samples : flat pixels the estimate used.
    """

    levels: F64
    sigma: F64
    samples: int

    def sigma_at(self, values: F64) -> F64:
        """(n, 3) noise std at the 8-bit values (n, 3), per channel."""
        v = np.asarray(values, np.float64).reshape(-1, 3)
        return np.stack([np.interp(v[:, c], self.levels, self.sigma[c]) for c in range(3)], 1)

    def sigma_table(self) -> NDArray[np.float32]:
        """(256, 3) noise std at each 8-bit level, per channel (:meth:`sigma_at`)."""
        lv = np.repeat(np.arange(256, dtype=np.float64)[:, None], 3, axis=1)
        return self.sigma_at(lv).astype(np.float32)


def immerkaer_response(channel: NDArray[np.float32]) -> NDArray[np.float32]:
    """|N * I| (same size; the border replicated) of one channel."""
    return np.abs(cv2.filter2D(channel, cv2.CV_32F, _IMMERKAER, borderType=cv2.BORDER_REPLICATE))


def robust_sigma(
    channel: NDArray, mask: NDArray[np.bool_] | None = None, max_pixels: int | None = None
) -> float:
    """Noise std of one channel over ``mask`` (all pixels when None): ``1.4826 *
    median(|N * I|) / 6``; pixels whose 3 x 3 neighbourhood leaves the mask are left out.
    With ``max_pixels``, a larger channel is measured on every k-th band of
    ``BAND_ROWS`` rows only (as :func:`estimate_noise`; the median of 2.6 Mpx took 55 ms,
    a fifth of a large object's blur estimate, for a precision a few hundred thousand
    pixels give as well). NaN when fewer than 9 pixels remain."""
    c = np.asarray(channel, np.float32)
    ok = np.ones(c.shape, np.uint8) if mask is None else np.asarray(mask, np.uint8)
    if max_pixels is not None and c.size > max_pixels:  # bands of rows, as estimate_noise
        rows = band_rows(*c.shape[:2], max_pixels)
        c, ok = c[rows], ok[rows]
        edge = np.flatnonzero(np.diff(rows) > 1)  # rows whose operator sees two bands
        ok[np.concatenate([edge, edge + 1])] = 0
    r = immerkaer_response(np.ascontiguousarray(c))
    ok = cv2.erode(ok, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                   borderValue=0).astype(bool)  # fmt: skip
    if ok.sum() < 9:
        return float("nan")
    return float(_MAD_TO_SIGMA * np.median(r[ok]))


def band_rows(
    h: int, w: int, max_pixels: int = MAX_PIXELS, band: int = BAND_ROWS
) -> NDArray[np.int64]:
    """(r,) the window rows :func:`estimate_noise` measures: all of them up to
    ``max_pixels``, else every k-th band of ``band`` rows, k the smallest that keeps at
    most ``max_pixels`` (one band at least)."""
    rows = np.arange(h)
    if h * w <= max_pixels:
        return rows
    k = int(np.ceil(h * w / max_pixels))
    while True:
        sel = rows[(rows // band) % k == 0]
        if len(sel) * w <= max_pixels or len(sel) <= band:
            return sel
        k += 1


def estimate_noise(
    frame_rgb: NDArray[np.uint8],
    window: tuple[int, int, int, int],
    exclude: NDArray[np.bool_] | None = None,
) -> NoiseProfile | None:
    """The frame's noise in ``window`` (u0, v0, u1, v1), without the ``exclude`` pixels
    (a mask of the window's shape: the object). None: too few flat pixels."""
    u0, v0, u1, v1 = window
    rows = band_rows(v1 - v0, u1 - u0)
    img = np.asarray(frame_rgb)[v0:v1, u0:u1][rows].astype(np.float32)
    if img.shape[0] < 8 or img.shape[1] < 8:
        return None
    keep = np.ones(img.shape[:2], np.uint8)
    if exclude is not None:
        keep[np.asarray(exclude, bool)[rows]] = 0
    if len(rows) < v1 - v0:  # the bands' first and last rows: their filters see two bands
        edge = np.flatnonzero(np.diff(rows) > 1)
        keep[np.concatenate([edge, edge + 1])] = 0
    # the operator's 3 x 3 support and the 5 x 5 level must not touch excluded pixels
    keep = cv2.erode(keep, np.ones((7, 7), np.uint8), borderType=cv2.BORDER_CONSTANT,
                     borderValue=0).astype(bool)  # fmt: skip
    if keep.sum() < MIN_SAMPLES:
        return None
    levels = 0.5 * (BIN_EDGES[:-1] + BIN_EDGES[1:])
    sig = np.full((3, len(levels)), np.nan)
    n_used = 0
    for c in range(3):
        ch = np.ascontiguousarray(img[..., c])
        r = immerkaer_response(ch)
        m = cv2.blur(ch, (5, 5), borderType=cv2.BORDER_REPLICATE)
        sm = cv2.GaussianBlur(ch, (3, 3), 0.8)
        # sqrt(gx^2 + gy^2) in float32: np.hypot's libm hypotf took 3 ms a 115k-px channel
        g = cv2.magnitude(
            cv2.Sobel(sm, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(sm, cv2.CV_32F, 0, 1, ksize=3)
        )
        flat = keep & (g <= np.percentile(g[keep], FLAT_PERCENTILE))
        rv, mv = r[flat], m[flat]
        n_used = max(n_used, int(flat.sum()))
        idx = np.clip(np.searchsorted(BIN_EDGES, mv, side="right") - 1, 0, len(levels) - 1)
        for k in range(len(levels)):
            sel = idx == k
            if sel.sum() >= MIN_BIN_SAMPLES:
                sig[c, k] = _MAD_TO_SIGMA * float(np.median(rv[sel]))
        good = np.isfinite(sig[c])
        if not good.any():
            if len(rv) < MIN_SAMPLES:
                return None
            sig[c] = _MAD_TO_SIGMA * float(np.median(rv))
        else:
            sig[c] = np.interp(levels, levels[good], sig[c, good])
    return NoiseProfile(levels, sig, n_used)


def add_noise(values: F64, weight: F64, profile: NoiseProfile, rng: np.random.Generator) -> F64:
    """8-bit values (n, 3) with the profile's noise at their level (the nearest 8-bit
    level's: :meth:`NoiseProfile.sigma_table`, a profile that changes by a fraction of a
    level's std from one level to the next; the interpolation per value took 55 ms of a
    large object's 0.4 s composite), scaled by ``weight`` (n,) in [0, 1] (the share of
    the pixel that is noise-free: the object's coverage after blending, see
    :func:`noise_weight`). Not rounded, not clipped."""
    v = np.asarray(values, np.float64).reshape(-1, 3)
    level = np.clip(np.rint(v), 0, 255).astype(np.uint8)
    table = profile.sigma_table()
    s = np.empty(v.shape, np.float32)
    for c in range(3):  # a 256-entry table per channel (faster than one 2-D fancy index)
        s[:, c] = np.take(np.ascontiguousarray(table[:, c]), level[:, c])
    s *= np.asarray(weight, np.float32).reshape(-1, 1)
    noise = rng.standard_normal(v.shape, dtype=np.float32)
    noise *= s
    return v + noise


def noise_weight(alpha: F64) -> F64:
    """Std factor of the noise to add where the object covers ``alpha`` of a pixel: the
    real background brings ``(1 - alpha)`` of its own noise, so ``sqrt(1 - (1 - a)^2)``
    completes the variance to the frame's."""
    a = np.clip(np.asarray(alpha, np.float64), 0.0, 1.0)
    return np.sqrt(np.clip(1.0 - (1.0 - a) ** 2, 0.0, 1.0))


# ---------------------------------------------------------------------------- sharpness
_RISE_TO_SIGMA = 2.0 * 1.2815515655446004  # 10-90 % rise of a Gaussian-blurred step
STEP_FLAT = 0.12  # a step's two ends: std at most this share of its contrast
STEP_MONOTONE = 0.15  # ... and its profile within this share of its rising envelope
SIDE_PX, SIDE_CONTRAST = 2.0, 0.6  # a silhouette edge: coverage differs this much 2 px across


def edge_sigma_px(
    gray: NDArray, points: F64, normals: F64, *, half_px: float = 6.0, min_contrast: float = 20.0
) -> F64:
    """Blur (Gaussian sigma, px) of step edges: at each point (n, 2) (u, v), the profile
    along its unit normal (n, 2) over +-``half_px`` is read (bilinear), its ends (1/8 of
    it each) give the two levels, and the 10-90 % rise distance / 2.563 is the sigma.
    NaN for what is not a step: contrast below ``min_contrast``, an end not flat (std
    above ``STEP_FLAT`` x the contrast: texture, shading) or a profile that falls back
    (more than ``STEP_MONOTONE`` of the contrast below its running maximum: a thin line
    or limb, whose far side lies within the profile)."""
    t, idx, env = step_profiles(gray, points, normals, half_px, min_contrast)
    out = np.full(len(np.asarray(points).reshape(-1, 2)), np.nan)
    t10 = np.array([np.interp(0.1, fi, t) for fi in env])
    t90 = np.array([np.interp(0.9, fi, t) for fi in env])
    out[idx] = (t90 - t10) / _RISE_TO_SIGMA
    return out


#: Rows per ``cv2.remap`` call: OpenCV's maps are limited to 32767 rows and columns.
REMAP_ROWS = 32000


def remap_rows(
    image: NDArray,
    mx: NDArray[np.float32],
    my: NDArray[np.float32],
    border: int = cv2.BORDER_CONSTANT,
) -> NDArray[np.float32]:
    """``cv2.remap`` (bilinear) of ``image`` at maps ``mx``, ``my`` (n, T), n unbounded:
    in blocks of :data:`REMAP_ROWS` rows (a ring of many edge pixels exceeds OpenCV's
    limit)."""
    src = np.asarray(image, np.float32)
    out = np.empty(mx.shape, np.float32)
    for i in range(0, len(mx), REMAP_ROWS):
        out[i : i + REMAP_ROWS] = cv2.remap(
            src, mx[i : i + REMAP_ROWS], my[i : i + REMAP_ROWS], cv2.INTER_LINEAR,
            borderMode=border,
        )  # fmt: skip
    return out


def step_profiles(
    gray: NDArray, points: F64, normals: F64, half_px: float = 6.0, min_contrast: float = 20.0
) -> tuple[NDArray[np.float32], NDArray[np.int64], F64]:
    """The step edges among ``points`` (n, 2) (:func:`edge_sigma_px`'s tests): (t (T,)
    offsets along the normal px, idx (m,) the points that are steps, env (m, T) their
    profiles' rising envelopes, 0 -> 1 across the edge)."""
    g = np.asarray(gray, np.float32)
    t = np.arange(-half_px, half_px + 1e-9, 0.25, dtype=np.float32)
    p = np.asarray(points, np.float32).reshape(-1, 2)
    if len(p) == 0:
        return t, np.zeros(0, np.int64), np.zeros((0, len(t)))
    n = np.asarray(normals, np.float32)
    mx = (p[:, 0:1] + t[None] * n[:, 0:1]).astype(np.float32)
    my = (p[:, 1:2] + t[None] * n[:, 1:2]).astype(np.float32)
    prof = remap_rows(g, mx, my, cv2.BORDER_REPLICATE).astype(np.float64)
    k = max(len(t) // 8, 2)
    lo, hi = prof[:, :k].mean(1), prof[:, -k:].mean(1)
    c = hi - lo
    ok = np.abs(c) >= min_contrast
    ok &= np.maximum(prof[:, :k].std(1), prof[:, -k:].std(1)) <= STEP_FLAT * np.abs(c)
    f = np.clip((prof[ok] - lo[ok, None]) / c[ok, None], 0.0, 1.0)  # 0 -> 1 across the edge
    env = np.maximum.accumulate(f, axis=1)  # monotonic envelope
    step = (env - f).max(axis=1) <= STEP_MONOTONE
    return t, np.flatnonzero(ok)[step], env[step]


def silhouette_band(coverage: NDArray[np.float32]) -> NDArray[np.bool_]:
    """(H, W) pixels next to where ``coverage`` (H, W) crosses 0.5: inside pixels with an
    outside 8-neighbour and the reverse (both sides of the line, whatever its direction;
    a band ``|coverage - 0.5| < t`` misses a binary mask's straight edges, where the
    smoothed values sit at 0.3 / 0.7)."""
    inside = (np.asarray(coverage) >= 0.5).astype(np.uint8)
    k3 = np.ones((3, 3), np.uint8)
    return np.asarray(cv2.dilate(inside, k3) != cv2.erode(inside, k3), bool)


def sharpness_inside_outside(
    out_rgb: NDArray[np.uint8],
    roi: tuple[int, int, int, int],
    alpha: NDArray,
    ring_px: int = 48,
    real_rgb: NDArray[np.uint8] | None = None,
) -> tuple[float, float]:
    """(median edge sigma of the object's silhouette, median edge sigma of the real
    edges in a ring of ``ring_px`` around it) in the composited frame, px; NaN where
    fewer than 10 edges qualified. Both sides are measured alike: Canny edges of the
    frame, profiles along the image gradient (:func:`edge_sigma_px`, step edges only).
    Silhouette edges: those next to where the coverage ``alpha`` (the ROI's; a binary
    mask will do), smoothed by a Gaussian of 1 px, crosses 0.5, with the object on one
    side and the background on the other (coverage differing by ``SIDE_CONTRAST``
    ``SIDE_PX`` to either side); real edges: those outside the object's mask grown by
    7 px, read in ``real_rgb`` (the frame before the object was added) when given: in the
    composited frame the ring also holds the object's own shadow, whose edges are not the
    camera's."""
    H, W = np.asarray(out_rgb).shape[:2]
    u0, v0, u1, v1 = roi
    a = np.zeros((H, W), np.float32)
    a[v0:v1, u0:u1] = alpha
    a_s = cv2.GaussianBlur(a, (5, 5), 1.0)
    silhouette = silhouette_band(a_s)
    obj = (a > 0.02).astype(np.uint8)
    near = cv2.dilate(obj, np.ones((2 * ring_px + 1,) * 2, np.uint8)).astype(bool)
    away = ~cv2.dilate(obj, np.ones((15, 15), np.uint8)).astype(bool)

    def edges(rgb: NDArray[np.uint8]) -> tuple[F32, NDArray[np.bool_], F32, F32]:
        gray = cv2.cvtColor(np.asarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float32)
        canny = cv2.Canny(np.clip(gray, 0, 255).astype(np.uint8), 40, 100).astype(bool)
        sm = cv2.GaussianBlur(gray, (5, 5), 1.0)
        return gray, canny, cv2.Sobel(sm, cv2.CV_32F, 1, 0), cv2.Sobel(sm, cv2.CV_32F, 0, 1)

    out_edges = edges(out_rgb)
    real_edges = out_edges if real_rgb is None else edges(real_rgb)

    def sigmas(img: tuple, sel: NDArray[np.bool_], across: bool = False) -> F64:
        gray, _, ix, iy = img
        vs, us = np.nonzero(sel)
        nr = np.stack([ix[vs, us], iy[vs, us]], 1)
        nr /= np.maximum(np.linalg.norm(nr, axis=1, keepdims=True), 1e-9)
        pts = np.stack([us, vs], 1).astype(float)
        if across:  # the edge separates the object from the background
            side = [remap_rows(a_s, (pts[:, 0:1] + d * nr[:, 0:1]).astype(np.float32),
                               (pts[:, 1:2] + d * nr[:, 1:2]).astype(np.float32))[:, 0]
                    for d in (-SIDE_PX, SIDE_PX)]  # fmt: skip
            keep = np.abs(side[1] - side[0]) > SIDE_CONTRAST
            pts, nr = pts[keep], nr[keep]
        return edge_sigma_px(gray, pts, nr)

    s_obj = sigmas(out_edges, out_edges[1] & silhouette, across=True)
    s_real = sigmas(real_edges, real_edges[1] & near & away)

    def med(x: F64) -> float:
        x = x[np.isfinite(x)]
        return float(np.median(x)) if len(x) >= 10 else float("nan")

    return med(s_obj), med(s_real)
