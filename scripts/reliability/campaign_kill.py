"""SIGKILL workers during a campaign: no variant lost, none made twice, a failing variant
fails alone, and a campaign submit is idempotent.

A prefork worker (concurrency 1) on Redis + PostgreSQL runs a campaign of 2 obstacles x
``draws`` placements on a small synthetic sequence (4 variants reduced, 8 in full):
- a dry run first (``?dry_run=true``, the API waits for the worker's expansion): the
  variants to expect, with their keys; the pool process running that expansion is
  SIGKILLed while it prepares (the message comes back: ``task_reject_on_worker_lost``,
  and the expansion runs again: 2 deliveries);
- 20 concurrent submits with one Idempotency-Key: one campaign row, one expansion (on the
  cached preparation: the same variant keys as the dry run);
- pool processes SIGKILLed while the variants run, at random moments (2 kills reduced, 5
  in full; in full the last is of the whole worker, which a new worker replaces: its jobs
  come back through the leases and the reaper);
- one variant is made to fail in its ``evaluate`` stage (the job machinery's test hook,
  set on that variant's job after the expansion): it must fail alone, with its reason.
Figures: variants expected / made / as job rows / in the campaign's table (each exactly
once), variants SUCCEEDED, the failed one's reason, archives per variant job in the store
(exactly 1), the campaign's end state (PARTIAL: one failed by design), the manifest's rows
and states, the kills by stage, the submits' status codes and campaign rows.
"""

from __future__ import annotations

import random
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from sqlalchemy import func, select

from osdar_platform.db import session_scope
from osdar_platform.models import Campaign, CampaignVariant, Job
from osdar_platform.store import store_from_url
from scripts.reliability import common as c

NAME = "campaign_kill"
END = {"SUCCEEDED", "PARTIAL", "FAILED", "CANCELLED"}


def campaign_spec(sequence_id: str, draws: int) -> dict[str, Any]:
    return {
        "name": "kill",
        "seed": 5,
        "sequences": [{"id": sequence_id, "name": "fire"}],
        "obstacles": [{"builtin": "person"}, {"builtin": "rock"}],
        "placements": [{"zone": "track", "distance_m": [4, 12], "view_half_angle_deg": 40}],
        "draws": draws,
        "job": {"cameras": ["rgb_center"], "lidar": True, "strategy": "ins"},
    }


