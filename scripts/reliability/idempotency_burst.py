"""N concurrent POST /v1/jobs with one Idempotency-Key over real HTTP: exactly one job.

The API runs under uvicorn on PostgreSQL; N threads (each its own HTTP connection) wait
on a barrier and submit the same spec with the same key. Figures: status codes, distinct
job ids returned, job rows with that key, messages sent to the broker, 5xx count.
"""

from __future__ import annotations

import threading
from collections import Counter
from pathlib import Path
from typing import Any

from celery import Celery
from sqlalchemy import func, select

from osdar_platform.db import session_scope
from osdar_platform.models import Job
from scripts.reliability import common as c

NAME = "idempotency_burst"


def run(
    workdir: Path, *, quick: bool = False, seed: int = 0, n: int | None = None
) -> dict[str, Any]:

    n = n or 100  # the figure asked for, in both forms (it takes seconds)
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel")
    with c.pg_database() as db:
        settings = c.reliability_settings(workdir / "var", database_url=db, broker_url="memory://")

        sent: list[str] = []
        celery = Celery("burst", broker="memory://", set_as_current=False)
        real_send = celery.send_task

        def send_task(name: str, *a: Any, **kw: Any) -> Any:
            sent.append(kw.get("task_id") or "")
            return real_send(name, *a, **kw)

        celery.send_task = send_task  # type: ignore[method-assign]
        secret = c.new_api_key(settings)
        with c.ApiServer(settings, celery_app=celery) as api, api.client(secret) as http:
            r = http.post("/v1/sequences", json={"path": str(seq)})
            r.raise_for_status()
            spec = c.job_spec(r.json()["id"])
            key = f"burst-{seed}"
            barrier = threading.Barrier(n)
            results: list[tuple[int, str | None]] = []
            lock = threading.Lock()

            def post() -> None:
                with api.client(secret, timeout=120) as own:
                    barrier.wait(60)
                    try:
                        resp = own.post("/v1/jobs", json=spec, headers={"Idempotency-Key": key})
                        out = (
                            resp.status_code,
                            resp.json().get("id") if resp.status_code < 300 else None,
                        )
                    except Exception as exc:
                        out = (-1, repr(exc))
                with lock:
                    results.append(out)

            threads = [threading.Thread(target=post) for _ in range(n)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(180)
            with session_scope(settings) as s:
                rows = s.scalar(
                    select(func.count()).select_from(Job).where(Job.idempotency_key == key)
                )
    codes = Counter(code for code, _ in results)
    return {
        "requests": n,
        "status_codes": dict(sorted(codes.items())),
        "server_errors_5xx": sum(v for k, v in codes.items() if k >= 500 or k < 0),
        "distinct_job_ids": len({i for code, i in results if code in (200, 201)}),
        "job_rows_with_key": int(rows or 0),
        "messages_sent": len(sent),
    }


def ok(f: dict[str, Any]) -> bool:
    return (
        f["server_errors_5xx"] == 0
        and f["distinct_job_ids"] == 1
        and f["job_rows_with_key"] == 1
        and f["messages_sent"] == 1
        and f["status_codes"] == {201: 1, 200: f["requests"] - 1}
    )


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
