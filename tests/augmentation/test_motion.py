"""Moving objects: a person walking across the track at a known speed (true poses).

The answer is known independently of the code under test: at time t the walker stands
at arc length s0 + 22 m on the TRUE ego centreline, offset -4 + v (t - t0) m to its left
(t0: the first frame's lidar timestamp), so its position at any sensor's timestamp, its
velocity, and where its lidar points must be, all follow from the ground truth.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from geometry.transforms import invert_T, quat_to_matrix, transform_points
from renderer.assets import build_obstacle
from renderer.assets.walk_cycle import gait_phase, walk_pose
from worker.augmentation.finish import finish_augmentation
from worker.augmentation.frame import augment_frames
from worker.augmentation.motion import path_position
from worker.augmentation.plan import plan_augmentation
from worker.augmentation.records import dump_chunk, dump_plan, load_chunk, load_plan
from worker.augmentation.spec import (
    AugmentSpec,
    MotionModel,
    ObjectSource,
    RenderSpec,
    SceneObject,
)
from worker.evaluation.object_error import truth_prepared
from worker.osdar.pcd import read_pcd
from worker.osdar.sequence import Sequence

pytestmark = pytest.mark.gl

SEQ = {"scene": "fire_site", "frames": 8, "scale": 0.15, "lidar_density": 0.35, "seed": 7}
SPEED = 1.4  # m/s, a walking pace
S_PATH, OFF0, OFF1 = 22.0, -4.0, 4.0


def _walker(gait: bool = True) -> SceneObject:
    return SceneObject(
        object=ObjectSource(builtin="person"),
        motion=MotionModel(path=((S_PATH, OFF0), (S_PATH, OFF1)), speed_mps=SPEED, gait=gait),
    )


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory):
    from worker.synth.generator import SynthConfig, generate

    base = tmp_path_factory.mktemp("motion")
    seq = base / "fire_walk"
    generate(seq, SynthConfig(**SEQ))
    truth = truth_prepared(seq)
    # lidar noise off: the walker's points must lie exactly on it (noise: test_frame.py)
    spec = AugmentSpec(objects=(_walker(),), render=RenderSpec(lidar_noise=False),
                       lidar_origins=str(seq / "ground_truth" / "lidar_origins.json"))  # fmt: skip
    plan = plan_augmentation(seq, spec, truth)
    chunk = augment_frames(plan, plan.frames, base / "scratch")
    out = base / "fire_walk_out"  # the chunk's files move there
    finish_augmentation(plan, [chunk], out, evaluate=False)
    return seq, truth, plan, chunk, out


def _times(seq: Path, stream: str) -> dict[int, float]:
    s = Sequence.open(seq)
    return dict(zip(s.frame_indices, s.timestamps(stream).tolist(), strict=True))


def _true_xy(truth, t: float, t0: float) -> np.ndarray:
    """The walker's true ground position (2,) at time t (module docstring)."""
    ego = truth.ego
    T0 = truth.track.interpolate(np.array([t0]))[0]
    s_abs = float(ego.project(T0[None, :3, 3]).s[0]) + S_PATH
    c, tg = ego.point([s_abs])[0], ego.tangent([s_abs])[0]
    left = np.array([-tg[1], tg[0]]) / np.hypot(tg[0], tg[1])
    off = min(OFF0 + SPEED * max(t - t0, 0.0), OFF1)
    return c[:2] + off * left


def test_the_pose_follows_each_sensors_own_timestamp(walk) -> None:
    seq, truth, plan, _, _ = walk
    lidar = _times(seq, "lidar")
    t0 = lidar[plan.frames[0]]
    walker = plan.objects[0]
    gaps = []
    for stream in [*plan.cameras, "lidar"]:
        times = _times(seq, stream)
        for f in plan.frames:
            p = walker.pose(stream, f)[:3, 3]
            assert np.linalg.norm(p[:2] - _true_xy(truth, times[f], t0)) < 1e-3, (stream, f)
            gaps.append(abs(times[f] - lidar[f]))
    assert max(gaps) > 1e-3  # the cameras' timestamps do differ from the lidar's


