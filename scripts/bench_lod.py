# ruff: noqa: T201 (a script: prints its table)
"""How few triangles does an obstacle need before its camera mask changes? (BENCHMARK.md)

For each obstacle of the library (detail 1 = the reference), the mesh is decimated
(renderer.assets.lod.simplify) to a falling series of face counts and its silhouette is
rasterised (pinhole, OpenCV polygon fill with 1/256 px vertices) as rgb_highres_center
sees it (fx = 7268 px) from 80 m (and other distances with --distances), from the front,
the side and at 45 deg, camera 2.5 m above the ground. The change against the reference
mask is the symmetric Hausdorff distance of the two outlines (px): 1 or 1.41 px means
single pixels flipped along the edge, "changed by more than 1 px" is > 1.5. The "faces
needed" is the smallest face count from which on every larger count all views stay
within that. Prints a table and the ratio faces /
projected height that sets renderer.assets.lod.FACES_PER_PX.

    .venv/bin/python scripts/bench_lod.py [--distances 80 40 20] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from renderer.assets.lod import (
    FACES_PER_PX,
    choose_detail,
    mask_change,
    project,
    rasterize,
    simplify,
    view_camera,
)
from renderer.assets.obstacles import OBSTACLES, build_obstacle

FX_HIGHRES = 7268.0
VIEWS_DEG = (0.0, 45.0, 90.0)
TOL_PX = 1.5  # one pixel, diagonal neighbours included (sqrt 2 = 1.41 passes)


def masks(mesh, ref_mesh, distance: float):
    """Reference and test silhouettes per view, on the reference's pixel window."""
    out = []
    for yaw in VIEWS_DEG:
        T = view_camera(yaw, distance)
        uv_ref = project(ref_mesh.vertices, T, FX_HIGHRES)
        lo = np.floor(uv_ref.min(axis=0)) - 4
        shape = tuple((np.ceil(uv_ref.max(axis=0) - lo) + 5).astype(int)[::-1])
        a = rasterize(uv_ref, ref_mesh.faces, lo, shape)
        b = rasterize(project(mesh.vertices, T, FX_HIGHRES), mesh.faces, lo, shape)
        out.append(mask_change(a, b))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--distances", type=float, nargs="+", default=[80.0])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    print(f"fx = {FX_HIGHRES:.0f} px, views {VIEWS_DEG} deg, tolerance {TOL_PX} px Hausdorff")
    print(
        f"{'object':12s} {'dist':>5s} {'h_px':>6s} {'full':>6s} {'needed':>7s} "
        f"{'faces/h':>8s} {'IoU@needed':>10s} {'xor@needed':>10s} {'IoU@200':>8s} "
        f"{'choose':>7s} {'s':>5s}"
    )
    ratios = []
    default_ratios: list[float] = []
    for name in OBSTACLES:
        ref = build_obstacle(name, seed=args.seed, detail=1.0)
        k_px = ref.meta.get("lod_faces_per_px", FACES_PER_PX)
        full = len(ref.faces)
        levels = [int(full * 0.5 ** (k / 2)) for k in range(1, 40)]
        levels = [f for f in levels if f >= 100]
        lods = {f: simplify(ref, f) for f in levels}
        for dist in args.distances:
            t0 = time.perf_counter()
            h_px = FX_HIGHRES * ref.size[2] / dist
            needed, at = full, {"iou": 1.0, "xor_px": 0}
            iou_200 = float("nan")
            for f in levels:  # falling face counts
                res = masks(lods[f], ref, dist)
                worst = max(r["hausdorff_px"] for r in res)
                if f >= 190:
                    iou_200 = min(r["iou"] for r in res)
                if worst > TOL_PX:
                    break
                needed = len(lods[f].faces)
                at = {"iou": min(r["iou"] for r in res), "xor_px": max(r["xor_px"] for r in res)}
            ratios.append(needed / h_px)
            print(
                f"{name:12s} {dist:5.0f} {h_px:6.0f} {full:6d} {needed:7d} {needed / h_px:8.2f} "
                f"{at['iou']:10.4f} {at['xor_px']:10d} {iou_200:8.4f} "
                f"{choose_detail(h_px, k_px):7d} "
                f"{time.perf_counter() - t0:5.1f}"
            )
            if name == "fallen_tree":
                continue  # its own constant (meta lod_faces_per_px), not the default's
            default_ratios.append(needed / h_px)
    print(
        f"faces/h_px without the tree: max {max(default_ratios):.2f}, median "
        f"{np.median(default_ratios):.2f} (lod.FACES_PER_PX = {FACES_PER_PX}); all: max "
        f"{max(ratios):.2f}"
    )


if __name__ == "__main__":
    main()
