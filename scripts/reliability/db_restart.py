"""PostgreSQL restarted while jobs run and clients poll: 0 lost, 0 duplicates, 503 not 500.

Prefork worker on Redis, the API on uvicorn, both on PostgreSQL. Jobs are submitted; when
the first is RUNNING, PostgreSQL is stopped (fast shutdown: every session is cut) for
``outage`` seconds and started again (the machine's own command), while a client polls
every job's status and archive. Workers and API reconnect; a stage that failed on the
database is redelivered or re-queued by the reaper. Figures: jobs lost (not SUCCEEDED in
the end), jobs with more than one archive, API answers by status while the database was
away (503 with Retry-After expected, never 500), time from PostgreSQL back to every job
done.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import httpx

from osdar_platform.store import store_from_url
from scripts.reliability import common as c

NAME = "db_restart"


def run(workdir: Path, *, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    n_jobs, outage = (2, 5.0) if quick else (6, 15.0)
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel")
    if not c.redis_up():
        raise c.Unavailable("Redis is not running")
    codes_down: Counter[int] = Counter()
    missing_retry_after = 0
    down = threading.Event()
    stop = threading.Event()
    with c.pg_database() as db, c.redis_db() as broker:
        settings = c.reliability_settings(workdir / "var", database_url=db, broker_url=broker)
        secret = c.new_api_key(settings)
        store = store_from_url(str(settings.store_url), settings)
        workers = c.Workers(settings, workdir / "worker.log", concurrency=1)
        ids: list[str] = []
        try:
            with (
                c.ApiServer(settings) as api,
                api.client(secret) as http,
                api.client(secret, timeout=10) as http2,
                c.ResultPoller(http2) as poller,
                workers,
            ):
                sid = http.post("/v1/sequences", json={"path": str(seq)}).json()["id"]
                ids = [
                    http.post("/v1/jobs", json=c.job_spec(sid)).json()["id"] for _ in range(n_jobs)
                ]
                poller.watched.extend(ids)

                def poll_while_down() -> None:
                    nonlocal missing_retry_after
                    with api.client(secret, timeout=10) as h:
                        while not stop.is_set():
                            if down.is_set():
                                for path in ("/v1/health", f"/v1/jobs/{ids[0]}", "/v1/jobs"):
                                    try:
                                        r = h.get(path)
                                    except httpx.TransportError:
                                        codes_down[0] += 1
                                        continue
                                    codes_down[r.status_code] += 1
                                    if r.status_code == 503 and "retry-after" not in r.headers:
                                        missing_retry_after += 1
                            stop.wait(0.2)

                prober = threading.Thread(target=poll_while_down, daemon=True)
                prober.start()
                c.wait_for(
                    lambda: any(
                        r.state.value == "RUNNING" and r.stage not in (None, "starting")
                        for r in c.job_rows(settings, ids).values()
                    ),
                    120,
                    "a job mid-run",
                )
                c.log("stopping PostgreSQL")
                c.pg_stop()
                down.set()
                time.sleep(outage)
                down.clear()
                c.pg_start()
                t_up = time.monotonic()
                c.log("PostgreSQL is back")
                rows = c.wait_terminal(settings, ids, 600)
                recovered_s = time.monotonic() - t_up
                stop.set()
                prober.join(10)
        finally:
            c.pg_start()  # whatever happened, leave the machine's PostgreSQL running
    lost = [jid for jid, row in rows.items() if row.state.value != "SUCCEEDED"]
    archives = {jid: c.archive_keys(store, jid) for jid in ids}
    return {
        "jobs": len(ids),
        "outage_s": outage,
        "jobs_lost": len(lost),
        "lost": {jid[:8]: f"{rows[jid].state.value}: {rows[jid].error}" for jid in lost},
        "jobs_with_more_than_one_archive": sum(len(a) > 1 for a in archives.values()),
        "attempts": {jid[:8]: rows[jid].attempt for jid in ids},
        "api_answers_while_down": {str(k): v for k, v in sorted(codes_down.items())},
        "api_5xx_other_than_503_while_down": sum(
            v for k, v in codes_down.items() if k >= 500 and k != 503
        ),
        "api_503_without_retry_after": missing_retry_after,
        "all_done_after_db_back_s": round(recovered_s, 1),
        **poller.figures(),
    }


def ok(f: dict[str, Any]) -> bool:
    return (
        f["jobs_lost"] == 0
        and f["jobs_with_more_than_one_archive"] == 0
        and f["api_5xx_other_than_503_while_down"] == 0
        and f["api_503_without_retry_after"] == 0
        and f["api_archive_before_success"] == 0
    )


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
