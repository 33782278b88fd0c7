"""Worker liveness in the database: a lease per stage a worker process runs.

A stage of an attempt (``runner._stage``, and ``run_job`` while it sends the workflow)
runs inside :func:`held`:

- **take**: a ``job_leases`` row (job, attempt, stage, holder ``hostname:pid``,
  ``expires_at = now + lease_ttl_s``); a previous row of the same stage and attempt is
  deleted (the stage was delivered again: its previous holder is gone). The job's
  ``broker_seen_at`` is set: the stage's message was in the broker a moment ago.
- **renew**: a daemon thread of the holder moves ``expires_at`` to ``now + lease_ttl_s``
  every ``lease_renew_s`` (at most a third of the TTL, so two missed renewals are
  tolerated) and stamps ``renewed_at``. A renewal that finds its row gone (the reaper
  re-queued the job) stops renewing; the stage stops at its next checkpoint.
- **release**: the row is deleted at the end of the stage. When the stage completed (its
  next message is being handed to the broker), ``broker_seen_at`` is set to now: once no
  lease of the attempt is left the job lives in the broker until the next stage takes one.

The reaper (``reaper.py``) re-queues a RUNNING job with an expired lease of its current
attempt. Timestamps are the workers' clocks (UTC): the hosts' clocks must agree to well
within ``lease_ttl_s``.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from sqlalchemy import delete, update
from sqlalchemy.exc import DBAPIError, OperationalError

from osdar_platform.db import session_scope, updated_rows
from osdar_platform.models import Job, JobLease, utcnow
from osdar_platform.settings import Settings

log = logging.getLogger(__name__)


class LeaseUnavailable(Exception):
    """The lease could not be taken (the database is unreachable): the stage did not
    start, and its message should go back to the broker (``tasks.py``)."""


def database_unreachable(exc: BaseException) -> bool:
    """True if ``exc`` (or what caused it) is a lost or refused database connection."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, LeaseUnavailable | OperationalError):
            return True
        if isinstance(e, DBAPIError) and e.connection_invalidated:
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def holder_name() -> str:
    """This process as a lease holder: ``hostname:pid`` (prefork children differ)."""
    return f"{socket.gethostname()}:{os.getpid()}"


@dataclass(frozen=True)
class Lease:
    """A taken lease (the ids its renewals and release need)."""

    id: int
    job_id: str
    attempt: int
    stage: str
    holder: str


def take(job_id: str, attempt: int, stage: str, *, settings: Settings) -> Lease:
    """Take the lease of ``stage`` of ``attempt`` (module docstring); raises
    :class:`LeaseUnavailable` if the database cannot be reached."""
    now = utcnow()
    holder = holder_name()
    try:
        with session_scope(settings) as s:
            s.execute(
                delete(JobLease).where(
                    JobLease.job_id == job_id,
                    JobLease.attempt == attempt,
                    JobLease.stage == stage,
                )
            )
            row = JobLease(
                job_id=job_id,
                attempt=attempt,
                stage=stage[:64],
                holder=holder[:255],
                taken_at=now,
                renewed_at=now,
                expires_at=now + timedelta(seconds=settings.lease_ttl_s),
            )
            s.add(row)
            s.flush()
            lease_id = int(row.id)
            s.execute(
                update(Job)
                .where(Job.id == job_id, Job.attempt == attempt)
                .values(broker_seen_at=now, updated_at=now)
            )
    except Exception as exc:
        if database_unreachable(exc):
            raise LeaseUnavailable(f"job {job_id} stage {stage}: database unreachable") from exc
        raise
    return Lease(lease_id, job_id, attempt, stage, holder)


def _mine(lease: Lease) -> list[Any]:
    """The lease's row, by id and by what it is (SQLite reuses the id of a deleted row)."""
    return [
        JobLease.id == lease.id,
        JobLease.job_id == lease.job_id,
        JobLease.attempt == lease.attempt,
        JobLease.stage == lease.stage[:64],
        JobLease.holder == lease.holder[:255],
    ]


def renew(lease: Lease, *, settings: Settings) -> bool:
    """Move the lease's expiry ``lease_ttl_s`` ahead; False if the row is gone."""
    now = utcnow()
    with session_scope(settings) as s:
        moved = updated_rows(
            s,
            update(JobLease)
            .where(*_mine(lease))
            .values(renewed_at=now, expires_at=now + timedelta(seconds=settings.lease_ttl_s)),
        )
    return bool(moved)


def release(lease: Lease, *, settings: Settings, handed_off: bool) -> None:
    """Delete the lease; ``handed_off``: the stage completed and its successor's message
    is on its way to the broker (module docstring)."""
    now = utcnow()
    with session_scope(settings) as s:
        s.execute(delete(JobLease).where(*_mine(lease)))
        if handed_off:
            s.execute(
                update(Job)
                .where(Job.id == lease.job_id, Job.attempt == lease.attempt)
                .values(broker_seen_at=now, updated_at=now)
            )


class Heartbeat(threading.Thread):
    """Renews one lease every ``lease_renew_s`` until :meth:`stop` (or the row is gone)."""

    def __init__(self, lease: Lease, settings: Settings) -> None:
        super().__init__(name=f"lease-{lease.job_id[:8]}-{lease.stage}", daemon=True)
        self.lease = lease
        self.settings = settings
        self.renewals = 0
        self.failures = 0
        self.lost = False
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.wait(self.settings.lease_renew_s):
            try:
                if not renew(self.lease, settings=self.settings):
                    self.lost = True
                    log.warning(
                        "job %s attempt %d: lease of %s was taken away (re-queued)",
                        self.lease.job_id, self.lease.attempt, self.lease.stage,
                    )  # fmt: skip
                    return
                self.renewals += 1
            except Exception as exc:  # the database is away: try again at the next beat
                self.failures += 1
                log.warning("job %s: lease renewal failed: %s", self.lease.job_id, exc)

    def stop(self) -> None:
        self._halt.set()


@contextmanager
def held(job_id: str, attempt: int, stage: str, *, settings: Settings) -> Iterator[Lease]:
    """Hold the lease of ``stage`` while the body runs (module docstring)."""
    lease = take(job_id, attempt, stage, settings=settings)
    beat = Heartbeat(lease, settings)
    beat.start()
    completed = False
    try:
        yield lease
        completed = True
    finally:
        beat.stop()
        beat.join(settings.lease_renew_s + 5)
        try:
            release(lease, settings=settings, handed_off=completed)
        except Exception as exc:  # the row expires by itself; the reaper decides then
            log.warning("job %s: lease release failed: %s", job_id, exc)


__all__ = [
    "Heartbeat",
    "Lease",
    "LeaseUnavailable",
    "database_unreachable",
    "held",
    "holder_name",
    "release",
    "renew",
    "take",
]
