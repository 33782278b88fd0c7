"""The job service's HTTP API, on SQLite and on PostgreSQL (the ``api`` fixture)."""

from __future__ import annotations

import asyncio
import io
import json
import re
import subprocess
import sys
import tarfile
import threading
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import func, select, update

from osdar_platform.models import Job, JobState
from tests.conftest_service import Api, make_settings, memory_celery, sent_tasks
from worker.orchestration.queue import PRIORITY_JOB, TASK_RUN_JOB

TETRA_OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


def submit(api: Api, who: str = "alice", **spec: Any) -> dict[str, Any]:
    r = api.client.post("/v1/jobs", json=api.job_spec(**spec), headers=api.h(who))
    assert r.status_code == 201, r.text
    return r.json()


def publish_fake_result(api: Api, job_id: str, archive: bytes) -> None:
    """What the publish step does: objects first, then one row update pointing at them."""
    store = api.client.app.state.store
    store.put_bytes(f"jobs/{job_id}/attempt-1/result.tar", archive)
    store.put_bytes(f"jobs/{job_id}/attempt-1/preview-0.png", b"\x89PNG fake")
    with api.sessions.begin() as s:
        s.execute(
            update(Job)
            .where(Job.id == job_id)
            .values(
                state=JobState.SUCCEEDED,
                result_key=f"jobs/{job_id}/attempt-1/result.tar",
                previews=[f"jobs/{job_id}/attempt-1/preview-0.png"],
                metrics={"rpe_px": {"rgb_center": 0.4}},
                progress_done=3,
            )
        )


def campaign_spec(api: Api) -> dict[str, Any]:
    """A one-rule campaign on the API's sequence (it stays PENDING: no worker here)."""
    return {
        "name": "authz",
        "sequences": [{"id": api.sequence_id}],
        "obstacles": [{"builtin": "rock"}],
        "job": {"cameras": ["rgb_center"]},
    }


def upload_asset(api: Api, who: str = "alice", data: bytes = TETRA_OBJ, ft: str = "obj") -> Any:
    return api.client.post(
        "/v1/assets",
        params={"name": "tetra", "file_type": ft},
        content=data,
        headers=api.h(who, **{"Content-Type": "application/octet-stream"}),
    )


# ------------------------------------------------------------------------------ basics
def test_health_needs_no_key(api: Api) -> None:
    r = api.client.get("/v1/health")
    assert r.status_code == 200
    assert r.json()["status"] == "ok" and r.json()["database"] == "ok"


def test_openapi_documents_every_route(api: Api) -> None:
    spec = api.client.get("/v1/openapi.json").json()
    assert set(spec["components"]["securitySchemes"]) == {"HTTPBearer", "APIKeyHeader"}
    for path, ops in spec["paths"].items():
        assert path.startswith("/v1/")
        for method, op in ops.items():
            assert op.get("summary"), (method, path)
            if path != "/v1/health":
                assert "security" in op and "401" in op["responses"], (method, path)
            ok = [c for c in op["responses"] if c.startswith("2")]
            assert ok, (method, path)
    body = spec["components"]["schemas"]["JobCreate"]
    assert body["required"] == ["sequence_id"]
    # one object (with a placement or a motion) or a list of objects, never both
    one, many = body["oneOf"]
    assert one["required"] == ["object"] and many["required"] == ["objects"]
    assert [a["required"] for a in one["anyOf"]] == [["placement"], ["motion"]]


def test_openapi_states_what_the_service_checks(api: Api) -> None:
    """What schemathesis' positive-data check found refused although schema-valid is now
    in the schema: ids' characters, absolute paths, exactly one object source, non-empty
    upload bodies, and the 403 / 404 of a registered path."""
    from jsonschema import Draft202012Validator

    spec = api.client.get("/v1/openapi.json").json()
    schemas = spec["components"]["schemas"]
    obj = Draft202012Validator(schemas["ObjectSpec"])
    assert obj.is_valid({"builtin": "cow"}) and obj.is_valid({"asset_id": "a1"})
    assert obj.is_valid({"builtin": "cow", "asset_id": None})
    assert not obj.is_valid({}) and not obj.is_valid({"builtin": "cow", "asset_id": "a1"})
    path = schemas["SequenceRegister"]["properties"]["path"]["pattern"]
    assert re.fullmatch(path, "/data/seq") and not re.fullmatch(path, "data/seq")
    assert schemas["JobCreate"]["properties"]["sequence_id"]["pattern"] == "^[A-Za-z0-9_-]{1,64}$"
    register = spec["paths"]["/v1/sequences"]["post"]["responses"]
    assert {"403", "404", "422"} <= set(register)
    for route in ("/v1/assets", "/v1/sequences/upload"):
        content = spec["paths"][route]["post"]["requestBody"]["content"]
        assert all(c["schema"]["minLength"] == 1 for c in content.values())


