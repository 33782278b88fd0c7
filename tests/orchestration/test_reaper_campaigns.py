"""The reaper and campaigns (worker/orchestration/reaper.py): a variant whose worker died
is re-queued like any job and made once; a campaign whose last variant ended without
finalizing it (re-run outside a task, or FAILED by the reaper as poison) is finalized by
the next sweep, with nobody reading it.

The real path: the API on SQLite records the campaign, the worker's expansion stage makes
the variant jobs, the jobs' real stages run in this process; a worker's death is its
stage's lease left to expire.
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import select, update

from osdar_platform.db import session_scope
from osdar_platform.models import CampaignState, Job, JobEvent, JobLease, JobState, utcnow
from tests.conftest_service import Api, memory_celery, sent_tasks, sqlite_api
from worker.campaign.service_expand import expand_campaign_stage
from worker.campaign.service_finalize import finalize_campaign
from worker.orchestration import lease, runner
from worker.orchestration.queue import TASK_FINALIZE_CAMPAIGN, TASK_RUN_JOB
from worker.orchestration.reaper import reap

pytestmark = pytest.mark.gl

SEQ = {"scene": "fire_site", "frames": 4, "scale": 0.1, "lidar_density": 0.15, "seed": 4}


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Api]:
    with sqlite_api(tmp_path_factory.mktemp("reaper_campaigns"), SEQ, "fire_reap") as a:
        yield a


def _campaign(api: Api, name: str, obstacles: list[str]) -> tuple[str, list[str]]:
    """A campaign of one explicit placement per obstacle, expanded: (id, its job ids)."""
    body: dict[str, Any] = {
        "name": name,
        "sequences": [{"id": api.sequence_id, "frame_range": [0, 1]}],
        "obstacles": [{"builtin": b} for b in obstacles],
        "placements": [{"explicit": {"mode": "track", "s": 7.0, "yaw_deg": 90}}],
        "job": {"cameras": ["rgb_center"], "strategy": "ins"},
    }
    r = api.client.post("/v1/campaigns", json=body, headers=api.h())
    assert r.status_code in (201, 202), r.text
    campaign_id = r.json()["id"]
    expand_campaign_stage(campaign_id, settings=api.settings, app=memory_celery())
    with session_scope(api.settings) as s:
        ids = s.scalars(select(Job.id).where(Job.campaign_id == campaign_id).order_by(Job.id))
        return campaign_id, list(ids)


def _worker_dies_in_a_chunk(api: Api, job_id: str) -> None:
    """Attempt 1 runs fetch and prepare, then its chunk's worker dies: the chunk's lease
    stops being renewed and expires."""
    attempt = runner.start_job(job_id, settings=api.settings)
    runner.fetch_sequence(job_id, attempt=attempt, settings=api.settings)
    runner.prepare_for_job(job_id, attempt=attempt, settings=api.settings)
    lease.take(job_id, attempt, "augment[0]", settings=api.settings)
    at = utcnow() - timedelta(seconds=1)
    ttl = timedelta(seconds=api.settings.lease_ttl_s)
    with session_scope(api.settings) as s:
        s.execute(update(JobLease).where(JobLease.job_id == job_id)
                  .values(taken_at=at - ttl, renewed_at=at - ttl, expires_at=at))  # fmt: skip


def _state(api: Api, campaign_id: str) -> str:
    r = api.client.get(f"/v1/campaigns/{campaign_id}", headers=api.h("bob"))
    assert r.status_code == 404  # another key's: no API read of alice's campaign here
    from osdar_platform.models import Campaign

    with session_scope(api.settings) as s:
        row = s.get(Campaign, campaign_id)
        assert row is not None
        return str(row.state.value)


def _finalize_sent(api: Api, campaign_id: str) -> bool:
    tasks = sent_tasks()
    finalize = [t for t in tasks if t["task"] == TASK_FINALIZE_CAMPAIGN]
    assert all(t["args"] == [campaign_id] for t in finalize), tasks
    return bool(finalize)


def test_a_requeued_variant_is_made_once_and_the_sweep_finalizes(api: Api) -> None:
    campaign_id, (dead, other) = _campaign(api, "reaped", ["person", "rock"])
    sent_tasks()
    _worker_dies_in_a_chunk(api, dead)
    app = memory_celery()

    report = reap(api.settings, app)
    assert report.requeued == [dead] and report.campaigns_nudged == []  # `other` is PENDING
    assert [t["task"] for t in sent_tasks()] == [TASK_RUN_JOB]
    # the re-sent message runs the job again: a new attempt, one result
    for job_id in (dead, other):
        assert runner.run_job_inline(job_id, settings=api.settings) == JobState.SUCCEEDED
    with session_scope(api.settings) as s:
        job = s.get(Job, dead)
        assert job is not None and job.attempt == 2 and job.result_key is not None
        assert "attempt-2/" in job.result_key
        kinds = [e.kind for e in s.scalars(select(JobEvent).where(JobEvent.job_id == dead))]
    assert kinds.count("requeued") == 1 and kinds.count("succeeded") == 1, kinds
    # run outside the tasks, nothing finalized the campaign: the next sweep does
    assert _state(api, campaign_id) == "RUNNING"
    report = reap(api.settings, app)
    assert report.campaigns_nudged == [campaign_id] and _finalize_sent(api, campaign_id)
    assert reap(api.settings, app).campaigns_nudged == []  # claimed: not sent twice
    assert finalize_campaign(campaign_id, settings=api.settings) == CampaignState.SUCCEEDED
    assert reap(api.settings, app).campaigns_nudged == [] and not _finalize_sent(api, campaign_id)


def test_a_variant_failed_by_the_reaper_ends_its_campaign(api: Api) -> None:
    campaign_id, (poison,) = _campaign(api, "poisoned", ["cow"])
    sent_tasks()
    _worker_dies_in_a_chunk(api, poison)
    with session_scope(api.settings) as s:
        s.execute(update(Job).where(Job.id == poison)
                  .values(deliveries=api.settings.max_deliveries))  # fmt: skip

    report = reap(api.settings, memory_celery())
    assert report.failed == [poison] and report.campaigns_nudged == [campaign_id]
    assert _finalize_sent(api, campaign_id)
    assert finalize_campaign(campaign_id, settings=api.settings) == CampaignState.FAILED
    from osdar_platform.models import CampaignVariant

    with session_scope(api.settings) as s:
        (row,) = s.scalars(select(CampaignVariant.row).where(
            CampaignVariant.campaign_id == campaign_id))  # fmt: skip
    assert row["state"] == "failed" and "poison" in row["error"], row
