"""Tests of the synthetic lidar (worker/synth/lidar_sim.py) on small procedural scenes."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from geometry.transforms import invert_T, pose_to_T, transform_points
from worker.synth.lidar_sim import (
    NOISE_TRUNCATION,
    LidarSimulator,
    cloud_points,
    default_sensors,
    sensors_to_json,
)
from worker.synth.scene_mesh import MATERIAL_ID, SceneMesh

# A UTM-like world offset: float32 must never see these magnitudes.
OFFSET = np.array([565_432.1, 5_933_210.7, 12.3])
FRAME_TIME = 1_631_441_453.3
POLE_XY = np.array([18.0, -4.0])  # relative to OFFSET
POLE_SIZE = np.array([0.4, 0.4, 7.0])
WALL_X = 35.0


def box(center: np.ndarray, size: np.ndarray, material: str) -> SceneMesh:
    """Axis-aligned box (12 triangles, outward normals)."""
    c = np.asarray(center, dtype=np.float64)
    h = 0.5 * np.asarray(size, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    v = c + corners * h
    # vertex index = 4*ix + 2*iy + iz
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = []
    for a, b, cc, d in quads:
        faces += [(a, b, cc), (a, cc, d)]
    return SceneMesh(v, faces, np.full(12, MATERIAL_ID[material]))


def plane(half: float, z: float, material: str = "ground") -> SceneMesh:
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return SceneMesh(v, [[0, 1, 2], [0, 2, 3]], [MATERIAL_ID[material]] * 2)


def railway_scene(offset: np.ndarray = OFFSET, wall: bool = True) -> SceneMesh:
    """Ground, two rails, a pole and (optionally) a wall across the track ahead."""
    # Rails in 5 m pieces: open3d's closest-point query (used by mesh_distance) is off by
    # centimetres on 400 m x 7 cm sliver triangles; ray casting itself is fine on them.
    rails = [
        box([x, y, -0.085], [5.0, 0.07, 0.17], "rail")
        for x in np.arange(-197.5, 200.0, 5.0)
        for y in (0.7175, -0.7175)
    ]
    parts = [
        plane(700.0, -0.5),
        *rails,
        box([*POLE_XY, -0.5 + POLE_SIZE[2] / 2], POLE_SIZE, "pole"),
    ]
    if wall:
        parts.append(box([WALL_X, 0.0, 4.0], [0.5, 60.0, 9.0], "building"))
    mesh = SceneMesh.concatenate(parts)
    mesh.vertices = mesh.vertices + offset
    return mesh


def moving_pose(
    speed: float = 20.0, yaw_rate: float = 0.3, offset: np.ndarray = OFFSET
) -> Callable[[np.ndarray], np.ndarray]:
    """T_world_base(t): moving along x at ``speed`` and turning at ``yaw_rate``."""

    def pose_at(t: np.ndarray) -> np.ndarray:
        tau = np.asarray(t, dtype=np.float64) - FRAME_TIME
        T = np.tile(np.eye(4), (len(tau), 1, 1))
        T[:, :3, :3] = Rotation.from_rotvec(np.outer(yaw_rate * tau, [0.0, 0.0, 1.0])).as_matrix()
        T[:, 0, 3] = speed * tau
        T[:, :3, 3] += offset
        return T

    return pose_at


def mesh_distance(mesh: SceneMesh, p_world: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Unsigned distance (n,) of world points to the mesh, via open3d, origin-relative."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((mesh.vertices - origin).astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    q = o3d.core.Tensor((p_world - origin).astype(np.float32))
    return scene.compute_distance(q).numpy().astype(np.float64)


@pytest.fixture(scope="module")
def moving_scan() -> tuple[SceneMesh, LidarSimulator, dict, dict]:
    mesh = railway_scene()
    sim = LidarSimulator(mesh, origin=OFFSET, seed=3, density=0.25)
    cloud, truth = sim.scan_with_ground_truth(FRAME_TIME, moving_pose())
    return mesh, sim, cloud, truth


def test_default_sensors_and_json() -> None:
    sensors = default_sensors()
    assert [s.sensor_index for s in sensors] == [0, 1, 2, 3, 4, 5]
    assert "Pandar64" in sensors[0].model
    assert all("Tele-15" in s.model for s in sensors[1:4])
    assert all("Honeycomb" in s.model for s in sensors[4:])
    z = [s.T_base_sensor[2, 3] for s in sensors]
    assert z[0] == max(z) and 3.0 <= z[0] <= 3.6
    assert max(z[4:]) < min(z[:4])  # honeycombs low
    assert sensors[4].T_base_sensor[1, 3] > 0 > sensors[5].T_base_sensor[1, 3]  # left, right
    # livox right / centre / left, each looking slightly outward
    fwd = [s.T_base_sensor[:3, 0] for s in sensors[1:4]]
    assert fwd[0][1] < 0 and abs(fwd[1][1]) < 1e-12 and fwd[2][1] > 0
    assert all(f[2] < 0 for f in fwd)  # slightly down
    js = sensors_to_json(sensors)
    assert [j["sensor_index"] for j in js] == list(range(6))
    for s, j in zip(sensors, js, strict=True):
        assert set(j) == {"sensor_index", "name", "model", "translation", "quaternion"}
        np.testing.assert_allclose(
            pose_to_T(j["translation"], j["quaternion"]), s.T_base_sensor, atol=1e-12
        )


def test_output_fields(moving_scan) -> None:
    _, _, cloud, truth = moving_scan
    assert {k: v.dtype for k, v in cloud.items()} == {
        "x": np.float32,
        "y": np.float32,
        "z": np.float32,
        "intensity": np.float32,
        "timestamp": np.float64,
        "sensor_index": np.uint8,
    }
    n = len(cloud["x"])
    assert n > 1000 and all(len(v) == n for v in cloud.values())
    assert truth["hit_world"].shape == (n, 3) and truth["hit_world"].dtype == np.float64
    assert set(np.unique(cloud["sensor_index"]).tolist()) == {0, 1, 2, 3, 4, 5}
    dt = cloud["timestamp"] - FRAME_TIME
    assert dt.min() >= -0.05 - 1e-6 and dt.max() < 0.05 + 1e-6
    # spinning sensors are phase-locked: straight ahead at the frame time
    p = cloud_points(cloud)
    ahead = (cloud["sensor_index"] == 0) & (np.abs(p[:, 1]) < 0.05 * p[:, 0])
    assert np.abs(dt[ahead]).max() < 0.002
    # intensity scales: Pandar / Livox integer 0..255, Honeycomb in [0, 1]
    i = cloud["intensity"]
    hc = cloud["sensor_index"] >= 4
    assert np.all(i >= 0) and i[~hc].max() <= 255 and np.all(i[~hc] == np.round(i[~hc]))
    assert i[~hc].max() > 1.0 and i[hc].max() <= 1.0 and i[hc].max() > 0.0
    # brighter rails than ground for the same sensor at similar range
    mat = truth["face_material"]
    near = (truth["range_true"] < 15) & (cloud["sensor_index"] == 0)
    rail = i[near & (mat == MATERIAL_ID["rail"])]
    ground = i[near & (mat == MATERIAL_ID["ground"])]
    assert rail.size and ground.size and np.median(rail) > np.median(ground)


def test_points_on_mesh_surface(moving_scan) -> None:
    """Deskewed output points, taken back to the world at frame_time, lie on the mesh."""
    mesh, sim, cloud, truth = moving_scan
    sigma = np.array([s.range_sigma for s in sim.sensors])[cloud["sensor_index"]]
    d_true = mesh_distance(mesh, truth["hit_world"], OFFSET)
    assert d_true.max() < 1e-3
    p_world = transform_points(truth["T_world_base"], cloud_points(cloud))
    d = mesh_distance(mesh, p_world, OFFSET)
    assert np.all(d < NOISE_TRUNCATION * sigma + 1e-3)
    assert np.mean(d < 3 * sigma + 1e-3) > 0.99
    # the range noise is there, with about the sensor's sigma
    err = truth["range_measured"] - truth["range_true"]
    assert 0.7 < np.std(err / sigma) < 1.3


def test_pole_points_at_true_position(moving_scan) -> None:
    _, _, cloud, truth = moving_scan
    pole = truth["face_material"] == MATERIAL_ID["pole"]
    assert pole.sum() > 20
    assert {0, 4, 5} & set(np.unique(cloud["sensor_index"][pole]).tolist())
    p_world = transform_points(truth["T_world_base"], cloud_points(cloud)[pole]) - OFFSET
    tol = NOISE_TRUNCATION * 0.025 + 1e-3
    lo = np.array([*(POLE_XY - POLE_SIZE[:2] / 2), -0.5]) - tol
    hi = np.array([*(POLE_XY + POLE_SIZE[:2] / 2), -0.5 + POLE_SIZE[2]]) + tol
    assert np.all((p_world >= lo) & (p_world <= hi))
    # and in the base frame at frame_time the pole is where the true pose puts it
    centre_base = transform_points(
        invert_T(truth["T_world_base"]), np.array([[*(OFFSET[:2] + POLE_XY), OFFSET[2]]])
    )[0]
    p_base = cloud_points(cloud)[pole]
    assert np.abs(np.median(p_base[:, :2], axis=0) - centre_base[:2]).max() < 0.3


def test_motion_compensation_no_smear(moving_scan) -> None:
    """A static wall hit over ~0.04 s of a 20 m/s, turning sweep stays a thin plane."""
    _, _, cloud, truth = moving_scan
    wall = (truth["face_material"] == MATERIAL_ID["building"]) & (cloud["sensor_index"] == 0)
    assert wall.sum() > 200
    dt = cloud["timestamp"][wall] - FRAME_TIME
    assert dt.max() - dt.min() > 0.015
    p_world = transform_points(truth["T_world_base"], cloud_points(cloud)[wall])
    resid = p_world[:, 0] - OFFSET[0] - (WALL_X - 0.25)
    assert np.abs(resid).max() < NOISE_TRUNCATION * 0.02 + 1e-3
    assert np.std(resid) < 0.03
    # without deskewing (each point in the base frame of its own emission time) it smears
    pose_at = moving_pose()
    T_base_world_i = invert_T(pose_at(cloud["timestamp"][wall]))
    hw = truth["hit_world"][wall]
    p_naive = np.einsum("nij,nj->ni", T_base_world_i[:, :3, :3], hw) + T_base_world_i[:, :3, 3]
    naive_world = transform_points(truth["T_world_base"], p_naive)
    assert np.ptp(naive_world[:, 0]) > 0.3


def test_ranges_from_mounting_poses(moving_scan) -> None:
    _, sim, cloud, truth = moving_scan
    p = cloud_points(cloud)
    r = np.linalg.norm(p - truth["origin_base"], axis=1)
    assert np.all(np.abs(r - truth["range_measured"]) < 2e-4 + 2e-6 * r)
    # the origins are the mounting poses moved with the true motion during the sweep
    pose_at = moving_pose()
    T_wb_i = pose_at(cloud["timestamp"])
    T_bw_ft = invert_T(truth["T_world_base"])
    for s in sim.sensors:
        k = cloud["sensor_index"] == s.sensor_index
        o_world = np.einsum("nij,j->ni", T_wb_i[k], s.T_base_sensor[:, 3])[:, :3]
        np.testing.assert_allclose(
            transform_points(T_bw_ft, o_world), truth["origin_base"][k], atol=1e-6
        )
    # static: every point of sensor k lies at its range from that sensor's mounting point
    mesh = railway_scene()
    cloud0, truth0 = LidarSimulator(mesh, origin=OFFSET, density=0.05).scan_with_ground_truth(
        FRAME_TIME, moving_pose(0.0, 0.0)
    )
    p0 = cloud_points(cloud0)
    for s in sim.sensors:
        k = cloud0["sensor_index"] == s.sensor_index
        assert k.any()
        r0 = np.linalg.norm(p0[k] - s.T_base_sensor[:3, 3], axis=1)
        assert np.all(np.abs(r0 - truth0["range_measured"][k]) < 2e-4 + 2e-6 * r0)
        assert r0.max() <= s.max_range and r0.min() >= s.min_range


def test_counts_flat_scene_full_density_and_scaling() -> None:
    mesh = plane(1500.0, 0.0)
    pose = moving_pose(20.0, 0.0, offset=np.zeros(3))
    counts = {}
    for density in (1.0, 0.5, 0.25):
        cloud = LidarSimulator(mesh, origin=np.zeros(3), density=density).scan(FRAME_TIME, pose)
        si = cloud["sensor_index"]
        counts[density] = np.array(
            [(si == 0).sum(), np.isin(si, [1, 2, 3]).sum(), np.isin(si, [4, 5]).sum()]
        )
    pandar, livox, honeycomb = counts[1.0]
    assert 60_000 <= pandar <= 115_000
    assert 50_000 <= livox <= 84_000
    assert 20_000 <= honeycomb <= 40_000
    np.testing.assert_allclose(counts[1.0] / counts[0.5], 2.0, rtol=0.05)
    np.testing.assert_allclose(counts[0.5] / counts[0.25], 2.0, rtol=0.05)
    # sky rays return nothing: no point above the plane, none beyond max range
    assert np.all(cloud["z"] < 0.2)


def test_determinism_from_seed() -> None:
    mesh = railway_scene()
    pose = moving_pose()
    a = LidarSimulator(mesh, origin=OFFSET, seed=7, density=0.05).scan(FRAME_TIME, pose)
    b = LidarSimulator(mesh, origin=OFFSET, seed=7, density=0.05).scan(FRAME_TIME, pose)
    c = LidarSimulator(mesh, origin=OFFSET, seed=8, density=0.05).scan(FRAME_TIME, pose)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert len(a["x"]) != len(c["x"]) or not np.array_equal(a["x"], c["x"])


def test_default_origin_and_validation() -> None:
    mesh = railway_scene()
    sim = LidarSimulator(mesh, density=0.05)
    centre = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
    np.testing.assert_allclose(sim.origin, centre)
    _, truth = sim.scan_with_ground_truth(FRAME_TIME, moving_pose())
    assert mesh_distance(mesh, truth["hit_world"], OFFSET).max() < 1e-3
    with pytest.raises(ValueError):
        LidarSimulator(mesh, density=0.0)
    with pytest.raises(ValueError):
        sim.scan(FRAME_TIME, lambda t: np.eye(4))