def test_registered_sequence_shows_frames_cameras_span(api: Api) -> None:
    r = api.client.get(f"/v1/sequences/{api.sequence_id}", headers=api.h())
    assert r.status_code == 200
    seq = r.json()
    assert seq["frames"] == 3 and seq["first_frame"] == 0 and seq["last_frame"] == 2
    assert seq["cameras"] == ["rgb_center", "rgb_highres_center"]
    assert 0.1 < seq["time_span_s"] < 0.3
    assert seq["validation"]["ok"] is True and seq["validation"]["lidar"] == "lidar"


@pytest.mark.parametrize(
    ("path", "needle"),
    [("relative/folder", "pattern '^/"), ("/tmp", "OSDaR23")],
)
def test_register_bad_folder_is_422_on_path(api: Api, path: str, needle: str) -> None:
    """A path that is not absolute (the schema says so) or not a sequence: 422 on the field."""
    r = api.client.post("/v1/sequences", json={"path": path}, headers=api.h())
    assert r.status_code == 422, r.text
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", "path"] and needle in err["msg"]


def test_register_a_missing_folder_is_404(api: Api) -> None:
    r = api.client.post("/v1/sequences", json={"path": "/nonexistent/seq"}, headers=api.h())
    assert r.status_code == 404 and "no such folder" in r.json()["detail"], r.text


# ------------------------------------------------------------------------------ auth
def _authed_routes(api: Api, ids: dict[str, str]) -> list[tuple[str, str]]:
    """(method, concrete path) of every documented route but health, with ids filled in."""
    spec = api.client.get("/v1/openapi.json").json()
    return [
        (method.upper(), path.format(**ids))
        for path, ops in spec["paths"].items()
        if path != "/v1/health"
        for method in ops
    ]


def test_no_key_and_wrong_key_are_401_everywhere(api: Api) -> None:
    ids = {
        "sequence_id": api.sequence_id,
        "job_id": "x",
        "asset_id": "x",
        "campaign_id": "x",
        "index": "0",
    }
    routes = _authed_routes(api, ids)
    assert len(routes) >= 15
    for method, path in routes:
        for headers in ({}, {"Authorization": "Bearer oar_wrong"}, {"X-API-Key": "nope"}):
            r = api.client.request(method, path, headers=headers)
            assert r.status_code == 401, (method, path, headers, r.text)
            assert "detail" in r.json()


def test_x_api_key_header_works(api: Api) -> None:
    r = api.client.get("/v1/sequences", headers={"X-API-Key": api.keys["alice"]})
    assert r.status_code == 200


def test_another_keys_objects_are_404_on_every_route(api: Api) -> None:
    job = submit(api)
    publish_fake_result(api, job["id"], b"archive-bytes")
    asset = upload_asset(api).json()
    campaign = api.client.post("/v1/campaigns", json=campaign_spec(api), headers=api.h()).json()
    ids = {
        "sequence_id": api.sequence_id,
        "job_id": job["id"],
        "asset_id": asset["id"],
        "campaign_id": campaign["id"],
        "index": "0",
    }
    routes = [
        (m, p)
        for m, p in _authed_routes(api, ids)
        if any(v in p for v in (api.sequence_id, job["id"], asset["id"], campaign["id"]))
    ]
    assert len(routes) == 15  # every route with an id (4 of campaigns)
    for method, path in routes:
        r = api.client.request(method, path, headers=api.h("bob"))
        assert r.status_code == 404, (method, path, r.text)
    # ... and nothing was touched: the owner still reads all of it
    assert api.client.get(f"/v1/jobs/{job['id']}/archive", headers=api.h()).content == (
        b"archive-bytes"
    )
    assert api.client.get(f"/v1/assets/{asset['id']}", headers=api.h()).status_code == 200
    assert api.client.get(f"/v1/jobs/{job['id']}", headers=api.h()).json()["state"] == "SUCCEEDED"
    # bob cannot use alice's sequence or asset in a job either
    spec = api.job_spec(object={"asset_id": asset["id"]})
    assert api.client.post("/v1/jobs", json=spec, headers=api.h("bob")).status_code == 404
    assert api.client.get("/v1/jobs", headers=api.h("bob")).json()["total"] == 0
    # ... nor in a campaign, and sees none of hers
    r = api.client.post("/v1/campaigns", json=campaign_spec(api), headers=api.h("bob"))
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "sequences", 0, "id"]
    assert api.client.get("/v1/campaigns", headers=api.h("bob")).json()["total"] == 0


