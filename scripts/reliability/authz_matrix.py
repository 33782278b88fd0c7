"""A second API key against the first key's objects: every id route answers 404.

Alice owns a registered sequence, an uploaded sequence, an asset, a QUEUED job, a
SUCCEEDED job with an archive and previews, and a campaign. Bob (his own valid key) calls
every route of the OpenAPI that takes an id, with every method, on each of Alice's objects;
then with random ids; no key and a wrong key must be 401 everywhere. Figures: requests, the share
that was 404 (must be 100 %), anything else listed, and that Alice still reads it all.
"""

from __future__ import annotations

import io
import tarfile
import uuid
from pathlib import Path
from typing import Any

from celery import Celery
from sqlalchemy import update

from osdar_platform.db import session_scope
from osdar_platform.models import Job, JobState
from scripts.reliability import common as c

NAME = "authz_matrix"
TETRA_OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


def _tar_of(folder: Path) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for p in sorted(folder.rglob("*")):
            if p.is_file() and "ground_truth" not in p.parts:
                tar.add(p, arcname=f"{folder.name}/{p.relative_to(folder).as_posix()}")
    return buf.getvalue()


def _fake_publish(settings: Any, store: Any, job_id: str) -> None:

    key = f"jobs/{job_id}/attempt-1/archive.tar.gz"
    store.put_bytes(key, b"alice's archive")
    store.put_bytes(f"jobs/{job_id}/previews/attempt-1/p.png", b"\x89PNG alice")
    with session_scope(settings) as s:
        s.execute(
            update(Job)
            .where(Job.id == job_id)
            .values(
                state=JobState.SUCCEEDED,
                result_key=key,
                previews=[f"jobs/{job_id}/previews/attempt-1/p.png"],
                metrics={"x": 1},
            )
        )


def _campaign(sequence_id: str) -> dict[str, Any]:
    return {"name": "alice", "sequences": [{"id": sequence_id}],
            "obstacles": [{"builtin": "rock"}], "job": {"cameras": ["rgb_center"]}}  # fmt: skip


def run(workdir: Path, *, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel")
    random_ids = 3 if quick else 20
    with c.pg_database() as db:
        settings = c.reliability_settings(workdir / "var", database_url=db, broker_url="memory://")

        celery = Celery("authz", broker="memory://", set_as_current=False)
        alice_key, bob_key = c.new_api_key(settings, "alice"), c.new_api_key(settings, "bob")
        with (
            c.ApiServer(settings, celery_app=celery) as api,
            api.client(alice_key) as alice,
            api.client(bob_key) as bob,
            api.client() as anon,
        ):
            reg = alice.post("/v1/sequences", json={"path": str(seq)}).json()["id"]
            up = alice.post("/v1/sequences/upload", content=_tar_of(seq)).json()["id"]
            asset = alice.post(
                "/v1/assets", params={"name": "t", "file_type": "obj"}, content=TETRA_OBJ
            ).json()["id"]
            queued = alice.post("/v1/jobs", json=c.job_spec(reg)).json()["id"]
            done = alice.post("/v1/jobs", json=c.job_spec(up)).json()["id"]
            _fake_publish(settings, api.app.state.store, done)
            campaign = alice.post("/v1/campaigns", json=_campaign(reg)).json()["id"]
            bob.post("/v1/sequences", json={"path": str(seq)})  # bob has objects of his own
            spec = api.client().get("/v1/openapi.json").json()
            routes = [(m.upper(), p) for p, ops in spec["paths"].items() for m in ops if "{" in p]
            objects = {"sequence_id": [reg, up], "asset_id": [asset], "job_id": [queued, done],
                       "campaign_id": [campaign]}  # fmt: skip
            rnd = [str(uuid.UUID(int=seed * 1000 + i)) for i in range(random_ids)]
            calls: list[tuple[str, str, str]] = []
            for method, path in routes:
                param = next(k for k in objects if "{" + k + "}" in path)
                for oid in objects[param] + rnd:
                    url = path.replace("{" + param + "}", oid).replace("{index}", "0")
                    calls.append((method, url, "alice's" if oid not in rnd else "random"))
            other: list[str] = []
            for method, url, kind in calls:
                r = bob.request(method, url)
                if r.status_code != 404:
                    other.append(f"{method} {url} ({kind}) -> {r.status_code}")
            unauth = [
                (
                    m.upper(),
                    p.replace("{sequence_id}", reg)
                    .replace("{job_id}", done)
                    .replace("{asset_id}", asset)
                    .replace("{campaign_id}", campaign)
                    .replace("{index}", "0"),
                )
                for p, ops in spec["paths"].items()
                for m in ops
                if p != "/v1/health"
            ]
            not_401 = []
            for method, url in unauth:
                for client, hdr in (
                    (anon, {}),
                    (anon, {"Authorization": "Bearer oar_forged"}),
                    (anon, {"X-API-Key": alice_key[:-2] + "xx"}),
                ):
                    r = client.request(method, url, headers=hdr)
                    if r.status_code != 401:
                        not_401.append(f"{method} {url} {list(hdr)} -> {r.status_code}")
            intact = (
                alice.get(f"/v1/jobs/{done}/archive").content == b"alice's archive"
                and alice.get(f"/v1/sequences/{up}").status_code == 200
                and alice.get(f"/v1/assets/{asset}").status_code == 200
                and alice.get(f"/v1/jobs/{queued}").json()["state"] == "QUEUED"
                and bob.get("/v1/jobs").json()["total"] == 0
                and alice.get(f"/v1/campaigns/{campaign}").json()["state"] == "PENDING"
                and bob.get("/v1/campaigns").json()["total"] == 0
            )
    n = len(calls)
    return {
        "routes_with_ids": len(routes),
        "cross_key_requests": n,
        "cross_key_404_percent": 100.0 * (n - len(other)) / max(n, 1),
        "cross_key_not_404": other[:20],
        "unauthenticated_requests": 3 * len(unauth),
        "unauthenticated_not_401": not_401[:20],
        "owner_objects_intact": intact,
    }


def ok(f: dict[str, Any]) -> bool:
    return (
        f["cross_key_404_percent"] == 100.0
        and not f["unauthenticated_not_401"]
        and f["owner_objects_intact"]
        and f["routes_with_ids"] >= 10
    )


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
