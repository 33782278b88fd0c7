"""The paper's table (OSDAR23.md) and ours on the synthetic counterparts of its sequences.

One row per (sequence, camera, strategy): RPE and jitter mean and std in pixels at the
camera's full resolution (:func:`worker.evaluation.evaluate.evaluate_strategies`, landmarks
30-80 m ahead clicked at the true pixels of their nearest lidar returns) and the seconds of a
full preparation with that strategy (no cache; KISS-ICP included for every strategy).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from worker.evaluation.evaluate import evaluate_strategies
from worker.preparation.config import PrepareConfig
from worker.preparation.lidar_alignment import corrections_from_summary
from worker.preparation.prepare import run_preparation
from worker.synth.generator import SynthConfig, generate

log = logging.getLogger(__name__)

#: scene -> the paper's sequence it stands for.
SEQUENCES = {
    "fire_site": "3_fire_site_3.1",
    "station": "5_station_bergedorf_5.1",
    "klein_flottbek": "6_station_klein_flottbek_6.2",
}
CAMERAS = ("rgb_center", "rgb_highres_center")
#: The paper's strategies -> ours: raw INS, KISS-ICP lidar odometry, rails-refined INS.
PAPER_STRATEGY = {"ins": "ins", "odometry": "odo", "rails": "refined"}

#: OSDAR23.md: (seq, camera) -> {paper strategy: (RPE mean, std, J mean, std)} px.
PAPER_TABLE: dict[tuple[str, str], dict[str, tuple[float, float, float, float]]] = {
    ("3_fire_site_3.1", "rgb_center"): {
        "ins": (81.3, 50.1, 2.71, 3.16), "odo": (25.3, 17.4, 1.91, 2.70),
        "refined": (31.1, 12.5, 1.54, 1.62)},
    ("3_fire_site_3.1", "rgb_highres_center"): {
        "ins": (89.0, 92.0, 4.23, 5.59), "odo": (56.8, 45.1, 3.11, 4.31),
        "refined": (22.0, 27.7, 2.14, 2.46)},
    ("5_station_bergedorf_5.1", "rgb_center"): {
        "ins": (63.7, 44.7, 3.10, 4.07), "odo": (43.9, 27.0, 2.17, 2.43),
        "refined": (60.1, 43.5, 3.10, 4.03)},
    ("5_station_bergedorf_5.1", "rgb_highres_center"): {
        "ins": (77.9, 106.6, 5.89, 7.44), "odo": (92.5, 70.8, 4.43, 5.55),
        "refined": (77.0, 107.7, 5.92, 7.56)},
    ("6_station_klein_flottbek_6.2", "rgb_center"): {
        "ins": (49.3, 13.0, 1.23, 0.99), "odo": (43.6, 5.3, 1.29, 0.96),
        "refined": (42.0, 9.3, 1.26, 0.93)},
    ("6_station_klein_flottbek_6.2", "rgb_highres_center"): {
        "ins": (31.4, 15.1, 1.45, 1.32), "odo": (20.9, 4.9, 1.29, 1.22),
        "refined": (18.9, 9.2, 1.78, 1.61)},
}  # fmt: skip


def paper_band(camera: str, kind: str = "ins") -> tuple[float, float]:
    """(min, max) of the paper's RPE means of one strategy on one camera over the three
    sequences: the 'paper's band' our raw INS should land in."""
    v = [row[kind][0] for (_, cam), row in PAPER_TABLE.items() if cam == camera]
    return min(v), max(v)


@dataclass
class BenchSettings:
    frames: int = 100
    scale: float = 0.1  # images: only overlays and the floor read them
    lidar_density: float = 1.0
    seed: int = 0
    strategies: tuple[str, ...] = ("ins", "odometry", "rails", "fused")
    scenes: tuple[str, ...] = tuple(SEQUENCES)
    voxel_size: float = 0.1
    #: The synthetic INS (:meth:`~worker.synth.ins_sim.InsErrorModel.profile`): "osdar23"
    #: wanders slowly like the real sequences' INS, whose raw reprojection errors are the
    #: paper's band.
    ins_profile: str = "osdar23"


