"""Evaluation results as plain-text tables (the lines ``osdar-ar`` prints): the paper's
RPE / jitter beside the true errors of synthetic data, per camera and strategy."""

from __future__ import annotations

from typing import Any


def _fmt(stats: dict[str, Any] | None) -> str:
    if not stats or stats.get("mean") is None:
        return "-"
    return f"{stats['mean']:.2f} ± {stats['std']:.2f}"


def rpe_tables(ev: dict[str, Any], gt: dict[str, Any]) -> list[str]:
    """Two tables, named for what they measure: the paper's RPE / jitter (the calibration
    point picked from the clicked landmark, projected with the poses, against the clicks:
    comparable with the paper's table) and, on synthetic data, the true error (the true 3D
    landmarks projected with the estimated poses against their true pixels)."""
    lines = ["  paper RPE / jitter (calibration point from the clicks, as the paper):"]
    lines.append(f"  {'camera':<20} {'track':<10} {'RPE px':>16} {'jitter px':>16}")
    chosen = str(ev.get("strategy") or "")
    for cam, m in (ev.get("rpe") or {}).items():  # the user's clicks: the chosen track
        rpe, jit = _fmt(m.get("rpe_px")), _fmt(m.get("jitter_px"))
        lines.append(f"  {cam:<20} {chosen:<10} {rpe:>16} {jit:>16}")
    if not ev.get("rpe"):  # synthetic clicks on the landmarks: every track evaluated
        for cam, tracks in (ev.get("paper_rpe") or {}).items():
            for name, st in tracks.items():
                rpe = _fmt({"mean": st.get("rpe_mean"), "std": st.get("rpe_std")})
                jit = _fmt({"mean": st.get("jitter_mean"), "std": st.get("jitter_std")})
                lines.append(f"  {cam:<20} {name:<10} {rpe:>16} {jit:>16}")
    landmark = gt.get("landmark_rpe") or {}
    if landmark:
        lines.append("  true error of the ground-truth landmarks (synthetic data only):")
        lines.append(f"  {'camera':<20} {'track':<10} {'error px':>16} {'change px':>16}")
        for cam, tracks in landmark.items():
            for name, m in tracks.items():
                err, jit = _fmt(m.get("rpe_px")), _fmt(m.get("jitter_px"))
                lines.append(f"  {cam:<20} {name:<10} {err:>16} {jit:>16}")
    return lines


def strategy_rpe_table(metrics: dict[str, Any]) -> list[str]:
    """The paper's RPE / jitter per camera and strategy of
    :func:`~worker.evaluation.evaluate.evaluate_strategies`' metrics, then the true pose
    error of each strategy where the sequence has ground truth."""
    lines = [
        "paper RPE / jitter (calibration point from the clicks, as the paper):",
        "camera              strategy   RPE mean±std px    jitter mean±std px   n",
    ]
    for cam, per in metrics["rpe"].items():
        for s, st in per.items():
            rpe = "-" if st["rpe_mean"] is None else f"{st['rpe_mean']:.2f}±{st['rpe_std']:.2f}"
            jit = (
                "-"
                if st["jitter_mean"] is None
                else (f"{st['jitter_mean']:.2f}±{st['jitter_std']:.2f}")
            )
            lines.append(f"{cam:<19} {s:<10} {rpe:<18} {jit:<20} {st['n']}")
    for s, te in (metrics.get("true_errors") or {}).items():
        if "translation_m_mean" in te:
            lines.append(
                f"true pose error {s}: {te['translation_m_mean']:.3f} m, "
                f"{te['rotation_deg_mean']:.3f} deg (mean)"
            )
    return lines


def pose_error_table(rows: list[dict[str, Any]]) -> list[str]:
    """The true pose errors of :func:`~worker.evaluation.pose_error.pose_error_rows`, one
    line per track (nothing when there are no rows)."""
    if not rows:
        return []
    lines = [
        "  true pose errors (ground_truth/poses.csv):",
        f"  {'track':<22} {'frames':>6} {'t mean m':>9} {'t max m':>9} "
        f"{'r mean deg':>10} {'r max deg':>10}",
    ]
    for r in rows:
        lines.append(
            f"  {r['track']:<22} {r['frames']:>6d} {r['translation_mean_m']:>9.3f} "
            f"{r['translation_max_m']:>9.3f} {r['rotation_mean_deg']:>10.3f} "
            f"{r['rotation_max_deg']:>10.3f}"
        )
    return lines
