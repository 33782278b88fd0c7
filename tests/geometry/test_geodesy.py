"""WGS84 <-> ECEF <-> world ENU: round trips, axes, meridian convergence."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import Geod

from geometry.geodesy import R_ecef_enu, WorldFrame, ecef_to_geodetic, geodetic_to_ecef
from worker.osdar.ins_poses import world_frame_from_ins
from worker.osdar.ins_tables import InsPva

HAMBURG = WorldFrame(53.5511, 9.9937, 40.0)
GEOD = Geod(ellps="WGS84")


def test_origin_maps_to_zero() -> None:
    p = HAMBURG.geodetic_to_world(53.5511, 9.9937, 40.0)
    assert p.shape == (1, 3)
    np.testing.assert_allclose(p, 0.0, atol=1e-9)


def test_ecef_known_values() -> None:
    # Equator / Greenwich on the ellipsoid: x = semi-major axis.
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 0.0, 0.0), [[6378137.0, 0.0, 0.0]], atol=1e-6)
    # North pole: z = semi-minor axis.
    np.testing.assert_allclose(geodetic_to_ecef(90.0, 0.0, 0.0)[0, 2], 6356752.314245, atol=1e-5)
    lat, lon, h = ecef_to_geodetic([[6378137.0 + 100.0, 0.0, 0.0]])
    np.testing.assert_allclose([lat[0], lon[0], h[0]], [0.0, 0.0, 100.0], atol=1e-9)


@pytest.mark.parametrize(
    "p_world",
    [
        [[0.0, 0.0, 0.0]],
        [[10_000.0, 0.0, 0.0], [0.0, -10_000.0, 0.0], [7_000.0, 7_000.0, 35.0], [-3.2, 5.1, 0.7]],
        [[300_000.0, -800_000.0, -2_000.0], [1.0e6, 1.0e6, 5.0e4]],  # far values
    ],
)
def test_world_geodetic_round_trip(p_world: list[list[float]]) -> None:
    p = np.asarray(p_world)
    lat, lon, h = HAMBURG.world_to_geodetic(p)
    back = HAMBURG.geodetic_to_world(lat, lon, h)
    assert back.dtype == np.float64
    np.testing.assert_allclose(back, p, atol=1e-3, rtol=0)


def test_geodetic_round_trip_10km() -> None:
    # Points on a 10 km ring around the origin, given as geodetic coordinates.
    az = np.linspace(0.0, 360.0, 13)[:-1]
    lon, lat, _ = GEOD.fwd(
        np.full_like(az, 9.9937), np.full_like(az, 53.5511), az, np.full_like(az, 10_000.0)
    )
    h = np.linspace(20.0, 60.0, len(az))
    p = HAMBURG.geodetic_to_world(lat, lon, h)
    np.testing.assert_allclose(np.linalg.norm(p[:, :2], axis=1), 10_000.0, rtol=1e-4)
    lat2, lon2, h2 = HAMBURG.world_to_geodetic(p)
    # 1e-8 deg is ~1 mm.
    np.testing.assert_allclose(lat2, lat, atol=1e-8, rtol=0)
    np.testing.assert_allclose(lon2, lon, atol=1e-8, rtol=0)
    np.testing.assert_allclose(h2, h, atol=1e-3, rtol=0)


def test_ecef_world_round_trip_large_magnitudes() -> None:
    p_ecef = geodetic_to_ecef([53.5, 53.6, 54.0], [9.9, 10.1, 11.0], [0.0, 40.0, 500.0])
    assert np.all(np.linalg.norm(p_ecef, axis=1) > 6.3e6)
    back = HAMBURG.world_to_ecef(HAMBURG.ecef_to_world(p_ecef))
    np.testing.assert_allclose(back, p_ecef, atol=1e-6, rtol=0)


def test_enu_axes_point_east_north_up() -> None:
    lat0, lon0, h0 = HAMBURG.latitude_deg, HAMBURG.longitude_deg, HAMBURG.height_m
    lon_n, lat_n, _ = GEOD.fwd(lon0, lat0, 0.0, 100.0)
    p_n = HAMBURG.geodetic_to_world(lat_n, lon_n, h0)[0]
    np.testing.assert_allclose(p_n[:2], [0.0, 100.0], atol=0.01)
    assert abs(p_n[2]) < 0.01  # the tangent plane drops by d^2 / 2R = 0.8 mm
    lon_e, lat_e, _ = GEOD.fwd(lon0, lat0, 90.0, 100.0)
    p_e = HAMBURG.geodetic_to_world(lat_e, lon_e, h0)[0]
    np.testing.assert_allclose(p_e[:2], [100.0, 0.0], atol=0.01)
    p_u = HAMBURG.geodetic_to_world(lat0, lon0, h0 + 100.0)[0]
    np.testing.assert_allclose(p_u, [0.0, 0.0, 100.0], atol=1e-6)


def test_R_ecef_enu_orthonormal_right_handed() -> None:
    R = R_ecef_enu([53.5511, -33.0, 0.0], [9.9937, 151.2, -70.0])
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-15
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-15)


def test_R_world_enu_at_origin_is_identity() -> None:
    np.testing.assert_allclose(HAMBURG.R_world_enu_at(53.5511, 9.9937)[0], np.eye(3), atol=1e-15)


def test_R_world_enu_at_matches_local_directions() -> None:
    """The local east / north / up at a point 10 km east, measured by finite differences."""
    lon, lat, _ = GEOD.fwd(9.9937, 53.5511, 90.0, 10_000.0)
    h = 40.0
    R = HAMBURG.R_world_enu_at(lat, lon)[0]
    p0 = HAMBURG.geodetic_to_world(lat, lon, h)[0]
    d = 1e-6  # deg, ~0.07 m east, 0.11 m north
    east = HAMBURG.geodetic_to_world(lat, lon + d, h)[0] - p0
    north = HAMBURG.geodetic_to_world(lat + d, lon, h)[0] - p0
    up = HAMBURG.geodetic_to_world(lat, lon, h + 1.0)[0] - p0
    for k, v in enumerate((east, north, up)):
        np.testing.assert_allclose(R[:, k], v / np.linalg.norm(v), atol=2e-7)
    # Meridian convergence: the local north is rotated by ~dlon * sin(lat) about up.
    gamma = np.arctan2(-R[0, 1], R[1, 1])
    expected = np.radians(lon - 9.9937) * np.sin(np.radians(53.5511))
    assert abs(gamma - expected) < 1e-5
    assert abs(gamma) > 1e-3  # it is not negligible at 10 km (~0.07 deg)


def test_T_world_other_round_trip() -> None:
    other = WorldFrame(53.60, 10.05, 25.0)
    T_h_o = HAMBURG.T_world_other(other)
    p_o = np.array([[12.0, -300.0, 4.0], [1000.0, 2000.0, 3.0]])
    lat, lon, h = other.world_to_geodetic(p_o)
    p_h = HAMBURG.geodetic_to_world(lat, lon, h)
    np.testing.assert_allclose(p_o @ T_h_o[:3, :3].T + T_h_o[:3, 3], p_h, atol=1e-6)


def test_json_round_trip_and_validation() -> None:
    d = HAMBURG.to_json()
    assert d == {"latitude": 53.5511, "longitude": 9.9937, "height": 40.0}
    assert WorldFrame.from_json(d) == HAMBURG
    with pytest.raises(ValueError, match="height"):
        WorldFrame.from_json({"latitude": 1.0, "longitude": 2.0})
    with pytest.raises(ValueError):
        WorldFrame(91.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        WorldFrame(float("nan"), 0.0, 0.0)


def _ins(ts: list[float], lat: list[float]) -> InsPva:
    n = len(ts)
    z = np.zeros(n)
    return InsPva(
        frame_idx=np.arange(n, dtype=np.int64),
        timestamp=np.asarray(ts, dtype=np.float64),
        latitude=np.asarray(lat, dtype=np.float64),
        longitude=np.full(n, 9.9937),
        height=np.full(n, 40.0),
        north_velocity=z,
        east_velocity=z,
        up_velocity=z,
        roll=z,
        pitch=z,
        azimuth=z,
    )


def test_world_frame_from_ins_uses_first_record() -> None:
    w = world_frame_from_ins(_ins([2.0, 1.0, 3.0], [53.0, 53.5, 54.0]))
    assert w == WorldFrame(53.5, 9.9937, 40.0)
    with pytest.raises(ValueError):
        world_frame_from_ins(_ins([], []))
