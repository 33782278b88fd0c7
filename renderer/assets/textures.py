"""Procedural detail textures of the built-in obstacles: bark, stone, fur, cloth, skin.

The built-in meshes come from marching cubes and have no UVs, so their textures are
mapped triplanarly (the renderer samples the texture along the three object axes at the
fragment's position, period ``period_m``: :class:`~renderer.mesh.Material`). A texture
here is a *detail* texture: a tileable grey pattern whose mean in linear light is 1 after
the material's ``base_color`` factor, so it multiplies the region's vertex colour (which
carries the colour scheme and the large patches) with fine structure and leaves its mean
brightness alone.

Tileable by construction: every pattern is built from periodic noise, white noise
filtered in the Fourier domain (power spectrum ~ 1 / f^beta), so the texture repeats
without seams. Everything follows from ``seed``.

=======  =========================================================================
bark     vertical fissures: noise stretched 1:8 along u (the trunk axis), deep
         dark furrows, 0.45 m period
stone    granular speckle over blotches, 0.35 m
fur      fine streaks along u over soft blotches, 0.30 m
cloth    a weave (two sine gratings) over wrinkles, 0.12 m
skin     faint mottling, 0.20 m
=======  =========================================================================
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from renderer.mesh import Material

F64 = NDArray[np.float64]
SIZE = 256
KINDS: dict[str, tuple[float, float]] = {
    # kind: (period m, contrast: the std of the linear factor around 1)
    "bark": (0.45, 0.35),
    "stone": (0.35, 0.22),
    "fur": (0.30, 0.14),
    "cloth": (0.12, 0.10),
    "skin": (0.20, 0.05),
}


def periodic_noise(rng: np.random.Generator, size: int, beta: float, stretch: float = 1.0) -> F64:
    """(size, size) zero-mean, unit-std tileable noise with power ~ 1 / f^beta; ``stretch``
    > 1 elongates the structures along axis 1 (u)."""
    white = rng.standard_normal((size, size))
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :] * stretch
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    spec = np.fft.rfft2(white) / f ** (beta / 2.0)
    spec[0, 0] = 0.0
    out = np.fft.irfft2(spec, s=(size, size))
    return (out - out.mean()) / max(float(out.std()), 1e-12)


def _pattern(kind: str, rng: np.random.Generator) -> F64:
    """(SIZE, SIZE) zero-mean pattern of a kind (before the contrast)."""
    n = SIZE
    if kind == "bark":
        fiss = periodic_noise(rng, n, 2.0, stretch=8.0)
        grain = periodic_noise(rng, n, 1.0)
        return -np.maximum(fiss - 0.3, 0.0) * 1.6 + 0.35 * grain
    if kind == "stone":
        return 0.7 * periodic_noise(rng, n, 2.6) + 0.6 * periodic_noise(rng, n, 0.5)
    if kind == "fur":
        return 0.8 * periodic_noise(rng, n, 1.2, stretch=6.0) + 0.5 * periodic_noise(rng, n, 3.0)
    if kind == "cloth":
        y, x = np.mgrid[0:n, 0:n] * (2 * np.pi / n)
        weave = np.sin(48 * x) * np.sin(48 * y)
        return 0.6 * weave + 0.8 * periodic_noise(rng, n, 3.0)
    if kind == "skin":
        return periodic_noise(rng, n, 2.2)
    raise ValueError(f"unknown texture kind {kind!r}; known: {sorted(KINDS)}")


@lru_cache(maxsize=64)
def _texture(kind: str, seed: int) -> tuple[NDArray[np.uint8], float]:
    rng = np.random.default_rng([int(seed) & (2**63 - 1), sorted(KINDS).index(kind), 0x7E47])
    _, contrast = KINDS[kind]
    p = _pattern(kind, rng)
    lin = np.clip(0.5 * (1.0 + contrast * p / max(float(p.std()), 1e-12)), 0.02, 1.0)
    srgb = np.where(lin <= 0.0031308, lin * 12.92, 1.055 * lin ** (1 / 2.4) - 0.055)
    img = np.round(srgb * 255.0).astype(np.uint8)
    img.setflags(write=False)
    # the mean of what the renderer will sample (the 8-bit values decoded to linear)
    q = img.astype(np.float64) / 255.0
    dec = np.where(q <= 0.04045, q / 12.92, ((q + 0.055) / 1.055) ** 2.4)
    return img, float(dec.mean())


def detail_texture(kind: str, seed: int) -> tuple[NDArray[np.uint8], float]:
    """(SIZE, SIZE, 3) uint8 sRGB grey texture and its mean in linear light."""
    img, mean = _texture(kind, int(seed))
    return np.repeat(img[..., None], 3, axis=2), mean


def detail_material(kind: str, seed: int, *, period_m: float | None = None) -> Material:
    """A triplanar, Lambertian material whose texture has linear mean 1 (module doc)."""
    img, mean = detail_texture(kind, seed)
    period, _ = KINDS[kind]
    return Material(
        name=f"{kind}-detail",
        base_color=np.array([1.0 / mean] * 3 + [1.0]),
        base_color_texture=img,
        triplanar_m=float(period if period_m is None else period_m),
        specular=False,
    )
