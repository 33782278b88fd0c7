"""SIGKILL workers at random points of jobs: 0 jobs lost, one archive per job.

A prefork worker (concurrency 1) on Redis + PostgreSQL runs one job at a time; each job
is killed once at a uniformly random moment of its run (measured on a clean job first):
- "child": SIGKILL of the pool process running the task; the parent sees the loss,
  ``task_reject_on_worker_lost`` puts the message back and it runs again at once;
- "worker": SIGKILL of the whole worker (parent and children, like an OOM-killed
  container); a new worker starts; the reaper re-queues the job when the killed stage's
  lease expires (10 s here: a new attempt), or, when the kill hit no leased stage, the
  unacknowledged message comes back after the visibility timeout (short here: 22 s).
A client polls every job's archive and state throughout (premature archives: 0), and
busy-looping processes load the machine (one in the reduced form, one per core in full).
Figures: jobs lost (not SUCCEEDED), archives per job in the store (exactly 1, the
published key), attempts and deliveries recorded, the stage each kill hit, recovery time.
"""

from __future__ import annotations

import random
import time
from collections import Counter
from pathlib import Path
from typing import Any

from osdar_platform.store import store_from_url
from scripts.reliability import common as c

NAME = "kill_workers"


def _figures(
    records: list[dict[str, Any]],
    n: int,
    missed: Any,
    duration: float,
    deaths: Any,
    poller_figures: dict[str, Any],
) -> dict[str, Any]:
    """The scenario's figures from the kills' records."""
    lost = [r for r in records if r["state"] != "SUCCEEDED"]
    return {
        "kills": len(records),
        "kills_asked": n,
        "kill_times_after_the_job_ended_redrawn": missed,
        "kills_by_kind": dict(Counter(r["kill"] for r in records)),
        "kills_by_stage": dict(Counter(str(r["stage_hit"]) for r in records)),
        "job_run_s": round(duration, 1),
        "jobs_lost": len(lost),
        "jobs_with_exactly_one_archive": sum(r["one_archive"] for r in records),
        "attempts_total": sum(r["attempts"] for r in records),
        "attempts_max": max((r["attempts"] for r in records), default=0),
        "deliveries_max": max((r["deliveries"] for r in records), default=0),
        "recovery_s_max": max((r["recovery_s"] for r in records), default=0),
        "worker_process_deaths_logged": deaths,
        **poller_figures,
        "lost": [{k: r[k] for k in ("job", "kill", "stage_hit", "state", "error")} for r in lost],
        "records": records,
    }


def run(
    workdir: Path, *, quick: bool = False, seed: int = 0, kills: int | None = None
) -> dict[str, Any]:

    n = kills or (3 if quick else 20)
    rng = random.Random(seed)
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel")
    with c.pg_database() as db, c.redis_db() as broker:
        settings = c.reliability_settings(
            workdir / "var",
            database_url=db,
            broker_url=broker,
            task_time_limit_s=20,
            task_soft_time_limit_s=15,
            visibility_margin_s=2,
            visibility_timeout_s=22,
        )
        secret = c.new_api_key(settings)
        workers = c.Workers(settings, workdir / "worker.log", concurrency=1)
        store = store_from_url(str(settings.store_url), settings)
        records: list[dict[str, Any]] = []
        with (
            c.ApiServer(settings) as api,
            api.client(secret) as http,
            api.client(secret) as http2,
            c.ResultPoller(http2) as poller,
            workers,
        ):
            sid = http.post("/v1/sequences", json={"path": str(seq)}).json()["id"]
            # two clean jobs (the first prepares the sequence, later ones reuse that):
            # how long a job runs here, from its start to its end
            for _ in range(2):
                clean = http.post("/v1/jobs", json=c.job_spec(sid)).json()["id"]
                row = c.wait_terminal(settings, [clean], 180)[clean]
                if row.state.value != "SUCCEEDED":
                    raise RuntimeError(f"a clean job did not succeed: {row.error}")
            duration = (row.finished_at - row.started_at).total_seconds()
            c.log(f"clean job: {duration:.1f}s")
            missed, i = 0, 0
            while len(records) < n and missed < 2 * n:
                kind = "worker" if (i % 4 == 3 or (quick and i == n - 1)) else "child"
                jid = http.post("/v1/jobs", json=c.job_spec(sid)).json()["id"]
                poller.watched.append(jid)
                c.wait_for(
                    lambda jid=jid: c.job_rows(settings, [jid])[jid].state.value != "QUEUED",
                    60,
                    "the job to start",
                )
                time.sleep(rng.uniform(0.0, 0.9 * duration))
                at = c.job_rows(settings, [jid])[jid]
                if at.state.value != "RUNNING":  # finished before the kill: not a kill of a job
                    missed += 1
                    continue
                stage = at.stage
                t_kill = time.monotonic()
                if kind == "child":
                    pid = workers.kill_child(rng)
                else:
                    pid = workers.kill_worker()
                    workers.start()
                row = c.wait_terminal(settings, [jid], 240)[jid]
                rec = {
                    "job": jid[:8],
                    "kill": kind,
                    "pid": pid,
                    "stage_hit": stage,
                    "state": row.state.value,
                    "attempts": row.attempt,
                    "deliveries": row.deliveries,
                    "error": row.error,
                    "recovery_s": round(time.monotonic() - t_kill, 1),
                    "archives": c.archive_keys(store, jid),
                    "result_key": row.result_key,
                    "stage_deliveries": sum(
                        1 for e in c.job_events(settings, jid) if e.kind == "stage_delivered"
                    ),
                }
                rec["one_archive"] = (
                    rec["archives"] == [row.result_key] if row.result_key else False
                )
                records.append(rec)
                i += 1
                c.log(
                    f"kill {i}/{n}: {kind} in {stage!r} -> {rec['state']} "
                    f"attempts={row.attempt} deliveries={row.deliveries} "
                    f"stage deliveries={rec['stage_deliveries']} "
                    f"archives={len(rec['archives'])} in {rec['recovery_s']}s"
                )
            deaths = workers.deaths()
    return _figures(records, n, missed, duration, deaths, poller.figures())


def ok(f: dict[str, Any]) -> bool:
    return (
        f["jobs_lost"] == 0
        and f["kills"] == f["kills_asked"]
        and f["jobs_with_exactly_one_archive"] == f["kills"]
        and f["api_archive_before_success"] == 0
    )


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
