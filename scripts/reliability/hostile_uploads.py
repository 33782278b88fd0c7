"""Hostile uploads: the archive attack set and a corpus of mutated files, end to end.

Against the API (uvicorn, PostgreSQL) and prefork workers (Redis):

1. every archive of the attack set (zip-slip, absolute paths, symlinks and hardlinks out,
   devices, 10,001 members, ratio and nested bombs, names too long...) uploaded as a
   sequence: refused with a 4xx naming the problem, and nothing written anywhere (the
   data folder is compared before and after; ``/tmp/evil.txt`` never appears);
2. a sequence with one file mutated (PNG 50k x 50k header, PCD whose POINTS overflows,
   NaN points, garbage CSV, broken OpenLABEL JSON, random bit flips...) uploaded, and a
   job submitted when the upload is accepted;
3. hostile meshes (glTF external uri, garbage glb, NaN vertices...) uploaded as assets,
   and a job submitted with each one accepted.

Figures: API 5xx (must be 0), worker process deaths (0), jobs not terminal within their
time limit (0), FAILED jobs without a readable reason (0), and every outcome with its
reason.
"""

from __future__ import annotations

import re
import shutil
import time
from pathlib import Path
from typing import Any

from scripts.reliability import common as c
from scripts.reliability import corpus

NAME = "hostile_uploads"
EVIL = (Path("/tmp/evil.txt"), Path("/tmp/l"))


def _tree(root: Path) -> set[str]:
    skip = ("osdar-ar.db", "broker.db", "celery-results.db", "worker.log")
    return {p.relative_to(root).as_posix() for p in root.rglob("*") if not p.name.startswith(skip)}


def _readable(reason: str | None) -> bool:
    return bool(reason) and "Traceback" not in reason and len(reason) < 2000


def _detail(r: Any) -> str:
    try:
        d = r.json().get("detail")
    except Exception:
        return r.text[:200]
    if isinstance(d, list) and d:
        return str(d[0].get("msg"))[:200]
    return str(d)[:200]


class Tally:
    """What the scenario saw: every input's outcome, the jobs it made, the API's 5xx."""

    def __init__(self) -> None:
        self.outcomes: dict[str, dict[str, Any]] = {}
        self.jobs: dict[str, str] = {}
        self.five_xx = 0

    def answered(self, r: Any) -> Any:
        self.five_xx += r.status_code >= 500
        return r

    def submit(self, http: Any, name: str, upload: Any, spec: dict[str, Any] | None) -> None:
        """Record an upload's answer and, when it was accepted, submit ``spec``."""
        out: dict[str, Any] = {"upload": upload.status_code}
        if upload.status_code == 201 and spec is not None:
            j = self.answered(http.post("/v1/jobs", json=spec))
            out["submit"] = j.status_code
            if j.status_code == 201:
                self.jobs[name] = j.json()["id"]
            else:
                out["reason"] = _detail(j)
        else:
            out["reason"] = _detail(upload)
        self.outcomes[name] = out


def _settings(workdir: Path, db: str, broker: str) -> Any:
    return c.reliability_settings(
        workdir / "var",
        database_url=db,
        broker_url=broker,
        max_archive_members=10_000,
        max_archive_total_bytes=40 * corpus.MiB,
        max_sequence_upload_bytes=128 * corpus.MiB,
        max_asset_upload_bytes=16 * corpus.MiB,
        max_mesh_vertices=500_000,
        task_time_limit_s=60,
        task_soft_time_limit_s=45,
    )


def _archive_attacks(http: Any, data: Path, settings: Any, tally: Tally) -> tuple[int, int]:
    """Upload every archive attack: (attacks, refused with a 4xx naming the problem and
    nothing written)."""
    attacks = corpus.archive_attacks(settings.max_archive_members)
    refused = 0
    for name, (blob, needle) in attacks.items():
        before = _tree(data)
        r = tally.answered(http.post("/v1/sequences/upload", content=blob))
        new = sorted(_tree(data) - before)
        good = 400 <= r.status_code < 500 and bool(re.search(needle, _detail(r))) and not new
        refused += good
        tally.outcomes[f"archive: {name}"] = {
            "status": r.status_code,
            "reason": _detail(r),
            "new_files": new[:5],
            "ok": good,
        }
    return len(attacks), refused