def make_sequence(root: Path, scene: str, s: BenchSettings, **extra: Any) -> Path:
    """Generate (once; deterministic from the settings) a synthetic sequence."""

    tag = f"{scene}_f{s.frames}_s{s.scale:g}_d{s.lidar_density:g}_r{s.seed}_{s.ins_profile}"
    tag += "".join(f"_{k}" for k in sorted(extra))
    folder = Path(root) / tag
    if not (folder / "ground_truth" / "meta.json").is_file():
        cfg = SynthConfig(
            scene=scene, frames=s.frames, scale=s.scale, lidar_density=s.lidar_density,
            seed=s.seed, ins_profile=s.ins_profile, **extra,
        )  # fmt: skip
        generate(folder, cfg)
    return folder


def prepare_timed(seq: Path, strategy: str, voxel_size: float = 0.1) -> tuple[Any, float]:
    """A full preparation (no cache) with one strategy: (PreparedSequence, seconds)."""

    cfg = PrepareConfig(strategy=strategy).with_overrides(registration={"voxel_size": voxel_size})
    t0 = time.perf_counter()
    prepared = run_preparation(seq, cfg)
    return prepared, time.perf_counter() - t0


def run_sequence(
    seq: Path, scene: str, s: BenchSettings, prepared_out: dict | None = None
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Rows of one sequence (every strategy, both cameras) and its evaluation metrics."""

    tracks, prep, world, corrections = {}, {}, None, None
    for strat in s.strategies:
        prepared, sec = prepare_timed(seq, strat, s.voxel_size)
        tracks[strat] = (prepared.track, prepared.cloud.xyz)
        prep[strat] = {"seconds": sec, "warnings": prepared.summary.get("warnings", [])}
        world = prepared.world
        corrections = corrections_from_summary(prepared.summary.get("lidar_alignment"))
        if prepared_out is not None:
            prepared_out[strat] = prepared
        log.info("bench %s %s: prepared in %.1f s", scene, strat, sec)
    metrics, per_frame = evaluate_strategies(
        seq, tracks, world=world, cameras=list(CAMERAS), preparation=prep,
        lidar_corrections=corrections,
    )  # fmt: skip
    rows = []
    for cam in CAMERAS:
        for strat in s.strategies:
            st = metrics["rpe"].get(cam, {}).get(strat, {})
            rows.append(
                {
                    "sequence": SEQUENCES.get(scene, scene),
                    "scene": scene,
                    "camera": cam,
                    "strategy": strat,
                    "rpe_mean": st.get("rpe_mean"),
                    "rpe_std": st.get("rpe_std"),
                    "jitter_mean": st.get("jitter_mean"),
                    "jitter_std": st.get("jitter_std"),
                    "landmark_mean": st.get("landmark_mean"),
                    "landmarks": len(st.get("landmarks") or {}),
                    "observations": st.get("n"),
                    "seconds": prep[strat]["seconds"],
                    "true_translation_m": (metrics.get("true_errors", {}).get(strat) or {}).get(
                        "translation_m_mean"
                    ),
                }
            )
    metrics["per_frame_rows"] = len(per_frame)
    return rows, {"metrics": metrics, "per_frame": per_frame}


def _pm(m: float | None, s: float | None, nd: int = 1) -> str:
    if m is None:
        return "-"
    return f"{m:.{nd}f}±{s:.{nd}f}" if s is not None else f"{m:.{nd}f}"


def format_table(rows: list[dict[str, Any]], strategies: list[str]) -> str:
    """The paper's layout: one line per (sequence, camera), RPE then jitter per strategy;
    the paper's value in brackets where it has that strategy."""
    cams = {"rgb_center": "C1", "rgb_highres_center": "C2"}
    head = ["seq", "cam"]
    head += [f"RPE {s}" for s in strategies] + [f"J {s}" for s in strategies]
    lines = [" | ".join(head)]
    keys = list(dict.fromkeys((r["sequence"], r["camera"]) for r in rows))
    for seq, cam in keys:
        by = {r["strategy"]: r for r in rows if r["sequence"] == seq and r["camera"] == cam}
        paper = PAPER_TABLE.get((seq, cam), {})
        cells = [seq.split("_")[-1], cams.get(cam, cam)]
        for kind, nd in (("rpe", 1), ("jitter", 2)):
            for s in strategies:
                r = by.get(s, {})
                c = _pm(r.get(f"{kind}_mean"), r.get(f"{kind}_std"), nd)
                p = paper.get(PAPER_STRATEGY.get(s, ""))
                if p is not None:
                    pm = p[0:2] if kind == "rpe" else p[2:4]
                    c += f" [{pm[0]:.{nd}f}±{pm[1]:.{nd}f}]"
                cells.append(c)
        lines.append(" | ".join(cells))
    return "\n".join(lines)
