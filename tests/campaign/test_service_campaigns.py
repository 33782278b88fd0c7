"""/v1/campaigns end to end on a tiny synthetic sequence (SQLite, local store): the API
records and checks a campaign, the worker's expansion stage (the real function the task
runs) prepares once, expands and makes the variant jobs, the jobs run inline (the real
stages), the last one finalizes the campaign (manifest JSON + CSV in the store).

Known answers: the dry run's variants are the embedded expansion's (same spec, same
variants, byte for byte); a redelivered expansion makes no variant twice; every variant
job reuses the campaign's one preparation; a failing variant fails alone (PARTIAL, its
reason in its row); cancelling before the expansion commits makes nothing.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select, update

from osdar_platform.models import CampaignState, Job, JobState
from tests.conftest_service import Api, memory_celery, sent_tasks, sqlite_api
from worker.campaign.expand import expand
from worker.campaign.service_expand import expand_campaign_stage
from worker.campaign.service_finalize import final_state, finalize_after_job
from worker.campaign.spec import CampaignSpec
from worker.campaign.variant import dump_variants
from worker.orchestration.queue import TASK_EXPAND_CAMPAIGN, TASK_RUN_JOB
from worker.orchestration.runner import run_job_inline
from worker.preparation.prepare import prepare

pytestmark = pytest.mark.gl

SEQ = {"scene": "fire_site", "frames": 6, "scale": 0.15, "lidar_density": 0.2, "seed": 3}


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Api]:
    with sqlite_api(tmp_path_factory.mktemp("campaign_api"), SEQ, "fire_camp") as a:
        yield a


def spec(api: Api, **kw: Any) -> dict[str, Any]:
    base: dict[str, Any] = {
        "name": "tiny",
        "seed": 11,
        "sequences": [{"id": api.sequence_id, "name": "fire"}],
        "obstacles": [{"builtin": "person"}, {"builtin": "rock"}],
        "placements": [{"zone": "track", "distance_m": [20, 45]}],
        "job": {"cameras": ["rgb_center"], "lidar": True, "strategy": "auto"},
    }
    return {**base, **kw}


def expand_now(api: Api, campaign_id: str) -> Any:
    """What the ``osdar_ar.campaign_expand`` task does (the jobs sent to the memory broker)."""
    return expand_campaign_stage(campaign_id, settings=api.settings, app=memory_celery())


def campaign_jobs(api: Api, campaign_id: str) -> list[Job]:
    with api.sessions() as s:
        rows = s.scalars(select(Job).where(Job.campaign_id == campaign_id).order_by(Job.id))
        return list(rows)


# ------------------------------------------------------------------------------ checks
@pytest.mark.parametrize(
    ("change", "loc"),
    [
        ({"sequences": [{"path": "/data/x"}]}, ["body", "sequences", 0, "path"]),
        ({"sequences": [{"id": "nope"}]}, ["body", "sequences", 0, "id"]),
        ({"job": {"cameras": ["rgb_left"]}}, ["body", "job", "cameras", 0]),
        ({"placements": [{"zone": "roof"}]}, ["body", "placements", 0, "rule", "zone"]),
        ({"obstacles": [{"asset_id": "a1b2"}]}, ["body", "obstacles", 0, "asset_id"]),
        ({"draws": 0}, ["body", "draws"]),
    ],
)
def test_a_bad_campaign_is_a_422_naming_the_field(
    api: Api, change: dict[str, Any], loc: list[Any]
) -> None:
    r = api.client.post("/v1/campaigns", json=spec(api, **change), headers=api.h())
    assert r.status_code == 422, r.text
    assert loc in [e["loc"] for e in r.json()["detail"]], r.json()
    assert not sent_tasks()


def test_another_keys_sequence_is_not_found_for_the_campaign(api: Api) -> None:
    r = api.client.post("/v1/campaigns", json=spec(api), headers=api.h("bob"))
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "sequences", 0, "id"]


# ------------------------------------------------------------------------------ dry run
def test_a_dry_run_returns_the_embedded_expansion_and_queues_nothing(api: Api) -> None:
    r = api.client.post("/v1/campaigns?dry_run=true", json=spec(api), headers=api.h())
    assert r.status_code == 202, r.text  # the wait is 0 here: poll
    cid = r.json()["id"]
    assert r.headers["Location"] == f"/v1/campaigns/{cid}"
    assert [t["task"] for t in sent_tasks()] == [TASK_EXPAND_CAMPAIGN]
    out = expand_now(api, cid)
    assert out.state == CampaignState.EXPANDED and out.sent == []
    body = api.client.get(f"/v1/campaigns/{cid}", headers=api.h()).json()
    assert body["state"] == "EXPANDED" and body["dry_run"]
    assert [v["id"] for v in body["variants"]] == ["v0000", "v0001"]
    assert all(v["job_id"] is None for v in body["variants"])
    assert campaign_jobs(api, cid) == []
    # the same variants as the embedded expansion on the same preparation
    folder = Path(
        api.client.get(f"/v1/sequences/{api.sequence_id}", headers=api.h()).json()["path"]
    )
    prepared = prepare(folder, cache_dir=api.settings.prepared_cache_dir)
    want = json.loads(
        dump_variants(expand(CampaignSpec.model_validate(spec(api)), {api.sequence_id: prepared}))
    )
    got = [{k: v[k] for k in ("index", "id", "key", "objects")} for v in body["variants"]]
    assert got == [{k: w[k] for k in ("index", "id", "key", "objects")} for w in want]
    res = body["variants"][0]["objects"][0]["resolved"]
    assert res["zone"] == "track" and 20.0 <= res["distance_first_view_m"] <= 45.0


# ------------------------------------------------------------------------------ a campaign
def test_a_campaign_runs_one_preparation_and_a_failing_variant_fails_alone(api: Api) -> None:
    body = spec(api, name="partial")
    h = api.h(**{"Idempotency-Key": "camp-1"})
    r = api.client.post("/v1/campaigns", json=body, headers=h)
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    # idempotent: the same key and spec is the same campaign; another spec a 409
    again = api.client.post("/v1/campaigns", json=body, headers=h)
    assert again.status_code == 200 and again.json()["id"] == cid
    other = api.client.post("/v1/campaigns", json={**body, "seed": 12}, headers=h)
    assert other.status_code == 409
    assert [t["args"] for t in sent_tasks()] == [[cid]]

    out = expand_now(api, cid)
    assert out.state == CampaignState.RUNNING and out.created == 2 and len(out.sent) == 2
    # a redelivered expansion (its worker killed after the commit) makes nothing twice
    again_out = expand_now(api, cid)
    assert again_out.created == 0
    jobs = campaign_jobs(api, cid)
    assert len(jobs) == 2
    assert {t["task"] for t in sent_tasks()} == {TASK_RUN_JOB}
    detail = api.client.get(f"/v1/campaigns/{cid}", headers=api.h()).json()
    assert detail["state"] == "RUNNING" and detail["progress"]["variants"] == 2
    by_variant = {v["id"]: v["job_id"] for v in detail["variants"]}
    # the second variant fails (the test hook of the job machinery), the first succeeds
    with api.sessions.begin() as s:
        job = s.get(Job, by_variant["v0001"])
        assert job is not None
        job.spec = {**job.spec, "_test": {"fail_in": "finish"}}
    for vid in ("v0000", "v0001"):
        run_job_inline(by_variant[vid], settings=api.settings)
        finalize_after_job(by_variant[vid], settings=api.settings)  # what the task does

    detail = api.client.get(f"/v1/campaigns/{cid}", headers=api.h()).json()
    assert detail["state"] == "PARTIAL", detail
    assert detail["progress"]["succeeded"] == 1 and detail["progress"]["failed"] == 1
    v0, v1 = detail["variants"]
    assert v0["state"] == "SUCCEEDED"
    assert v0["links"]["archive"] == f"/v1/jobs/{v0['job_id']}/archive"
    assert v1["state"] == "FAILED" and v1["error"] and v1["row"]["error"] == v1["error"]
    # one preparation: the campaign's expansion made it, both jobs reused it
    for j in campaign_jobs(api, cid):
        assert j.metrics is not None and j.metrics["preparation"]["reused"] is True, j.metrics
    # the manifest, JSON and CSV, with the gauge and the AR quality of the variant made
    m = api.client.get(detail["links"]["manifest_json"], headers=api.h())
    assert m.status_code == 200
    doc = m.json()
    assert doc["summary"] == {
        "variants": 2,
        "done": 1,
        "failed": 1,
        "cancelled": 0,
        "state": "PARTIAL",
    }
    row0 = doc["variants"][0]
    assert row0["state"] == "done" and row0["job_id"] == v0["job_id"]
    assert row0["gauge"] is not None and row0["archive_bytes"] > 0
    assert row0["quality"]["rgb_center"]["bound_px_median"] is not None
    assert doc["variants"][1]["state"] == "failed"
    c = api.client.get(detail["links"]["manifest_csv"], headers=api.h())
    rows = list(csv.DictReader(io.StringIO(c.text)))
    assert [r["variant"] for r in rows] == ["v0000", "v0001"]
    assert rows[0]["objects"] == "1" and rows[0]["class"] in ("person", "rock")
    # Range on the manifest and on a variant's archive (the local store streams)
    part = api.client.get(detail["links"]["manifest_json"], headers=api.h(Range="bytes=0-9"))
    assert part.status_code == 206 and part.content == m.content[:10]
    arch = api.client.get(v0["links"]["archive"], headers=api.h(Range="bytes=2-"))
    assert arch.status_code == 206 and int(arch.headers["Content-Range"].split("/")[1]) > 2
    # another key sees nothing of it
    assert api.client.get(f"/v1/campaigns/{cid}", headers=api.h("bob")).status_code == 404
    assert api.client.get(detail["links"]["manifest_csv"], headers=api.h("bob")).status_code == 404
    # an ended campaign cannot be cancelled
    assert api.client.post(f"/v1/campaigns/{cid}/cancel", headers=api.h()).status_code == 409


def test_a_campaign_is_listed_with_its_progress(api: Api) -> None:
    r = api.client.get("/v1/campaigns", headers=api.h())
    assert r.status_code == 200
    items = r.json()["items"]
    assert items and all(set(i["progress"]) >= {"variants", "succeeded", "fraction"} for i in items)
    assert api.client.get("/v1/campaigns", headers=api.h("bob")).json()["total"] == 0


# ------------------------------------------------------------------------------ cancel
def test_cancel_before_the_expansion_makes_nothing(api: Api) -> None:
    r = api.client.post("/v1/campaigns", json=spec(api, name="cancel-early"), headers=api.h())
    cid = r.json()["id"]
    c = api.client.post(f"/v1/campaigns/{cid}/cancel", headers=api.h())
    assert c.status_code == 202 and c.json()["state"] == "CANCELLED"
    out = expand_now(api, cid)  # the expansion message arrives afterwards
    assert out.state == CampaignState.CANCELLED and out.created == 0
    assert campaign_jobs(api, cid) == []


def test_cancel_a_running_campaign_cancels_its_variant_jobs(api: Api) -> None:
    r = api.client.post("/v1/campaigns", json=spec(api, name="cancel-late"), headers=api.h())
    cid = r.json()["id"]
    expand_now(api, cid)
    sent_tasks()
    c = api.client.post(f"/v1/campaigns/{cid}/cancel", headers=api.h())
    assert c.status_code == 202
    assert {j.state for j in campaign_jobs(api, cid)} == {JobState.CANCELLED}
    # the finalize task the API sent: the worker's function
    from worker.campaign.service_finalize import finalize_campaign

    assert finalize_campaign(cid, settings=api.settings) == CampaignState.CANCELLED
    body = api.client.get(f"/v1/campaigns/{cid}", headers=api.h()).json()
    assert body["state"] == "CANCELLED" and body["summary"]["cancelled"] == 2


def test_a_campaign_whose_rule_cannot_be_placed_fails_with_the_issue(api: Api) -> None:
    bad = spec(api, name="impossible", placements=[{"zone": "platform", "distance_m": [20, 45]}])
    cid = api.client.post("/v1/campaigns", json=bad, headers=api.h()).json()["id"]
    out = expand_now(api, cid)
    assert out.state == CampaignState.FAILED and out.created == 0
    body = api.client.get(f"/v1/campaigns/{cid}", headers=api.h()).json()
    assert body["state"] == "FAILED" and body["issues"] and "placements[0]" in body["error"]
    assert campaign_jobs(api, cid) == []


def test_final_state_of_the_variants() -> None:
    S, F, C = JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED
    assert final_state([S, S], False) == CampaignState.SUCCEEDED
    assert final_state([S, F], False) == CampaignState.PARTIAL
    assert final_state([S, C], True) == CampaignState.PARTIAL
    assert final_state([F, C], True) == CampaignState.CANCELLED
    assert final_state([F, F], False) == CampaignState.FAILED


def test_campaign_jobs_do_not_count_against_the_per_key_job_limit(api: Api) -> None:
    settings = api.client.app.state.settings
    with api.sessions() as s:
        before = {j.id: j.state for j in s.scalars(select(Job))}
    assert any(j.campaign_id for j in campaign_jobs_all(api))
    with api.sessions.begin() as s:
        s.execute(update(Job).where(Job.campaign_id.is_not(None)).values(state=JobState.QUEUED))
        s.execute(update(Job).where(Job.campaign_id.is_(None)).values(state=JobState.CANCELLED))
    limit, settings.max_concurrent_jobs_per_key = settings.max_concurrent_jobs_per_key, 1
    try:
        r = api.client.post("/v1/jobs", json=api.job_spec(), headers=api.h())
        assert r.status_code == 201, r.text
        r = api.client.post("/v1/jobs", json=api.job_spec(), headers=api.h())
        assert r.status_code == 429, r.text  # the limit holds for jobs of their own
    finally:
        settings.max_concurrent_jobs_per_key = limit
        with api.sessions.begin() as s:  # every other test's jobs as they were
            for job_id, state in before.items():
                s.execute(update(Job).where(Job.id == job_id).values(state=state))
            s.execute(
                update(Job).where(Job.id.not_in(list(before))).values(state=JobState.CANCELLED)
            )


def campaign_jobs_all(api: Api) -> list[Job]:
    with api.sessions() as s:
        return list(s.scalars(select(Job).where(Job.campaign_id.is_not(None))))


# ------------------------------------------------------------------------------ the CLI
@pytest.fixture(scope="module")
def live_url(api: Api) -> Iterator[str]:
    """The same app under uvicorn on loopback (the CLI speaks real HTTP to it)."""
    import threading
    import time

    import uvicorn

    from worker.orchestration.embedded import free_port

    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(
            api.client.app, host="127.0.0.1", port=port, log_level="warning", lifespan="off"
        )
    )
    thread = threading.Thread(target=server.run, name="campaign-api", daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)


def test_cli_submit_resolves_paths_and_download_resumes(
    api: Api, live_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import yaml

    from worker.cli import main

    folder = api.client.get(f"/v1/sequences/{api.sequence_id}", headers=api.h()).json()["path"]
    body = spec(api, name="cli", obstacles=[{"builtin": "cow"}])
    body["sequences"] = [{"path": folder, "name": "fire"}]
    body["placements"] = [{"zone": "track", "distance_m": [20, 45], "sequences": [folder]}]
    spec_file = tmp_path / "cli.yaml"
    spec_file.write_text(yaml.safe_dump(body))
    common = ["--url", live_url, "--key", api.keys["alice"]]
    sent_tasks()
    assert main(["campaign", "submit", str(spec_file), *common]) == 0
    cid = capsys.readouterr().out.strip().splitlines()[-1]
    row = api.client.get(f"/v1/campaigns/{cid}", headers=api.h()).json()
    # the path was resolved to the key's registered sequence, in the placement filter too
    assert row["spec"]["sequences"][0]["id"] == api.sequence_id
    assert row["spec"]["placements"][0]["sequences"] == [api.sequence_id]
    # a retried submit is the same campaign (the Idempotency-Key is the resolved spec's)
    assert main(["campaign", "submit", str(spec_file), *common]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == cid
    assert [t["args"] for t in sent_tasks()] == [[cid]]
    # bob has no such sequence: the CLI registers the folder for him
    assert (
        main(["campaign", "submit", str(spec_file), "--url", live_url, "--key", api.keys["bob"]])
        == 0
    )
    bob_cid = capsys.readouterr().out.strip().splitlines()[-1]
    bob = api.client.get(f"/v1/campaigns/{bob_cid}", headers=api.h("bob")).json()
    assert bob["spec"]["sequences"][0]["id"] != api.sequence_id

    # the download needs an ended campaign
    out = tmp_path / "dl"
    assert main(["campaign", "download", cid, "--out", str(out), *common]) == 2
    expand_now(api, cid)
    for job in campaign_jobs(api, cid):
        run_job_inline(job.id, settings=api.settings)
        finalize_after_job(job.id, settings=api.settings)
    assert main(["campaign", "download", cid, "--out", str(out), *common]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    (row0,) = manifest["variants"]
    archive = out / row0["archive"]
    data = archive.read_bytes()
    assert len(data) == row0["archive_bytes"] and (out / "manifest.csv").is_file()
    # a download cut in the middle resumes from the partial file (Range)
    archive.unlink()
    partial = archive.with_name(archive.name + ".partial")
    partial.write_bytes(data[: len(data) // 2])
    ranges: list[str] = []
    real_stream = __import__("httpx").Client.stream

    def spy(self: Any, method: str, url: Any, **kw: Any) -> Any:
        ranges.append((kw.get("headers") or {}).get("Range", ""))
        return real_stream(self, method, url, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("httpx.Client.stream", spy)
        assert main(["campaign", "download", cid, "--out", str(out), *common]) == 0
    assert f"bytes={len(data) // 2}-" in ranges
    assert archive.read_bytes() == data and not partial.exists()


# ------------------------------------------------------------------------------ dashboard
def _dashboard(api: Api, secret: str) -> Any:
    """A TestClient logged in to the dashboard with ``secret``."""
    import re

    from fastapi.testclient import TestClient

    client = TestClient(api.client.app)
    page = client.get("/dashboard/login")
    token = re.search(r'name="token" value="([^"]+)"', page.text)
    assert token is not None, page.text
    r = client.post(
        "/dashboard/login",
        data={"api_key": secret, "token": token.group(1), "next": "/dashboard/jobs"},
        follow_redirects=False,
    )
    assert r.status_code == 303, r.text
    return client


def _partial_campaign(api: Api) -> dict[str, Any]:
    items = api.client.get("/v1/campaigns?state=PARTIAL", headers=api.h()).json()["items"]
    assert items, "test_a_campaign_runs_one_preparation_and_a_failing_variant_fails_alone first"
    detail: dict[str, Any] = api.client.get(items[0]["links"]["self"], headers=api.h()).json()
    return detail


def test_the_campaign_page_shows_previews_and_a_quality_histogram(api: Api) -> None:
    import re

    c = _partial_campaign(api)
    alice = _dashboard(api, api.keys["alice"])
    listing = alice.get("/dashboard/campaigns")
    assert listing.status_code == 200 and f"/dashboard/campaigns/{c['id']}" in listing.text
    page = alice.get(f"/dashboard/campaigns/{c['id']}")
    assert page.status_code == 200
    svg = re.search(r"<svg class=\"histogram\".*?</svg>", page.text, re.S)
    assert svg is not None, page.text
    bars = re.findall(r'<rect x="[^"]+" y="[^"]+" width="[^"]+" height="([^"]+)"', svg.group(0))
    # one variant made (the other failed): one bar of full height, nine empty
    assert len(bars) == 10 and sorted(float(h) for h in bars)[-2:] == [0.0, 140.0]
    rpe = c["variants"][0]["row"]["quality"]["rgb_center"]["rpe_px_mean"]
    assert f"{rpe:.2f}" in page.text  # the table shows the manifest's value
    thumbs = re.findall(r'<img class="thumb" src="([^"]+)"', page.text)
    assert len(thumbs) == 1  # the failed variant has no preview
    png = alice.get(thumbs[0])
    assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
    # the job list links each variant job to its campaign
    jobs = alice.get("/dashboard/jobs")
    assert f'href="/dashboard/campaigns/{c["id"]}"' in jobs.text
    assert "Operations" not in jobs.text  # an ordinary key sees no operator panel


def test_an_ordinary_key_sees_only_its_own_and_an_operator_sees_everything(api: Api) -> None:
    import re

    from osdar_platform.keys import create_api_key

    c = _partial_campaign(api)
    job_id = c["variants"][0]["job_id"]
    bob = _dashboard(api, api.keys["bob"])
    assert bob.get(f"/dashboard/campaigns/{c['id']}").status_code == 404
    assert c["id"] not in bob.get("/dashboard/campaigns").text
    assert bob.get(f"/dashboard/jobs/{job_id}").status_code == 404
    assert job_id not in bob.get("/dashboard/jobs").text
    assert bob.get(f"/dashboard/api/jobs/{job_id}").status_code == 404

    with api.sessions.begin() as s:
        pepper = api.settings.api_key_pepper.get_secret_value()
        _, secret = create_api_key(session=s, name="ops", operator=True, pepper=pepper)
    ops = _dashboard(api, secret)
    assert ops.get(f"/dashboard/campaigns/{c['id']}").status_code == 200
    assert c["id"][:8] in ops.get("/dashboard/campaigns").text
    assert ops.get(f"/dashboard/jobs/{job_id}").status_code == 200
    assert ops.get(f"/dashboard/api/jobs/{job_id}").json()["state"] == "SUCCEEDED"
    assert ops.get(f"/dashboard/jobs/{job_id}/archive").status_code == 200
    page = ops.get("/dashboard/jobs").text
    assert "Operations" in page and job_id[:8] in page
    # the failure rate of the last 24 h, against the rows: FAILED / (SUCCEEDED + FAILED)
    with api.sessions() as s:
        states = [j.state for j in s.scalars(select(Job).where(Job.finished_at.is_not(None)))]
    ok, failed = states.count(JobState.SUCCEEDED), states.count(JobState.FAILED)
    assert failed > 0 and f"{100 * failed / (ok + failed):.1f} % ({failed} failed" in page
    # the memory broker has no worker to answer a ping: zero alive, said as such
    assert re.search(r'class="js-workers">0<', page), page
    # the operator's role is for the dashboard: the API still scopes it to its own objects
    as_ops = {"Authorization": f"Bearer {secret}"}
    assert api.client.get(f"/v1/campaigns/{c['id']}", headers=as_ops).status_code == 404


def test_a_lost_expansion_or_finalize_is_sent_again_when_the_campaign_is_read(api: Api) -> None:
    from datetime import timedelta

    from osdar_platform.models import Campaign, utcnow
    from worker.orchestration.queue import TASK_FINALIZE_CAMPAIGN

    ids = {}
    for name in ("lost-pending", "lost-expanding", "fresh-expanding"):
        r = api.client.post("/v1/campaigns", json=spec(api, name=name), headers=api.h())
        ids[name] = r.json()["id"]
    sent_tasks()
    long_ago = utcnow() - timedelta(hours=10)  # past the grace and any task's time limit
    with api.sessions.begin() as s:
        for name, state in (
            ("lost-pending", CampaignState.PENDING),
            ("lost-expanding", CampaignState.EXPANDING),
        ):
            s.execute(
                update(Campaign)
                .where(Campaign.id == ids[name])
                .values(state=state, updated_at=long_ago)
            )
        s.execute(
            update(Campaign)
            .where(Campaign.id == ids["fresh-expanding"])
            .values(state=CampaignState.EXPANDING)
        )
    for name in ids:
        api.client.get(f"/v1/campaigns/{ids[name]}", headers=api.h())
        api.client.get(f"/v1/campaigns/{ids[name]}", headers=api.h())  # a second read: no resend
    sent = sent_tasks()
    assert sorted(t["args"][0] for t in sent) == sorted(
        [ids["lost-pending"], ids["lost-expanding"]]
    )
    assert {t["task"] for t in sent} == {TASK_EXPAND_CAMPAIGN}
    # a RUNNING campaign whose variants all ended without a finalize: sent once
    expand_now(api, ids["lost-pending"])
    sent_tasks()
    for job in campaign_jobs(api, ids["lost-pending"]):
        api.client.post(f"/v1/jobs/{job.id}/cancel", headers=api.h())
    sent_tasks()
    api.client.get(f"/v1/campaigns/{ids['lost-pending']}", headers=api.h())
    api.client.get(f"/v1/campaigns/{ids['lost-pending']}", headers=api.h())
    assert [t["task"] for t in sent_tasks()] == [TASK_FINALIZE_CAMPAIGN]
