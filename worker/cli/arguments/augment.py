"""``osdar-ar augment``: a virtual obstacle added to a sequence."""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "augment",
        help="add a virtual obstacle to a sequence (cameras, lidar, annotations)",
        description="Augment SEQ with a virtual object and write the result to OUT in the "
        "OSDaR23 layout (every input file present: augmented where the object shows, "
        "byte-identical elsewhere) plus OUT/metrics.json (per-stage timings; the object's "
        "errors where SEQ has ground_truth/). The preparation is cached and reused.",
    )
    p.add_argument("sequence", type=Path)
    p.add_argument(
        "--object",
        required=True,
        help="built-in obstacle (person, rock, fallen_tree, cow, horse, elephant) or a "
        "mesh file (.glb, .gltf, .obj, .ply)",
    )
    p.add_argument("--object-scale", type=float, default=1.0, help="uniform size factor")
    p.add_argument("--mesh-units", type=float, default=None, help="metres per mesh file unit")
    p.add_argument("--seed", type=int, default=0, help="seed of the built-in obstacle")
    p.add_argument(
        "--place",
        default="s=40,offset=0,yaw=90",
        help='track "s=40,offset=0,yaw=90" (m along the ego track from the first frame, '
        'm left, deg from the track direction), world "mode=world,x=..,y=..,yaw=..", or '
        'lidar frame "frame=12,x=..,y=..,yaw=.."',
    )
    p.add_argument("--cameras", default=None, help="comma-separated (default: the front ones)")
    p.add_argument("--no-lidar", action="store_true", help="leave the point clouds unchanged")
    p.add_argument("--frames", default=None, metavar="FIRST:LAST", help="frame range, inclusive")
    p.add_argument("--strategy", default="auto", help="ins, odometry, rails, fused or auto")
    p.add_argument(
        "--lidar-origins",
        default="single",
        help="'single' (the base frame origin, the paper's fallback), 'x,y,z', or a "
        "lidar_origins.json file of per-sensor origins",
    )
    p.add_argument("--clicks", type=Path, default=None, help="clicked landmark pixels file")
    p.add_argument("--png-compression", type=int, default=1, help="zlib level 0-9")
    p.add_argument("--no-blur", action="store_true")
    p.add_argument("--no-lab-match", action="store_true")
    p.add_argument("--shadow", type=float, default=0.6, help="shadow strength 0-1")
    p.add_argument(
        "--exposure-ms", type=float, default=None,
        help="the cameras' exposure, for the object's motion blur (0: none; default: the "
        "assumption of renderer/camera_optics.py)",
    )  # fmt: skip
    p.add_argument(
        "--aperture-mm", type=float, default=None,
        help="effective aperture diameter, for the object's defocus (0: a pinhole; default: "
        "the assumption of renderer/camera_optics.py)",
    )  # fmt: skip
    p.add_argument(
        "--pixel-offset", action="store_true", help="compensate the calibration point's offset"
    )
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--out", type=Path, required=True, help="output sequence folder")
    p.add_argument("--force", action="store_true", help="replace OUT if it exists")
    p.add_argument("--no-evaluate", action="store_true", help="skip the ground-truth errors")
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="cache of prepared artifacts (default: prepared/ in the workers' cache, "
        "$OSDAR_AR_CACHE_DIR, itself default ./var/cache)",
    )
    p.set_defaults(command_group="augment")