def _mutated_inputs(
    http: Any, workdir: Path, seq: Path, quick: bool, seed: int, tally: Tally
) -> None:
    """Upload mutated sequences and hostile meshes; submit a job for each accepted one."""
    clean = http.post("/v1/sequences", json={"path": str(seq)}).json()["id"]
    for name, mutate in corpus.sequence_mutations(quick, seed).items():
        copy = workdir / "mut" / seq.name
        shutil.rmtree(copy.parent, ignore_errors=True)
        shutil.copytree(seq, copy, ignore=shutil.ignore_patterns("ground_truth"))
        mutate(copy)
        r = tally.answered(http.post("/v1/sequences/upload", content=corpus.tar_folder(copy)))
        spec = c.job_spec(r.json()["id"]) if r.status_code == 201 else None
        tally.submit(http, f"file: {name}", r, spec)
    for name, (ft, blob) in corpus.mesh_corpus(quick, seed).items():
        params = {"name": "m", "file_type": ft}
        r = tally.answered(http.post("/v1/assets", params=params, content=blob))
        spec = None
        if r.status_code == 201:
            spec = c.job_spec(clean, object={"asset_id": r.json()["id"], "scale": 1.0})
        tally.submit(http, f"mesh: {name}", r, spec)


def _wait_for_jobs(http: Any, settings: Any, concurrency: int, tally: Tally) -> float:
    """Every job terminal within its time limit (+ queueing behind the others): the wait."""
    t0 = time.monotonic()
    budget = 90 + 40 * len(tally.jobs) / concurrency
    rows = c.wait_terminal(settings, list(tally.jobs.values()), budget)
    for name, jid in tally.jobs.items():
        row = rows[jid]
        took = None
        if row.started_at and row.finished_at:
            took = (row.finished_at - row.started_at).total_seconds()
        tally.outcomes[name].update(
            state=row.state.value, reason=row.error, seconds=took, deliveries=row.deliveries
        )
        tally.answered(http.get(f"/v1/jobs/{jid}"))
    return time.monotonic() - t0


def run(workdir: Path, *, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel")
    evil_before = [p.exists() for p in EVIL]
    tally = Tally()
    with c.pg_database() as db, c.redis_db() as broker:
        settings = _settings(workdir, db, broker)
        secret = c.new_api_key(settings)
        workers = c.Workers(settings, workdir / "worker.log", concurrency=2)
        with c.ApiServer(settings) as api, api.client(secret, timeout=300) as http, workers:
            data = Path(settings.data_dir)
            for sub in ("sequences", "tmp"):  # made by the first upload; not the attack's
                (data / sub).mkdir(parents=True, exist_ok=True)
            n_attacks, refused = _archive_attacks(http, data, settings, tally)
            _mutated_inputs(http, workdir, seq, quick, seed, tally)
            waited = _wait_for_jobs(http, settings, workers.concurrency, tally)
            deaths = workers.deaths()
        tmp_left = list((Path(settings.data_dir) / "tmp").glob("*"))
    outcomes = tally.outcomes
    states = [o.get("state") for o in outcomes.values() if "state" in o]
    failed = [o for o in outcomes.values() if o.get("state") == "FAILED"]
    refused_at_upload = [
        o for k, o in outcomes.items() if not k.startswith("archive") and "state" not in o
    ]
    limit = settings.task_time_limit_s
    return {
        "archive_attacks": n_attacks,
        "archive_attacks_refused_cleanly": refused,
        "evil_files_created": [
            str(p) for p, b in zip(EVIL, evil_before, strict=True) if p.exists() and not b
        ],
        "tmp_files_left": len(tmp_left),
        "mutated_inputs": len(outcomes) - n_attacks,
        "refused_at_upload_or_submit_4xx": len(refused_at_upload),
        "jobs": len(tally.jobs),
        "jobs_failed": len(failed),
        "jobs_succeeded_harmless_mutation": states.count("SUCCEEDED"),
        "jobs_not_terminal": sum(1 for s in states if s not in c.TERMINAL),
        "jobs_failed_without_readable_reason": sum(not _readable(o["reason"]) for o in failed),
        "jobs_over_time_limit": sum(
            1 for o in outcomes.values() if (o.get("seconds") or 0) > limit
        ),
        "jobs_with_redeliveries": sum(
            1 for o in outcomes.values() if (o.get("deliveries") or 0) > 1
        ),
        "wait_s": round(waited, 1),
        "api_5xx": tally.five_xx,
        "worker_deaths": deaths,
        "outcomes": outcomes,
    }


def ok(f: dict[str, Any]) -> bool:
    return (
        f["api_5xx"] == 0
        and f["worker_deaths"] == 0
        and f["jobs_not_terminal"] == 0
        and f["jobs_failed_without_readable_reason"] == 0
        and not f["evil_files_created"]
        and f["archive_attacks_refused_cleanly"] == f["archive_attacks"]
        and f["jobs_over_time_limit"] == 0
        and f["tmp_files_left"] == 0
    )


def print_outcomes(f: dict[str, Any]) -> None:
    for name, o in f["outcomes"].items():
        print(f"  {name:<45} {o}")  # noqa: T201


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
