"""A poison job that kills its worker process in every delivery: FAILED, the queue drains.

The job carries the test-only hook ``crash_in`` (honoured only in environment "test"):
the pool process exits at once in that stage. Good jobs are queued behind it. Figures:
deliveries of the poisoned stage (bounded by max_deliveries + 1, the last one refused
without running), its reason, time to FAILED, the good jobs' outcome, the queue length
at the end.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from sqlalchemy import select

from osdar_platform.db import session_scope
from osdar_platform.models import ApiKey, Job, JobState
from scripts.reliability import common as c
from worker.orchestration.celery_app import QUEUE, make_celery
from worker.orchestration.queue import enqueue_job

NAME = "poison"


def run(workdir: Path, *, quick: bool = False, seed: int = 0) -> dict[str, Any]:

    stages = ["prepare"] if quick else ["run_job", "fetch", "prepare", "evaluate", "publish"]
    n_good = 1 if quick else 3
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel")
    with c.pg_database() as db, c.redis_db() as broker:
        settings = c.reliability_settings(workdir / "var", database_url=db, broker_url=broker)
        secret = c.new_api_key(settings)
        workers = c.Workers(settings, workdir / "worker.log", concurrency=1)
        out: dict[str, Any] = {}
        with c.ApiServer(settings) as api, api.client(secret) as http, workers:
            sid = http.post("/v1/sequences", json={"path": str(seq)}).json()["id"]
            spec = http.post("/v1/jobs", json=c.job_spec(sid)).json()["spec"]
            with session_scope(settings) as s:
                owner = s.scalar(select(ApiKey.id))
            poison: dict[str, str] = {}
            t0 = time.monotonic()
            for stage in stages:
                with session_scope(settings) as s:
                    job = Job(
                        owner_id=owner,
                        sequence_id=sid,
                        state=JobState.QUEUED,
                        spec={**spec, "_test": {"crash_in": stage}},
                        progress_total=4,
                    )
                    s.add(job)
                    s.flush()
                    poison[stage] = job.id
                enqueue_job(poison[stage], settings=settings, app=make_celery(settings))
            good = [http.post("/v1/jobs", json=c.job_spec(sid)).json()["id"] for _ in range(n_good)]
            rows = c.wait_terminal(settings, [*poison.values(), *good], 600)
            elapsed = time.monotonic() - t0
            for stage, jid in poison.items():
                row = rows[jid]
                delivered = [
                    e.message for e in c.job_events(settings, jid) if e.kind == "stage_delivered"
                ]
                out[stage] = {
                    "state": row.state.value,
                    "reason": row.error,
                    "deliveries": row.deliveries,
                    "attempts": row.attempt,
                    "stage_deliveries": delivered.count(stage) or row.deliveries,
                }
            queue_left = c.redis_client().llen(QUEUE)
            deaths = workers.deaths()
    return {
        "poison_jobs": len(poison),
        "poison_failed": sum(1 for v in out.values() if v["state"] == "FAILED"),
        "poison_reason_readable": all("poison" in (v["reason"] or "") for v in out.values()),
        "max_deliveries_setting": settings.max_deliveries,
        "max_stage_deliveries_seen": max(v["stage_deliveries"] for v in out.values()),
        "worker_process_deaths": deaths,
        "good_jobs": n_good,
        "good_jobs_succeeded": sum(1 for j in good if rows[j].state.value == "SUCCEEDED"),
        "queue_left": int(queue_left),
        "all_done_s": round(elapsed, 1),
        "per_stage": out,
    }


def ok(f: dict[str, Any]) -> bool:
    return (
        f["poison_failed"] == f["poison_jobs"]
        and f["poison_reason_readable"]
        and f["max_stage_deliveries_seen"] <= f["max_deliveries_setting"] + 1
        and f["good_jobs_succeeded"] == f["good_jobs"]
        and f["queue_left"] == 0
    )


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
