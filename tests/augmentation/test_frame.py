"""One frame's lidar: the object points get the real sensor's range noise and dropout.

A synthetic sequence's lidar has known noise (worker.synth.lidar_sim.default_sensors:
Gaussian range noise of 2 cm (Pandar, Livox) and 2.5 cm (Honeycomb) truncated at 3 sigma,
0.5 % dropout): the augmented object's points must scatter along their rays around the
object's surface as the real surface points do around theirs, the labels' point vectors
must point at them, and the same job must write the same clouds.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from geometry.transforms import invert_T, transform_points
from renderer.lidar_cast import point_origins
from worker.augmentation.finish import finish_augmentation
from worker.augmentation.frame import augment_frames
from worker.augmentation.lidar_noise import (
    REMEASURE_M,
    lidar_noise_near,
    noise_key_frames,
    object_spheres,
)
from worker.augmentation.plan import plan_augmentation
from worker.augmentation.spec import AugmentSpec, ObjectSource, PlacementModel, RenderSpec
from worker.evaluation.object_error import truth_prepared
from worker.osdar.pcd import read_pcd
from worker.synth.lidar_sim import default_sensors

pytestmark = pytest.mark.gl

SEQ = {"scene": "fire_site", "frames": 4, "scale": 0.15, "lidar_density": 0.2, "seed": 11}
TRUE_SIGMA = {s.sensor_index: s.range_sigma for s in default_sensors()}
MIN_POINTS = 40  # object points of a sensor (all frames) for its spread to be compared


@pytest.fixture(scope="module")
def noisy_run(tmp_path_factory: pytest.TempPathFactory):
    from worker.synth.generator import SynthConfig, generate

    base = tmp_path_factory.mktemp("lidar_noise")
    seq = base / "fire_noise"
    generate(seq, SynthConfig(**SEQ))  # type: ignore[arg-type]
    spec = AugmentSpec(
        object=ObjectSource(builtin="cow", seed=4),
        placement=PlacementModel.parse("s=18,offset=0,yaw=60"),
        lidar_origins=str(seq / "ground_truth" / "lidar_origins.json"),
        render=RenderSpec(lidar_noise=True),
    )
    plan = plan_augmentation(seq, spec, truth_prepared(seq))
    chunk = augment_frames(plan, plan.frames, base / "scratch")
    metrics = finish_augmentation(plan, [chunk], base / "out", evaluate=False)
    return seq, plan, chunk, metrics, base / "out"


def _object_scene(plan, frame: int) -> o3d.t.geometry.RaycastingScene:
    """The object's mesh in the base frame of ``frame``'s lidar."""
    obj = plan.objects[0]
    T_base_obj = invert_T(plan.T_world_base["lidar"][frame]) @ obj.pose("lidar", frame)
    mesh = obj.mesh("lidar", frame, full=True)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(transform_points(T_base_obj, mesh.vertices).astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    return scene


def test_object_points_scatter_like_the_real_surface(noisy_run) -> None:
    """Range residual of the object points against the mesh (along each point's own ray):
    per sensor its std is within [0.8, 1.25] of the real points' known range noise."""
    _, plan, chunk, _, out = noisy_run
    residuals: dict[int, list[float]] = {}
    for rec in chunk.frames:
        idx = np.asarray(rec.annotation.lidar_indices if rec.annotation else [], np.int64)
        if len(idx) == 0:
            continue
        cloud = read_pcd(out / plan.uris[rec.frame_idx]["lidar"].lstrip("/"))
        p = np.stack([cloud.fields[k][idx] for k in "xyz"], 1).astype(np.float64)
        sub = {k: np.asarray(v)[idx] for k, v in cloud.fields.items()}
        o = point_origins(sub, plan.lidar_origins)
        r = np.linalg.norm(p - o, axis=1)
        rays = np.concatenate([o, (p - o) / r[:, None]], axis=1).astype(np.float32)
        t_hit = _object_scene(plan, rec.frame_idx).cast_rays(o3d.core.Tensor(rays))["t_hit"]
        res = r - t_hit.numpy().astype(np.float64)
        assert np.all(np.isfinite(res)), "a labelled point's ray misses the object"
        for s in np.unique(sub["sensor_index"]):
            residuals.setdefault(int(s), []).extend(res[sub["sensor_index"] == s].tolist())
    tested = {s: v for s, v in residuals.items() if len(v) >= MIN_POINTS}
    assert tested, {s: len(v) for s, v in residuals.items()}
    for s, v in tested.items():
        ratio = float(np.std(v)) / TRUE_SIGMA[s]
        assert 0.8 <= ratio <= 1.25, (s, len(v), ratio)
        assert np.max(np.abs(v)) <= 3.0 * 1.25 * TRUE_SIGMA[s] + 1e-3  # truncated at 3 sigma


def test_labels_point_at_the_object_points_of_the_thinned_cloud(noisy_run) -> None:
    """The labels' lidar vec indexes the written cloud (fewer points where object rays were
    dropped): those points are on the object, every other point is an input point in
    the input's order."""
    seq, plan, chunk, _, out = noisy_run
    labels = json.loads(next(out.glob("*_labels.json")).read_text())["openlabel"]
    oid = next(k for k, o in labels["objects"].items() if "_synthetic_" in o["name"])
    n_dropped = n_object = 0
    for rec in chunk.frames:
        uri = plan.uris[rec.frame_idx]["lidar"].lstrip("/")
        src, cloud = read_pcd(seq / uri), read_pcd(out / uri)
        idx = np.asarray(rec.annotation.lidar_indices if rec.annotation else [], np.int64)
        vecs = labels["frames"][str(rec.frame_idx)]["objects"].get(oid, {})
        vecs = vecs.get("object_data", {}).get("vec", [])
        assert [v["val"] for v in vecs] == ([idx.tolist()] if len(idx) else [])
        if len(idx) == 0:
            continue
        p = np.stack([cloud.fields[k][idx] for k in "xyz"], 1).astype(np.float32)
        d = _object_scene(plan, rec.frame_idx).compute_distance(o3d.core.Tensor(p)).numpy()
        # within the 3 sigma truncation of the range noise each sensor's points were given
        applied = {s: e["range_sigma_m"] for s, e in rec.lidar_noise.items()}
        sig = np.array([applied.get(int(s), 0.0) for s in cloud.fields["sensor_index"][idx]])
        assert np.all(d <= 3.0 * np.nan_to_num(sig) + 1e-3)
        # the rest: input rows, in order, with only object rays missing
        others = np.setdiff1d(np.arange(len(cloud)), idx)
        rows_in = np.stack([src.fields[k] for k in src.fields], 1)
        rows_out = np.stack([cloud.fields[k][others] for k in cloud.fields], 1)
        where = {r.tobytes(): i for i, r in enumerate(rows_in)}
        pos = np.array([where[r.tobytes()] for r in rows_out])
        assert np.all(np.diff(pos) > 0)
        n_dropped += len(src) - len(cloud)
        n_object += len(idx)
    assert n_object > 2 * MIN_POINTS
    # 0.5 % dropout on Pandar and Honeycomb, none measurable on the Livox rosettes
    assert n_dropped <= 0.05 * (n_object + n_dropped)


def test_the_same_job_writes_the_same_clouds(noisy_run, tmp_path: Path) -> None:
    _, plan, chunk, _, out = noisy_run
    again = augment_frames(plan, plan.frames[:2], tmp_path / "again")
    for a, b in zip(again.frames, chunk.frames[:2], strict=True):
        uri = plan.uris[a.frame_idx]["lidar"].lstrip("/")
        assert (tmp_path / "again" / uri).read_bytes() == (out / uri).read_bytes()
        assert a.annotation.lidar_indices == b.annotation.lidar_indices
        assert json.dumps(a.lidar_noise) == json.dumps(b.lidar_noise)  # NaN != NaN


def test_the_noise_estimate_is_in_the_metrics(noisy_run) -> None:
    """metrics.json's lidar.noise: per sensor the frames' estimates summarised (median,
    min, max of the per-frame records)."""
    _, _, chunk, metrics, out = noisy_run
    on_disk = json.loads((out / "metrics.json").read_text())["lidar"]["noise"]
    sensors = sorted({s for r in chunk.frames for s in r.lidar_noise})
    assert sorted(int(s) for s in on_disk) == sensors and len(sensors) >= 2
    assert on_disk == json.loads(json.dumps(metrics["lidar"]["noise"]))
    for s, e in on_disk.items():
        per = [r.lidar_noise[int(s)] for r in chunk.frames if int(s) in r.lidar_noise]
        sig = [x["range_sigma_m"] for x in per if np.isfinite(x["range_sigma_m"])]
        assert e["frames"] == len(per)
        if sig:
            assert e["range_sigma_m"]["median"] == pytest.approx(float(np.median(sig)))
            assert e["range_sigma_m"]["min"] == pytest.approx(min(sig))
        else:
            assert e["range_sigma_m"] is None
        assert e["dropout"]["max"] == pytest.approx(max(x["dropout"] for x in per))


def test_without_lidar_noise_the_clouds_keep_their_length(noisy_run, tmp_path: Path) -> None:
    seq, plan, _, _, _ = noisy_run
    spec = plan.spec.model_copy(update={"render": RenderSpec(lidar_noise=False)})
    quiet = plan_augmentation(seq, spec, truth_prepared(seq))
    chunk = augment_frames(quiet, quiet.frames[:1], tmp_path)
    rec = chunk.frames[0]
    uri = quiet.uris[rec.frame_idx]["lidar"].lstrip("/")
    assert len(read_pcd(tmp_path / uri)) == len(read_pcd(seq / uri))
    assert rec.lidar_noise == {}


def test_key_frames_follow_the_objects_motion_in_the_base_frame() -> None:
    """A new key frame once some object moved more than REMEASURE_M since the last one:
    at 1 m a frame (a train at 10 m/s, 10 Hz) every 6th frame; a second object that
    stays put does not hold the first back; a standing train keeps one key."""
    step = REMEASURE_M / 5.0  # 5 frames reach REMEASURE_M exactly: not more
    moving = {f: np.array([[40.0 - step * f, 0.0, 1.0], [60.0, 3.0, 1.0]]) for f in range(14)}
    keys = noise_key_frames(moving)
    assert sorted(set(keys.values())) == [0, 6, 12]
    assert all(keys[f] == 6 * (f // 6) for f in range(14))
    standing = {f: np.array([[40.0, 0.0, 1.0]]) for f in range(30, 40)}
    assert set(noise_key_frames(standing).values()) == {30}


def test_each_frame_gets_its_key_frames_noise(noisy_run) -> None:
    """The plan measured the noise at each key frame on that frame's own cloud (what
    lidar_noise_near gives there), and every frame's record carries its key's estimate."""
    seq, plan, chunk, _, _ = noisy_run
    assert set(plan.lidar_noise_keys) == set(plan.frames)
    assert set(plan.lidar_noise) == set(plan.lidar_noise_keys.values())
    for key, est in plan.lidar_noise.items():
        cloud = read_pcd(seq / plan.uris[key]["lidar"].lstrip("/"))
        spheres = object_spheres(plan.objects, plan.T_world_base["lidar"][key], "lidar", key)
        direct = lidar_noise_near(cloud.fields, plan.lidar_origins, spheres)
        assert json.dumps({s: dataclasses.asdict(v) for s, v in direct.items()}) == json.dumps(
            {s: dataclasses.asdict(v) for s, v in est.items()}
        )
    for rec in chunk.frames:
        key = plan.lidar_noise_keys[rec.frame_idx]
        want = {s: dataclasses.asdict(v) for s, v in plan.lidar_noise[key].items()}
        assert json.dumps(rec.lidar_noise) == json.dumps(want)


def test_the_first_frame_from_the_plans_decode_is_the_file_decoded(noisy_run, tmp_path) -> None:
    """The plan's lighting decoded the first frame's images; the frames stage takes them
    (nothing is left after the chunk) and writes the bytes a fresh decode writes."""
    from worker.augmentation.plan import _DECODED

    seq, plan, chunk, _, _ = noisy_run
    assert not _DECODED  # taken, or dropped at the end of the chunk
    assert chunk.frames[0].frame_idx == plan.frames[0]
    again = plan_augmentation(seq, plan.spec, truth_prepared(seq))
    f0 = again.frames[0]
    assert len(_DECODED) == len(again.cameras)
    taken = augment_frames(again, [f0], tmp_path / "taken")
    assert not _DECODED and taken.frames[0].timings["decode"] < 0.05
    fresh = augment_frames(again, [f0], tmp_path / "fresh")
    for cam in again.cameras:
        uri = again.uris[f0][cam].lstrip("/")
        assert (tmp_path / "taken" / uri).read_bytes() == (tmp_path / "fresh" / uri).read_bytes()
        assert fresh.frames[0].cameras[cam].augmented


def test_frame_order_gives_this_process_the_first_frame() -> None:
    from worker.augmentation.pool import frame_order

    frames = list(range(10, 20))
    assert frame_order(frames, 0) == frames
    assert frame_order(frames, 1) == [11, 12, 10, *range(13, 20)]
    assert sorted(frame_order(frames, 2)) == frames and frame_order(frames, 2)[4] == 10
    assert frame_order(frames[:3], 2) == frames[:3]


def test_key_frames_measured_after_the_plan_give_the_same_clouds(
    noisy_run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A plan made without the noise (a pool's: its parent measures the key frames while
    the children start) writes the clouds and records the eager plan does; a process
    that reads the plan's record takes the estimates the first one shared, without
    measuring them again."""
    import worker.augmentation.lidar_noise as ln
    from worker.augmentation.records import dump_plan, load_plan

    seq, plan, chunk, _, out = noisy_run
    lazy = plan_augmentation(seq, plan.spec, truth_prepared(seq), measure_noise=False)
    assert lazy.lidar_noise == {} and sorted(lazy.lidar_noise_spheres) == sorted(plan.lidar_noise)
    lazy.lidar_noise_dir = str(tmp_path / "shared")
    (tmp_path / "shared").mkdir()
    record = dump_plan(lazy)  # as the pool's children get it: before anything is measured
    assert ln.measure_pending_noise(lazy) == len(plan.lidar_noise)
    assert len(list((tmp_path / "shared").glob("*.json"))) == len(plan.lidar_noise)

    def refuse(*args, **kwargs):
        raise AssertionError("measured again although the estimate was shared")

    monkeypatch.setattr(ln, "measure_key_noise", refuse)
    child = load_plan(record)
    again = augment_frames(child, child.frames, tmp_path / "again")
    for a, b in zip(again.frames, chunk.frames, strict=True):
        uri = plan.uris[a.frame_idx]["lidar"].lstrip("/")
        assert (tmp_path / "again" / uri).read_bytes() == (out / uri).read_bytes()
        assert json.dumps(a.lidar_noise) == json.dumps(b.lidar_noise)  # NaN != NaN
