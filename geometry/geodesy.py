"""WGS84 geodetic <-> ECEF <-> the sequence's local East-North-Up world frame.

Conventions (see ../shared/design/ARCHITECTURE.md):

- geodetic coordinates are WGS84 latitude / longitude in degrees and *ellipsoidal* height in
  metres (EPSG:4979, as NovAtel's INSPVA reports them); ECEF is EPSG:4978 (metres);
- the world frame of a sequence is East-North-Up with its origin at a reference point (the
  first INS record's position, see :func:`world_frame_from_ins`) and its axes those of the
  tangent plane of the ellipsoid at that point: x east, y north, z up along the ellipsoid
  normal. It is a Cartesian frame: far from the origin, "up" of the world frame is no longer
  the local vertical (meridian convergence and Earth curvature); :meth:`WorldFrame.R_world_enu_at`
  gives the exact rotation between the local tangent frame at any point and the world frame;
- everything is float64. The ECEF <-> ENU step is a rigid transform done in float64 around
  the origin's ECEF position, so a round trip is exact to well below 1 mm even with ECEF
  magnitudes (~6.4e6 m) and points tens of km away.

pyproj ``Transformer`` objects are not thread-safe; one is kept per thread.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pyproj import Transformer

F64 = NDArray[np.float64]

logger = logging.getLogger(__name__)

_GEODETIC_CRS = "EPSG:4979"  # WGS84 geographic 3D: lat, lon (deg), ellipsoidal height (m)
_ECEF_CRS = "EPSG:4978"  # WGS84 geocentric (m)

_local = threading.local()


def _transformers() -> tuple[Transformer, Transformer]:
    """(geodetic -> ECEF, ECEF -> geodetic) pyproj transformers of this thread."""
    pair = getattr(_local, "pair", None)
    if pair is None:
        fwd = Transformer.from_crs(_GEODETIC_CRS, _ECEF_CRS, always_xy=True)
        inv = Transformer.from_crs(_ECEF_CRS, _GEODETIC_CRS, always_xy=True)
        pair = (fwd, inv)
        _local.pair = pair
    return pair


def geodetic_to_ecef(lat_deg: ArrayLike, lon_deg: ArrayLike, h_m: ArrayLike) -> F64:
    """WGS84 latitude, longitude (deg), ellipsoidal height (m) -> ECEF points.

    Parameters
    ----------
    lat_deg, lon_deg, h_m : scalars or (n,) arrays (broadcast together).

    Returns
    -------
    (n, 3) float64 ECEF coordinates (m).
    """
    lat, lon, h = np.broadcast_arrays(
        np.atleast_1d(np.asarray(lat_deg, dtype=np.float64)),
        np.atleast_1d(np.asarray(lon_deg, dtype=np.float64)),
        np.atleast_1d(np.asarray(h_m, dtype=np.float64)),
    )
    if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(lon)) and np.all(np.isfinite(h))):
        raise ValueError("geodetic coordinates must be finite")
    if np.any(np.abs(lat) > 90.0):
        raise ValueError(f"latitude out of [-90, 90] deg: {float(np.max(np.abs(lat)))}")
    fwd, _ = _transformers()
    x, y, z = fwd.transform(lon.ravel(), lat.ravel(), h.ravel())
    return np.stack([x, y, z], axis=-1).astype(np.float64)


def ecef_to_geodetic(p_ecef: ArrayLike) -> tuple[F64, F64, F64]:
    """ECEF points (n, 3) m -> latitude, longitude (n,) deg, ellipsoidal height (n,) m."""
    p = np.asarray(p_ecef, dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(p)):
        raise ValueError("ECEF coordinates must be finite")
    _, inv = _transformers()
    lon, lat, h = inv.transform(p[:, 0], p[:, 1], p[:, 2])
    return (
        np.asarray(lat, dtype=np.float64),
        np.asarray(lon, dtype=np.float64),
        np.asarray(h, dtype=np.float64),
    )


def R_ecef_enu(lat_deg: ArrayLike, lon_deg: ArrayLike) -> F64:
    """Rotation of the local East-North-Up tangent frame at (lat, lon) into ECEF.

    Columns are the east, north and up unit vectors in ECEF (geodetic latitude, i.e. up is
    the ellipsoid normal).

    Parameters
    ----------
    lat_deg, lon_deg : scalars or (n,) arrays.

    Returns
    -------
    (n, 3, 3) float64; ``p_ecef_direction = R @ p_enu_direction``.
    """
    lat, lon = np.broadcast_arrays(
        np.atleast_1d(np.radians(np.asarray(lat_deg, dtype=np.float64))),
        np.atleast_1d(np.radians(np.asarray(lon_deg, dtype=np.float64))),
    )
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    zero = np.zeros_like(sl)
    east = np.stack([-so, co, zero], axis=-1)
    north = np.stack([-sl * co, -sl * so, cl], axis=-1)
    up = np.stack([cl * co, cl * so, sl], axis=-1)
    return np.stack([east, north, up], axis=-1)


@dataclass(frozen=True)
class WorldFrame:
    """Local East-North-Up world frame of a sequence.

    Origin at WGS84 (``latitude_deg``, ``longitude_deg``, ``height_m`` ellipsoidal); axes x
    east, y north, z up of the tangent plane at the origin. Serialised to
    ``ground_truth/world.json`` and the preparation cache with :meth:`to_json`.
    """

    latitude_deg: float
    longitude_deg: float
    height_m: float

    def __post_init__(self) -> None:
        vals = (self.latitude_deg, self.longitude_deg, self.height_m)
        if not all(np.isfinite(v) for v in vals):
            raise ValueError(f"world frame origin must be finite, got {vals}")
        if abs(self.latitude_deg) > 90.0:
            raise ValueError(f"latitude {self.latitude_deg} deg is out of [-90, 90]")
        # Plain floats (not numpy scalars) so that equality and JSON behave.
        object.__setattr__(self, "latitude_deg", float(self.latitude_deg))
        object.__setattr__(self, "longitude_deg", float(self.longitude_deg))
        object.__setattr__(self, "height_m", float(self.height_m))

    # -- cached geometry of the origin ------------------------------------------------------

    @cached_property
    def origin_ecef(self) -> F64:
        """(3,) ECEF position of the origin (m), read-only."""
        p: F64 = geodetic_to_ecef(self.latitude_deg, self.longitude_deg, self.height_m)[0]
        p.setflags(write=False)
        return p

    @cached_property
    def R_ecef_world(self) -> F64:
        """(3, 3) rotation of the world axes into ECEF, read-only."""
        R: F64 = R_ecef_enu(self.latitude_deg, self.longitude_deg)[0]
        R.setflags(write=False)
        return R

    # -- conversions ------------------------------------------------------------------------

    def ecef_to_world(self, p_ecef: ArrayLike) -> F64:
        """ECEF points (n, 3) -> world points (n, 3)."""
        p = np.asarray(p_ecef, dtype=np.float64).reshape(-1, 3)
        return (p - self.origin_ecef) @ self.R_ecef_world

    def world_to_ecef(self, p_world: ArrayLike) -> F64:
        """World points (n, 3) -> ECEF points (n, 3)."""
        p = np.asarray(p_world, dtype=np.float64).reshape(-1, 3)
        return p @ self.R_ecef_world.T + self.origin_ecef

    def geodetic_to_world(self, lat_deg: ArrayLike, lon_deg: ArrayLike, h_m: ArrayLike) -> F64:
        """WGS84 lat, lon (deg), ellipsoidal height (m), scalars or (n,) -> world points (n, 3)."""
        return self.ecef_to_world(geodetic_to_ecef(lat_deg, lon_deg, h_m))

    def world_to_geodetic(self, p_world: ArrayLike) -> tuple[F64, F64, F64]:
        """World points (n, 3) -> latitude, longitude (n,) deg, ellipsoidal height (n,) m."""
        return ecef_to_geodetic(self.world_to_ecef(p_world))

    def R_world_enu_at(self, lat_deg: ArrayLike, lon_deg: ArrayLike) -> F64:
        """Rotation from the local ENU tangent frame at (lat, lon) to the world frame.

        Exact (through ECEF): ``R_world_enu = R_ecef_world^T @ R_ecef_enu(lat, lon)``. At the
        origin it is the identity; elsewhere it is mostly a rotation about up by the meridian
        convergence (about ``dlon * sin(lat)``) plus the tilt of the vertical (~1.6e-4 rad per
        km).

        Parameters
        ----------
        lat_deg, lon_deg : scalars or (n,) arrays.

        Returns
        -------
        (n, 3, 3) float64.
        """
        R_world_enu: F64 = np.einsum("ji,njk->nik", self.R_ecef_world, R_ecef_enu(lat_deg, lon_deg))
        return R_world_enu

    def T_world_other(self, other: WorldFrame) -> F64:
        """(4, 4) pose of another world frame in this one (``p_this = T @ p_other``), exact."""
        T = np.eye(4)
        T[:3, :3] = self.R_world_enu_at(other.latitude_deg, other.longitude_deg)[0]
        T[:3, 3] = self.geodetic_to_world(other.latitude_deg, other.longitude_deg, other.height_m)[
            0
        ]
        return T

    # -- serialisation ----------------------------------------------------------------------

    def to_json(self) -> dict[str, float]:
        """``{"latitude": deg, "longitude": deg, "height": m}`` (ellipsoidal height)."""
        return {
            "latitude": self.latitude_deg,
            "longitude": self.longitude_deg,
            "height": self.height_m,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> WorldFrame:
        """Inverse of :meth:`to_json`."""
        try:
            return cls(float(data["latitude"]), float(data["longitude"]), float(data["height"]))
        except KeyError as exc:
            raise ValueError(
                f"world frame JSON needs latitude, longitude, height; missing {exc}"
            ) from exc