def test_cuboids_move_at_the_walking_speed_and_carry_the_velocity(walk) -> None:
    seq, _, plan, chunk, out = walk
    lidar = _times(seq, "lidar")
    centres, ts = [], []
    for rec in chunk.frames:
        ann = rec.annotation
        assert ann is not None
        T_wb = plan.T_world_base["lidar"][rec.frame_idx]
        centres.append(transform_points(T_wb, np.array([ann.cuboid[:3]]))[0])
        ts.append(lidar[rec.frame_idx])
        # the velocity attribute: SPEED along the walking direction, lidar frame axes
        v_world = T_wb[:3, :3] @ np.asarray(ann.velocity)
        want = plan.objects[0].velocity(rec.frame_idx)
        assert np.linalg.norm(want) == pytest.approx(SPEED, rel=1e-9)
        assert np.allclose(v_world, want, atol=1e-6)
    c, t = np.array(centres), np.array(ts)
    # least-squares velocity of the cuboid centres over the frames; the bound: the walk
    # cycle moves the limbs' box by at most +-0.08 m (one bound for every frame) over
    # (t[-1] - t[0]) s of walking, i.e. 2 x 0.08 / duration m/s
    A = np.column_stack([t - t[0], np.ones_like(t)])
    v_fit = np.linalg.lstsq(A, c[:, :2], rcond=None)[0][0]
    tol = 2 * 0.08 / (t[-1] - t[0])
    assert abs(np.linalg.norm(v_fit) - SPEED) < tol, (v_fit, tol)
    # the labels carry it (raillabel reads vec attributes)
    raillabel = pytest.importorskip("raillabel")
    scene = raillabel.load(next(out.glob("*_labels.json")))
    speeds = [a.attributes["speedMps"] for fr in scene.frames.values()
              for a in fr.annotations.values() if type(a).__name__ == "Cuboid"]  # fmt: skip
    assert len(speeds) == len(plan.frames) and np.allclose(speeds, SPEED, atol=1e-4)


def test_lidar_points_lie_on_the_walker_at_the_lidar_timestamp_inside_its_cuboid(walk) -> None:
    seq, truth, plan, chunk, out = walk
    lidar = _times(seq, "lidar")
    t0 = lidar[plan.frames[0]]
    rest = build_obstacle("person")
    total = 0
    for rec in chunk.frames:
        f = rec.frame_idx
        idx = np.asarray(rec.annotation.lidar_indices, dtype=np.int64)
        if len(idx) == 0:
            continue
        cloud = read_pcd(out / plan.uris[f]["lidar"].lstrip("/"))
        p_base = np.stack([cloud.fields[k][idx] for k in "xyz"], 1).astype(np.float64)
        # the walker as the ground truth has it at this lidar timestamp: position from the
        # true centreline, heading along the walk (+left), limbs at the cycle's phase
        t = lidar[f]
        xy = _true_xy(truth, t, t0)
        T_obj = plan.objects[0].pose("lidar", f)  # its height and heading
        assert np.linalg.norm(T_obj[:2, 3] - xy) < 1e-3
        walked = SPEED * (t - t0)
        posed = walk_pose(rest, gait_phase(walked, float(rest.size[2])))
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(posed.vertices.astype(np.float32)),
                            o3d.core.Tensor(posed.faces.astype(np.uint32)))  # fmt: skip
        T_obj_base = invert_T(T_obj) @ plan.T_world_base["lidar"][f]
        d = scene.compute_distance(
            o3d.core.Tensor(transform_points(T_obj_base, p_base).astype(np.float32))
        ).numpy()
        assert d.max() < 2e-3, (f, d.max())
        # and inside the frame's cuboid (lidar frame), 1 cm slack
        cub = rec.annotation.cuboid
        R = quat_to_matrix(np.array(cub[3:7]))
        q = (p_base - np.array(cub[:3])) @ R
        assert np.all(np.abs(q) <= np.array(cub[7:10]) / 2 + 0.01), f
        total += len(idx)
    assert total > 20, total


def test_path_positions_stop_or_bounce() -> None:
    m = MotionModel(path=((0.0, 0.0), (3.0, 0.0), (3.0, 4.0)), speed_mps=2.0, start_s=1.0)
    p, d, walked = path_position(m, np.array([0.0, 1.0, 2.0, 3.5, 10.0]))
    assert np.allclose(p, [[0, 0], [0, 0], [2, 0], [3, 2], [3, 4]])
    assert np.allclose(d[:3], [1, 0]) and np.allclose(d[3:], [0, 1])
    assert np.allclose(walked, [0, 0, 2, 5, 7])  # stopped at 7 m (the path's length)
    b = m.model_copy(update={"end": "bounce"})
    p, d, _ = path_position(b, np.array([1.0 + 8.0 / 2.0]))  # 8 m: 1 m back from the end
    assert np.allclose(p, [[3, 3]]) and np.allclose(d, [[0, -1]])
    with pytest.raises(ValueError, match="length"):
        MotionModel(path=((1.0, 1.0), (1.0, 1.0)), speed_mps=1.0)


