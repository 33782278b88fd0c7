"""Redis restarted mid-job (no persistence: every queued and unacked message is lost).

Prefork worker, PostgreSQL, the API on uvicorn. Jobs are submitted; when the first is
RUNNING, Redis is shut down (``redis-cli shutdown nosave``), a job is submitted while it
is down (the API keeps it PENDING), and Redis is started again (the machine's own command)
after ``outage`` seconds. The worker reconnects; the reaper (every worker runs it) sees
Redis's ``run_id`` changed and re-queues the active jobs handed to the broker before the
new Redis started that no live lease holds (worker/orchestration/reaper.py), and sends
the PENDING one. Figures: jobs lost (not SUCCEEDED in the end), re-queued by the reaper
and by which rule, archives per job in the store (exactly one: the published key), API
5xx, time from Redis back to every job done, attempts.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from osdar_platform.store import store_from_url
from scripts.reliability import common as c

NAME = "redis_restart"


def run(workdir: Path, *, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    n_jobs, outage = (2, 3.0) if quick else (6, 10.0)
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel")
    if not c.redis_up():
        raise c.Unavailable("Redis is not running")
    with c.pg_database() as db, c.redis_db() as broker:
        settings = c.reliability_settings(workdir / "var", database_url=db, broker_url=broker)
        secret = c.new_api_key(settings)
        workers = c.Workers(settings, workdir / "worker.log", concurrency=1)
        five_xx = 0
        try:
            with c.ApiServer(settings) as api, api.client(secret) as http, workers:
                sid = http.post("/v1/sequences", json={"path": str(seq)}).json()["id"]
                ids = [
                    http.post("/v1/jobs", json=c.job_spec(sid)).json()["id"] for _ in range(n_jobs)
                ]
                c.wait_for(
                    lambda: any(
                        r.state.value == "RUNNING" and r.stage not in (None, "starting")
                        for r in c.job_rows(settings, ids).values()
                    ),
                    120,
                    "a job mid-run",
                )
                stages = {
                    r.id[:8]: f"{r.state.value}/{r.stage}"
                    for r in c.job_rows(settings, ids).values()
                }
                c.log(f"stopping Redis; jobs {stages}")
                c.redis_stop()
                t_down = time.monotonic()
                r = http.post("/v1/jobs", json=c.job_spec(sid))
                five_xx += r.status_code >= 500
                during = r.json().get("state") if r.status_code < 300 else f"HTTP {r.status_code}"
                if r.status_code < 300:
                    ids.append(r.json()["id"])
                for jid in ids:
                    five_xx += http.get(f"/v1/jobs/{jid}").status_code >= 500
                time.sleep(max(0.0, outage - (time.monotonic() - t_down)))
                c.redis_start()
                t_up = time.monotonic()
                c.log("Redis is back")
                rows = c.wait_terminal(settings, ids, 300)
                recovered_s = time.monotonic() - t_up
                for jid in ids:
                    five_xx += http.get(f"/v1/jobs/{jid}").status_code >= 500
                events = {jid: c.job_events(settings, jid) for jid in ids}
                store = store_from_url(str(settings.store_url), settings)
                archives = {jid: c.archive_keys(store, jid) for jid in ids}
        finally:
            c.redis_start()  # whatever happened, leave the machine's Redis running
    lost = [jid for jid, row in rows.items() if row.state.value != "SUCCEEDED"]
    return {
        "jobs": len(ids),
        "outage_s": outage,
        "stages_when_stopped": stages,
        "job_submitted_during_outage": during,
        "jobs_lost": len(lost),
        "lost": {jid[:8]: f"{rows[jid].state.value}: {rows[jid].error}" for jid in lost},
        "requeued_by_reaper": sum(1 for ev in events.values() for e in ev if e.kind == "requeued"),
        "requeued_by_rule": _rules(events),
        "jobs_with_exactly_one_archive": sum(
            1 for jid in ids if archives[jid] == [rows[jid].result_key]
        ),
        "extra_archives": sum(max(0, len(a) - 1) for a in archives.values()),
        "pending_enqueue_failed": sum(
            1 for ev in events.values() for e in ev if e.kind == "enqueue_failed"
        ),
        "attempts": {jid[:8]: rows[jid].attempt for jid in ids},
        "all_done_after_redis_back_s": round(recovered_s, 1),
        "api_5xx": five_xx,
    }


def _rules(events: dict[str, list[Any]]) -> dict[str, int]:
    """Re-queues per reaper rule (the first words of its reason)."""
    out: dict[str, int] = {}
    for ev in events.values():
        for e in ev:
            if e.kind == "requeued":
                rule = (e.message or "").split(" (")[0].split(":")[0]
                out[rule] = out.get(rule, 0) + 1
    return out


def ok(f: dict[str, Any]) -> bool:
    return (
        f["jobs_lost"] == 0
        and f["api_5xx"] == 0
        and f["jobs_with_exactly_one_archive"] == f["jobs"]
    )


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
