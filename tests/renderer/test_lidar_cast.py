"""Tests of renderer/lidar_cast.py on clouds of the synthetic lidar rig."""

# ruff: noqa: RUF005 (numpy vector + list offsets, not list concatenation)

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh

from geometry.transforms import invert_T, make_T
from renderer.assets.obstacles import build_obstacle
from renderer.lidar_cast import (
    cast_object,
    hidden_from,
    origins_from_json,
    point_origins,
)
from renderer.lidar_noise import measure_lidar_noise
from renderer.mesh import ObjectMesh
from worker.synth.lidar_sim import LidarSimulator, default_sensors, sensors_to_json
from worker.synth.scene_mesh import MATERIAL_ID, SceneMesh

FRAME_TIME = 1_631_441_453.3
GROUND_Z = -0.3  # ground below the base frame's top-of-rail origin
BOX_HALF = np.array([0.6, 0.9, 0.0])
BOX_H = 1.6
INTENSITY_SCALE = {0: 255.0, 1: 255.0, 2: 255.0, 3: 255.0, 4: 1.0, 5: 1.0}
PAPER_ORIGIN = np.zeros(3)  # the single origin: the merged lidar frame's origin


def _quad_box(lo: np.ndarray, hi: np.ndarray, material: str) -> SceneMesh:
    tm = trimesh.creation.box(bounds=[lo, hi])
    return SceneMesh(tm.vertices, tm.faces, np.full(len(tm.faces), MATERIAL_ID[material]))


def _scene() -> SceneMesh:
    ground = SceneMesh(
        np.array(
            [
                [-300, -300, GROUND_Z],
                [300, -300, GROUND_Z],
                [300, 300, GROUND_Z],
                [-300, 300, GROUND_Z],
            ],
            dtype=float,
        ),
        [[0, 1, 2], [0, 2, 3]],
        [MATERIAL_ID["ground"]] * 2,
    )
    wall = _quad_box(np.array([45.0, -40.0, GROUND_Z]), np.array([46.0, 40.0, 12.0]), "building")
    return SceneMesh.concatenate([ground, wall])


def _static_pose(t: np.ndarray) -> np.ndarray:
    """A train standing still: the mounting poses are the exact ray origins."""
    return np.tile(np.eye(4), (len(np.atleast_1d(t)), 1, 1))


@pytest.fixture(scope="module")
def scan() -> dict[str, np.ndarray]:
    sim = LidarSimulator(_scene(), origin=np.zeros(3), seed=5, density=0.35, nthreads=2)
    cloud = sim.scan(FRAME_TIME, _static_pose)
    assert len(cloud["x"]) > 20_000
    return cloud


@pytest.fixture(scope="module")
def true_origins() -> dict[int, np.ndarray]:
    return origins_from_json(sensors_to_json(default_sensors()))


def box_mesh() -> ObjectMesh:
    tm = trimesh.creation.box(extents=[2 * BOX_HALF[0], 2 * BOX_HALF[1], BOX_H])
    v = tm.vertices + [0.0, 0.0, BOX_H / 2]
    n = len(v)
    return ObjectMesh(v, tm.faces, np.full((n, 3), 0.5), np.full(n, 0.6), "box")


def T_box() -> np.ndarray:
    c, s = np.cos(np.deg2rad(30.0)), np.sin(np.deg2rad(30.0))
    return make_T([[c, -s, 0], [s, c, 0], [0, 0, 1]], [20.0, 0.8, GROUND_Z])


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint8).reshape(len(a), -1)