# ------------------------------------------------------------------------------ jobs
def test_submit_queues_the_job_and_sends_the_message(api: Api) -> None:
    sent_tasks()
    job = submit(api)
    assert job["state"] == "QUEUED"
    assert job["progress"] == {"done": 0, "total": 3}
    assert job["spec"]["object"] == {"builtin": "cow", "asset_id": None, "scale": 1.0}
    assert sent_tasks() == [
        {"task": TASK_RUN_JOB, "id": job["id"], "args": [job["id"]], "priority": PRIORITY_JOB}
    ]
    events = api.client.get(f"/v1/jobs/{job['id']}/events", headers=api.h()).json()
    assert [e["kind"] for e in events] == ["created", "queued"]


def test_a_failed_send_leaves_the_job_pending(api: Api) -> None:
    dispatcher = api.client.app.state.dispatcher

    class Down:
        def send_task(self, *a: Any, **k: Any) -> None:
            raise ConnectionError("broker down")

    saved, dispatcher.celery_app = dispatcher.celery_app, Down()
    try:
        job = submit(api)
    finally:
        dispatcher.celery_app = saved
    assert job["state"] == "PENDING"
    kinds = [e["kind"] for e in api.client.get(job["links"]["events"], headers=api.h()).json()]
    assert kinds == ["created", "enqueue_failed"]
    api.client.post(f"/v1/jobs/{job['id']}/cancel", headers=api.h())


BAD_BODIES = [
    ({"object": None}, ["body", "object"]),
    ({"object": {"builtin": "cow", "asset_id": "a"}}, ["body", "object"]),
    ({"object": {"builtin": "dragon"}}, ["body", "object", "builtin"]),
    ({"object": {"builtin": "cow", "scale": -1}}, ["body", "object", "scale"]),
    ({"placement": {"mode": "orbit"}}, ["body", "placement"]),
    ({"placement": {"mode": "track"}}, ["body", "placement", "track", "s"]),
    (
        {"placement": {"mode": "lidar_frame", "xyz": [1, 2, 3]}},
        ["body", "placement", "lidar_frame"],
    ),
    ({"strategy": "teleport"}, ["body", "strategy"]),
    ({"frame_range": [2, 1]}, ["body", "frame_range"]),
    ({"frame_range": [0]}, ["body", "frame_range"]),
    ({"cameras": []}, ["body", "cameras"]),
    ({"cameras": ["rgb_center", "rgb_center"]}, ["body", "cameras"]),
    ({"cameras": ["../etc"]}, ["body", "cameras", 0]),
    ({"render": {"png_compression": 12}}, ["body", "render", "png_compression"]),
    ({"render": {"exposure_ms": -1}}, ["body", "render", "exposure_ms"]),
    ({"clicks": {"rgb_center": {"one": [1, 2]}}}, ["body", "clicks"]),
    ({"colour": "red"}, ["body", "colour"]),
    ({"sequence_id": 5}, ["body", "sequence_id"]),
]


@pytest.mark.parametrize(("override", "loc"), BAD_BODIES)
def test_schema_errors_are_422_with_the_location(api: Api, override: dict, loc: list) -> None:
    r = api.client.post("/v1/jobs", json=api.job_spec(**override), headers=api.h())
    assert r.status_code == 422, r.text
    locs = [e["loc"][: len(loc)] for e in r.json()["detail"]]
    assert loc in locs, r.json()
    assert all(e["msg"] for e in r.json()["detail"])


def test_malformed_json_and_wrong_types_are_4xx(api: Api) -> None:
    h = api.h(**{"Content-Type": "application/json"})
    for body in (b"{", b"[]", b"null", b"\xff\xfe", json.dumps({"a": "b" * 10000}).encode()):
        r = api.client.post("/v1/jobs", content=body, headers=h)
        assert r.status_code == 422, (body[:20], r.text)
    r = api.client.post("/v1/jobs", content=b'{"sequence_id": NaN}', headers=h)
    assert r.status_code == 422
    r = api.client.post("/v1/jobs", json=api.job_spec(), headers=api.h(**{"Idempotency-Key": ""}))
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["header", "Idempotency-Key"]


