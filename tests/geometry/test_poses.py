"""NovAtel attitude conventions, INS -> base poses, PoseTrack interpolation and CSV."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.geodesy import WorldFrame
from geometry.poses import (
    InsToLidar,
    PoseTrack,
    R_enu_ins_from_novatel,
    novatel_attitude_from_R,
    reexpress,
)
from geometry.transforms import make_T
from worker.osdar.ins_poses import ins_to_base_poses
from worker.osdar.ins_tables import InsPva

HAMBURG = WorldFrame(53.5511, 9.9937, 40.0)
EX, EY, EZ = np.eye(3)


# -- NovAtel attitude -------------------------------------------------------------------------


def test_azimuth_zero_and_ninety() -> None:
    R0 = R_enu_ins_from_novatel(0.0, 0.0, 0.0)[0]
    np.testing.assert_allclose(R0, np.eye(3), atol=1e-15)  # X east, Y north, Z up
    R90 = R_enu_ins_from_novatel(0.0, 0.0, 90.0)[0]
    np.testing.assert_allclose(R90 @ EY, [1.0, 0.0, 0.0], atol=1e-15)  # forward -> east
    np.testing.assert_allclose(R90 @ EX, [0.0, -1.0, 0.0], atol=1e-15)  # right -> south
    R180 = R_enu_ins_from_novatel(0.0, 0.0, 180.0)[0]
    np.testing.assert_allclose(R180 @ EY, [0.0, -1.0, 0.0], atol=1e-15)
    R270 = R_enu_ins_from_novatel(0.0, 0.0, 270.0)[0]
    np.testing.assert_allclose(R270 @ EY, [-1.0, 0.0, 0.0], atol=1e-15)


def test_positive_pitch_raises_the_nose() -> None:
    R = R_enu_ins_from_novatel(0.0, 10.0, 90.0)[0]
    c, s = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
    np.testing.assert_allclose(R @ EY, [c, 0.0, s], atol=1e-15)  # nose east and up
    np.testing.assert_allclose(R @ EX, [0.0, -1.0, 0.0], atol=1e-15)  # right axis stays level


def test_positive_roll_lowers_the_right_side() -> None:
    R = R_enu_ins_from_novatel(10.0, 0.0, 0.0)[0]
    c, s = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
    np.testing.assert_allclose(R @ EX, [c, 0.0, -s], atol=1e-15)  # right side down
    np.testing.assert_allclose(R @ EZ, [s, 0.0, c], atol=1e-15)  # roof tilts right
    np.testing.assert_allclose(R @ EY, [0.0, 1.0, 0.0], atol=1e-15)  # nose unchanged


def test_rotation_order_is_intrinsic_z_x_y() -> None:
    """Heading first, then pitch about the new X, then roll about the new Y (NovAtel)."""
    rng = np.random.default_rng(1)
    roll, pitch, az = rng.uniform(-60, 60, 20), rng.uniform(-60, 60, 20), rng.uniform(0, 360, 20)
    R = R_enu_ins_from_novatel(roll, pitch, az)
    R_ref = Rotation.from_euler("ZXY", np.radians(np.stack([-az, pitch, roll], 1))).as_matrix()
    np.testing.assert_allclose(R, R_ref, atol=1e-14)


def test_attitude_round_trip_with_wrap() -> None:
    rng = np.random.default_rng(2)
    roll = np.concatenate([rng.uniform(-179.9, 179.9, 200), [0.0, 5.0, -5.0, 0.0, 0.0, 0.0]])
    pitch = np.concatenate([rng.uniform(-89.0, 89.0, 200), [0.0, -3.0, 2.0, 0.0, 0.0, 0.0]])
    az_in = np.concatenate(
        [rng.uniform(-720.0, 720.0, 200), [0.0, 359.999, -10.0, 370.0, 360.0, -0.0]]
    )
    r, p, a = novatel_attitude_from_R(R_enu_ins_from_novatel(roll, pitch, az_in))
    assert np.all((a >= 0.0) & (a < 360.0))
    np.testing.assert_allclose(r, roll, atol=1e-9)
    np.testing.assert_allclose(p, pitch, atol=1e-9)
    d_az = (a - az_in + 180.0) % 360.0 - 180.0
    np.testing.assert_allclose(d_az, 0.0, atol=1e-9)
    np.testing.assert_allclose(a[-6:], [0.0, 359.999, 350.0, 10.0, 0.0, 0.0], atol=1e-9)


def test_attitude_gimbal_lock_is_consistent() -> None:
    R = R_enu_ins_from_novatel(30.0, 90.0, 40.0)
    r, p, a = novatel_attitude_from_R(R)
    np.testing.assert_allclose(R_enu_ins_from_novatel(r, p, a), R, atol=1e-9)


# -- INS -> lidar -----------------------------------------------------------------------------


def test_nominal_ins_to_lidar_axes() -> None:
    cal = InsToLidar.nominal()
    R = cal.T_ins_base[:3, :3]
    np.testing.assert_allclose(R @ EX, [0.0, 1.0, 0.0], atol=1e-15)  # base forward = INS Y
    np.testing.assert_allclose(R @ EY, [-1.0, 0.0, 0.0], atol=1e-15)  # base left = -INS X
    np.testing.assert_allclose(R @ EZ, [0.0, 0.0, 1.0], atol=1e-15)
    assert cal.latency_s == 0.0
    np.testing.assert_array_equal(cal.translation, 0.0)


def test_ins_to_lidar_json_round_trip() -> None:
    T = make_T(Rotation.from_euler("xyz", [0.01, -0.02, 1.6]).as_matrix(), [0.3, -1.2, 0.5])
    cal = InsToLidar.from_T(T, latency_s=0.021)
    d = cal.to_json()
    assert set(d) == {"translation", "quaternion", "latency_s"}
    back = InsToLidar.from_json(d)
    np.testing.assert_allclose(back.T_ins_base, T, atol=1e-15)
    assert back.latency_s == 0.021
    assert back == cal and back != InsToLidar.nominal()
    assert InsToLidar.from_json({}) == InsToLidar.nominal()


def _pva(ts: np.ndarray, lat: np.ndarray, lon: np.ndarray, az: np.ndarray) -> InsPva:
    n = len(ts)
    z = np.zeros(n)
    return InsPva(
        frame_idx=np.arange(n, dtype=np.int64) + 7,
        timestamp=ts,
        latitude=lat,
        longitude=lon,
        height=np.full(n, 40.0),
        north_velocity=z,
        east_velocity=z,
        up_velocity=z,
        roll=z,
        pitch=z,
        azimuth=az,
    )


def test_ins_to_base_poses_heading_and_latency_sign() -> None:
    ts = 1631441453.3 + 0.1 * np.arange(3)
    ins = _pva(ts, np.full(3, 53.5511), np.full(3, 9.9937), np.full(3, 90.0))
    cal = InsToLidar(translation=np.array([0.0, 0.0, 0.0]), latency_s=0.05)
    track = ins_to_base_poses(ins, HAMBURG, cal)
    # Stamp t describes the true time t - latency.
    np.testing.assert_allclose(track.timestamps, ts - 0.05, atol=1e-6)
    np.testing.assert_array_equal(track.frame_idx, [7, 8, 9])
    R = track.T[0, :3, :3]
    np.testing.assert_allclose(R @ EX, [1.0, 0.0, 0.0], atol=1e-12)  # base forward = east
    np.testing.assert_allclose(R @ EY, [0.0, 1.0, 0.0], atol=1e-12)  # base left = north
    np.testing.assert_allclose(track.positions, 0.0, atol=1e-9)


def test_ins_to_base_poses_lever_arm_and_meridian_convergence() -> None:
    # An INS 20 km east heading north (azimuth 0 = local north, which is not world +y there).
    lat, lon = np.array([53.5511]), np.array([10.3])
    ins = _pva(np.array([100.0]), lat, lon, np.array([0.0]))
    lever = np.array([0.0, 2.0, 0.0])  # base origin 2 m ahead of the INS
    track = ins_to_base_poses(ins, HAMBURG, InsToLidar(translation=lever))
    R_world_enu = HAMBURG.R_world_enu_at(lat, lon)[0]
    north_world = R_world_enu @ EY
    p_ins = HAMBURG.geodetic_to_world(lat, lon, 40.0)[0]
    np.testing.assert_allclose(track.T[0, :3, 3], p_ins + 2.0 * north_world, atol=1e-9)
    np.testing.assert_allclose(track.T[0, :3, :3] @ EX, north_world, atol=1e-12)
    assert abs(north_world[0]) > 1e-3  # convergence ~0.25 deg, applied


def test_ins_to_base_poses_drops_non_finite() -> None:
    ts = np.arange(3, dtype=np.float64)
    ins = _pva(ts, np.array([53.5511, np.nan, 53.5512]), np.full(3, 9.9937), np.zeros(3))
    assert len(ins_to_base_poses(ins, HAMBURG)) == 2


# -- PoseTrack --------------------------------------------------------------------------------


def _two_pose_track() -> PoseTrack:
    T0 = make_T(np.eye(3), [0.0, 0.0, 0.0])
    T1 = make_T(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [10.0, 2.0, -4.0])
    return PoseTrack([100.0, 101.0], np.stack([T0, T1]))


def test_slerp_midpoint() -> None:
    track = _two_pose_track()
    T = track.interpolate([100.5, 100.25])
    np.testing.assert_allclose(T[0, :3, 3], [5.0, 1.0, -2.0], atol=1e-12)
    ang = Rotation.from_matrix(T[:, :3, :3]).as_euler("zyx", degrees=True)
    np.testing.assert_allclose(ang[:, 0], [45.0, 22.5], atol=1e-9)
    np.testing.assert_allclose(ang[:, 1:], 0.0, atol=1e-9)
    np.testing.assert_allclose(track.interpolate(101.0)[0], track.T[1], atol=1e-12)


def test_extrapolation_constant_velocity_and_limit() -> None:
    track = _two_pose_track()
    T = track.interpolate([101.1, 99.9])
    np.testing.assert_allclose(T[0, :3, 3], [11.0, 2.2, -4.4], atol=1e-12)
    np.testing.assert_allclose(T[1, :3, 3], [-1.0, -0.2, 0.4], atol=1e-12)
    yaw = Rotation.from_matrix(T[:, :3, :3]).as_euler("zyx", degrees=True)[:, 0]
    np.testing.assert_allclose(yaw, [99.0, -9.0], atol=1e-9)
    with pytest.raises(ValueError, match=r"101\.3.*\[100\.0+, 101\.0+\]"):
        track.interpolate([100.5, 101.3])
    with pytest.raises(ValueError, match="outside"):
        track.interpolate(99.7)
    track.interpolate(101.3, max_extrapolation_s=0.5)


def test_single_pose_track() -> None:
    track = PoseTrack([5.0], np.eye(4)[None])
    np.testing.assert_allclose(track.interpolate(5.0)[0], np.eye(4))
    with pytest.raises(ValueError):
        track.interpolate(5.01)


def test_unsorted_and_duplicate_timestamps(caplog: pytest.LogCaptureFixture) -> None:
    Ts = np.tile(np.eye(4), (4, 1, 1))
    Ts[:, 0, 3] = [3.0, 1.0, 2.0, 9.0]
    with caplog.at_level(logging.WARNING, logger="geometry.poses"):
        track = PoseTrack([3.0, 1.0, 2.0, 2.0], Ts, frame_idx=[3, 1, 2, 22])
    assert "duplicate" in caplog.text
    np.testing.assert_array_equal(track.timestamps, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(track.positions[:, 0], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(track.frame_idx, [1, 2, 3])


def test_csv_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 5
    ts = 1631441453.3 + 0.1 * np.arange(n) + np.array([0.0, -0.000496, 0.0021, 0.0, 0.000001])
    ts = np.round(ts, 6)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 1, (n, 3))).as_matrix()
    T[:, :3, 3] = rng.normal(0, 300.0, (n, 3))
    track = PoseTrack(ts, T)
    path = tmp_path / "poses.csv"
    track.to_csv(path, frame_idx=np.arange(n) + 12)
    text = path.read_text().splitlines()
    assert text[0] == "frame_idx,timestamp,x,y,z,qx,qy,qz,qw"
    assert text[1].startswith("12,1631441453.300000000,")
    back = PoseTrack.from_csv(path)
    np.testing.assert_array_equal(back.timestamps, track.timestamps)
    np.testing.assert_array_equal(back.positions, track.positions)
    np.testing.assert_allclose(back.T, track.T, atol=1e-15)
    np.testing.assert_array_equal(back.frame_idx, np.arange(n) + 12)
    back.to_csv(tmp_path / "again.csv")  # uses its own frame_idx
    again = (tmp_path / "again.csv").read_text().splitlines()
    # Time and position text is identical; quaternions may differ in the last ulp (via R).
    assert [r.split(",")[:5] for r in again] == [r.split(",")[:5] for r in text]
    PoseTrack(ts, T).to_csv(tmp_path / "dense.csv")  # no frame numbers: -1
    np.testing.assert_array_equal(PoseTrack.from_csv(tmp_path / "dense.csv").frame_idx, -1)


def test_relative_errors() -> None:
    track = _two_pose_track()
    offset = make_T(Rotation.from_euler("x", 1.0, degrees=True).as_matrix(), [0.0, 0.1, 0.0])
    other = PoseTrack(track.timestamps, track.T @ offset)
    dt, dr = track.relative_errors(other)
    np.testing.assert_allclose(dt, 0.1, atol=1e-12)
    np.testing.assert_allclose(dr, 1.0, atol=1e-9)
    dt0, dr0 = track.relative_errors(track)
    np.testing.assert_allclose(dt0, 0.0, atol=0)
    np.testing.assert_allclose(dr0, 0.0, atol=1e-6)


def test_reexpress_is_exact() -> None:
    other = WorldFrame(53.56, 10.01, 30.0)
    track = _two_pose_track()
    moved = reexpress(track, HAMBURG, other)
    # A point fixed on the vehicle has the same geodetic coordinates in both frames.
    p_h = track.T[:, :3, 3]
    p_o = moved.T[:, :3, 3]
    np.testing.assert_allclose(
        np.stack(other.world_to_geodetic(p_o)), np.stack(HAMBURG.world_to_geodetic(p_h)), atol=1e-9
    )
    back = reexpress(moved, other, HAMBURG)
    np.testing.assert_allclose(back.T, track.T, atol=1e-9)
