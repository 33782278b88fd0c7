"""Celery tasks: thin wrappers over the plain functions of ``worker/orchestration/runner.py``.

Tasks get ids (job id, attempt), never objects. ``osdar_ar.run_job`` is what the API
sends (task id = job id); it starts an attempt and launches the job's stages::

    fetch -> prepare -> group(augment_chunk x N)
    the chunk that completes the last one: finish -> evaluate -> package -> publish

The chunks are joined in our database, not by a Celery chord (whose end the database
result backend finds by polling once a second): each chunk records its result on the
job's row, and the one chunk task that claims the finish token sends ``finish`` and the
stages after it (``chunk_join.py``; the reaper sends ``finish`` again if that send was
lost). No task stores a Celery result.

A stage that stops the job (cancelled, failed, superseded by a newer attempt) raises
``Ignore``: the message is acknowledged and the rest of the workflow is not sent. The job
row already says why. A stage that could not reach the database is rejected with
``requeue``: its message goes back to the broker and the stage runs again (``run_job``
holds a lease while it sends the workflow).

Campaigns (worker/campaign/service_expand.py, service_finalize.py): ``osdar_ar.
campaign_expand`` prepares a campaign's sequences, expands it and makes its variant jobs;
after a campaign job's publish, failure or cancel, its campaign is finalized when every
variant is finished (``osdar_ar.campaign_finalize`` does the same when the API asks).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, NoReturn, ParamSpec, TypeVar

from celery import Task, chain, group, shared_task
from celery.exceptions import Ignore, Reject

from osdar_platform.settings import get_settings
from worker.campaign.service_expand import expand_campaign_stage
from worker.campaign.service_finalize import finalize_after_job, finalize_campaign
from worker.orchestration import chunk_join, lease, runner, state
from worker.orchestration.lease import database_unreachable
from worker.orchestration.queue import (
    TASK_AUGMENT_CHUNK,
    TASK_EVALUATE,
    TASK_EXPAND_CAMPAIGN,
    TASK_FETCH,
    TASK_FINALIZE_CAMPAIGN,
    TASK_FINISH,
    TASK_PACKAGE,
    TASK_PREPARE,
    TASK_PUBLISH,
    TASK_RUN_JOB,
)
from worker.orchestration.state import JobCancelled, JobFailed, JobStop

log = logging.getLogger(__name__)

TASK_NAMES = (
    TASK_RUN_JOB,
    TASK_FETCH,
    TASK_PREPARE,
    TASK_AUGMENT_CHUNK,
    TASK_FINISH,
    TASK_EVALUATE,
    TASK_PACKAGE,
    TASK_PUBLISH,
    TASK_EXPAND_CAMPAIGN,
    TASK_FINALIZE_CAMPAIGN,
)


_P = ParamSpec("_P")
_R = TypeVar("_R")


class JobTask(Task[Any, Any]):
    """Every job task: acknowledged late, put back when its worker process dies."""

    acks_late = True
    reject_on_worker_lost = True
    ignore_result = True


def _give_back(exc: BaseException) -> NoReturn:
    """The database is unreachable: put the message back (it runs again, on this or
    another worker) after ``lease_renew_s``, so a long outage is no busy loop."""
    delay = get_settings().lease_renew_s
    log.warning("database unreachable, message back to the broker in %.0fs: %s", delay, exc)
    time.sleep(delay)
    raise Reject(str(exc)[:500], requeue=True) from exc


def _stage(fn: Callable[_P, _R], *args: _P.args, **kwargs: _P.kwargs) -> _R:
    try:
        return fn(*args, **kwargs)
    except JobStop as stop:
        log.info("%s stopped the job: %s", getattr(fn, "__name__", fn), stop)
        if isinstance(stop, (JobFailed, JobCancelled)) and args:
            _after_job(str(args[0]))
        raise Ignore() from stop
    except Exception as exc:
        if database_unreachable(exc):
            _give_back(exc)
        raise


def _after_job(job_id: str) -> None:
    """A job ended: finalize its campaign if it was the last variant (best effort; the
    API asks again when it sees every variant finished)."""
    try:
        finalize_after_job(job_id, settings=get_settings())
    except Exception:
        log.exception("job %s: finalizing its campaign failed (the API will ask again)", job_id)


def workflow(app: Any, job_id: str, attempt: int, chunks: list[list[int]]) -> Any:
    """The stages of one attempt up to its chunks, as a Celery canvas: the chunks (every
    job has at least one) are sent together when ``prepare`` completes; the rest comes
    from the chunk that completes the last one (module docstring)."""

    def step(name: str, *args: Any) -> Any:
        return app.signature(name, args=args, immutable=True)

    parts = [step(TASK_AUGMENT_CHUNK, job_id, attempt, i, f) for i, f in enumerate(chunks)]
    last = parts[0] if len(parts) == 1 else group(parts)
    return chain(step(TASK_FETCH, job_id, attempt), step(TASK_PREPARE, job_id, attempt), last)


@shared_task(name=TASK_RUN_JOB, bind=True, base=JobTask)
def run_job(self: Task[Any, Any], job_id: str) -> None:
    """Start an attempt (poison jobs are FAILED here) and launch its stages."""
    attempt = _stage(runner.start_job, job_id)
    settings = get_settings()
    try:
        with lease.held(job_id, attempt, "run_job", settings=settings):
            chunks = runner.plan_chunks(job_id, attempt=attempt)
            workflow(self.app, job_id, attempt, chunks).apply_async()
    except Exception as exc:
        if database_unreachable(exc):
            _give_back(exc)  # delivered again: a new attempt starts
        state.mark_failed(
            job_id, f"start: could not schedule the stages ({exc})", attempt=attempt,
            settings=get_settings(),
        )  # fmt: skip
        _after_job(job_id)
        raise Ignore() from exc


@shared_task(name=TASK_FETCH, base=JobTask)
def fetch(job_id: str, attempt: int) -> str:
    return str(_stage(runner.fetch_sequence, job_id, attempt=attempt))


@shared_task(name=TASK_PREPARE, base=JobTask)
def prepare(job_id: str, attempt: int) -> str:
    return str(_stage(runner.prepare_for_job, job_id, attempt=attempt).key)


@shared_task(name=TASK_AUGMENT_CHUNK, bind=True, base=JobTask)
def augment_chunk(
    self: Task[Any, Any], job_id: str, attempt: int, index: int, frames: list[int]
) -> None:
    """One chunk, recorded done; the chunk that completes the last one sends ``finish``."""
    _stage(runner.augment_chunk, job_id, index, frames, attempt=attempt)
    token = _stage(chunk_join.claim_finish, job_id, attempt, settings=get_settings())
    if token is not None:
        chunk_join.send_finish(self.app, job_id, attempt, token)


@shared_task(name=TASK_FINISH, base=JobTask)
def finish(job_id: str, attempt: int, token: str) -> dict[str, Any]:
    """After every chunk (the message of the chunk that claimed ``token``)."""
    return _stage(runner.finish_job, job_id, token=token, attempt=attempt)


@shared_task(name=TASK_EVALUATE, base=JobTask)
def evaluate(job_id: str, attempt: int) -> None:
    _stage(runner.evaluate_job, job_id, attempt=attempt)


@shared_task(name=TASK_PACKAGE, base=JobTask)
def package(job_id: str, attempt: int) -> str:
    return str(_stage(runner.package_job, job_id, attempt=attempt))


@shared_task(name=TASK_PUBLISH, base=JobTask)
def publish(archive: str | None, job_id: str, attempt: int) -> str | None:
    key = _stage(runner.publish_job, job_id, archive, attempt=attempt)
    _after_job(job_id)
    return key


@shared_task(name=TASK_EXPAND_CAMPAIGN, base=JobTask)
def campaign_expand(campaign_id: str) -> None:
    """Prepare, expand and make the variant jobs of a campaign (service_expand.py)."""
    expand_campaign_stage(campaign_id, settings=get_settings())


@shared_task(name=TASK_FINALIZE_CAMPAIGN, base=JobTask)
def campaign_finalize(campaign_id: str) -> None:
    """The manifest and the final state once every variant is finished."""
    finalize_campaign(campaign_id, settings=get_settings())


__all__ = ["TASK_NAMES", "campaign_expand", "campaign_finalize", "run_job", "workflow"]