def _submit_burst(http: Any, spec: dict[str, Any], n: int) -> Counter[int]:
    codes: Counter[int] = Counter()
    lock = threading.Lock()
    barrier = threading.Barrier(n)

    def one() -> None:
        barrier.wait()
        r = http.post("/v1/campaigns", json=spec, headers={"Idempotency-Key": "kill-1"})
        with lock:
            codes[r.status_code] += 1

    threads = [threading.Thread(target=one) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    return codes


def _campaign(http: Any, cid: str) -> dict[str, Any]:
    body: dict[str, Any] = http.get(f"/v1/campaigns/{cid}", params={"variants_limit": 1000}).json()
    return body


def _running_job(settings: Any, cid: str) -> dict[str, Any] | None:
    with session_scope(settings) as s:
        job = s.scalar(select(Job).where(Job.campaign_id == cid, Job.state == "RUNNING").limit(1))
        return None if job is None else {"id": job.id, "stage": job.stage}


def _kill_child(workers: Any, rng: random.Random) -> int | None:
    """SIGKILL the pool process, then wait for the parent to fork its replacement (the
    next kill must hit a live process)."""
    pid = workers.kill_child(rng)
    c.wait_for(
        lambda: any(k != pid for p in workers.alive() for k in workers.children(p)),
        60,
        "the replacement pool process",
    )
    return pid


def _dry_run_killed(
    http: Any, settings: Any, workers: Any, spec: dict[str, Any], rng: random.Random
) -> tuple[Any, dict[str, Any] | None]:
    """The dry run, its expansion's pool process SIGKILLed while it prepares (a fresh
    preparation: seconds); returns the response and the kill (None: none landed)."""
    out: dict[str, Any] = {}

    def post() -> None:
        out["r"] = http.post("/v1/campaigns", params={"dry_run": True}, json=spec, timeout=300)

    t = threading.Thread(target=post)
    t.start()
    kill = None
    try:
        row = c.wait_for(lambda: _expanding(settings), 60, "the dry run's expansion")
        time.sleep(rng.uniform(0.0, 1.0))
        if _expanding(settings):
            kill = {
                "kill": "child",
                "stage_hit": f"expand: {row['stage']}",
                "pid": _kill_child(workers, rng),
            }
            c.log(f"kill 1: child in {kill['stage_hit']!r}")
    finally:
        t.join(300)
    return out.get("r"), kill


def _expanding(settings: Any) -> dict[str, Any] | None:
    with session_scope(settings) as s:
        row = s.scalar(select(Campaign).where(Campaign.state == "EXPANDING").limit(1))
        return None if row is None else {"id": row.id, "stage": row.stage}


#: Seconds each variant's augment stage sleeps (the runner's test hook).
VARIANT_SLEEP_S = 3.0


def _kill_during_variants(
    settings: Any, cid: str, workers: Any, rng: random.Random, quick: bool, n: int
) -> list[dict[str, Any]]:
    """Kill a pool process (the last time, in the full form, the whole worker) at random
    moments while the campaign's variants run."""
    kills: list[dict[str, Any]] = []
    for i in range(n):
        time.sleep(rng.uniform(0.5, 4.0))
        run = c.wait_for(lambda: _running_job(settings, cid), 120, "a running variant")
        whole = not quick and i == n - 1
        pid = workers.kill_worker() if whole else _kill_child(workers, rng)
        if whole:
            workers.start()
        kills.append(
            {
                "kill": "worker" if whole else "child",
                "pid": pid,
                "stage_hit": run["stage"],
                "job": run["id"][:8],
            }
        )
        c.log(f"kill {i + 1}: {kills[-1]['kill']} in {run['stage']!r}")
    return kills


def _figures(
    expected: dict[str, Any],
    detail: dict[str, Any],
    failing: dict[str, Any],
    dry_deliveries: Any,
    variant_rows: Any,
    per_job: dict[str, Any],
    archives: dict[str, Any],
    manifest: dict[str, Any],
    codes: Any,
    rows: Any,
    kills: list[dict[str, Any]],
    wall: float,
    deaths: Any,
) -> dict[str, Any]:
    """The scenario's figures from what the run observed."""
    made = {v["id"]: v["key"] for v in detail["variants"]}
    ok_jobs = [j for j, (st, *_rest) in per_job.items() if st == "SUCCEEDED"]
    failed = [(j, err) for j, (st, err, *_r) in per_job.items() if st == "FAILED"]
    one_archive = sum(
        1 for j, (st, _e, key, _a) in per_job.items() if st == "SUCCEEDED" and archives[j] == [key]
    )
    return {
        "variants_expected": len(expected),
        "variants_made": len(made),
        "variants_same_keys_as_the_dry_run": made == expected,
        "dry_run_expansion_deliveries": dry_deliveries,
        "variant_rows": variant_rows,
        "variant_job_rows": len(per_job),
        "variant_jobs_succeeded": len(ok_jobs),
        "variant_jobs_failed": len(failed),
        "failed_reason": failed[0][1] if failed else None,
        "failed_is_the_designed_one": [f[0] for f in failed] == [failing["job_id"]],
        "jobs_with_exactly_one_archive": one_archive,
        "archives_of_failed_jobs": sum(len(archives[j]) for j, _ in failed),
        "attempts_max": max((a for *_x, a in per_job.values()), default=0),
        "campaign_state": detail["state"],
        "campaign_summary": detail["summary"],
        "manifest_rows": len(manifest["variants"]),
        "manifest_states": dict(Counter(r["state"] for r in manifest["variants"])),
        "submit_status_codes": dict(codes),
        "campaign_rows_for_the_key": rows,
        "kills": len(kills),
        "kills_by_kind": dict(Counter(k["kill"] for k in kills)),
        "kills_by_stage": dict(Counter(str(k["stage_hit"]) for k in kills)),
        "campaign_wall_s": round(wall, 1),
        "worker_process_deaths_logged": deaths,
        "records": kills,
    }


def run(workdir: Path, *, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    rng = random.Random(seed)
    draws = 2 if quick else 4
    kills_during_variants = 2 if quick else 5
    # long enough that a variant is still running when the scenario has set its hooks
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel24", frames=24)
    with c.pg_database() as db, c.redis_db() as broker:
        settings = c.reliability_settings(
            workdir / "var",
            database_url=db,
            broker_url=broker,
            campaign_dry_run_wait_s=120,
            task_time_limit_s=40,
            task_soft_time_limit_s=35,
            visibility_margin_s=2,
            visibility_timeout_s=42,
        )
        secret = c.new_api_key(settings)
        workers = c.Workers(settings, workdir / "worker.log", concurrency=1)
        store = store_from_url(str(settings.store_url), settings)
        kills: list[dict[str, Any]] = []
        with c.ApiServer(settings) as api, api.client(secret) as http, workers:
            sid = http.post("/v1/sequences", json={"path": str(seq)}).json()["id"]
            spec = campaign_spec(sid, draws)
            dry, kill = _dry_run_killed(http, settings, workers, spec, rng)
            if kill is not None:
                kills.append(kill)
            if dry is None or dry.status_code != 200:
                raise RuntimeError(f"dry run: {None if dry is None else dry.text[:500]}")
            expected = {v["id"]: v["key"] for v in dry.json()["variants"]}
            with session_scope(settings) as s:
                dry_deliveries = s.scalar(
                    select(Campaign.deliveries).where(Campaign.id == dry.json()["id"])
                )
            c.log(f"dry run: {len(expected)} variants")
            # 20 concurrent submits, one Idempotency-Key
            codes = _submit_burst(http, spec, 20)
            with session_scope(settings) as s:
                rows = s.scalar(
                    select(func.count())
                    .select_from(Campaign)
                    .where(Campaign.idempotency_key == "kill-1")
                )
                cid = s.scalar(select(Campaign.id).where(Campaign.idempotency_key == "kill-1"))
            t0 = time.monotonic()
            c.wait_for(
                lambda: _campaign(http, cid)["state"] not in ("PENDING", "EXPANDING"),
                120,
                "the expansion to commit",
            )
            detail = _campaign(http, cid)
            failing = detail["variants"][-1]  # the last variant fails by design
            with session_scope(settings) as s:
                # every variant's augment takes a few seconds, so that the kills find one
                # running on an idle machine too (the tiny sequence's variants took
                # 1 s each: all were done before the first kill)
                for v in detail["variants"]:
                    job = s.get(Job, v["job_id"])
                    hooks: dict[str, Any] = {"sleep_in": {"augment": VARIANT_SLEEP_S}}
                    if v["job_id"] == failing["job_id"]:
                        hooks["fail_in"] = "evaluate"
                    job.spec = {**job.spec, "_test": hooks}
            kills += _kill_during_variants(
                settings, cid, workers, rng, quick, kills_during_variants
            )
            c.wait_for(lambda: _campaign(http, cid)["state"] in END, 600, "the campaign's end")
            wall = time.monotonic() - t0
            detail = _campaign(http, cid)
            manifest = http.get(f"/v1/campaigns/{cid}/manifest.json").json()
            with session_scope(settings) as s:
                jobs = list(s.scalars(select(Job).where(Job.campaign_id == cid)))
                variant_rows = s.scalar(
                    select(func.count())
                    .select_from(CampaignVariant)
                    .where(CampaignVariant.campaign_id == cid)
                )
                per_job = {j.id: (j.state.value, j.error, j.result_key, j.attempt) for j in jobs}
            archives = {jid: c.archive_keys(store, jid) for jid in per_job}
            deaths = workers.deaths()
    return _figures(
        expected,
        detail,
        failing,
        dry_deliveries,
        variant_rows,
        per_job,
        archives,
        manifest,
        codes,
        rows,
        kills,
        wall,
        deaths,
    )


def ok(f: dict[str, Any]) -> bool:
    n = f["variants_expected"]
    return (
        n >= 4
        and f["variants_same_keys_as_the_dry_run"]
        and f["variants_made"] == f["variant_rows"] == f["variant_job_rows"] == n
        and f["variant_jobs_succeeded"] == n - 1
        and f["variant_jobs_failed"] == 1
        and f["failed_is_the_designed_one"]
        and "test hook" in str(f["failed_reason"])
        and f["jobs_with_exactly_one_archive"] == n - 1
        and f["archives_of_failed_jobs"] == 0
        and f["campaign_state"] == "PARTIAL"
        and f["manifest_rows"] == n
        and f["manifest_states"] == {"done": n - 1, "failed": 1}
        and f["submit_status_codes"] == {201: 1, 200: 19}
        and f["campaign_rows_for_the_key"] == 1
        and f["kills"] >= 3
        and f["worker_process_deaths_logged"] >= f["kills"]
    )


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