@pytest.mark.parametrize(
    ("override", "loc", "needle"),
    [
        ({"cameras": ["rgb_center", "rgb_left"]}, ["body", "cameras", 1], "rgb_left"),
        ({"frame_range": [0, 7]}, ["body", "frame_range", 1], "outside"),
        ({"frame_range": [5, 7]}, ["body", "frame_range", 0], "[0, 2]"),
        (
            {"placement": {"mode": "lidar_frame", "xyz": [5, 0, 0], "frame_idx": 9}},
            ["body", "placement", "frame_idx"],
            "frame 9",
        ),
        ({"clicks": {"ir_center": {"0": [1, 2]}}}, ["body", "clicks", "ir_center"], "camera"),
        ({"clicks": {"rgb_center": {"40": [1, 2]}}}, ["body", "clicks", "rgb_center", "40"], "40"),
    ],
)
def test_spec_impossible_on_the_sequence_is_422_naming_the_field(
    api: Api, override: dict, loc: list, needle: str
) -> None:
    r = api.client.post("/v1/jobs", json=api.job_spec(**override), headers=api.h())
    assert r.status_code == 422, r.text
    match = [e for e in r.json()["detail"] if e["loc"] == loc]
    assert match and needle in match[0]["msg"], r.json()


def test_unknown_sequence_or_asset_is_404(api: Api) -> None:
    r = api.client.post("/v1/jobs", json=api.job_spec(sequence_id="nope"), headers=api.h())
    assert r.status_code == 404 and "sequence nope" in r.json()["detail"]
    spec = api.job_spec(object={"asset_id": "nope"})
    r = api.client.post("/v1/jobs", json=spec, headers=api.h())
    assert r.status_code == 404 and "asset nope" in r.json()["detail"]


def test_job_with_an_uploaded_asset(api: Api) -> None:
    asset = upload_asset(api).json()
    job = submit(api, object={"asset_id": asset["id"], "scale": 2.0})
    assert job["spec"]["object"]["asset_id"] == asset["id"]
    r = api.client.delete(f"/v1/assets/{asset['id']}", headers=api.h())
    assert r.status_code == 409  # used by an active job
    api.client.post(f"/v1/jobs/{job['id']}/cancel", headers=api.h())
    assert api.client.delete(f"/v1/assets/{asset['id']}", headers=api.h()).status_code == 204


# ------------------------------------------------------------------------------ idempotency
def test_idempotency_key_returns_the_same_job(api: Api) -> None:
    sent_tasks()
    h = api.h(**{"Idempotency-Key": f"once-{api.backend}"})
    first = api.client.post("/v1/jobs", json=api.job_spec(), headers=h)
    again = api.client.post("/v1/jobs", json=api.job_spec(), headers=h)
    assert (first.status_code, again.status_code) == (201, 200)
    assert first.json()["id"] == again.json()["id"]
    assert len(sent_tasks()) == 1
    other = api.client.post("/v1/jobs", json=api.job_spec(strategy="odometry"), headers=h)
    assert other.status_code == 409 and "Idempotency-Key" in other.json()["detail"]
    # keys are per API key: bob's same header names another job
    bob = api.client.post(
        "/v1/jobs",
        json=api.job_spec(sequence_id=_bob_sequence(api)),
        headers=api.h("bob", **{"Idempotency-Key": f"once-{api.backend}"}),
    )
    assert bob.status_code == 201 and bob.json()["id"] != first.json()["id"]


def _bob_sequence(api: Api) -> str:
    if "bob_seq" not in api.keys:
        path = api.client.get(f"/v1/sequences/{api.sequence_id}", headers=api.h()).json()["path"]
        r = api.client.post("/v1/sequences", json={"path": path}, headers=api.h("bob"))
        api.keys["bob_seq"] = r.json()["id"]
    return api.keys["bob_seq"]


