# ruff: noqa: T201 (a script: prints its table)
"""Render + composite cost per frame at full sensor resolution vs the PNG encode floor.

For both front cameras at their real resolution: a ~20k-triangle object (icosphere
"boulder", 1.6 m) standing on a ground proxy on the track at the positions of a synthetic
sequence's true poses (the train approaches it), lit from the frame; per frame the time of
``ObjectRenderer.render`` + ``composite`` (medians) against ``cv2.imencode`` of the same
frame at PNG levels 1..3. A worst case (an elephant-sized box at 3 m filling the image) is
timed too.

    .venv/bin/python scripts/bench_render.py [--seq /tmp/seqs/fire_site] [--frames 12]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
import trimesh

from geometry.camera import CameraModel
from geometry.poses import PoseTrack
from geometry.transforms import make_T
from renderer.composite import composite
from renderer.lighting import estimate_lighting
from renderer.mesh import ObjectMesh, ProxyMesh
from renderer.object_render import ObjectRenderer
from worker.osdar.sequence import Sequence

CAMERAS = ("rgb_center", "rgb_highres_center")


def boulder() -> ObjectMesh:
    s = trimesh.creation.icosphere(subdivisions=5, radius=0.8)  # 20480 triangles
    rng = np.random.default_rng(0)
    v = np.asarray(s.vertices) * (1.0 + 0.08 * rng.standard_normal((len(s.vertices), 1)))
    v[:, 2] += 0.7
    col = np.tile(np.array([0.35, 0.32, 0.28], np.float32), (len(v), 1))
    return ObjectMesh(v, s.faces, col, np.full(len(v), 0.3, np.float32), "rock")


def elephant_box() -> ObjectMesh:
    b = trimesh.creation.box(extents=(3.5, 2.5, 3.2))
    v = np.asarray(b.vertices) + np.array([0.0, 0.0, 1.6])
    return ObjectMesh(v, b.faces, np.full((len(v), 3), 0.3, np.float32), np.ones(len(v)))


def median_ms(f, *args, n: int = 3, **kw) -> float:
    """Median wall time (ms) of ``f(*args, **kw)`` over ``n`` calls."""
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        f(*args, **kw)
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", type=Path, default=Path("/tmp/seqs/fire_site"))
    ap.add_argument("--frames", type=int, default=12)
    args = ap.parse_args()

    seq = Sequence.open(args.seq)
    meta = json.loads((args.seq / "ground_truth/meta.json").read_text())
    track = PoseTrack.from_csv(args.seq / "ground_truth/poses_dense.csv")
    idx = seq.frame_indices
    pick = np.linspace(0, len(idx) - 1, min(args.frames, len(idx))).round().astype(int)
    obj, big = boulder(), elephant_box()
    print(f"sequence {args.seq.name}: {len(pick)} frames; object {len(obj.faces)} triangles")
    for name in CAMERAS:
        cam = CameraModel.from_json(meta["cameras_full_resolution"][name])
        ts = seq.timestamps(name)
        T_first = track.interpolate(np.array([ts[0]]))[0]
        # The object on the track ahead of the first pose; a ground plane under it.
        T_world_obj = T_first @ make_T(np.eye(3), [100.0, 0.0, 0.0])
        g = T_world_obj[:3, 3]
        quad = np.array([[-200, -200, 0], [200, -200, 0], [200, 200, 0], [-200, 200, 0.0]])
        ground = ProxyMesh(g + quad, np.array([[0, 1, 2], [0, 2, 3]]))
        rr = ObjectRenderer(cam)
        t0 = time.perf_counter()
        rr.render(obj, T_world_obj, T_first, proxies=ground)  # warm-up (shaders, maps)
        warm = time.perf_counter() - t0
        rows = []
        for k in pick:
            img = cv2.resize(seq.image(idx[k], name), (cam.width, cam.height), cv2.INTER_LINEAR)
            T_wb = track.interpolate(np.array([ts[k]]))[0]
            t = time.perf_counter()
            light = estimate_lighting(img, cam, T_wb)
            t_light = time.perf_counter() - t
            t = time.perf_counter()
            r = rr.render(obj, T_world_obj, T_wb, proxies=ground, light=light)
            t_render = time.perf_counter() - t
            t = time.perf_counter()
            composite(img, r, speed_mps=15.0)
            t_comp = time.perf_counter() - t
            roi_px = 0 if r.roi is None else (r.roi[2] - r.roi[0]) * (r.roi[3] - r.roi[1])
            rows.append((t_light, t_render, t_comp, roi_px, r.distance_m))
        a = np.array(rows)
        bgr = np.ascontiguousarray(img[..., ::-1])
        enc = {
            lvl: median_ms(cv2.imencode, ".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, lvl])
            for lvl in (1, 2, 3)
        }
        per_frame = 1e3 * float(np.median(a[:, 0] + a[:, 1] + a[:, 2]))
        print(f"\n{name} {cam.width}x{cam.height}  (first call incl. setup {warm * 1e3:.0f} ms)")
        print(f"  object distance {a[:, 4].min():.0f}..{a[:, 4].max():.0f} m, "
              f"ROI median {np.median(a[:, 3]) / 1e3:.0f} kpx")  # fmt: skip
        print(f"  median ms: lighting {1e3 * np.median(a[:, 0]):.1f}, render "
              f"{1e3 * np.median(a[:, 1]):.1f}, composite {1e3 * np.median(a[:, 2]):.1f}, "
              f"total {per_frame:.1f}")  # fmt: skip
        for lvl, ms in enc.items():
            print(f"  PNG encode level {lvl}: {ms:.0f} ms -> render+composite = "
                  f"{100 * per_frame / ms:.1f} % of it")  # fmt: skip
        # Worst case: an elephant-sized box at 3 m filling the whole image.
        T_big = T_first @ make_T(np.eye(3), [4.8, 0.0, 0.0])
        img0 = cv2.resize(seq.image(idx[0], name), (cam.width, cam.height))
        rb = rr.render(big, T_big, T_first, proxies=ground)
        ms_r = median_ms(rr.render, big, T_big, T_first, proxies=ground)
        ms_c = median_ms(composite, img0, rb)
        print(f"  worst case (full-frame elephant at 3 m, ROI {rb.roi}): render {ms_r:.0f} ms, "
              f"composite {ms_c:.0f} ms")  # fmt: skip
        rr.close()


if __name__ == "__main__":
    main()
