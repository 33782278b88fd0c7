"""The object store unreachable for a while during publish: 0 lost jobs, no partial archive.

The store is S3 on moto's server (loopback, in this process); workers are prefork on
Redis + PostgreSQL. For each job, the S3 server is stopped when the job reaches its
``package`` or ``publish`` stage and started again ``outage`` seconds later. The
worker's store calls retry with exponential backoff (osdar_platform/retry.py; every retry
is a ``store_retry`` job event). Meanwhile a watcher reads the API and, whenever S3 is
up, every archive object in the bucket, and checks each is a complete tar.gz; busy-looping
processes load the machine (one in the reduced form, one per core in full).
Figures: jobs lost, retries and their delays, archives per job, partial archives seen.
"""

from __future__ import annotations

import contextlib
import io
import logging
import tarfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
from moto.server import ThreadedMotoServer

from osdar_platform.store import S3Store, store_from_url
from scripts.reliability import common as c
from worker.orchestration.embedded import free_port

NAME = "store_outage"
BUCKET = "osdar-rel"


class Moto:
    """moto's S3 server on a fixed loopback port that can be stopped and started again
    (its state lives in this process, so objects survive the outage)."""

    def __init__(self) -> None:

        self.port = free_port()
        self.server: Any = None
        self.up = threading.Event()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> None:

        logging.getLogger("werkzeug").setLevel(logging.ERROR)  # one line per request
        deadline = time.monotonic() + 20
        while True:
            try:
                self.server = ThreadedMotoServer(
                    ip_address="127.0.0.1", port=self.port, verbose=False
                )
                self.server.start()
                break
            except OSError:  # the port still closing
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        self.up.set()

    def stop(self) -> None:
        self.up.clear()
        self.server.stop()


def _complete(store: Any, key: str) -> bool:
    data = b"".join(store.open_read(key))
    try:
        with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
            for m in tar:
                if m.isfile():
                    tar.extractfile(m).read()
        return True
    except (tarfile.TarError, EOFError, OSError):
        return False


class Watcher:
    """A client reading every watched job's archive, then its state (see
    ``common.ResultPoller``), and, whenever S3 is up, every archive object in the bucket:
    counts premature archives, 5xx, transport errors, and archives that are not complete."""

    def __init__(self, http: Any, store: Any, moto: Moto) -> None:
        self.http, self.store, self.moto = http, store, moto
        self.jobs: list[str] = []
        self.seen = {
            "checked": 0,
            "partial": 0,
            "api_archive_early": 0,
            "api_5xx": 0,
            "api_transport_errors": 0,
        }
        self._stop = threading.Event()
        self._done: set[str] = set()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Watcher:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(10)

    def _run(self) -> None:
        while not self._stop.is_set():
            for jid in list(self.jobs):
                self._poll_api(jid)
            if self.moto.up.is_set():
                with contextlib.suppress(Exception):
                    self._check_store()
            self._stop.wait(0.3)

    def _poll_api(self, jid: str) -> None:
        seen = self.seen
        try:  # the archive, then the state
            a = self.http.get(f"/v1/jobs/{jid}/archive", headers={"Range": "bytes=0-1"})
            r = self.http.get(f"/v1/jobs/{jid}")
        except httpx.TransportError:  # a keep-alive connection closed by the server
            seen["api_transport_errors"] += 1
            return
        seen["api_5xx"] += r.status_code >= 500
        state = r.json().get("state") if r.status_code == 200 else None
        seen["api_5xx"] += a.status_code >= 500 and self.moto.up.is_set()
        if a.status_code in (200, 206) and state != "SUCCEEDED":
            seen["api_archive_early"] += 1

    def _check_store(self) -> None:
        for key in self.store.list("jobs/"):
            if key.endswith("archive.tar.gz") and key not in self._done:
                self.seen["checked"] += 1
                if _complete(self.store, key):
                    self._done.add(key)
                else:
                    self.seen["partial"] += 1


def _settings(workdir: Path, db: str, broker: str, moto: Moto) -> Any:
    return c.reliability_settings(
        workdir / "var",
        database_url=db,
        broker_url=broker,
        store_url=f"s3://{BUCKET}/rel",
        s3_endpoint_url=moto.url,
        aws_access_key_id="testing",
        aws_secret_access_key="testing",
        store_retries=8,
        store_retry_base_s=0.5,
        store_retry_max_s=8,
    )