def test_idempotency_under_20_concurrent_submissions(api: Api) -> None:
    sent_tasks()
    key = f"race-{api.backend}"
    h = api.h(**{"Idempotency-Key": key})
    results: list[Any] = []
    barrier = threading.Barrier(20)

    def post() -> None:
        barrier.wait()
        results.append(api.client.post("/v1/jobs", json=api.job_spec(), headers=h))

    threads = [threading.Thread(target=post) for _ in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    codes = sorted(r.status_code for r in results)
    assert codes == [200] * 19 + [201], [r.text for r in results if r.status_code >= 300]
    assert len({r.json()["id"] for r in results}) == 1
    with api.sessions() as s:
        rows = s.scalar(select(func.count()).select_from(Job).where(Job.idempotency_key == key))
    assert rows == 1
    assert len(sent_tasks()) == 1


# ------------------------------------------------------------------------------ cancel
def test_cancel_a_queued_job(api: Api) -> None:
    job = submit(api)
    r = api.client.post(f"/v1/jobs/{job['id']}/cancel", headers=api.h())
    assert r.status_code == 202
    assert r.json()["state"] == "CANCELLED" and r.json()["cancel_requested"] is True
    assert r.json()["finished_at"] is not None
    again = api.client.post(f"/v1/jobs/{job['id']}/cancel", headers=api.h())
    assert again.status_code == 202 and again.json()["state"] == "CANCELLED"


def test_cancel_a_running_job_sets_the_flag_only(api: Api) -> None:
    job = submit(api)
    with api.sessions.begin() as s:
        s.execute(update(Job).where(Job.id == job["id"]).values(state=JobState.RUNNING))
    r = api.client.post(f"/v1/jobs/{job['id']}/cancel", headers=api.h())
    assert r.json()["state"] == "RUNNING" and r.json()["cancel_requested"] is True
    with api.sessions.begin() as s:  # the worker notices and stops
        s.execute(update(Job).where(Job.id == job["id"]).values(state=JobState.CANCELLED))


def test_cancel_a_finished_job_is_409(api: Api) -> None:
    job = submit(api)
    publish_fake_result(api, job["id"], b"x")
    r = api.client.post(f"/v1/jobs/{job['id']}/cancel", headers=api.h())
    assert r.status_code == 409 and "SUCCEEDED" in r.json()["detail"]


# ------------------------------------------------------------------------------ listing
def test_pagination_and_filters(api: Api) -> None:
    who = f"pager-{api.backend}"
    api.new_key(who)
    path = api.client.get(f"/v1/sequences/{api.sequence_id}", headers=api.h()).json()["path"]
    seq = api.client.post("/v1/sequences", json={"path": path}, headers=api.h(who)).json()["id"]
    ids = [submit(api, who, sequence_id=seq)["id"] for _ in range(5)]
    api.client.post(f"/v1/jobs/{ids[0]}/cancel", headers=api.h(who))
    pages = [
        api.client.get("/v1/jobs", params={"limit": 2, "offset": o}, headers=api.h(who)).json()
        for o in (0, 2, 4)
    ]
    assert [p["total"] for p in pages] == [5, 5, 5]
    seen = [j["id"] for p in pages for j in p["items"]]
    assert seen == ids[::-1]  # newest first, no repeats, no gaps
    cancelled = api.client.get("/v1/jobs", params={"state": "CANCELLED"}, headers=api.h(who))
    assert [j["id"] for j in cancelled.json()["items"]] == [ids[0]]
    both = api.client.get(
        "/v1/jobs", params=[("state", "CANCELLED"), ("state", "QUEUED")], headers=api.h(who)
    )
    assert both.json()["total"] == 5
    none = api.client.get("/v1/jobs", params={"sequence_id": "other"}, headers=api.h(who))
    assert none.json()["total"] == 0
    r = api.client.get("/v1/jobs", params={"limit": 0}, headers=api.h(who))
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "limit"]
    r = api.client.get("/v1/jobs", params={"state": "DONE"}, headers=api.h(who))
    assert r.status_code == 422
    seqs = api.client.get("/v1/sequences", params={"limit": 1}, headers=api.h(who)).json()
    assert seqs["total"] == 1 and seqs["items"][0]["id"] == seq


# ------------------------------------------------------------------------------ results
def test_download_whole_and_ranges(api: Api) -> None:
    job = submit(api)
    payload = bytes(range(256)) * 8192  # 2 MiB: more than one store chunk
    publish_fake_result(api, job["id"], payload)
    url = f"/v1/jobs/{job['id']}/archive"
    full = api.client.get(url, headers=api.h())
    assert full.status_code == 200 and full.content == payload
    assert full.headers["accept-ranges"] == "bytes"
    assert "attachment" in full.headers["content-disposition"]
    part = api.client.get(url, headers=api.h(Range="bytes=1000-1999"))
    assert part.status_code == 206 and part.content == payload[1000:2000]
    assert part.headers["content-range"] == f"bytes 1000-1999/{len(payload)}"
    tail = api.client.get(url, headers=api.h(Range="bytes=-10"))
    assert tail.status_code == 206 and tail.content == payload[-10:]
    open_end = api.client.get(url, headers=api.h(Range=f"bytes={len(payload) - 5}-"))
    assert open_end.content == payload[-5:]
    bad = api.client.get(url, headers=api.h(Range=f"bytes={len(payload)}-"))
    assert bad.status_code == 416 and bad.headers["content-range"] == f"bytes */{len(payload)}"
    metrics = api.client.get(f"/v1/jobs/{job['id']}/metrics", headers=api.h())
    assert metrics.json() == {"rpe_px": {"rgb_center": 0.4}}
    previews = api.client.get(f"/v1/jobs/{job['id']}/previews", headers=api.h()).json()
    assert previews == [f"/v1/jobs/{job['id']}/previews/0"]
    png = api.client.get(previews[0], headers=api.h())
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert api.client.get(f"{previews[0][:-1]}1", headers=api.h()).status_code == 404
    status = api.client.get(f"/v1/jobs/{job['id']}", headers=api.h()).json()
    assert status["result_available"] and status["links"]["archive"] == url


