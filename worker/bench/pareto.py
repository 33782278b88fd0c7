"""Speed against error over the knobs (BENCHMARK.md): strategy x registration voxel size.

Each configuration is a full preparation (seconds, no cache) evaluated with the paper's
RPE on one camera (error_px = RPE mean over landmarks' observations, full-resolution px).
The Pareto front: configurations no other one beats on both seconds and error.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib
import matplotlib.pyplot as plt

from worker.bench.paper import prepare_timed
from worker.evaluation.evaluate import evaluate_strategies
from worker.preparation.lidar_alignment import corrections_from_summary


def config_name(strategy: str, voxel_size: float) -> str:
    return f"{strategy} voxel={voxel_size:g}"


def run_configs(
    seq: Path,
    configs: list[tuple[str, float]],
    camera: str = "rgb_highres_center",
    known: dict[str, dict[str, Any]] | None = None,
) -> list[dict[str, Any]]:
    """[{config, strategy, voxel_size, seconds, error_px, jitter_px}] for each config;
    ``known`` {config name: {"seconds", "error_px", "jitter_px"}} is reused, not rerun."""

    out = []
    for strategy, voxel in configs:
        name = config_name(strategy, voxel)
        if known and name in known:
            out.append({"config": name, "strategy": strategy, "voxel_size": voxel, **known[name]})
            continue
        prepared, sec = prepare_timed(seq, strategy, voxel)
        m, _ = evaluate_strategies(
            seq, {strategy: (prepared.track, prepared.cloud.xyz)}, world=prepared.world,
            cameras=[camera],
            lidar_corrections=corrections_from_summary(prepared.summary.get("lidar_alignment")),
        )  # fmt: skip
        st = m["rpe"].get(camera, {}).get(strategy, {})
        out.append(
            {
                "config": name,
                "strategy": strategy,
                "voxel_size": voxel,
                "seconds": sec,
                "error_px": st.get("rpe_mean"),
                "jitter_px": st.get("jitter_mean"),
            }
        )
    return out


def pareto_front(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The non-dominated rows (lower seconds and lower error_px are better), by seconds."""
    ok = [r for r in rows if r.get("error_px") is not None]
    front = [
        r
        for r in ok
        if not any(
            o is not r
            and o["seconds"] <= r["seconds"]
            and o["error_px"] <= r["error_px"]
            and (o["seconds"] < r["seconds"] or o["error_px"] < r["error_px"])
            for o in ok
        )
    ]
    return sorted(front, key=lambda r: r["seconds"])


def plot_pareto(rows: list[dict[str, Any]], out_png: Path, title: str = "") -> Path | None:
    ok = [r for r in rows if r.get("error_px") is not None]
    if not ok:
        return None

    matplotlib.use("Agg")

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for strat in dict.fromkeys(r["strategy"] for r in ok):
        sel = [r for r in ok if r["strategy"] == strat]
        ax.scatter([r["seconds"] for r in sel], [r["error_px"] for r in sel], label=strat)
        for r in sel:
            ax.annotate(f"{r['voxel_size']:g}", (r["seconds"], r["error_px"]), fontsize=7)
    front = pareto_front(ok)
    ax.plot([r["seconds"] for r in front], [r["error_px"] for r in front], "k--", lw=1,
            label="Pareto front")  # fmt: skip
    ax.set_xlabel("preparation seconds")
    ax.set_ylabel("RPE mean (px, full resolution)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=80)
    plt.close(fig)
    return out_png