def slab_entry(o: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Analytic ray / box entry distance (object frame), inf where the ray misses."""
    lo = np.array([-BOX_HALF[0], -BOX_HALF[1], 0.0])
    hi = np.array([BOX_HALF[0], BOX_HALF[1], BOX_H])
    d = p - o
    r = np.linalg.norm(d, axis=1)
    d = d / r[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((tmax >= tmin) & (tmax > 0), np.maximum(tmin, 0.0), np.inf)


def test_box_cast_true_origins(scan, true_origins) -> None:
    mesh, T = box_mesh(), T_box()
    res = cast_object(scan, mesh, T, true_origins, intensity_scale=INTENSITY_SCALE)
    idx = res.object_indices
    n = len(scan["x"])
    assert res.moved == len(idx) > 100
    assert list(res.fields) == list(scan) and all(len(v) == n for v in res.fields.values())
    assert {k: v.dtype for k, v in res.fields.items()} == {k: v.dtype for k, v in scan.items()}

    # object_indices are exactly the points whose coordinates changed
    changed = np.zeros(n, dtype=bool)
    for k in "xyz":
        changed |= (_bits(res.fields[k]) != _bits(scan[k])).any(axis=1)
    np.testing.assert_array_equal(np.flatnonzero(changed), idx)
    # everything else is bit-identical, and the other fields everywhere
    keep = np.ones(n, dtype=bool)
    keep[idx] = False
    for k in scan:
        assert np.array_equal(_bits(res.fields[k])[keep], _bits(scan[k])[keep]), k
    for k in ("timestamp", "sensor_index"):
        assert np.array_equal(_bits(res.fields[k]), _bits(scan[k])), k

    # moved points lie on the surface (< 1 mm)
    Ti = invert_T(T)
    q = np.stack([res.fields[k][idx] for k in "xyz"], axis=1).astype(np.float64)
    q_obj = q @ Ti[:3, :3].T + Ti[:3, 3]
    sc = o3d.t.geometry.RaycastingScene()
    sc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                     o3d.core.Tensor(mesh.faces.astype(np.uint32)))  # fmt: skip
    dist = sc.compute_distance(o3d.core.Tensor(q_obj.astype(np.float32))).numpy()
    assert dist.max() < 1e-3

    # the moved set is the analytic one: rays from the true origins entering the box
    # before the measured point
    p = np.stack([scan[k] for k in "xyz"], axis=1).astype(np.float64)
    o = point_origins(scan, true_origins)
    p_obj, o_obj = p @ Ti[:3, :3].T + Ti[:3, 3], o @ Ti[:3, :3].T + Ti[:3, 3]
    entry = slab_entry(o_obj, p_obj)
    expected = np.flatnonzero(entry < np.linalg.norm(p_obj - o_obj, axis=1))
    assert len(np.setxor1d(expected, idx)) <= 2  # float32 ties on the box edges at most
    # no object point is hidden from its true sensor
    assert not hidden_from(mesh, T, q, o[idx]).any()

    # intensity: reflectivity x |cos|, in the sensor's scale and quantisation
    inten = res.fields["intensity"][idx].astype(np.float64)
    sidx = scan["sensor_index"][idx]
    scale = np.array([INTENSITY_SCALE[int(s)] for s in sidx])
    np.testing.assert_allclose(inten, scale * 0.6 * res.cos_incidence, atol=0.5 + 1e-6)
    assert np.all(inten[scale > 1] == np.round(inten[scale > 1]))
    assert np.all((inten >= 0) & (inten <= scale))
    by_sensor = {int(s): int((sidx == s).sum()) for s in np.unique(sidx)}
    print(f"\nbox at 20 m: {res.moved} points moved, by sensor {by_sensor}")
    assert len(by_sensor) >= 3


def test_input_untouched_and_misses(scan, true_origins) -> None:
    before = {k: v.copy() for k, v in scan.items()}
    T_far = make_T(np.eye(3), [0.0, 280.0, GROUND_Z])  # beyond every return
    res = cast_object(scan, box_mesh(), T_far, true_origins)
    assert res.moved == 0 and len(res.object_indices) == 0
    for k in scan:
        assert np.array_equal(_bits(res.fields[k]), _bits(before[k]))
        assert np.array_equal(_bits(scan[k]), _bits(before[k]))
        assert res.fields[k] is not scan[k]


def test_origin_validation(scan, true_origins) -> None:
    partial = {k: v for k, v in true_origins.items() if k != 4}
    with pytest.raises(ValueError, match="sensor_index \\[4\\]"):
        cast_object(scan, box_mesh(), T_box(), partial)
    no_sidx = {k: v for k, v in scan.items() if k != "sensor_index"}
    with pytest.raises(ValueError, match="sensor_index field"):
        cast_object(no_sidx, box_mesh(), T_box(), true_origins)
    res = cast_object(no_sidx, box_mesh(), T_box(), PAPER_ORIGIN)  # single origin: fine
    assert res.moved > 0


def test_range_noise_is_seeded(scan, true_origins) -> None:
    a = cast_object(scan, box_mesh(), T_box(), true_origins, range_sigma=0.02, seed=1)
    b = cast_object(scan, box_mesh(), T_box(), true_origins, range_sigma=0.02, seed=1)
    c = cast_object(scan, box_mesh(), T_box(), true_origins, range_sigma=0.02, seed=2)
    assert np.array_equal(a.fields["x"], b.fields["x"])
    assert not np.array_equal(a.fields["x"], c.fields["x"])
    np.testing.assert_array_equal(a.object_indices, c.object_indices)


def test_per_sensor_origins_gain_over_single_origin(scan, true_origins) -> None:
    """The paper's single origin puts points where no sensor could see them."""
    T = make_T(np.eye(3), [20.0, 0.0, GROUND_Z])
    singles = {"base0": PAPER_ORIGIN, "pandar": true_origins[0]}
    o_true = point_origins(scan, true_origins)

    def pts(r, idx):
        return np.stack([r.fields[k][idx] for k in "xyz"], axis=1).astype(np.float64)

    rows = []
    for name in ("box", "person", "cow"):
        mesh = box_mesh() if name == "box" else build_obstacle(name, seed=0, detail=0.6)
        true = cast_object(scan, mesh, T, true_origins, intensity_scale=INTENSITY_SCALE)
        ti = true.object_indices
        assert not hidden_from(mesh, T, pts(true, ti), o_true[ti]).any()
        for label, origin in singles.items():
            single = cast_object(scan, mesh, T, origin, intensity_scale=INTENSITY_SCALE)
            si = single.object_indices
            hid = hidden_from(mesh, T, pts(single, si), o_true[si]).mean()
            common = np.intersect1d(ti, si)
            d = np.linalg.norm(pts(true, common) - pts(single, common), axis=1)
            rms = float(np.sqrt(np.mean(d**2)))
            sym = len(np.setxor1d(ti, si))
            rows.append((name, label, len(ti), len(si), sym, hid, rms))
            assert rms > 0.0 and sym > 0
    print("\nobject  single   moved(true) moved(single) set-diff hidden(single) RMS(m)")
    for name, label, mt, ms, sym, hs, rms in rows:
        print(f"{name:7s} {label:7s} {mt:11d} {ms:13d} {sym:8d} {hs:14.3f} {rms:7.3f}")
    assert max(r[5] for r in rows) > 0.0  # some single-origin points are impossible


# ----------------------------------------------------------------- sensor noise and dropout
def ring_cloud(sigma: float, drop: float, seed: int, origin=(0.0, 0.0, 2.0), sensor=0):
    """A ring lidar (elevations -16..-2 deg every 0.5 deg, azimuth every 0.2 deg over
    +-40 deg) at ``origin`` seeing the ground z = 0 and a wall x = 25: Gaussian range
    noise ``sigma`` (m) and a random ``drop`` fraction of rays without return."""
    rng = np.random.default_rng(seed)
    el, az = np.meshgrid(np.radians(np.arange(-16.0, -1.9, 0.5)),
                         np.radians(np.arange(-40.0, 40.0, 0.2)), indexing="ij")  # fmt: skip
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
    o = np.asarray(origin, float)
    t_ground = -o[2] / d[:, 2]
    t_wall = np.where(d[:, 0] > 1e-9, (25.0 - o[0]) / np.maximum(d[:, 0], 1e-9), np.inf)
    t = np.minimum(t_ground, t_wall)
    t = t + sigma * rng.standard_normal(len(t))
    keep = rng.random(len(t)) >= drop
    p = o + t[keep, None] * d[keep]
    n = len(p)
    return {"x": p[:, 0].astype(np.float32), "y": p[:, 1].astype(np.float32),
            "z": p[:, 2].astype(np.float32), "intensity": np.full(n, 10.0, np.float32),
            "sensor_index": np.full(n, sensor, np.int32)}  # fmt: skip


@pytest.mark.parametrize(
    ("sigma", "drop", "seed"), [(0.02, 0.08, 0), (0.05, 0.0, 1), (0.01, 0.2, 2)]
)
def test_noise_and_dropout_measured_from_the_real_points(sigma, drop, seed) -> None:
    a = ring_cloud(sigma, drop, seed, sensor=0)
    b = ring_cloud(2 * sigma, 0.5 * drop, seed + 10, origin=(0.0, 0.3, 2.2), sensor=1)
    cloud = {k: np.concatenate([a[k], b[k]]) for k in a}
    origins = {0: np.array([0.0, 0.0, 2.0]), 1: np.array([0.0, 0.3, 2.2])}
    est = measure_lidar_noise(cloud, origins, centre_base=[15.0, 0.0, 0.8], radius=1.5)
    for s, (sg, dr) in {0: (sigma, drop), 1: (2 * sigma, 0.5 * drop)}.items():
        e = est[s]
        assert 0.8 <= e.range_sigma_m / sg <= 1.25, (s, e)
        assert abs(e.dropout - dr) < 0.025, (s, e)
        assert e.rings >= 5 and e.points > 500


def test_object_points_get_the_sensor_noise_and_dropout() -> None:
    cloud = ring_cloud(0.0, 0.0, 5)
    n = len(cloud["x"])
    box = trimesh.creation.box(extents=(2.0, 6.0, 3.0))
    v = np.asarray(box.vertices) + [0.0, 0.0, 1.5]
    mesh = ObjectMesh(v, box.faces, np.full((len(v), 3), 0.5), np.full(len(v), 0.5))
    T = np.eye(4)
    T[:3, 3] = [15.0, 0.0, 0.0]
    o = {0: np.array([0.0, 0.0, 2.0])}
    exact = cast_object(cloud, mesh, T, o)
    noisy = cast_object(cloud, mesh, T, o, range_sigma={0: 0.03}, dropout={0: 0.1}, seed=3)
    assert exact.kept is None and len(exact.fields["x"]) == n
    assert noisy.kept is not None and len(noisy.fields["x"]) == n - len(noisy.dropped)
    assert abs(len(noisy.dropped) / exact.moved - 0.1) < 0.03
    # the points kept on the object: their range error along the ray is the noise asked
    src = noisy.kept[noisy.object_indices]
    pos = {int(i): k for k, i in enumerate(exact.object_indices)}
    j = np.array([pos[int(i)] for i in src])
    p_exact = np.stack([exact.fields[k][exact.object_indices[j]] for k in "xyz"], 1).astype(float)
    p_noisy = np.stack([noisy.fields[k][noisy.object_indices] for k in "xyz"], 1).astype(float)
    err = np.linalg.norm(p_noisy - o[0], axis=1) - np.linalg.norm(p_exact - o[0], axis=1)
    assert 0.8 <= float(np.std(err)) / 0.03 <= 1.25
    # every other point is untouched
    others = np.setdiff1d(np.arange(len(noisy.fields["x"])), noisy.object_indices)
    np.testing.assert_array_equal(noisy.fields["x"][others], cloud["x"][noisy.kept[others]])
