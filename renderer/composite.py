"""Composite a rendered object into a real frame (OpenCV, ROI only).

:func:`composite` works in linear light inside ``render.roi`` and leaves every other pixel
(and every ROI pixel that neither the object nor its shadow touches) byte-identical:

1. **Lightness matching (LAB).** The object's colour (linear -> sRGB -> CIE LAB) keeps its
   a, b; its L channel statistics over the object (alpha > 0.5) are moved toward those of
   the real frame in a ring around the object (``ring`` = dilated mask minus a 2 px
   dilation, width ~1/4 of the object's size, 6..48 px; the ring may extend beyond the ROI:
   it is only read). The blend is partial, so an object keeps its own albedo contrast:
   ``L' = mu_r' + (L - mu_o) * k`` with ``mu_r' = mu_o + LAB_MEAN_BLEND (mu_r - mu_o)`` and
   ``k = (sd_r / sd_o) ** LAB_STD_BLEND`` (k clipped to [0.5, 2]).
2. **Blur** of the premultiplied object layer (colour x alpha and alpha together, so
   edges stay consistent). With ``match_sharpness`` (default) the Gaussian is the
   frame's own: the blur of the real step edges in the ROI grown by ``NOISE_WINDOW_PX``
   (object excluded; :mod:`renderer.frame_blur`, from the edges across the motion
   direction, so the motion blur below is not counted twice), less the render's own edge
   spread (``ObjectRender.edge_var_px2``: a pixel's box and the supersampled lens
   resampling, 1/12 to 1/6 px^2), and never below the defocus at the object's
   distance (the real edges around may be farther). Without it, or with too
   few edges, the lens model: a Gaussian with sigma = sqrt(sigma_optics^2 + sigma_defocus^2)
   where sigma_optics = ``OPTICS_SIGMA_PX`` x image scale (a real lens and demosaicing
   never give a one-pixel-sharp edge) and sigma_defocus = fx x ``APERTURE_M`` /
   (4 x distance) (the blur disc of a lens focused at infinity, aperture diameter
   ``APERTURE_M``, as a Gaussian of the disc's standard deviation): the camera's own
   resolution at that distance. Motion blur: a line kernel along the anchor's image
   motion, length ``|motion_uv_per_m| x speed x exposure`` px (the train's forward motion
   during the exposure).
3. **Soft edges**: coverage feathered with a Gaussian of ``FEATHER_SIGMA_PX`` (also when
   ``blur=False``; with the lens model combined with its Gaussian; a measured frame blur
   includes it), on top of the renderer's anti-aliased coverage.
4. **Shadow**: real pixels (linear) x (1 - shadow_strength x shadow), shadow blurred like
   the object.
5. **Pixel offset**: the object and shadow layers are shifted by ``pixel_offset`` (du,
   dv) px with ``cv2.warpAffine`` (bilinear) before blending (calibration-error
   compensation).
6. ``out = object_premultiplied + (1 - alpha) x shadowed_background``, linear -> sRGB.
7. **Sensor noise** (``match_noise``): the frame's noise, measured per channel as a
   function of intensity in the flat real pixels of the ROI grown by
   ``NOISE_WINDOW_PX`` (object excluded; :mod:`renderer.sensor_noise`), is added to the
   object's pixels in 8-bit units with std ``sigma(value) x sqrt(1 - (1 - alpha)^2)``
   (the real background already brings ``1 - alpha`` of its own), seeded by
   ``noise_seed`` and the ROI's corner (the same job gives the same bytes); then
   rounded to uint8.

When ``render.roi`` is None the input array itself is returned (writers can then copy the
original file byte-identically).
"""

from __future__ import annotations

import functools
import logging

import cv2
import numpy as np
from numpy.typing import NDArray

from renderer.camera_optics import APERTURE_M, EXPOSURE_S
from renderer.frame_blur import estimate_blur_sigma
from renderer.lighting import SRGB8_TO_LINEAR, linear_to_srgb
from renderer.object_render import ObjectRender
from renderer.sensor_noise import NoiseProfile, add_noise, estimate_noise, noise_weight

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

