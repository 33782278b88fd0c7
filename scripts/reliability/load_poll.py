"""Load: many clients polling job status over HTTP while jobs run.

The API under uvicorn (PostgreSQL, Redis) and a prefork worker; jobs are submitted and
``clients`` threads (each its own HTTP connection and API key's token bucket wide open)
poll GET /v1/jobs/{id} in a loop for ``duration`` seconds. Figures: requests, p50/p90/p99/max
latency, errors (non-200 or transport), jobs finished during the run.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

from scripts.reliability import common as c

NAME = "load_poll"


def run(workdir: Path, *, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    clients, duration, n_jobs = (8, 10.0, 2) if quick else (32, 60.0, 6)
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel")
    with c.pg_database() as db, c.redis_db() as broker:
        settings = c.reliability_settings(workdir / "var", database_url=db, broker_url=broker)
        secret = c.new_api_key(settings)
        workers = c.Workers(settings, workdir / "worker.log", concurrency=1)
        with c.ApiServer(settings) as api, api.client(secret) as http, workers:
            sid = http.post("/v1/sequences", json={"path": str(seq)}).json()["id"]
            ids = [http.post("/v1/jobs", json=c.job_spec(sid)).json()["id"] for _ in range(n_jobs)]
            lat: list[float] = []
            errors: list[str] = []
            lock = threading.Lock()
            stop = time.monotonic() + duration

            def poll(k: int) -> None:
                mine, errs = [], []
                with api.client(secret, timeout=30) as own:
                    i = 0
                    while time.monotonic() < stop:
                        jid = ids[(k + i) % len(ids)]
                        i += 1
                        t0 = time.perf_counter()
                        try:
                            r = own.get(f"/v1/jobs/{jid}")
                            ok = r.status_code == 200
                            err = None if ok else f"HTTP {r.status_code}"
                        except Exception as exc:
                            err = type(exc).__name__
                        mine.append(time.perf_counter() - t0)
                        if err:
                            errs.append(err)
                with lock:
                    lat.extend(mine)
                    errors.extend(errs)

            threads = [threading.Thread(target=poll, args=(k,)) for k in range(clients)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(duration + 60)
            rows = c.job_rows(settings, ids)
            finished = sum(1 for r in rows.values() if r.state.value in c.TERMINAL)
    ms = [x * 1000 for x in lat]
    return {
        "clients": clients,
        "duration_s": duration,
        "jobs": n_jobs,
        "jobs_finished_during_load": finished,
        "requests": len(ms),
        "requests_per_s": round(len(ms) / duration, 1),
        "latency_ms_p50": round(c.percentile(ms, 50), 1),
        "latency_ms_p90": round(c.percentile(ms, 90), 1),
        "latency_ms_p99": round(c.percentile(ms, 99), 1),
        "latency_ms_max": round(max(ms, default=0), 1),
        "errors": len(errors),
        "error_kinds": sorted(set(errors))[:10],
    }


def ok(f: dict[str, Any]) -> bool:
    return f["errors"] == 0 and f["requests"] > 0


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
