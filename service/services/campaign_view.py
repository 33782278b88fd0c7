"""What the dashboard's campaign pages show: variant rows with a preview each, and the
quality histogram as plain numbers the template draws as inline SVG (no image library, no
geometry: the values are the manifest rows' ``quality``, written by the worker)."""

from __future__ import annotations

import math
from typing import Any

from osdar_platform.models import Job
from service.services import dashboard as view

#: The quality measure of the histogram, by preference (the manifest's per-camera fields).
MEASURES = (
    ("rpe_px_mean", "the paper's RPE (px, mean over frames)"),
    ("bound_px_median", "placement bound (px, median of the per-frame 90 % bound)"),
)


def quality_values(rows: list[dict[str, Any] | None], camera: str) -> tuple[str, str, list[float]]:
    """(measure, its label, one value per variant) of the first measure any variant has."""
    for measure, label in MEASURES:
        values = []
        for row in rows:
            q = ((row or {}).get("quality") or {}).get(camera) or {}
            x = q.get(measure)
            if isinstance(x, int | float) and math.isfinite(x):
                values.append(float(x))
        if values:
            return measure, label, values
    return MEASURES[0][0], MEASURES[0][1], []


def histogram(
    values: list[float], *, bins: int = 10, width: int = 480, height: int = 160
) -> dict[str, Any] | None:
    """Bars of a histogram of ``values`` in an SVG box of ``width`` x ``height`` (y grows
    down; 20 px margin below for the axis labels). None without values."""
    if not values:
        return None
    lo, hi = min(values), max(values)
    if hi - lo < 1e-9:
        lo, hi = lo - 0.5, hi + 0.5
    step = (hi - lo) / bins
    counts = [0] * bins
    for v in values:
        counts[min(bins - 1, int((v - lo) / step))] += 1
    plot_h, bar_w = height - 20, width / bins
    top = max(counts)
    bars = []
    for i, n in enumerate(counts):
        h = plot_h * n / top
        bars.append({
            "x": round(i * bar_w + 1, 1), "y": round(plot_h - h, 1),
            "w": round(bar_w - 2, 1), "h": round(h, 1), "count": n,
            "lo": round(lo + i * step, 2), "hi": round(lo + (i + 1) * step, 2),
        })  # fmt: skip
    return {
        "width": width, "height": height, "axis_y": plot_h, "bars": bars, "n": len(values),
        "lo": round(lo, 2), "hi": round(hi, 2), "max_count": top,
        "median": round(sorted(values)[len(values) // 2], 2),
    }  # fmt: skip


def preview_index(job: Job | None, cameras: list[str]) -> int | None:
    """The preview of a variant: its first camera's middle frame (None before SUCCEEDED)."""
    if job is None or job.state.value != "SUCCEEDED" or not job.previews:
        return None
    groups = view.preview_groups([str(k) for k in job.previews], cameras)
    for g in groups["cameras"]:
        frames = g["frames"]
        if frames:
            index: int = frames[len(frames) // 2]["index"]
            return index
    return None


def variant_row(v: Any, job: Job | None, cameras: list[str]) -> dict[str, Any]:
    """One variant as the campaign page lists it."""
    objects = []
    for o in (v.variant or {}).get("objects") or []:
        r = o.get("resolved") or {}
        s, off = r.get("s_job_m"), r.get("offset_m")
        where = f"s {s:.1f} m, offset {off:+.2f} m" if s is not None and off is not None else "-"
        objects.append(f"{o.get('class_name')} ({r.get('zone') or 'explicit'}, {where})")
    row = v.row or {}
    gauge = row.get("gauge") or {}
    q = (row.get("quality") or {}).get(cameras[0] if cameras else "", {}) or {}
    return {
        "id": v.variant_id,
        "sequence": v.sequence_label,
        "objects": "; ".join(objects),
        "job": None if job is None else view.job_status(job),
        "job_id": v.job_id,
        "preview": preview_index(job, cameras),
        "intrudes": gauge.get("intrudes"),
        "rpe": q.get("rpe_px_mean"),
        "bound": q.get("bound_px_median"),
    }


__all__ = ["MEASURES", "histogram", "preview_index", "quality_values", "variant_row"]
