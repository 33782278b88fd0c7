"""Results that are the same for every job on one prepared sequence, computed once.

A job's evaluation (RPE / jitter of the chosen strategy's poses, the paper's RPE of the
strategies, the true errors on synthetic data: :func:`worker.evaluation.evaluate.
evaluate_sequence`) depends on the input sequence, its preparation and the cameras, never
on the objects placed: every variant of a campaign on one sequence computed it again, the
largest fixed cost of a short variant (0.5-1 s of 2-3 s on 8 frames,
scripts/bench_campaign_throughput.py). The RPE plot of the report is a function of that
evaluation's series. Both are kept under ``<cache_dir>/shared/`` beside the prepared
cache, keyed by the preparation's key (which covers the sequence's content, the
preparation's config and clicks, and its revision), the cameras and
:data:`EVALUATION_REVISION`; a file appears only by an atomic rename, so concurrent jobs at
worst compute the same result twice.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import uuid
from pathlib import Path
from typing import Any

from worker.evaluation.evaluate import evaluate_sequence, plot_rpe_jitter
from worker.osdar.errors import atomic_write_bytes
from worker.preparation.artifact import PreparedSequence

log = logging.getLogger(__name__)

#: Bump when evaluate_sequence's or plot_rpe_jitter's output changes: results of older
#: code are then not read.
EVALUATION_REVISION = 1


def _digest(value: Any) -> str:
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def shared_dir(cache_dir: str | Path) -> Path:
    return Path(cache_dir) / "shared"


def sequence_evaluation(
    seq_folder: str | Path,
    prepared: PreparedSequence,
    cameras: list[str],
    *,
    cache_dir: str | Path,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """:func:`evaluate_sequence` of (sequence, preparation, cameras), from the cache when
    a job on the same ones computed it (module docstring). Returns (metrics, series)."""
    key = _digest({"prepared": prepared.key, "cameras": cameras, "rev": EVALUATION_REVISION})
    path = shared_dir(cache_dir) / f"evaluation-{key}.json"
    if path.is_file():
        try:
            cached = json.loads(path.read_text())
            return dict(cached["metrics"]), dict(cached["series"])
        except (OSError, ValueError, KeyError, TypeError) as exc:  # torn or foreign: redo
            log.warning("cached evaluation %s unreadable (%s): computed again", path, exc)
    metrics, series = evaluate_sequence(seq_folder, prepared, cameras)
    # the JSON round trip a reader gets (the job's metrics are JSON in the database anyway)
    data = json.dumps({"metrics": metrics, "series": series})
    atomic_write_bytes(path, data.encode())
    out = json.loads(data)
    return dict(out["metrics"]), dict(out["series"])


def rpe_plot(series: dict[str, Any], out_png: str | Path, title: str, *,
             cache_dir: str | Path) -> Path | None:  # fmt: skip
    """:func:`plot_rpe_jitter` at ``out_png``, the plot copied from the cache when the same
    series and title were plotted before (None when there is nothing to plot)."""
    if not series:
        return None
    key = _digest({"series": series, "title": title, "rev": EVALUATION_REVISION})
    cached = shared_dir(cache_dir) / f"rpe-{key}.png"
    out = Path(out_png)
    if not cached.is_file():
        cached.parent.mkdir(parents=True, exist_ok=True)
        tmp = cached.with_name(f"{cached.stem}.{os.getpid()}.{uuid.uuid4().hex}.png")
        try:
            if plot_rpe_jitter(series, tmp, title) is None:
                return None
            tmp.replace(cached)
        finally:
            tmp.unlink(missing_ok=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, cached.read_bytes())
    return out


__all__ = ["EVALUATION_REVISION", "rpe_plot", "sequence_evaluation", "shared_dir"]
