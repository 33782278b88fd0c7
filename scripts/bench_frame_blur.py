# ruff: noqa: T201 (a script: prints its table)
"""Accuracy and speed of renderer.frame_blur.estimate_blur_sigma on camera-made frames.

Accuracy: the test frames of tests/renderer/test_frame_blur.py (boxes; ballast with a
track; seeds 0-2, noise 2 and 4 levels): estimate / true edge spread per blur sigma.
Speed: median ms of one estimate on a full-resolution frame (4112 x 2504, the
rgb_highres cameras) for the composite's window (an object's ROI of 200 x 400 px grown
by 48 px) and for the whole frame.

    .venv/bin/python scripts/bench_frame_blur.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from renderer.frame_blur import estimate_blur_sigma
from tests.renderer import test_frame_blur as tf


def accuracy() -> None:
    for kind in ("boxes", "ballast"):
        for noise in (2.0, 4.0):
            cells = []
            for sigma in (0.3, 0.4, 0.5, 0.6, 0.8, 1.2, 1.6, 2.0):
                r = []
                for seed in range(3):
                    scene = tf.boxes(seed) if kind == "boxes" else tf.ballast(seed)
                    img = tf.camera(scene, sigma, noise, seed)
                    est = estimate_blur_sigma(img, (0, 0, tf.W, tf.H), tf.EXCLUDE)
                    r.append(np.nan if est is None else est / tf.true_spread(sigma))
                cells.append(f"{sigma}: {np.nanmin(r):.2f}-{np.nanmax(r):.2f}")
            print(f"{kind:8s} noise {noise}: " + "  ".join(cells))


def speed(repeats: int = 7) -> None:
    H, W = 2504, 4112
    tile = tf.camera(tf.ballast(0), 1.0, 2.0, 0)
    frame = np.ascontiguousarray(np.tile(tile, (H // tf.H + 1, W // tf.W + 1, 1))[:H, :W])
    u0, v0 = 2000, 1200
    win = (u0 - 48, v0 - 48, u0 + 200 + 48, v0 + 400 + 48)
    exclude = np.zeros((win[3] - win[1], win[2] - win[0]), bool)
    exclude[48:-48, 48:-48] = True
    for name, w, ex in (("window 296x496", win, exclude), ("full frame", (0, 0, W, H), None)):
        ts = []
        for _ in range(repeats):
            tic = time.perf_counter()
            estimate_blur_sigma(frame, w, ex)
            ts.append(time.perf_counter() - tic)
        print(f"speed {name}: median {1e3 * float(np.median(ts)):.1f} ms ({repeats} runs)")


if __name__ == "__main__":
    accuracy()
    speed()