LAB_MEAN_BLEND = 0.6
LAB_STD_BLEND = 0.5
OPTICS_SIGMA_PX = 0.6  # at the sensor's full resolution
FEATHER_SIGMA_PX = 0.5
NOISE_WINDOW_PX = 48
_CHANGE_EPS = 1.0 / 4096.0
DEPTH_MEDIAN_PIXELS = 250_000


def defocus_sigma_px(render: ObjectRender, aperture_m: float = APERTURE_M) -> float:
    """Gaussian sigma (px) of the lens's defocus at the object's distance (module doc), for
    an effective aperture diameter ``aperture_m`` (0: a pinhole)."""
    if aperture_m <= 0.0:  # a pinhole: no defocus at any distance
        return 0.0
    d = render.distance_m if np.isfinite(render.distance_m) and render.distance_m > 0 else 1e9
    # Median visible depth is the better distance when the object is there (read on a
    # grid of at most DEPTH_MEDIAN_PIXELS: a large object's 2.6 Mpx took 9 ms).
    depth = render.depth
    if depth.size > DEPTH_MEDIAN_PIXELS:
        k = int(np.ceil(np.sqrt(depth.size / DEPTH_MEDIAN_PIXELS)))
        depth = depth[::k, ::k]
    if depth.size and np.any(np.isfinite(depth)):
        d = float(np.nanmedian(depth))
    return float(render.focal_px * aperture_m / (4.0 * max(d, 0.1)))


def blur_sigma_px(render: ObjectRender, aperture_m: float = APERTURE_M) -> float:
    """Gaussian sigma (px) of the object's optical blur at its distance (see module doc)."""
    scale = render.pixel_scale if render.pixel_scale > 0 else 1.0
    return float(np.hypot(OPTICS_SIGMA_PX * scale, defocus_sigma_px(render, aperture_m)))