def test_no_archive_before_the_job_finished_is_409(api: Api) -> None:
    job = submit(api)
    for what in ("archive", "metrics"):
        r = api.client.get(f"/v1/jobs/{job['id']}/{what}", headers=api.h())
        assert r.status_code == 409 and "QUEUED" in r.json()["detail"]
    api.client.post(f"/v1/jobs/{job['id']}/cancel", headers=api.h())


# ------------------------------------------------------------------------------ uploads
def _tar_gz(folder: Path) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        tf.add(
            folder, arcname=folder.name, filter=lambda ti: None if "ground_truth" in ti.name else ti
        )
    return buf.getvalue()


def test_upload_a_sequence_archive_then_delete_it(api: Api, synth_sequence_dir: Path) -> None:
    data = _tar_gz(synth_sequence_dir)
    r = api.client.post(
        "/v1/sequences/upload",
        params={"name": "uploaded"},
        content=data,
        headers=api.h(**{"Content-Type": "application/gzip"}),
    )
    assert r.status_code == 201, r.text
    seq = r.json()
    assert seq["source"] == "upload" and seq["frames"] == 3 and seq["name"] == "uploaded"
    assert seq["validation"]["archive"]["kind"] == "tar"
    folder = Path(seq["path"])
    assert (folder / "fire_site_tiny_labels.json").is_file()
    assert Path(api.settings.sequences_dir).resolve() in folder.parents
    job = submit(api, sequence_id=seq["id"])
    assert api.client.delete(f"/v1/sequences/{seq['id']}", headers=api.h()).status_code == 409
    api.client.post(f"/v1/jobs/{job['id']}/cancel", headers=api.h())
    assert api.client.delete(f"/v1/sequences/{seq['id']}", headers=api.h()).status_code == 204
    assert not folder.exists()
    assert api.client.get(f"/v1/sequences/{seq['id']}", headers=api.h()).status_code == 404
    assert api.client.get(f"/v1/jobs/{job['id']}", headers=api.h()).json()["sequence_id"] is None


def test_upload_attack_archive_is_refused(api: Api) -> None:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tf:
        info = tarfile.TarInfo("../../escaped.txt")
        info.size = 3
        tf.addfile(info, io.BytesIO(b"bad"))
    r = api.client.post("/v1/sequences/upload", content=buf.getvalue(), headers=api.h())
    assert r.status_code == 422 and "'..'" in r.json()["detail"][0]["msg"]
    assert list(Path(api.settings.sequences_dir).glob("*/escaped.txt")) == []
    r = api.client.post("/v1/sequences/upload", content=b"not an archive", headers=api.h())
    assert r.status_code == 422 and "not a tar or zip" in r.json()["detail"][0]["msg"]


def test_upload_over_the_limit_is_413(api: Api) -> None:
    big = b"\0" * (api.settings.max_sequence_upload_bytes + 1)
    r = api.client.post("/v1/sequences/upload", content=big, headers=api.h())
    assert r.status_code == 413
    r = upload_asset(api, data=b"v 0 0 0\n" * 200_000)
    assert r.status_code == 413
    assert list((Path(api.settings.data_dir) / "tmp").glob("upload-*")) == []


def test_upload_over_the_limit_reads_a_bounded_number_of_bytes(api: Api) -> None:
    """Raw ASGI: a 64 MiB body without Content-Length; the app stops after the cap."""
    limit = api.settings.max_sequence_upload_bytes
    chunk = b"\0" * 65536
    pulled = 0

    async def receive() -> dict[str, Any]:
        nonlocal pulled
        pulled += len(chunk)
        return {"type": "http.request", "body": chunk, "more_body": pulled < 64 * 2**20}

    sent: list[dict[str, Any]] = []

    async def send(message: dict[str, Any]) -> None:
        sent.append(message)

    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": "/v1/sequences/upload",
        "raw_path": b"/v1/sequences/upload",
        "query_string": b"",
        "root_path": "",
        "headers": [(b"authorization", f"Bearer {api.keys['alice']}".encode())],
        "client": ("127.0.0.1", 1),
        "server": ("testserver", 80),
        "state": {},
    }
    asyncio.run(api.client.app(scope, receive, send))
    assert sent[0]["status"] == 413
    assert pulled <= limit + len(chunk)


