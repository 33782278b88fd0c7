"""What an operator key sees on the dashboard besides everyone's jobs and campaigns: the
workers alive, the queue depth and the failure rate (read from the database and the
broker, never from the pipeline)."""

from __future__ import annotations

from collections.abc import Callable
from datetime import timedelta
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from osdar_platform.models import Job, JobState, utcnow

#: The window of the failure rate.
WINDOW_H = 24


def overview(session: Session, broker: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """Jobs waiting and running (every key), the failure rate of the jobs finished in the
    last :data:`WINDOW_H` hours, FAILED / (SUCCEEDED + FAILED) (cancelled ones are no
    failure), and the broker's view (:func:`worker.orchestration.queue.broker_overview`)."""
    by_state = dict(
        session.execute(select(Job.state, func.count()).group_by(Job.state)).tuples().all()
    )
    since = utcnow() - timedelta(hours=WINDOW_H)
    recent = dict(
        session.execute(
            select(Job.state, func.count()).where(Job.finished_at >= since).group_by(Job.state)
        )
        .tuples()
        .all()
    )
    ok, failed = recent.get(JobState.SUCCEEDED, 0), recent.get(JobState.FAILED, 0)
    b = broker()
    workers = b.get("workers")
    return {
        "waiting": by_state.get(JobState.PENDING, 0) + by_state.get(JobState.QUEUED, 0),
        "running": by_state.get(JobState.RUNNING, 0),
        "queue_messages": b.get("queue_messages"),
        "workers": workers,
        "workers_alive": None if workers is None else len(workers),
        "broker_error": b.get("error"),
        "window_h": WINDOW_H,
        "finished": ok + failed + recent.get(JobState.CANCELLED, 0),
        "failed": failed,
        "failure_rate": round(failed / (ok + failed), 4) if ok + failed else None,
    }


__all__ = ["WINDOW_H", "overview"]
