"""Synthetic INS: exactness with no errors, error magnitudes, determinism, latency sign."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.geodesy import WorldFrame
from geometry.poses import InsToLidar, PoseTrack
from geometry.transforms import invert_T
from worker.osdar.ins_poses import ins_to_base_poses, world_frame_from_ins
from worker.synth.ins_sim import (
    HAMBURG,
    IMU_RATE_HZ,
    InsErrorModel,
    reexpress,
    simulate_ins,
    unix_to_gps_week,
)

T0 = 1631441453.3
FX_PX = 4609.5  # rgb_center focal length

PoseFn = Callable[[np.ndarray], np.ndarray]


def arc(
    speed: float = 10.0,
    yaw_rate: float = 0.02,
    yaw0: float = 0.3,
    grade: float = 0.01,
    start: tuple[float, float, float] = (5.0, -3.0, 0.5),
) -> PoseFn:
    """Exact true T_world_base(t): constant speed on a circular arc with a constant grade.

    yaw is the angle of base x (forward) from east, counter-clockwise; uphill is nose up
    (a negative rotation about base y, which points left).
    """

    def f(t: np.ndarray) -> np.ndarray:
        s = np.asarray(t, dtype=np.float64) - T0
        yaw = yaw0 + yaw_rate * s
        if yaw_rate == 0.0:
            x, y = speed * s * np.cos(yaw0), speed * s * np.sin(yaw0)
        else:
            r = speed / yaw_rate
            x, y = r * (np.sin(yaw) - np.sin(yaw0)), -r * (np.cos(yaw) - np.cos(yaw0))
        T = np.tile(np.eye(4), (len(s), 1, 1))
        pitch = np.full_like(s, -np.arctan(grade))
        T[:, :3, :3] = Rotation.from_euler("ZY", np.stack([yaw, pitch], 1)).as_matrix()
        T[:, :3, 3] = np.stack([x, y, grade * speed * s], 1) + start
        return T

    return f


def frames(n: int = 100) -> tuple[np.ndarray, np.ndarray]:
    jitter = np.tile([0.0, 0.0013, -0.0021, 0.0004], n)[:n]
    return T0 + 0.1 * np.arange(n) + jitter, np.arange(n, dtype=np.int64) + 12


def truth_in(ins_world: WorldFrame, f: PoseFn, ts: np.ndarray) -> PoseTrack:
    """The true base track at ts, re-expressed in the INS-defined world frame."""
    return reexpress(PoseTrack(ts, f(ts)), HAMBURG, ins_world)


def test_perfect_profile_reproduces_true_poses() -> None:
    f = arc()
    ts, fi = frames()
    sim = simulate_ins(f, ts, fi, InsErrorModel.profile("perfect"))
    assert len(sim.inspva) == len(ts)
    assert sim.world == world_frame_from_ins(sim.inspva)
    # With no error the nominal assumption is the truth.
    for cal in (sim.ins_to_lidar, InsToLidar.nominal()):
        est = ins_to_base_poses(sim.inspva, sim.world, cal)
        dt, dr = est.relative_errors(truth_in(sim.world, f, ts))
        assert dt.max() < 1e-3
        assert np.radians(dr.max()) < 1e-6


def test_true_calibration_recovers_misaligned_latent_ins() -> None:
    """Lever arm + boresight + latency without noise: the TRUE calibration undoes them."""
    f = arc()
    ts, fi = frames()
    model = InsErrorModel(
        lever_arm_m=(0.8, -0.3, 0.4), boresight_deg=(0.2, -0.4, 1.5), latency_s=0.03
    )
    sim = simulate_ins(f, ts, fi, model)
    est = ins_to_base_poses(sim.inspva, sim.world, sim.ins_to_lidar)
    np.testing.assert_allclose(est.timestamps, ts - 0.03, atol=1e-6)
    dt, dr = est.relative_errors(
        PoseTrack(est.timestamps, f(est.timestamps)).transformed(sim.world.T_world_other(HAMBURG))
    )
    assert dt.max() < 1e-3 and np.radians(dr.max()) < 1e-6
    # With the nominal assumption the raw INS sees T_world_base @ make_T(R_bore, lever_arm).
    raw = ins_to_base_poses(sim.inspva, sim.world, InsToLidar.nominal())
    truth = reexpress(PoseTrack(ts - 0.03, f(ts - 0.03)), HAMBURG, sim.world)
    T_err = invert_T(truth.T) @ raw.T
    np.testing.assert_allclose(
        T_err[:, :3, 3], np.broadcast_to(model.lever_arm_m, (100, 3)), atol=1e-6
    )
    ypr = Rotation.from_matrix(T_err[:, :3, :3]).as_euler("ZYX", degrees=True)
    np.testing.assert_allclose(ypr, np.broadcast_to([1.5, -0.4, 0.2], (100, 3)), atol=1e-6)
    j = InsToLidar.from_json(sim.ins_to_lidar.to_json())
    np.testing.assert_allclose(j.T_ins_base, invert_T(model.T_base_ins), atol=1e-15)


def test_velocity_and_attitude_tables() -> None:
    # Heading north-east (yaw0 = 45 deg from east => azimuth 45), straight, 1 % uphill.
    f = arc(speed=12.0, yaw_rate=0.0, yaw0=np.pi / 4, grade=0.01)
    ts, fi = frames(20)
    sim = simulate_ins(f, ts, fi, InsErrorModel.profile("perfect"))
    v = 12.0 * np.sqrt(0.5)
    np.testing.assert_allclose(sim.inspva.north_velocity, v, rtol=1e-3)
    np.testing.assert_allclose(sim.inspva.east_velocity, v, rtol=1e-3)
    np.testing.assert_allclose(sim.inspva.up_velocity, 0.12, atol=2e-3)
    np.testing.assert_allclose(sim.inspva.azimuth, 45.0, atol=1e-3)
    np.testing.assert_allclose(sim.inspva.pitch, np.degrees(np.arctan(0.01)), atol=1e-3)
    np.testing.assert_allclose(sim.inspva.roll, 0.0, atol=1e-3)
    assert np.all(sim.insstdev.latitude_stdev < 0.1) and np.all(sim.insstdev.latitude_stdev > 0.005)


def test_corrimu_increments_on_a_left_turn() -> None:
    speed, omega = 10.0, 0.05  # left turn (counter-clockwise seen from above)
    f = arc(speed=speed, yaw_rate=omega, grade=0.0)
    ts, fi = frames(30)
    sim = simulate_ins(f, ts, fi, InsErrorModel.profile("perfect"))
    c = sim.corrimu
    np.testing.assert_allclose(c.yaw_rate, omega / IMU_RATE_HZ, rtol=1e-3)  # right-handed about Z
    np.testing.assert_allclose(c.pitch_rate, 0.0, atol=1e-9)
    np.testing.assert_allclose(c.roll_rate, 0.0, atol=1e-9)
    # Centripetal acceleration v * omega points left, i.e. along -X (X is right).
    np.testing.assert_allclose(c.lateral_acc, -speed * omega / IMU_RATE_HZ, rtol=1e-3)
    np.testing.assert_allclose(c.longitudinal_acc, 0.0, atol=1e-6)
    np.testing.assert_allclose(c.vertical_acc, 0.0, atol=1e-6)
    week, ms = unix_to_gps_week([T0])
    assert week[0] == 2175  # GPS week of 2021-09-12
    assert c.gps_week_number[0] == 2175
    np.testing.assert_allclose(
        c.gps_week_milliseconds[1] - c.gps_week_milliseconds[0], 101.3, atol=1e-3
    )
    assert 0 <= ms[0] < 604800e3


def test_determinism_from_seed() -> None:
    f = arc()
    ts, fi = frames()
    hard = InsErrorModel.profile("hard", seed=5)
    a = simulate_ins(f, ts, fi, hard)
    b = simulate_ins(f, ts, fi, hard)
    c = simulate_ins(f, ts, fi, InsErrorModel.profile("hard", seed=6))
    for name in ("latitude", "longitude", "height", "azimuth", "north_velocity"):
        np.testing.assert_array_equal(getattr(a.inspva, name), getattr(b.inspva, name))
    np.testing.assert_array_equal(a.insstdev.latitude_stdev, b.insstdev.latitude_stdev)
    np.testing.assert_array_equal(a.dropped_frames, b.dropped_frames)
    assert not np.array_equal(a.inspva.latitude[:5], c.inspva.latitude[:5])


def _enu_errors(model: InsErrorModel, n: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """Reported minus true INS positions (world ENU ~ local ENU near the origin)."""
    f = arc(speed=5.0)
    ts, fi = frames(n)
    sim = simulate_ins(f, ts, fi, model)
    p_rep = HAMBURG.geodetic_to_world(sim.inspva.latitude, sim.inspva.longitude, sim.inspva.height)
    p_true = (f(ts) @ model.T_base_ins)[:, :3, 3]
    return p_rep - p_true, ts


def test_white_position_noise_magnitude() -> None:
    err, _ = _enu_errors(InsErrorModel(position_noise_m=(0.05, 0.05, 0.1), seed=1))
    np.testing.assert_allclose(err.std(axis=0), [0.05, 0.05, 0.1], rtol=0.15)
    np.testing.assert_allclose(err.mean(axis=0), 0.0, atol=0.015)


def test_random_walk_magnitude() -> None:
    err, ts = _enu_errors(InsErrorModel(position_random_walk_m=(0.1, 0.1, 0.0), seed=2))
    steps = np.diff(err, axis=0) / np.sqrt(np.diff(ts))[:, None]
    np.testing.assert_allclose(steps[:, :2].std(axis=0), 0.1, rtol=0.15)
    np.testing.assert_allclose(err[0], 0.0, atol=1e-6)  # starts at the truth


def test_paper_profile_raw_ins_errors() -> None:
    """Raw INS (nominal assumption) vs truth: dm-level positions, ~0.5 deg, tens of px."""
    f = arc()
    ts, fi = frames()
    model = InsErrorModel.profile("paper", seed=3)
    sim = simulate_ins(f, ts, fi, model)
    raw = ins_to_base_poses(sim.inspva, sim.world, InsToLidar.nominal())
    truth = truth_in(sim.world, f, ts)
    dt, dr = raw.relative_errors(truth)
    assert 0.2 < dt.mean() < 1.5
    bore = np.linalg.norm(model.boresight_deg)
    assert abs(np.median(dr) - bore) < 0.15
    # Pixel error of landmarks 30-80 m ahead (pinhole, x forward -> depth).
    p_base = np.array([[30.0, 3.0, 1.0], [50.0, -4.0, 3.0], [80.0, 5.0, 6.0]])
    px = []
    for T_true, T_raw in zip(truth.T, raw.T, strict=True):
        p_world = p_base @ T_true[:3, :3].T + T_true[:3, 3]
        T_inv = invert_T(T_raw)
        q = p_world @ T_inv[:3, :3].T + T_inv[:3, 3]
        uv_true = FX_PX * p_base[:, 1:] / p_base[:, :1]
        uv_raw = FX_PX * q[:, 1:] / q[:, :1]
        px.append(np.linalg.norm(uv_raw - uv_true, axis=1))
    px = np.concatenate(px)
    assert 10.0 < px.mean() < 150.0


def test_dropouts_remove_rows() -> None:
    f = arc()
    ts, fi = frames()
    sim = simulate_ins(f, ts, fi, InsErrorModel(dropout_frames=[12, 50, 111]))
    assert len(sim.inspva) == len(sim.insstdev) == len(sim.corrimu) == 97
    assert not np.isin([12, 50, 111], sim.inspva.frame_idx).any()
    np.testing.assert_array_equal(sim.dropped_frames, [12, 50, 111])
    # The world frame is the first *reported* record: frame 13 here.
    assert sim.world.latitude_deg == sim.inspva.latitude[0]
    assert sim.inspva.frame_idx[0] == 13
    sim2 = simulate_ins(f, ts, fi, InsErrorModel(dropout_fraction=0.3, seed=4))
    assert 50 < len(sim2.inspva) < 90
    with pytest.raises(ValueError):
        simulate_ins(f, ts[:2], fi[:2], InsErrorModel(dropout_frames=[12, 13]))


def test_gnss_jump_steps_and_stdev() -> None:
    model = InsErrorModel(jumps=[(62, (1.0, -0.5, 0.0))])
    err, _ = _enu_errors(model, n=100)
    k = 62 - 12
    np.testing.assert_allclose(err[:k], 0.0, atol=1e-6)
    np.testing.assert_allclose(err[k:, :2], np.broadcast_to([1.0, -0.5], (100 - k, 2)), atol=1e-3)
    sim = simulate_ins(arc(), *frames(100), model)
    sd = sim.insstdev.latitude_stdev
    assert sd[k] > 5.0 * np.median(sd[:k])
    random_jumps = InsErrorModel(jump_rate_hz=0.5, jump_magnitude_m=1.0, jump_decay_s=2.0, seed=9)
    err_r, _ = _enu_errors(random_jumps, n=200)
    assert np.abs(err_r).max() > 0.3


def test_latency_shifts_positions_back_along_the_track() -> None:
    speed, lat_s = 10.0, 0.05
    f = arc(speed=speed, yaw_rate=0.0, yaw0=np.pi / 2, grade=0.0)  # due north
    ts, fi = frames(30)
    sim = simulate_ins(f, ts, fi, InsErrorModel(latency_s=lat_s))
    # Ignoring the latency: the pose at stamp t is the true pose at t - latency, i.e. behind.
    raw = ins_to_base_poses(sim.inspva, sim.world, InsToLidar.nominal())
    truth = truth_in(sim.world, f, ts)
    d = raw.positions - truth.positions
    np.testing.assert_allclose(d[:, 1], -speed * lat_s, atol=1e-3)  # 0.5 m south = behind
    np.testing.assert_allclose(d[:, [0, 2]], 0.0, atol=1e-3)
    # With the true latency the records move to t - latency and match the truth there.
    fixed = ins_to_base_poses(sim.inspva, sim.world, sim.ins_to_lidar)
    dt, _ = fixed.relative_errors(truth, max_extrapolation_s=0.1)
    assert dt.max() < 1e-3
    # Reading the INS track at a sensor time t uses stamp t + latency: the truth at t.
    t_sensor = ts[5:10] + 0.003
    np.testing.assert_allclose(
        fixed.interpolate(t_sensor)[:, :3, 3], truth.interpolate(t_sensor)[:, :3, 3], atol=1e-3
    )


def test_profiles() -> None:
    assert InsErrorModel.profile("perfect") == InsErrorModel()
    good, paper = InsErrorModel.profile("good"), InsErrorModel.profile("paper")
    assert max(good.boresight_deg) < max(paper.boresight_deg)
    assert 0.3 <= paper.boresight_deg[2] <= 0.5 and 0.2 <= paper.boresight_deg[1] <= 0.3
    assert paper.latency_s == pytest.approx(0.02)
    assert InsErrorModel.profile("paper", seed=7).seed == 7
    with pytest.raises(ValueError, match="unknown"):
        InsErrorModel.profile("nope")
    assert InsErrorModel.model_validate_json(paper.model_dump_json()) == paper


def test_accepts_pose_track_input() -> None:
    f = arc()
    ts, fi = frames(40)
    dense_t = T0 - 0.5 + 0.01 * np.arange(500)
    sim_track = simulate_ins(
        PoseTrack(dense_t, f(dense_t)), ts, fi, InsErrorModel.profile("perfect")
    )
    sim_fn = simulate_ins(f, ts, fi, InsErrorModel.profile("perfect"))
    d = HAMBURG.geodetic_to_world(
        sim_track.inspva.latitude, sim_track.inspva.longitude, sim_track.inspva.height
    ) - HAMBURG.geodetic_to_world(
        sim_fn.inspva.latitude, sim_fn.inspva.longitude, sim_fn.inspva.height
    )
    assert np.abs(d).max() < 1e-3


def test_slow_drift_is_large_but_smooth() -> None:
    """The "osdar23" drift: decimetres and tenths of a degree over the run, small per frame."""
    from worker.synth.ins_sim import _smooth_drift

    t = np.arange(0.0, 200.0, 0.1)
    sigma = np.array([0.5, 0.5, 0.15, 0.5])
    d = _smooth_drift(np.random.default_rng(0), t, sigma, 10.0)
    assert np.allclose(d.std(axis=0), sigma, rtol=0.25)
    step = np.abs(np.diff(d, axis=0)).max(axis=0)
    # periods of 6-17 s: at most ~0.17 sigma per 0.1 s frame (white noise would step ~1.4)
    assert np.all(step < 0.3 * sigma)
    model = InsErrorModel.profile("osdar23")
    assert model.heading_drift_deg > 0 and model.position_drift_m[0] > 0
    assert InsErrorModel.profile("paper").heading_drift_deg == 0.0  # other profiles unchanged