def test_asset_upload_list_and_bad_meshes(api: Api) -> None:
    r = upload_asset(api)
    assert r.status_code == 201, r.text
    asset = r.json()
    assert (asset["vertices"], asset["faces"], asset["size"]) == (4, 4, len(TETRA_OBJ))
    listed = api.client.get("/v1/assets", headers=api.h()).json()
    assert asset["id"] in [a["id"] for a in listed["items"]]
    r = upload_asset(api, data=b"garbage that is no mesh", ft="glb")
    assert r.status_code == 422, r.text
    gltf = json.dumps({"asset": {"version": "2.0"}, "buffers": [{"uri": "file:///etc/passwd"}]})
    r = upload_asset(api, data=gltf.encode(), ft="gltf")
    assert r.status_code == 422 and "external uri" in r.json()["detail"][0]["msg"]
    r = upload_asset(api, ft="exe")
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "file_type"]


# ------------------------------------------------------------------------------ limits
def test_rate_limit_is_429_with_retry_after(tmp_path: Path, api: Api) -> None:
    from fastapi.testclient import TestClient

    from service.app import create_app

    settings = make_settings(tmp_path, str(api.settings.database_url)).model_copy(
        update={"rate_limit_per_s": 0.5, "rate_limit_burst": 3}
    )
    app = create_app(settings, celery_app=memory_celery())
    with TestClient(app) as client:
        codes = [client.get("/v1/sequences", headers=api.h()).status_code for _ in range(4)]
        assert codes == [200, 200, 200, 429]
        r = client.get("/v1/sequences", headers=api.h())
        assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1
        assert client.get("/v1/sequences", headers=api.h("bob")).status_code == 200  # per key
        assert client.get("/v1/health").status_code == 200
    app.state.engine.dispose()


def test_concurrent_jobs_per_key_is_429(api: Api) -> None:
    from osdar_platform.models import ApiKey
    from service.errors import TooManyRequests
    from service.schemas import JobCreate
    from service.services.jobs import create_job

    who = f"busy-{api.backend}"
    api.new_key(who)
    path = api.client.get(f"/v1/sequences/{api.sequence_id}", headers=api.h()).json()["path"]
    seq = api.client.post("/v1/sequences", json={"path": path}, headers=api.h(who)).json()["id"]
    settings = api.settings.model_copy(update={"max_concurrent_jobs_per_key": 2})
    spec = JobCreate.model_validate(api.job_spec(sequence_id=seq))
    with api.sessions() as session:
        owner = session.scalar(select(ApiKey).where(ApiKey.name == who))
        for _ in range(2):
            create_job(
                session=session, spec=spec, owner=owner, idempotency_key=None, settings=settings
            )
        with pytest.raises(TooManyRequests, match="at most 2"):
            create_job(
                session=session, spec=spec, owner=owner, idempotency_key=None, settings=settings
            )


# ------------------------------------------------------------------------------ layering
def test_the_service_imports_no_geometry() -> None:
    code = "import sys, json; import service.app; print(json.dumps(sorted(m for m in sys.modules)))"
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).parents[2],
        env={"OSDAR_AR_DATA_DIR": "/nonexistent/osdar-ar-import-test", "PATH": "/usr/bin"},
    )
    mods = set(json.loads(out.stdout))
    heavy = {"numpy", "scipy", "open3d", "cv2", "moderngl", "trimesh", "renderer", "celery"}
    heavy |= {"geometry", "worker.osdar", "worker.preparation.prepare", "worker.synth"}
    assert not (mods & heavy), sorted(mods & heavy)
    assert "fastapi" in mods and "osdar_platform.models" in mods


def test_registered_paths_must_lie_under_the_configured_roots(
    api: Api, synth_sequence_dir: Path, tmp_path: Path
) -> None:
    from osdar_platform.models import ApiKey
    from service.errors import Forbidden
    from service.services.sequences import register_sequence

    with api.sessions() as session:
        owner = session.scalar(select(ApiKey).where(ApiKey.name == "alice"))
        elsewhere = api.settings.model_copy(update={"sequence_roots": [tmp_path]})
        with pytest.raises(Forbidden, match="outside the folders"):
            register_sequence(
                session=session,
                owner=owner,
                path=str(synth_sequence_dir),
                name=None,
                settings=elsewhere,
            )
        escape = str(tmp_path / ".." / synth_sequence_dir.parent.name / synth_sequence_dir.name)
        with pytest.raises(Forbidden, match="outside the folders"):
            register_sequence(
                session=session, owner=owner, path=escape, name=None, settings=elsewhere
            )
        inside = api.settings.model_copy(update={"sequence_roots": [synth_sequence_dir.parent]})
        seq = register_sequence(
            session=session, owner=owner, path=str(synth_sequence_dir), name="x", settings=inside
        )
        assert seq.frames == 3


