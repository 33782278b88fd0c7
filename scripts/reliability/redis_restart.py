"""Redis restarted mid-job (no persistence: every queued and unacked message is lost).

Prefork worker, PostgreSQL, the API on uvicorn. Jobs are submitted; when the first is
RUNNING, Redis is shut down (``redis-cli shutdown nosave``), a job is submitted while it
is down (the API keeps it PENDING), and Redis is started again (the machine's own command)
after ``outage`` seconds. The worker reconnects; the reaper (every worker runs it) finds
the active jobs no broker message names and re-queues them, and sends the PENDING one.
Figures: jobs lost (not SUCCEEDED in the end), re-queued by the reaper, API 5xx, time
from Redis back to every job done, attempts.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

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
        "pending_enqueue_failed": sum(
            1 for ev in events.values() for e in ev if e.kind == "enqueue_failed"
        ),
        "attempts": {jid[:8]: rows[jid].attempt for jid in ids},
        "all_done_after_redis_back_s": round(recovered_s, 1),
        "api_5xx": five_xx,
    }


def ok(f: dict[str, Any]) -> bool:
    return f["jobs_lost"] == 0 and f["api_5xx"] == 0


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
