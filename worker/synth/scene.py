"""The procedural railway scene: tracks, one triangle mesh, and ground-truth elements.

A :class:`Scene` is what the synthetic sequence generator drives a train through and what
the camera and lidar simulations see. Presets are built in :mod:`worker.synth.scenes`;
the pieces in :mod:`worker.synth.scene_builders`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from worker.synth.scene_mesh import SceneMesh
from worker.synth.track import Track

F64 = NDArray[np.float64]

# Formation (sub-ballast) level below top of rail, metres.
FORMATION_DEPTH = 0.75


@dataclass(frozen=True)
class Landmark:
    """A point a person would click in an image: pole tops, sign-board corners.

    id: unique within the scene; kind: e.g. ``pole_top`` (catenary and signal poles),
    ``sign_corner``, ``sign_center``, ``platform_corner``; xyz: (3,) world position.
    """

    id: str
    kind: str
    xyz: F64


@dataclass(frozen=True)
class Pole:
    """A vertical pole: base (3,) world point at ground level, height (m), radius (m)."""

    id: str
    kind: str
    base: F64
    height: float
    radius: float

    @property
    def top(self) -> F64:
        return self.base + np.array([0.0, 0.0, self.height])


@dataclass(frozen=True)
class Platform:
    """A platform: top outline polygon (n, 3) world (counter-clockwise seen from above),
    height (m) of its top above top of rail, and the track it serves."""

    id: str
    polygon: F64
    height: float
    track_id: int


@dataclass
class Scene:
    """A procedural railway scene in a local ENU world frame (float64).

    tracks: all tracks, ``tracks[0]`` the ego track (track_id 0); mesh: the whole scene;
    landmarks, poles, platforms: ground truth; extent: (2, 3) [min, max] corners of the
    detailed region (the far ground ring reaches beyond); drive_range: (s_start, s_end) arc
    lengths on the ego track a train may drive; speed_mps: preset's default speed;
    origin_offset: (3,) constant added to every coordinate (far-origin hard case);
    name, seed: how it was built.
    """

    name: str
    seed: int
    tracks: list[Track]
    mesh: SceneMesh
    landmarks: list[Landmark] = field(default_factory=list)
    poles: list[Pole] = field(default_factory=list)
    platforms: list[Platform] = field(default_factory=list)
    extent: F64 = field(default_factory=lambda: np.zeros((2, 3)))
    drive_range: tuple[float, float] = (0.0, 0.0)
    speed_mps: float = 0.0
    origin_offset: F64 = field(default_factory=lambda: np.zeros(3))

    @property
    def ego(self) -> Track:
        return self.tracks[0]

    def landmark(self, landmark_id: str) -> Landmark:
        for lm in self.landmarks:
            if lm.id == landmark_id:
                return lm
        raise KeyError(landmark_id)


class Terrain:
    """Ground height: flat formation near the tracks, gently uneven further away.

    Height = formation level of the nearest track point (a smooth regional level) plus
    non-negative low-frequency noise that fades in between ``flat_width`` and
    ``flat_width + blend`` metres from the nearest track centreline and fades out again
    towards the border of the detailed region (where the coarse far ground takes over).
    """

    def __init__(
        self,
        tracks: list[Track],
        rng: np.random.Generator,
        amplitude: float = 1.2,
        flat_width: float = 10.0,
        blend: float = 18.0,
        bounds_xy: F64 | None = None,
        border: float = 60.0,
    ) -> None:
        pts = np.vstack([t.point(t.sample(1.0)) for t in tracks])
        self._tree = cKDTree(pts[:, :2])
        self._z = pts[:, 2] - FORMATION_DEPTH
        self.amplitude = float(amplitude)
        self.flat_width = float(flat_width)
        self.blend = float(blend)
        self.bounds_xy = bounds_xy
        self.border = float(border)
        n = 6
        self._k = rng.uniform(2 * np.pi / 220.0, 2 * np.pi / 45.0, size=n)
        ang = rng.uniform(0, np.pi, size=n)
        self._dir = np.column_stack([np.cos(ang), np.sin(ang)])
        self._phase = rng.uniform(0, 2 * np.pi, size=n)
        self._amp = rng.uniform(0.5, 1.0, size=n)
        self._amp /= self._amp.sum()

    def track_distance(self, xy: ArrayLike) -> tuple[F64, F64]:
        """(distance (n,) to the nearest track centreline sample, its formation z (n,))."""
        xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))[:, :2]
        d, i = self._tree.query(xy)
        return d, self._z[i]

    def base_level(self, xy: ArrayLike) -> F64:
        """Regional level without noise (n,)."""
        return self.track_distance(xy)[1]

    def noise(self, xy: F64) -> F64:
        """Non-negative noise in [0, amplitude] (n,)."""
        ref = np.asarray(self._tree.data[0])
        ph = (xy - ref) @ self._dir.T * self._k + self._phase
        return self.amplitude * (0.5 + 0.5 * (np.sin(ph) @ self._amp))

    def height(self, xy: ArrayLike) -> F64:
        """Ground height (n,) at world xy (n, 2)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))[:, :2]
        d, z0 = self.track_distance(xy)
        w = np.clip((d - self.flat_width) / self.blend, 0.0, 1.0)
        w = w * w * (3 - 2 * w)
        if self.bounds_xy is not None:
            lo, hi = self.bounds_xy
            e = np.minimum(xy - lo, hi - xy).min(axis=1)
            w = w * np.clip(e / self.border, 0.0, 1.0)
        return z0 + w * self.noise(xy)
