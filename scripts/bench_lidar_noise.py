# ruff: noqa: T201 (a script: prints its table)
"""Accuracy of renderer.lidar_noise on synthetic sequences of known range noise.

Per scene/seed: a 4-frame synthetic sequence (scale 0.15, lidar density 0.2; the
sensors' true range noise from worker.synth.lidar_sim.default_sensors), one object
augmented with ``render.lidar_noise`` on, and per sensor: the per-frame estimate / the
true noise (min-max over the frames), and the std of the object points' range residual
against the object's mesh along their own rays / the true noise (the measure of
tests/augmentation/test_frame.py; printed with at least 40 points).

    .venv/bin/python scripts/bench_lidar_noise.py [--runs fire_site:11:cow ...]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from geometry.transforms import invert_T, transform_points
from renderer.lidar_cast import point_origins
from worker.augmentation.finish import finish_augmentation
from worker.augmentation.frame import augment_frames
from worker.augmentation.plan import plan_augmentation
from worker.augmentation.spec import (
    AugmentSpec,
    ObjectSource,
    PlacementModel,
    RenderSpec,
)
from worker.evaluation.object_error import truth_prepared
from worker.osdar.pcd import read_pcd
from worker.synth.generator import SynthConfig, generate
from worker.synth.lidar_sim import default_sensors

RUNS = [
    "fire_site:11:cow", "fire_site:12:cow", "fire_site:13:cow", "fire_site:14:cow",
    "station:11:cow", "station:12:cow", "straight_sparse:11:cow", "tight_curve:11:cow",
    "tight_curve:12:cow", "switch:11:cow", "switch:12:cow", "klein_flottbek:11:cow",
    "fire_site:11:person", "station:11:person", "switch:11:horse",
]  # fmt: skip
TRUE = {s.sensor_index: s.range_sigma for s in default_sensors()}


def one(scene: str, seed: int, builtin: str, base: Path) -> str:
    seq = base / "seq"
    generate(seq, SynthConfig(scene=scene, frames=4, scale=0.15, lidar_density=0.2, seed=seed))
    spec = AugmentSpec(
        object=ObjectSource(builtin=builtin, seed=4),
        placement=PlacementModel.parse("s=18,offset=0,yaw=60"),
        lidar_origins=str(seq / "ground_truth" / "lidar_origins.json"),
        render=RenderSpec(lidar_noise=True),
    )
    plan = plan_augmentation(seq, spec, truth_prepared(seq))
    chunk = augment_frames(plan, plan.frames, base / "scratch")
    finish_augmentation(plan, [chunk], base / "out", evaluate=False)
    est: dict[int, list[float]] = {}
    res: dict[int, list[float]] = {}
    for rec in chunk.frames:
        for s, e in rec.lidar_noise.items():
            est.setdefault(int(s), []).append(e["range_sigma_m"] / TRUE[int(s)])
        idx = np.asarray(rec.annotation.lidar_indices if rec.annotation else [], np.int64)
        if len(idx) == 0:
            continue
        cloud = read_pcd(base / "out" / plan.uris[rec.frame_idx]["lidar"].lstrip("/"))
        p = np.stack([cloud.fields[k][idx] for k in "xyz"], 1).astype(np.float64)
        sub = {k: np.asarray(v)[idx] for k, v in cloud.fields.items()}
        o = point_origins(sub, plan.lidar_origins)
        r = np.linalg.norm(p - o, axis=1)
        obj = plan.objects[0]
        T = invert_T(plan.T_world_base["lidar"][rec.frame_idx]) @ obj.pose("lidar", rec.frame_idx)
        mesh = obj.mesh("lidar", rec.frame_idx, full=True)
        scene_rc = o3d.t.geometry.RaycastingScene()
        scene_rc.add_triangles(
            o3d.core.Tensor(transform_points(T, mesh.vertices).astype(np.float32)),
            o3d.core.Tensor(mesh.faces.astype(np.uint32)),
        )
        rays = np.concatenate([o, (p - o) / r[:, None]], axis=1).astype(np.float32)
        t_hit = scene_rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        for s in np.unique(sub["sensor_index"]):
            res.setdefault(int(s), []).extend((r - t_hit)[sub["sensor_index"] == s].tolist())
    cells = [f"{scene}/{seed}/{builtin}"]
    for s in sorted(est):
        e = np.array(est[s])
        v = res.get(s, [])
        spread = f" obj {np.std(v) / TRUE[s]:.2f} (n={len(v)})" if len(v) >= 40 else ""
        cells.append(f"s{s}: est {np.nanmin(e):.2f}-{np.nanmax(e):.2f}{spread}")
    return "  ".join(cells)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", nargs="*", default=RUNS, help="scene:seed:builtin")
    args = ap.parse_args()
    for run in args.runs:
        scene, seed, builtin = run.split(":")
        with tempfile.TemporaryDirectory() as tmp:
            print(one(scene, int(seed), builtin, Path(tmp)), flush=True)


if __name__ == "__main__":
    main()