def _job_through_an_outage(
    http: Any, settings: Any, store: Any, moto: Moto, sid: str, outage: float, watcher: Watcher
) -> dict[str, Any]:
    """Submit one job, stop S3 when it reaches package / publish, start it ``outage``
    seconds later, wait for the job's end: its record."""
    jid = http.post("/v1/jobs", json=c.job_spec(sid)).json()["id"]
    watcher.jobs.append(jid)

    def at_publish() -> bool:
        row = c.job_rows(settings, [jid])[jid]
        return row.stage in ("package", "publish") or row.state.value in c.TERMINAL

    c.wait_for(at_publish, 180, "the package stage", every=0.05)
    stage = c.job_rows(settings, [jid])[jid].stage
    moto.stop()
    t_down = time.monotonic()
    time.sleep(outage)
    moto.start()
    row = c.wait_terminal(settings, [jid], 240)[jid]
    retries = [e for e in c.job_events(settings, jid) if e.kind == "store_retry"]
    c.log(f"job {jid[:8]}: {row.state.value}, {len(retries)} retries")
    return {
        "job": jid[:8],
        "stage_at_outage": stage,
        "state": row.state.value,
        "error": row.error,
        "retries": len(retries),
        "delays_s": [e.data.get("delay_s") for e in retries],
        "ops": sorted({e.data.get("op") for e in retries}),
        "done_after_outage_s": round(time.monotonic() - t_down - outage, 1),
        "archives": c.archive_keys(store, jid),
        "result_key": row.result_key,
    }


def run(workdir: Path, *, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    n_jobs, outage = (2, 8.0) if quick else (5, 20.0)
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel")
    moto = Moto()
    moto.start()
    try:
        with c.pg_database() as db, c.redis_db() as broker:
            settings = _settings(workdir, db, broker, moto)
            store = store_from_url(str(settings.store_url), settings)
            assert isinstance(store, S3Store)
            store.create_bucket()
            secret = c.new_api_key(settings)
            workers = c.Workers(settings, workdir / "worker.log", concurrency=1)
            with (
                c.ApiServer(settings) as api,
                api.client(secret) as http,
                api.client(secret) as http2,
                workers,
                Watcher(http2, store, moto) as watcher,
            ):
                sid = http.post("/v1/sequences", json={"path": str(seq)}).json()["id"]
                records = [
                    _job_through_an_outage(http, settings, store, moto, sid, outage, watcher)
                    for _ in range(n_jobs)
                ]
                time.sleep(1.0)
    finally:
        with contextlib.suppress(Exception):
            moto.stop()
    return _figures(records, watcher.seen, n_jobs, outage, quick)


def _figures(
    records: list[dict[str, Any]], seen: dict[str, int], n_jobs: int, outage: float, quick: bool
) -> dict[str, Any]:
    lost = [r for r in records if r["state"] != "SUCCEEDED"]
    return {
        "jobs": n_jobs,
        "outage_s": outage,
        "jobs_lost": len(lost),
        "store_retries_total": sum(r["retries"] for r in records),
        "jobs_that_retried": sum(1 for r in records if r["retries"]),
        "max_backoff_delay_s": max((max(r["delays_s"] or [0]) for r in records), default=0),
        "jobs_with_exactly_one_archive": sum(
            1 for r in records if r["result_key"] and r["archives"] == [r["result_key"]]
        ),
        "archive_objects_checked": seen["checked"],
        "partial_archives_visible": seen["partial"],
        "api_archive_before_success": seen["api_archive_early"],
        "api_5xx": seen["api_5xx"],
        "api_transport_errors_of_the_watcher": seen["api_transport_errors"],
        "records": records,
    }


def ok(f: dict[str, Any]) -> bool:
    return (
        f["jobs_lost"] == 0
        and f["partial_archives_visible"] == 0
        and f["jobs_with_exactly_one_archive"] == f["jobs"]
        and f["jobs_that_retried"] >= 1
        and f["api_archive_before_success"] == 0
        and f["api_5xx"] == 0
    )


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
