# ruff: noqa: T201 (a script: prints its table)
"""Benchmark of the augmentation step against its I/O floor (BENCHMARK.md).

    .venv/bin/python scripts/bench_augment.py /tmp/seqs/fire_site_full --workers 2 --runs 3

Per run, in the same process and with the same worker count:

- **floor**: decode and re-encode every PNG frame of the augmented cameras with the same
  settings (``cv2.imread`` + ``cv2.imencode`` at the spec's compression level + an
  atomic write: the job's own PNG path, no colour conversion) and read and write every
  PCD (``read_pcd`` + ``write_pcd``), in a process pool of ``--workers`` (started before
  the clock: the floor is the I/O alone);
- **job**: :func:`worker.augmentation.augment.augment` with the prepared sequence given
  (the preparation is cached per sequence and reported apart), evaluation off, pool
  start, planning, frames and assembly all inside the clock.

Prints per-stage seconds (medians over runs), job / floor (median of the per-run
ratios) and the frames stage alone / floor. Then the camera's look in the last job's
output (``--look-frames`` frames per camera, the object's poly2d from the labels): the
robust noise inside the object over the frame's noise at the same level measured around
it (renderer/sensor_noise.py; the issue's bound [0.8, 1.25]), and the edge sigma of the
object's silhouette over that of the real step edges around it (both read alike,
``sharpness_inside_outside``; the real edges in the input frame, where the object's own
shadow in the ring is not; the same bound). With ``--origins`` (default
``SEQ/ground_truth/lidar_origins.json`` when present) it also compares the lidar cast
with per-sensor origins against the paper's single origin on every frame.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from geometry.transforms import invert_T
from renderer.lidar_cast import hidden_from, origins_from_json, point_origins
from renderer.sensor_noise import estimate_noise, robust_sigma, sharpness_inside_outside
from worker.augmentation.augment import augment
from worker.augmentation.frame import cast_frame_lidar
from worker.augmentation.plan import plan_augmentation
from worker.augmentation.spec import AugmentSpec, ObjectSource, PlacementModel, RenderSpec
from worker.bench.floor import measure_floor
from worker.osdar.pcd import read_pcd
from worker.osdar.sequence import Sequence, find_labels_file, uri_to_path
from worker.preparation.config import PrepareConfig
from worker.preparation.prepare import prepare

log = logging.getLogger("bench_augment")


def origins_gain(seq_folder: Path, spec: AugmentSpec, prepared: Any, origins_file: Path) -> None:
    """Per-sensor origins vs the single origin, against the per-sensor cast as reference."""
    plan = plan_augmentation(seq_folder, spec, prepared)
    if plan.lidar_stream is None:
        return
    true_o = origins_from_json(json.loads(origins_file.read_text()))
    n_true = n_single = missed = extra = hidden = 0
    disp = []
    for f in plan.frames:
        path = uri_to_path(seq_folder, plan.uris[f][plan.lidar_stream])
        fields = read_pcd(path).fields
        T_base_obj = invert_T(plan.T_world_base[plan.lidar_stream][f]) @ plan.T_world_obj
        new_t, idx_t, _ = cast_frame_lidar(fields, plan.obj_full, T_base_obj, true_o)
        new_s, idx_s, _ = cast_frame_lidar(fields, plan.obj_full, T_base_obj, np.zeros(3))
        n_true += len(idx_t)
        n_single += len(idx_s)
        missed += len(np.setdiff1d(idx_t, idx_s))
        extra += len(np.setdiff1d(idx_s, idx_t))
        if len(idx_s):
            pts = np.stack([new_s[k][idx_s] for k in "xyz"], 1).astype(np.float64)
            o = point_origins({k: v[idx_s] for k, v in fields.items()}, true_o)
            hidden += int(hidden_from(plan.obj_full, T_base_obj, pts, o).sum())
        common = np.intersect1d(idx_t, idx_s)
        if len(common):
            a = np.stack([new_t[k][common] for k in "xyz"], 1).astype(np.float64)
            b = np.stack([new_s[k][common] for k in "xyz"], 1).astype(np.float64)
            disp.append(np.linalg.norm(a - b, axis=1))
    d = np.concatenate(disp) if disp else np.zeros(0)
    print(f"\nlidar origins over {len(plan.frames)} frames (reference: per-sensor cast)")
    print(f"  object points: per-sensor {n_true}, single origin {n_single}")
    if n_true:
        print(f"  single origin misses {missed} ({100 * missed / n_true:.1f} %) of the points")
    if n_single:
        print(
            f"  single origin moves {extra} ({100 * extra / n_single:.1f} %) points the true "
            f"rays do not reach the object with; {hidden} ({100 * hidden / n_single:.1f} %) "
            "lie on faces their own sensor cannot see"
        )
    if len(d):
        print(
            f"  points on the object in both: position difference median "
            f"{1000 * np.median(d):.1f} mm, max {1000 * d.max():.1f} mm"
        )


def _rgb(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def look_check(seq: Sequence, out: Path, cams: list[str], n_frames: int) -> dict[str, Any]:
    """Noise and sharpness of the object against its surroundings in the output frames."""
    aug = Sequence.open(out)
    ol = json.loads(find_labels_file(out).read_text())["openlabel"]
    noise, sharp = [], []
    frames = seq.frame_indices
    for f in frames[:: max(1, len(frames) // max(n_frames, 1))][:n_frames]:
        objs = ol["frames"].get(str(f), {}).get("objects", {})
        for cam in cams:
            polys = [
                p["val"]
                for o in objs.values()
                for p in o.get("object_data", {}).get("poly2d", [])
                if p.get("coordinate_system") == cam
            ]
            if not polys:
                continue
            src, dst = _rgb(seq.image_path(f, cam)), _rgb(aug.image_path(f, cam))
            H, W = src.shape[:2]
            mask = np.zeros((H, W), np.uint8)
            for val in polys:
                cv2.fillPoly(mask, [np.round(np.reshape(val, (-1, 2))).astype(np.int32)], 1)
            inner = cv2.erode(mask, np.ones((7, 7), np.uint8)).astype(bool)
            if inner.sum() < 300:
                continue
            vs, us = np.nonzero(mask)
            win = (max(us.min() - 60, 0), max(vs.min() - 60, 0), min(us.max() + 61, W),
                   min(vs.max() + 61, H))  # fmt: skip
            prof = estimate_noise(src, win, cv2.dilate(mask, np.ones((9, 9), np.uint8))[
                win[1]:win[3], win[0]:win[2]].astype(bool))  # fmt: skip
            if prof is None:
                continue
            level = np.median(dst[inner].astype(float), axis=0)
            want = prof.sigma_at(level[None])[0]
            got = np.array([robust_sigma(dst[..., c], inner) for c in range(3)])
            noise.append(float(np.median(got / np.maximum(want, 1e-6))))
            s_obj, s_real = sharpness_inside_outside(
                dst, (0, 0, W, H), mask.astype(np.float32), real_rgb=src
            )
            if np.isfinite(s_obj) and np.isfinite(s_real) and s_real > 0:
                sharp.append(s_obj / s_real)
    res = {
        "views": len(noise),
        "noise_ratio_median": float(np.median(noise)) if noise else float("nan"),
        "noise_ratio_range": [float(np.min(noise)), float(np.max(noise))] if noise else [],
        "sharpness_ratio_median": float(np.median(sharp)) if sharp else float("nan"),
        "sharpness_ratio_range": [float(np.min(sharp)), float(np.max(sharp))] if sharp else [],
    }
    print(f"\ncamera look over {res['views']} object views (inside / around the object):")
    print(f"  robust noise ratio: median {res['noise_ratio_median']:.3f}, range "
          f"{np.round(res['noise_ratio_range'], 3).tolist()} (bound [0.8, 1.25])")  # fmt: skip
    print(f"  edge sigma ratio:   median {res['sharpness_ratio_median']:.3f}, range "
          f"{np.round(res['sharpness_ratio_range'], 3).tolist()} (bound [0.8, 1.25])")  # fmt: skip
    return res


def camera_optics(seq_folder: Path) -> dict[str, float]:
    """RenderSpec's ``exposure_ms`` and ``aperture_mm`` of a synthetic sequence's cameras
    (``ground_truth/meta.json``'s ``camera_optics``); {} when it has none."""
    meta = seq_folder / "ground_truth" / "meta.json"
    optics = json.loads(meta.read_text()).get("camera_optics") if meta.is_file() else None
    if not optics:
        return {}
    return {
        "exposure_ms": 1000.0 * float(optics["exposure_s"]),
        "aperture_mm": 1000.0 * float(optics["aperture_m"]),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--object", default="person")
    ap.add_argument("--place", default="s=40,offset=0,yaw=90")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--strategy", default="auto")
    ap.add_argument("--png-compression", type=int, default=1)
    ap.add_argument("--cache-dir", type=Path, default=Path("/tmp/osdar_bench_cache"))
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/osdar_bench_augment"))
    ap.add_argument("--origins", type=Path, default=None, help="per-sensor lidar_origins.json")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("--look-frames", type=int, default=6, help="frames for the look check (0: off)")
    ap.add_argument("--antialias", default="auto", help="the renderer's auto, none or ssaa<s>")
    ap.add_argument(
        "--optics", choices=("sequence", "default"), default="sequence",
        help="the cameras' exposure and aperture: the sequence's own (a synthetic one's "
        "ground_truth/meta.json: pinholes at the frame's instant) or RenderSpec's defaults",
    )  # fmt: skip
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    seq = Sequence.open(args.sequence)
    optics = camera_optics(args.sequence) if args.optics == "sequence" else {}
    spec = AugmentSpec(
        object=ObjectSource.from_cli(args.object),
        placement=PlacementModel.parse(args.place),
        strategy=args.strategy,
        render=RenderSpec(png_compression=args.png_compression, antialias=args.antialias, **optics),
    )
    tic = time.perf_counter()
    prepared = prepare(
        args.sequence, PrepareConfig(strategy=args.strategy), cache_dir=args.cache_dir
    )
    t_prep = time.perf_counter() - tic
    cams = spec.camera_names(seq.cameras)
    streams = cams + ([seq.lidar_stream] if seq.lidar_stream else [])
    frames = seq.frame_indices
    print(
        f"{seq.name}: {len(frames)} frames, streams {', '.join(streams)}, "
        f"{args.workers} worker(s), PNG level {args.png_compression}, antialias "
        f"{args.antialias}, exposure "
        f"{spec.render.exposure_ms:g} ms, aperture {spec.render.aperture_mm:g} mm; preparation "
        f"{t_prep:.1f} s ({'reused' if prepared.summary.get('reused') else 'computed'})"
    )
    floors, jobs, frame_walls, ratios, stage_runs = [], [], [], [], []
    out = args.scratch / "out"
    for run in range(args.runs):
        order = ("floor", "job") if run % 2 == 0 else ("job", "floor")
        for what in order:
            if what == "floor":
                floors.append(
                    measure_floor(
                        seq, frames, streams, args.workers, args.png_compression,
                        args.scratch / "floor",
                    )
                )  # fmt: skip
            else:
                tic = time.perf_counter()
                m = augment(
                    args.sequence, spec, out, prepared=prepared, workers=args.workers,
                    overwrite=True, evaluate=False,
                )  # fmt: skip
                jobs.append(time.perf_counter() - tic)
                frame_walls.append(m["timings_s"]["frames_total_wall"])
                stage_runs.append(m["timings_s"])
                visible = {c: v["visible_frames"] for c, v in m["cameras"].items()}
        ratios.append(jobs[-1] / floors[-1])
        print(
            f"  run {run + 1}: floor {floors[-1]:.2f} s, job {jobs[-1]:.2f} s "
            f"(frames {frame_walls[-1]:.2f} s), ratio {ratios[-1]:.3f}"
        )
    look = look_check(seq, out, cams, args.look_frames) if args.look_frames > 0 else {}
    shutil.rmtree(args.scratch, ignore_errors=True)
    keys = [k for k, v in stage_runs[0].items() if isinstance(v, float)]
    med = {k: statistics.median(r.get(k, 0.0) for r in stage_runs) for k in keys}
    print(f"\nobject visible in {visible} of {len(frames)} frames")
    print("per-stage seconds (median; frames_* are summed over the workers' processes):")
    for k, v in med.items():
        print(f"  {k:<22} {v:8.3f}")
    result = {
        "sequence": seq.name,
        "frames": len(frames),
        "workers": args.workers,
        "floor_s": floors,
        "job_s": jobs,
        "frames_wall_s": frame_walls,
        "ratio_job_floor": ratios,
        "ratio_median": statistics.median(ratios),
        "ratio_frames_floor_median": statistics.median(
            fw / fl for fw, fl in zip(frame_walls, floors, strict=True)
        ),
        "stages_median_s": med,
        "look": look,
    }
    print(
        f"\nfloor {statistics.median(floors):.2f} s, job {statistics.median(jobs):.2f} s: "
        f"job / floor = {result['ratio_median']:.3f} (median of {args.runs}); "
        f"frames stage / floor = {result['ratio_frames_floor_median']:.3f}; target <= 1.2"
    )
    origins = args.origins or args.sequence / "ground_truth" / "lidar_origins.json"
    if origins.is_file():
        origins_gain(args.sequence, spec, prepared, origins)
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