def test_a_job_spec_with_motion_parses() -> None:
    spec = AugmentSpec.from_job_spec({
        "object": {"builtin": "cow"},
        "motion": {"mode": "world", "path": [[10, 0], [30, 5]], "speed_mps": 0.8},
    })  # fmt: skip
    (obj,) = spec.scene_objects
    assert obj.motion is not None and obj.motion.mode == "world" and obj.motion.speed_mps == 0.8
    assert json.loads(spec.model_dump_json())["motion"]["path"] == [[10.0, 0.0], [30.0, 5.0]]


def test_a_moving_plan_survives_its_record(walk) -> None:
    """The plan a pool's workers read back: poses per stream and frame, walk-cycle phases
    and velocities come back exactly, and a frame augmented from it is the same."""
    _, _, plan, chunk, _ = walk
    back = load_plan(dump_plan(plan))
    (w0,), (w1,) = plan.objects, back.objects
    assert w1.moving and w1.phases is not None
    for st in w0.poses:
        for f in plan.frames:
            assert np.array_equal(w1.pose(st, f), w0.pose(st, f))
            assert w1.phases[st][f] == w0.phases[st][f]
    assert all(np.array_equal(w1.velocity(f), w0.velocity(f)) for f in plan.frames)
    again = load_chunk(dump_chunk(chunk))
    assert [r.annotation.cuboid for r in again.frames] == [
        r.annotation.cuboid for r in chunk.frames
    ]


def test_the_walkers_gauge_label_follows_it_frame_by_frame(walk) -> None:
    """Walking from 4 m right of the centreline towards it, the walker's lateral distance
    to the clearance envelope shrinks at its walking speed (up to the walk cycle's box
    wobble), and it is outside the envelope (1.775 m) all along this short walk."""
    seq, _, plan, _, _ = walk
    lidar = _times(seq, "lidar")
    g = plan.objects[0].gauge
    t = np.array([lidar[f] for f in plan.frames])
    lat = np.array([g[f].lateral_distance_m for f in plan.frames])
    assert not any(g[f].intrusion for f in plan.frames) and np.all(lat > 0)
    slope = np.polyfit(t - t[0], lat, 1)[0]
    assert abs(slope + SPEED) < 2 * 0.08 / (t[-1] - t[0]), slope


def test_a_world_path_is_walked_at_its_speed_and_bounces(walk) -> None:
    """A cow wandering in world coordinates, there and back (``end: bounce``): its pose at
    each lidar timestamp is the path point speed x elapsed time along, heading along, and
    its legs swing with the distance walked."""
    seq, truth, plan0, _, _ = walk
    lidar = _times(seq, "lidar")
    t0 = lidar[plan0.frames[0]]
    p0 = plan0.objects[0].pose("lidar", plan0.frames[0])[:2, 3]
    a, b = p0 + np.array([3.0, 0.0]), p0 + np.array([3.3, 0.0])  # 0.3 m: it turns back
    cow = SceneObject(
        object=ObjectSource(builtin="cow"),
        motion=MotionModel(mode="world", path=(tuple(a), tuple(b)), speed_mps=0.8, end="bounce"),
    )
    plan = plan_augmentation(seq, AugmentSpec(objects=(cow,)), truth)
    for f in plan.frames:
        d = 0.8 * (lidar[f] - t0) % 0.6
        along = d if d <= 0.3 else 0.6 - d
        T = plan.objects[0].pose("lidar", f)
        assert np.linalg.norm(T[:2, 3] - (a + np.array([along, 0.0]))) < 1e-6, f
        heading = np.degrees(np.arctan2(T[1, 0], T[0, 0]))
        wrapped = (heading - (0.0 if d <= 0.3 else 180.0) + 180.0) % 360.0 - 180.0
        assert abs(wrapped) < 1e-6, (f, heading)
    # the cow walks: its legs' phase follows the distance walked (one cycle per 0.6 lengths)
    cow_plan = plan.objects[0]
    length = float(cow_plan.obj_full.size[0])
    for f in plan.frames:
        walked = 0.8 * (lidar[f] - t0)
        assert cow_plan.phases["lidar"][f] == pytest.approx(2 * np.pi * walked / (0.6 * length))
