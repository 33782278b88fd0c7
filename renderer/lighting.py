"""Lighting of a virtual object: sun direction and intensity, sky and ground ambient.

The object shader (renderer/object_render.py) computes, per pixel, in linear RGB:

    colour = albedo * (mix(ambient_rgb, sky_rgb, (1 + n.up) / 2)
                       + sun_intensity * max(n.sun, 0) * (1 - self_shadow))

so ``sky_rgb`` is what an upward-facing white Lambertian surface receives from the sky,
``ambient_rgb`` what a downward-facing one receives from the ground (bounce light), and
``sun_intensity`` what a white surface facing the sun receives from it, all in the linear
pixel units of the frame (an sRGB frame decoded to linear [0, 1]).

:func:`estimate_lighting` is deliberately simple and documented:

- **sky_rgb** = median linear colour of the frame's sky pixels: pixels whose viewing ray
  (through the real camera model and the vehicle pose) points more than
  ``SKY_MIN_ELEV_DEG`` above the horizon and that are among the bright ones there (which
  drops poles, wires and trees against the sky). A white horizontal surface under a sky of
  uniform radiance L reflects L, so the sky's pixel value is its irradiance in pixel units.
  Fallback when the pose sees no sky: the top 15 % of the image rows.
- **ambient_rgb** = median linear colour of the pixels looking more than
  ``GROUND_MAX_ELEV_DEG`` below the horizon (the ground a downward-facing surface sees).
- **sun_intensity** = ``SUN_TO_SKY_CLEAR`` x the sky's mean linear value x a clearness in
  [0, 1] from the sky's blueness (blue/red ratio: 1.05 grey overcast -> 0, >= 1.55 deep
  blue -> 1). Overcast skies give little or no direct sun.
- **sun direction**: NOT estimated from the pixels. Shading statistics of a single frame
  without scene normals do not determine it reliably (the sun is usually outside the
  field of view of a forward camera). It is the caller's ``sun_dir_world`` (e.g. from
  :func:`sun_dir_enu` with the sequence's position and timestamp, since the world frame is
  local East-North-Up), else ``DEFAULT_SUN_DIR_WORLD``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry.camera import CameraModel

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

# A mid-latitude late-morning sun from the south-east (also the synthetic scenes' default).
DEFAULT_SUN_DIR_WORLD: tuple[float, float, float] = (0.45, -0.55, 0.7)
SKY_MIN_ELEV_DEG = 3.0
GROUND_MAX_ELEV_DEG = -3.0
SUN_TO_SKY_CLEAR = 2.0
_GRID = (96, 160)  # rows, columns of the sampling grid


def _unit(v: ArrayLike) -> F64:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"direction {v} has no usable norm")
    return v / n


@dataclass
class Lighting:
    """Light of a frame in its world frame (linear RGB in the frame's pixel units).

    sun_dir_world : (3,) unit vector from the scene towards the sun (world frame).
    sun_intensity : irradiance of a white surface facing the sun (0: overcast / no sun).
    ambient_rgb : (3,) light reaching a downward-facing surface (ground bounce).
    sky_rgb : (3,) light reaching an upward-facing surface from the sky.
    """

    sun_dir_world: F64 = field(default_factory=lambda: _unit(DEFAULT_SUN_DIR_WORLD))
    sun_intensity: float = 0.75
    ambient_rgb: F64 = field(default_factory=lambda: np.array([0.17, 0.16, 0.14]))
    sky_rgb: F64 = field(default_factory=lambda: np.array([0.36, 0.40, 0.48]))

    def __post_init__(self) -> None:
        self.sun_dir_world = _unit(self.sun_dir_world)
        self.sun_intensity = float(max(0.0, self.sun_intensity))
        self.ambient_rgb = np.clip(np.asarray(self.ambient_rgb, np.float64).reshape(3), 0, None)
        self.sky_rgb = np.clip(np.asarray(self.sky_rgb, np.float64).reshape(3), 0, None)

    @property
    def sun_elevation(self) -> float:
        """Sun elevation above the world horizontal (rad)."""
        return float(np.arcsin(np.clip(self.sun_dir_world[2], -1.0, 1.0)))

    @property
    def casts_shadows(self) -> bool:
        """True when there is direct sun above the horizon."""
        return self.sun_intensity > 1e-4 and self.sun_dir_world[2] > 0.02


def srgb_to_linear(c: ArrayLike) -> NDArray[np.float32]:
    """sRGB-encoded values in [0, 1] -> linear (IEC 61966-2-1), float32."""
    c = np.asarray(c, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


#: (256,) float32: linear light of each 8-bit sRGB value
SRGB8_TO_LINEAR = srgb_to_linear(np.arange(256, dtype=np.float32) / 255.0)


def linear_to_srgb(c: ArrayLike) -> NDArray[np.float32]:
    """Linear values -> sRGB-encoded, clipped to [0, 1], float32."""
    c = np.clip(np.asarray(c, dtype=np.float32), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1 / 2.4) - 0.055).astype(np.float32)


def sun_dir_enu(lat_deg: float, lon_deg: float, unix_s: float) -> F64:
    """Unit vector towards the sun in local East-North-Up at a place and UNIX time.

    NOAA's low-precision solar position (declination and equation of time from the
    fractional year; ~0.5 deg), no refraction. Enough for shading and shadow direction.
    """
    days = unix_s / 86400.0
    # Days since Jan 1 00:00 UTC (365.2422-day years from the epoch: within a day).
    d0 = days % 365.2422
    hour = (unix_s % 86400.0) / 3600.0
    # NOAA's fractional year: 2 pi / 365 (day_of_year - 1 + (hour - 12) / 24).
    g = 2.0 * np.pi / 365.0 * (d0 - 0.5)
    eqtime = 229.18 * (
        0.000075
        + 0.001868 * np.cos(g)
        - 0.032077 * np.sin(g)
        - 0.014615 * np.cos(2 * g)
        - 0.040849 * np.sin(2 * g)
    )
    decl = (
        0.006918
        - 0.399912 * np.cos(g)
        + 0.070257 * np.sin(g)
        - 0.006758 * np.cos(2 * g)
        + 0.000907 * np.sin(2 * g)
        - 0.002697 * np.cos(3 * g)
        + 0.00148 * np.sin(3 * g)
    )
    tst = hour * 60.0 + eqtime + 4.0 * lon_deg  # true solar time (min)
    ha = np.radians(tst / 4.0 - 180.0)  # hour angle
    lat = np.radians(lat_deg)
    # Direction in ENU from declination and hour angle (hour angle > 0: afternoon, west).
    e = -np.cos(decl) * np.sin(ha)
    n = np.cos(lat) * np.sin(decl) - np.sin(lat) * np.cos(decl) * np.cos(ha)
    u = np.sin(lat) * np.sin(decl) + np.cos(lat) * np.cos(decl) * np.cos(ha)
    return _unit([e, n, u])


def estimate_lighting(
    frame_rgb: NDArray[np.uint8],
    camera: CameraModel,
    T_world_base: ArrayLike,
    *,
    sun_dir_world: ArrayLike | None = None,
) -> Lighting:
    """A simple lighting estimate from one frame (see the module docstring for the model).

    Parameters
    ----------
    frame_rgb : (H, W, 3) uint8 sRGB frame of ``camera`` (any resolution with the
        camera's aspect; pixels are mapped by the size ratio).
    camera : the camera model.
    T_world_base : (4, 4) vehicle pose at this camera's timestamp.
    sun_dir_world : (3,) towards the sun in the world frame; default
        ``DEFAULT_SUN_DIR_WORLD`` (the sun direction is not estimated from pixels).
    """
    img = np.asarray(frame_rgb)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"frame must be (H, W, 3), got {img.shape}")
    H, W = img.shape[:2]
    rows = np.linspace(0, H - 1, min(_GRID[0], H)).round().astype(int)
    cols = np.linspace(0, W - 1, min(_GRID[1], W)).round().astype(int)
    vv, uu = np.meshgrid(rows, cols, indexing="ij")
    lin = srgb_to_linear(img[vv, uu].astype(np.float32) / 255.0).reshape(-1, 3)
    # Pixel centres of the frame in the camera's pixel grid.
    uv = np.stack(
        [(uu.ravel() + 0.5) * camera.width / W - 0.5, (vv.ravel() + 0.5) * camera.height / H - 0.5],
        axis=1,
    )
    rays_opt, ok = camera.unproject(uv)
    R_world_opt = (np.asarray(T_world_base, dtype=np.float64) @ camera.T_base_opt)[:3, :3]
    rays_world = rays_opt @ R_world_opt.T
    elev = np.degrees(np.arcsin(np.clip(rays_world[:, 2], -1.0, 1.0)))
    lum = lin @ np.array([0.2126, 0.7152, 0.0722], np.float32)

    sky = ok & (elev > SKY_MIN_ELEV_DEG)
    if sky.sum() >= 20:
        sky &= lum >= 0.5 * np.percentile(lum[sky], 90)
        sky_rgb = np.median(lin[sky], axis=0)
        sky_src = f"{int(sky.sum())} sky samples"
    else:
        top = vv.ravel() < 0.15 * H
        sky_rgb = np.median(lin[top], axis=0)
        sky_src = "top rows (no sky above the horizon in view)"
    ground = ok & (elev < GROUND_MAX_ELEV_DEG)
    if ground.sum() >= 20:
        ambient_rgb = np.median(lin[ground], axis=0)
    else:
        ambient_rgb = 0.4 * sky_rgb
    blue_red = float(sky_rgb[2] / max(sky_rgb[0], 1e-4))
    clearness = float(np.clip((blue_red - 1.05) / 0.5, 0.0, 1.0))
    sun_intensity = SUN_TO_SKY_CLEAR * float(np.mean(sky_rgb)) * clearness
    sun = _unit(DEFAULT_SUN_DIR_WORLD if sun_dir_world is None else sun_dir_world)
    log.debug(
        "lighting: sky %s from %s, ambient %s, clearness %.2f, sun %.3f",
        np.round(sky_rgb, 3),
        sky_src,
        np.round(ambient_rgb, 3),
        clearness,
        sun_intensity,
    )
    return Lighting(sun, sun_intensity, ambient_rgb, sky_rgb)
