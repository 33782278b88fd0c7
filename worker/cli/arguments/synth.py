"""``osdar-ar synth``: a synthetic OSDaR23-layout sequence with ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "synth",
        help="generate a synthetic OSDaR23-layout sequence with ground truth",
        description="Generate a synthetic OSDaR23 sequence (cameras, lidar, INS) from a "
        "procedural railway scene with the real OSDaR23 calibration; ground truth goes to "
        "OUT/ground_truth/.",
    )
    p.add_argument("out", type=Path, help="output folder; its name is the sequence name")
    p.add_argument("--scene", default="fire_site", help="scene preset (see --list-scenes)")
    p.add_argument("--list-scenes", action="store_true", help="list scene presets and exit")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument(
        "--scale",
        type=float,
        default=0.25,
        help="image size relative to the real resolution (1.0 = 2464x1600, 4112x2504)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cameras", default="rgb_center,rgb_highres_center")
    p.add_argument(
        "--lidar-density",
        type=float,
        default=1.0,
        help="fraction of the real lidars' rays (1.0 = OSDaR23 point counts)",
    )
    p.add_argument(
        "--ins-profile",
        default="paper",
        help="INS error profile: paper, good, perfect, hard, osdar23",
    )
    p.add_argument(
        "--ins",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an INS error-model field, e.g. --ins latency_s=0.05 "
        "(JSON values: --ins 'jumps=[[40,[3,0,0]]]')",
    )
    p.add_argument("--speed", type=float, default=None, help="train speed m/s (scene default)")
    p.add_argument("--stationary", action="store_true", help="train stands still")
    p.add_argument(
        "--bogies",
        default=None,
        metavar="OVERHANG,SPACING",
        help="the train body on two bogies, e.g. 3,19: the base OVERHANG m ahead of the "
        "front bogie, bogie centres SPACING m apart (default: the base on the centreline)",
    )
    p.add_argument(
        "--lidar-blind-ahead",
        type=float,
        default=0.0,
        metavar="M",
        help="the lidars see nothing nearer than M m ahead of the base (default 0)",
    )
    p.add_argument(
        "--merge-error",
        default=None,
        metavar="DEG,M",
        help="per-lidar calibration error of the merged clouds (rotation deg, translation m "
        "standard deviations; default: the INS profile's, 0.03,0.015 for osdar23)",
    )
    p.add_argument(
        "--far-origin",
        action="store_true",
        help="build and render the scene at UTM magnitudes (hard case 1)",
    )
    p.add_argument("--first-counter", type=int, default=0)
    p.add_argument("--drop-frames", default="", help="comma-separated frame counters to drop")
    p.add_argument("--pcd-data", default="binary", choices=["ascii", "binary", "binary_compressed"])
    p.add_argument(
        "--calibration",
        type=Path,
        default=None,
        help="OSDaR23 labels file with the real calibration "
        "(default: ../shared/data/osdar23/1_calibration_1.1_labels.json)",
    )
    p.add_argument("--force", action="store_true", help="replace OUT if it exists")
    p.set_defaults(command_group="synth")