def _window(render: ObjectRender, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    """The render's ROI grown by ``NOISE_WINDOW_PX`` inside a frame of ``shape``."""
    u0, v0, u1, v1 = render.roi  # type: ignore[misc]
    H, W = shape[:2]
    m = NOISE_WINDOW_PX
    return max(u0 - m, 0), max(v0 - m, 0), min(u1 + m, W), min(v1 + m, H)


def _object_mask(render: ObjectRender, window: tuple[int, int, int, int]) -> NDArray[np.bool_]:
    a0, b0, a1, b1 = window
    u0, v0, u1, v1 = render.roi  # type: ignore[misc]
    out = np.zeros((b1 - b0, a1 - a0), bool)
    out[v0 - b0 : v1 - b0, u0 - a0 : u1 - a0] = render.alpha > 0.02
    return out


def frame_blur(
    frame_rgb: NDArray[np.uint8], render: ObjectRender, motion_uv: tuple[float, float]
) -> float | None:
    """The frame's step-edge blur sigma (px) around the render's object, from the edges
    across ``motion_uv`` (module doc, step 2); None: too few edges."""
    if render.roi is None:
        return None
    win = _window(render, frame_rgb.shape)
    return estimate_blur_sigma(frame_rgb, win, _object_mask(render, win), motion_uv)


def gaussian_sigma_px(
    render: ObjectRender, frame_sigma: float | None, aperture_m: float = APERTURE_M
) -> float:
    """The Gaussian the object layer gets (module doc, steps 2 and 3): the frame's own
    blur less the render's own edge spread (``render.edge_var_px2``, px^2), never below
    the lens's defocus at the object's distance; without a frame estimate the lens model
    with the feather."""
    if frame_sigma is None:
        return float(np.hypot(blur_sigma_px(render, aperture_m), FEATHER_SIGMA_PX))
    own = float(np.sqrt(max(frame_sigma**2 - render.edge_var_px2, 0.0)))
    return max(own, defocus_sigma_px(render, aperture_m))


def _sampled_gaussian(s: float, k: int) -> F64:
    """(2k + 1,) the Gaussian of parameter ``s`` sampled at the integers, normalised."""
    n = np.arange(-k, k + 1, dtype=np.float64)
    w = np.exp(-0.5 * (n / s) ** 2)
    return np.asarray(w / w.sum(), np.float64)


def gaussian_kernel(sigma: float) -> F32:
    """(2k + 1,) a sampled Gaussian whose variance is ``sigma^2`` px^2: its parameter is
    found by bisection, since sampling a small one falls short (``sigma`` 0.49 px as the
    parameter: 0.20 px^2 instead of 0.24). Not the discrete analogue of the Gaussian
    (Lindeberg's ``exp(-t) I_n(t)``): its excess kurtosis ``1 / t`` gives an edge
    of the right variance a sharper core, which the frame's estimate
    (:mod:`renderer.frame_blur`) and the eye read as less blur. The last few kernels
    are kept (a composite blurs two layers alike): a copy is returned."""
    return _bisected_kernel(float(sigma)).copy()


@functools.lru_cache(maxsize=16)
def _bisected_kernel(sigma: float) -> F32:
    """:func:`gaussian_kernel`'s bisection (40 steps, about 1 ms)."""
    k = int(np.ceil(4.0 * sigma)) + 1
    n2 = np.arange(-k, k + 1, dtype=np.float64) ** 2
    lo, hi = 1e-3, float(sigma) + 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if float(np.sum(_sampled_gaussian(mid, k) * n2)) < sigma * sigma:
            lo = mid
        else:
            hi = mid
    return _sampled_gaussian(0.5 * (lo + hi), k).astype(np.float32)


def gaussian_blur(img: F32, sigma: float) -> F32:
    """``img`` (H, W[, C]) float32 blurred by a Gaussian of variance ``sigma^2`` px^2 in
    each direction (:func:`gaussian_kernel`; zero outside the image)."""
    if sigma < 0.05:
        return img
    g = gaussian_kernel(sigma)
    return np.asarray(
        cv2.sepFilter2D(img, cv2.CV_32F, g, g, borderType=cv2.BORDER_CONSTANT), np.float32
    )


def _motion(img: F32, vec: tuple[float, float]) -> F32:
    """Box blur along ``vec`` (px), length |vec| (sub-pixel lengths: a 2-tap kernel)."""
    length = float(np.hypot(*vec))
    if length < 0.25:
        return img
    n = int(np.ceil(length)) * 2 + 1
    k = np.zeros((n, n), np.float32)
    c = n // 2
    steps = max(8, 4 * int(np.ceil(length)))
    for t in np.linspace(-0.5, 0.5, steps):
        x, y = c + t * vec[0], c + t * vec[1]
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        for dy, wy in ((0, 1 - fy), (1, fy)):
            for dx, wx in ((0, 1 - fx), (1, fx)):
                if 0 <= y0 + dy < n and 0 <= x0 + dx < n:
                    k[y0 + dy, x0 + dx] += wx * wy
    k /= k.sum()
    return np.asarray(cv2.filter2D(img, -1, k, borderType=cv2.BORDER_CONSTANT), np.float32)


def _lab_match(
    frame_rgb: NDArray[np.uint8], render: ObjectRender, color_lin: F32, alpha: F32
) -> F32:
    """The object's colour (linear) with its L statistics moved toward the ring's."""
    assert render.roi is not None
    u0, v0, u1, v1 = render.roi
    H, W = frame_rgb.shape[:2]
    obj = alpha > 0.5
    if np.count_nonzero(obj) < 4:
        return color_lin
    rows, cols = np.flatnonzero(obj.any(axis=1)), np.flatnonzero(obj.any(axis=0))
    size = max(rows[-1] - rows[0], cols[-1] - cols[0]) + 1
    ring_w = int(np.clip(size // 4, 6, 48))
    # Window: the ROI grown by the ring (read-only outside the ROI).
    a0, b0 = max(u0 - ring_w, 0), max(v0 - ring_w, 0)
    a1, b1 = min(u1 + ring_w, W), min(v1 + ring_w, H)
    free = np.full((b1 - b0, a1 - a0), 255, np.uint8)  # 0 on the object
    free[v0 - b0 : v1 - b0, u0 - a0 : u1 - a0][alpha > 0.02] = 0
    dist = cv2.distanceTransform(free, cv2.DIST_L2, 3)
    ring = (dist > 2.5) & (dist <= ring_w)
    if ring.sum() < 8:
        return color_lin
    real = frame_rgb[b0:b1, a0:a1][ring].astype(np.float32)[:, None] / 255.0
    L_r = cv2.cvtColor(real, cv2.COLOR_RGB2Lab)[:, 0, 0]
    has = np.flatnonzero(alpha > 0)  # the object's pixels, gathered once by flat index
    # the object's colour is linear already: OpenCV's linear-RGB conversions, not its
    # sRGB ones after an encode of ours (a third of this function's time on a fallen tree)
    rgb = color_lin.reshape(-1, 3)[has]
    lab = cv2.cvtColor(np.clip(rgb, 0.0, 1.0, out=rgb)[:, None], cv2.COLOR_LRGB2Lab)
    L_o = lab[:, 0, 0][obj.reshape(-1)[has]]
    mu_o, sd_o = float(L_o.mean()), float(L_o.std())
    mu_r, sd_r = float(L_r.mean()), float(L_r.std())
    k = float(np.clip((max(sd_r, 0.5) / max(sd_o, 0.5)) ** LAB_STD_BLEND, 0.5, 2.0))
    mu_t = mu_o + LAB_MEAN_BLEND * (mu_r - mu_o)
    lab[:, 0, 0] = np.clip(mu_t + (lab[:, 0, 0] - mu_o) * k, 0.0, 100.0)
    log.debug("LAB match: L object %.1f+-%.1f, ring %.1f+-%.1f -> mean %.1f, gain %.2f",
              mu_o, sd_o, mu_r, sd_r, mu_t, k)  # fmt: skip
    # zero where alpha is: the colour counts only where the object covers a pixel
    out = np.zeros(color_lin.shape, np.float32)
    out.reshape(-1, 3)[has] = np.clip(cv2.cvtColor(lab, cv2.COLOR_Lab2LRGB)[:, 0], 0.0, 1.0)
    return out


def frame_noise(frame_rgb: NDArray[np.uint8], render: ObjectRender) -> NoiseProfile | None:
    """The frame's noise profile around the render's object (module doc, step 7)."""
    if render.roi is None:
        return None
    win = _window(render, frame_rgb.shape)
    prof = estimate_noise(frame_rgb, win, _object_mask(render, win))
    if prof is None:
        log.debug("noise: too few flat pixels around roi %s: none added", render.roi)
    return prof


def composite(
    frame_rgb: NDArray[np.uint8],
    render: ObjectRender,
    *,
    speed_mps: float = 0.0,
    exposure_s: float = EXPOSURE_S,
    aperture_m: float = APERTURE_M,
    lab_match: bool = True,
    blur: bool = True,
    shadow_strength: float = 0.6,
    pixel_offset: tuple[float, float] = (0.0, 0.0),
    match_noise: bool = True,
    match_sharpness: bool = True,
    noise_seed: int = 0,
) -> NDArray[np.uint8]:
    """The frame (H, W, 3) uint8 sRGB with the rendered object (and its shadow) blended in.

    Returns a new array (only ``render.roi`` differs), or ``frame_rgb`` itself when
    ``render.roi`` is None. :func:`composite_into` blends into the frame itself.
    """
    if render.roi is None:
        return frame_rgb
    out = np.array(frame_rgb, copy=True)
    composite_into(
        out, render, speed_mps=speed_mps, exposure_s=exposure_s, aperture_m=aperture_m,
        lab_match=lab_match, blur=blur, shadow_strength=shadow_strength,
        pixel_offset=pixel_offset, match_noise=match_noise, match_sharpness=match_sharpness,
        noise_seed=noise_seed,
    )  # fmt: skip
    return out


def composite_into(
    frame: NDArray[np.uint8],
    render: ObjectRender,
    *,
    speed_mps: float = 0.0,
    exposure_s: float = EXPOSURE_S,
    aperture_m: float = APERTURE_M,
    lab_match: bool = True,
    blur: bool = True,
    shadow_strength: float = 0.6,
    pixel_offset: tuple[float, float] = (0.0, 0.0),
    match_noise: bool = True,
    match_sharpness: bool = True,
    noise_seed: int = 0,
) -> bool:
    """:func:`composite` in place: ``frame`` (H, W, 3) uint8 sRGB, any strides (e.g. the
    RGB view ``bgr[..., ::-1]`` of a decoded BGR image), gets the object blended into
    its ROI, read before it is written. Returns whether any byte changed."""
    if render.roi is None:
        return False
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise ValueError(f"frame must be (H, W, 3) uint8, got {frame.shape} {frame.dtype}")
    u0, v0, u1, v1 = render.roi
    if render.alpha.shape != (v1 - v0, u1 - u0):
        raise ValueError("render arrays do not match its roi")
    H, W = frame.shape[:2]
    if u1 > W or v1 > H:
        raise ValueError(f"roi {render.roi} outside a {W}x{H} frame")

    alpha = np.asarray(render.alpha, np.float32)
    color = np.asarray(render.color, np.float32)
    if lab_match:
        color = _lab_match(frame, render, color, alpha)
    layer = np.empty((*alpha.shape, 4), np.float32)  # premultiplied rgb, alpha
    np.multiply(color, alpha[..., None], out=layer[..., :3])
    layer[..., 3] = alpha
    shade = np.multiply(render.shadow, np.float32(shadow_strength), dtype=np.float32)

    sigma = FEATHER_SIGMA_PX
    if blur:
        vec = np.asarray(render.motion_uv_per_m, np.float64) * speed_mps * exposure_s
        motion = (float(vec[0]), float(vec[1])) if np.all(np.isfinite(vec)) else (0.0, 0.0)
        measured = frame_blur(frame, render, motion) if match_sharpness else None
        sigma = gaussian_sigma_px(render, measured, aperture_m)
        if motion != (0.0, 0.0):
            layer = _motion(layer, motion)
    layer = gaussian_blur(layer, sigma)
    shade = gaussian_blur(shade, sigma)
    du, dv = float(pixel_offset[0]), float(pixel_offset[1])
    if du != 0.0 or dv != 0.0:
        M = np.array([[1.0, 0.0, du], [0.0, 1.0, dv]], np.float32)
        size = (layer.shape[1], layer.shape[0])
        layer, shade = (
            cv2.warpAffine(x, M, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=0)
            for x in (layer, shade)
        )  # fmt: skip

    a = np.clip(layer[..., 3], 0.0, 1.0)
    sh = np.clip(shade, 0.0, 1.0)
    changed = (a > _CHANGE_EPS) | (sh > _CHANGE_EPS)
    if not changed.any():
        return False
    # the changed pixels gathered once by their flat index (each boolean index of the
    # ROI's arrays was a gather of its own)
    vs, us = np.nonzero(changed)
    flat = vs * changed.shape[1] + us
    a_c = a.reshape(-1)[flat]
    keep = (1.0 - a_c) * (1.0 - sh.reshape(-1)[flat])  # (k,) of the real pixel's light
    real8 = frame[v0:v1, u0:u1][vs, us]  # (k, 3) uint8
    res = SRGB8_TO_LINEAR[real8]  # (k, 3) linear
    res *= keep[:, None]
    res += layer.reshape(-1, 4)[flat, :3]
    enc8 = linear_to_srgb(res).astype(np.float64) * 255.0
    profile = frame_noise(frame, render) if match_noise else None
    if profile is not None:
        rng = np.random.default_rng([int(noise_seed) & (2**63 - 1), u0, v0, 0x5E45])
        enc8 = add_noise(enc8, noise_weight(a_c), profile, rng)
    enc = np.clip(np.round(enc8), 0, 255).astype(np.uint8)
    if np.array_equal(enc, real8):
        return False
    frame[v0 + vs, u0 + us] = enc
    return True