def test_results_are_served_only_once_the_job_succeeded(api: Api) -> None:
    """The gate is the state, not whether a result key or metrics happen to be set: a
    RUNNING job whose row already points at an archive (a stale or re-run attempt) serves
    no archive, metrics or previews, and its status says no result is available."""
    job = submit(api)
    publish_fake_result(api, job["id"], b"tar bytes")
    with api.sessions.begin() as s:
        s.execute(update(Job).where(Job.id == job["id"]).values(state=JobState.RUNNING))
    for what in ("archive", "metrics", "previews", "previews/0"):
        r = api.client.get(f"/v1/jobs/{job['id']}/{what}", headers=api.h())
        assert r.status_code == 409 and "RUNNING" in r.json()["detail"], (what, r.text)
    status = api.client.get(f"/v1/jobs/{job['id']}", headers=api.h()).json()
    assert status["result_available"] is False
    with api.sessions.begin() as s:
        s.execute(update(Job).where(Job.id == job["id"]).values(state=JobState.SUCCEEDED))
    assert api.client.get(f"/v1/jobs/{job['id']}/archive", headers=api.h()).content == b"tar bytes"
    assert api.client.get(f"/v1/jobs/{job['id']}/previews", headers=api.h()).json()


def test_405_allow_names_every_method_of_the_path(api: Api) -> None:
    """A 405 lists exactly the methods the path is served with, across routes: PUT
    /v1/jobs allows GET and POST (two routes); /v1/sequences/upload is POST only, not a
    sequence named "upload"."""
    cases = {
        ("PUT", "/v1/jobs"): "GET, POST",
        ("PATCH", "/v1/assets/abc"): "DELETE, GET",
        ("GET", "/v1/sequences/upload"): "POST",
        ("DELETE", "/v1/sequences/upload"): "POST",
        ("POST", "/v1/health"): "GET",
    }
    for (method, path), allow in cases.items():
        r = api.client.request(method, path, headers=api.h())
        assert r.status_code == 405 and r.headers["allow"] == allow, (method, path, r.headers)


def test_the_database_away_is_503_with_retry_after_never_500(tmp_path: Path) -> None:
    """PostgreSQL restarting (here: nothing listening): every route that needs the
    database answers 503 with Retry-After, health too; none answers 500."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from tests.conftest_service import make_settings, memory_celery
    from worker.orchestration.embedded import free_port

    url = f"postgresql+psycopg://nobody@127.0.0.1:{free_port()}/absent"
    app = create_app(make_settings(tmp_path, url), celery_app=memory_celery())
    with TestClient(app) as client:
        h = {"Authorization": "Bearer osk_not_checked_before_the_database"}
        for method, path in (
            ("GET", "/v1/health"),
            ("GET", "/v1/jobs"),
            ("GET", "/v1/jobs/abc"),
            ("POST", "/v1/jobs/abc/cancel"),
        ):
            r = client.request(method, path, headers=h)
            assert r.status_code == 503, (method, path, r.status_code, r.text)
            assert int(r.headers["retry-after"]) > 0


@pytest.mark.parametrize(
    ("method", "url", "body", "status"),
    [
        ("GET", "/v1/jobs/%00", None, 422),
        ("GET", "/v1/jobs/a%00b/archive", None, 422),
        ("GET", "/v1/assets/%00", None, 422),
        ("DELETE", "/v1/assets/%00", None, 422),
        ("GET", "/v1/sequences/%00", None, 404),  # no route: an id has no NUL
        ("GET", "/v1/jobs?sequence_id=%00", None, 422),
        ("POST", "/v1/jobs", {"sequence_id": "\u0000"}, 422),
        ("POST", "/v1/jobs", {"object": {"asset_id": "a\u0000"}}, 422),
        ("POST", "/v1/sequences", {"path": "/tmp/a\u0000b"}, 422),
    ],
)
def test_nul_characters_never_reach_the_database(
    api: Api, method: str, url: str, body: dict | None, status: int
) -> None:
    """Found by the dashboard fuzz: PostgreSQL refuses NUL in text, and an id or path with
    one was a 500. Ids have a pattern in the schema, paths refuse NUL: 4xx on both backends."""
    if url == "/v1/jobs" and body is not None:
        body = api.job_spec(**body)
    r = api.client.request(method, url, json=body, headers=api.h())
    assert r.status_code == status, r.text
