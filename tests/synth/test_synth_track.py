"""Railway alignment geometry of the synthetic scene."""

from __future__ import annotations

import numpy as np
import pytest

from worker.synth.track import RAIL_HEAD_SPACING, AlignedTrack, Alignment, Profile


def _circle_radius(p: np.ndarray) -> float:
    p = p - p[0]  # far-origin coordinates: fit relative to a nearby point
    A = np.column_stack([2 * p[:, 0], 2 * p[:, 1], np.ones(len(p))])
    b = (p[:, :2] ** 2).sum(1)
    c = np.linalg.lstsq(A, b, rcond=None)[0]
    return float(np.sqrt(c[2] + c[0] ** 2 + c[1] ** 2))


@pytest.fixture
def curve() -> AlignedTrack:
    al = Alignment().straight(100.0).clothoid(60.0, 190.0, 0.15).arc(150.0)
    al.clothoid(60.0, None, 0.0).straight(50.0)
    return AlignedTrack(al, (5.0e5, 5.9e6, 30.0), 0.4, Profile((0.0, 200.0), (0.0, 0.01)))


def test_arc_radius_and_length(curve: AlignedTrack) -> None:
    assert curve.length == pytest.approx(420.0)
    p = curve.point(np.linspace(165.0, 305.0, 15))
    assert _circle_radius(p) == pytest.approx(190.0, abs=1e-6)
    # straight part is straight
    q = curve.point(np.linspace(0, 100, 11))[:, :2]
    d = q - q[0]
    assert np.abs(d[:, 0] * d[-1, 1] - d[:, 1] * d[-1, 0]).max() < 1e-6


def test_clothoid_curvature_linear_and_heading_consistent(curve: AlignedTrack) -> None:
    s = np.linspace(101.0, 159.0, 30)
    k = curve.curvature(s)
    np.testing.assert_allclose(k, (s - 100.0) / 60.0 / 190.0, atol=1e-12)
    # heading from finite differences of points
    h = 1e-2
    dp = curve.point(s + h)[:, :2] - curve.point(s - h)[:, :2]
    np.testing.assert_allclose(np.arctan2(dp[:, 1], dp[:, 0]), curve.heading(s), atol=1e-7)
    # curvature from heading differences
    np.testing.assert_allclose(
        (curve.heading(s + h) - curve.heading(s - h)) / (2 * h), k, atol=1e-8
    )


def test_cant_ramps_and_roll(curve: AlignedTrack) -> None:
    np.testing.assert_allclose(curve.cant([50.0, 130.0, 200.0, 400.0]), [0.0, 0.075, 0.15, 0.0])
    T = curve.frame_at(200.0)[0]
    left, right = curve.rail_points(200.0, "left")[0], curve.rail_points(200.0, "right")[0]
    assert np.linalg.norm(left - right) == pytest.approx(RAIL_HEAD_SPACING)
    assert right[2] - left[2] == pytest.approx(0.15, abs=1e-3)  # left curve: right rail up
    assert np.arcsin(-T[2, 1]) == pytest.approx(np.arcsin(0.15 / RAIL_HEAD_SPACING), abs=2e-3)
    np.testing.assert_allclose(0.5 * (left + right), T[:3, 3], atol=1e-9)


def test_frames_orthonormal_on_centreline(curve: AlignedTrack) -> None:
    s = np.linspace(0.0, curve.length, 57)
    T = curve.frame_at(s)
    R = T[:, :3, :3]
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(T[:, :3, 3], curve.point(s), atol=1e-9)
    np.testing.assert_allclose(R[:, :, 0], curve.tangent(s), atol=1e-12)
    # gradient: z rises 1 % after 200 m
    assert curve.tangent(300.0)[0, 2] == pytest.approx(0.01 / np.hypot(1, 0.01), abs=1e-9)
    dz = curve.point(310.0)[0, 2] - curve.point(300.0)[0, 2]
    assert dz == pytest.approx(0.1, abs=1e-9)


def test_parallel_offset_distance(curve: AlignedTrack) -> None:
    par = curve.offset(4.5, 1)
    s = np.linspace(0.0, par.length, 40)
    p = par.point(s)
    sp = par.to_parent(s)
    d = p[:, :2] - curve.point(sp)[:, :2]
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 4.5, atol=1e-9)
    # perpendicular to the parent's tangent, so it is truly the nearest distance
    np.testing.assert_allclose(np.einsum("ij,ij->i", d, curve.tangent(sp)[:, :2]), 0.0, atol=1e-9)
    # inner track of a left curve is shorter
    assert par.length == pytest.approx(
        curve.length - 4.5 * (curve.heading(curve.length)[0] - 0.4), abs=1e-3
    )


def test_branch_tangent_continuity(curve: AlignedTrack) -> None:
    br = curve.branch(50.0, 300.0, "right", 120.0, 2, turn_angle=1 / 9)
    np.testing.assert_allclose(br.point(0.0), curve.point(50.0), atol=1e-9)
    np.testing.assert_allclose(br.tangent(0.0), curve.tangent(50.0), atol=1e-9)
    assert br.heading(30.0)[0] == pytest.approx(0.4 - 30.0 / 300.0)
    assert br.heading(100.0)[0] == pytest.approx(0.4 - 1 / 9)
    h = 1e-2
    s_end = 300.0 / 9
    assert np.linalg.norm((br.point(s_end + h) - br.point(s_end - h))[0, :2]) == pytest.approx(
        2 * h, rel=1e-6
    )


def test_a_body_on_two_bogies_stands_outside_the_curve() -> None:
    """The generator's train on two bogies (overhang a = 3 m, spacing b = 19 m) in a flat
    R = 600 m arc: its base lies a (a + b) / 2R = 5.5 cm outside the centreline, its
    heading is the chord's, (a + b / 2) / R = 1.19 deg short of the tangent's at the base,
    its up axis is the rail plane's; on a straight it is on the centreline."""
    from scipy.spatial.transform import Rotation

    from worker.synth.generator import Trajectory

    al = Alignment().straight(100.0).arc(200.0, 600.0)
    track = AlignedTrack(al, (0.0, 0.0, 0.0), 0.0, Profile())
    traj = Trajectory(track, 0.0, 10.0, 0.0, 0.0, seed=0, body_motion=False, bogies=(3.0, 19.0))
    s = np.array([60.0, 200.0])  # straight; well inside the arc
    T = traj(s / 10.0)
    on = track.frame_at(s)
    np.testing.assert_allclose(T[0], on[0], atol=1e-9)
    lateral = (T[1, :3, 3] - on[1, :3, 3]) @ on[1, :3, 1]  # left +; the arc turns left
    assert lateral == pytest.approx(-3.0 * 22.0 / 1200.0, abs=2e-4)
    yaw = Rotation.from_matrix(on[1, :3, :3].T @ T[1, :3, :3]).as_rotvec()
    assert np.degrees(yaw[2]) == pytest.approx(-np.degrees(12.5 / 600.0), abs=2e-3)
    np.testing.assert_allclose(T[1, :3, 2], on[1, :3, 2], atol=1e-9)
