"""Downloads with an S3 store (moto's server on loopback): after the ownership check the
API answers 307 to a short-lived presigned URL and the store serves the bytes, Range
included, so a client resumes there; with the local store the API streams (tested in
test_service_api.py and tests/campaign/test_service_campaigns.py)."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlparse

import httpx
import pytest
from sqlalchemy import update

from osdar_platform.models import Campaign, CampaignState, Job, JobState
from tests.conftest_service import Api, make_settings, memory_celery

DATA = bytes(range(256)) * 4096  # 1 MiB


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@dataclass
class S3Api:
    api: Api
    job_id: str
    queued_job: str
    campaign_id: str


@pytest.fixture(scope="module")
def s3api(tmp_path_factory: pytest.TempPathFactory, synth_sequence_dir: Path) -> Iterator[S3Api]:
    from fastapi.testclient import TestClient
    from moto.server import ThreadedMotoServer

    from osdar_platform.migrate import upgrade
    from osdar_platform.store import S3Store
    from service.app import create_app

    port = _free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    data = tmp_path_factory.mktemp("s3_downloads")
    url = f"sqlite:///{data}/osdar-ar.db"
    upgrade(database_url=url)
    settings = make_settings(
        data,
        url,
        store_url="s3://dl-bucket/osdar",
        s3_endpoint_url=f"http://127.0.0.1:{port}",
        aws_access_key_id="testing",
        aws_secret_access_key="testing",
        download_url_ttl_s=120,
    )
    app = create_app(settings, celery_app=memory_celery())
    store = app.state.store
    assert isinstance(store, S3Store)
    store.create_bucket()
    try:
        with TestClient(app) as client:
            api = Api("sqlite", client, settings, app.state.sessions)
            api.new_key("alice")
            api.new_key("bob")
            r = client.post(
                "/v1/sequences", json={"path": str(synth_sequence_dir)}, headers=api.h()
            )
            api.sequence_id = r.json()["id"]
            done = client.post("/v1/jobs", json=api.job_spec(), headers=api.h()).json()["id"]
            queued = client.post("/v1/jobs", json=api.job_spec(), headers=api.h()).json()["id"]
            key = f"jobs/{done}/attempt-1/archive.tar.gz"
            store.put_bytes(key, DATA)
            with api.sessions.begin() as s:
                s.execute(
                    update(Job)
                    .where(Job.id == done)
                    .values(state=JobState.SUCCEEDED, result_key=key)
                )
                c = Campaign(
                    owner_id=_key_id(api),
                    name="c",
                    spec={},
                    state=CampaignState.PARTIAL,
                    manifest_json_key="campaigns/c1/manifest.json",
                    manifest_csv_key="campaigns/c1/manifest.csv",
                )
                s.add(c)
                s.flush()
                cid = c.id
            store.put_bytes("campaigns/c1/manifest.json", b'{"variants": []}')
            store.put_bytes("campaigns/c1/manifest.csv", b"variant,key\n")
            yield S3Api(api, done, queued, cid)
    finally:
        app.state.engine.dispose()
        server.stop()


def _key_id(api: Api) -> int:
    from osdar_platform.keys import find_api_key

    with api.sessions() as s:
        pepper = api.settings.api_key_pepper.get_secret_value()
        key = find_api_key(session=s, secret=api.keys["alice"], pepper=pepper)
        assert key is not None
        return key.id


def _redirect(r: Any) -> str:
    assert r.status_code == 307, r.text
    assert r.headers["Cache-Control"] == "no-store"
    location: str = r.headers["Location"]
    return location


def test_an_archive_download_redirects_to_a_short_lived_presigned_url(s3api: S3Api) -> None:
    api = s3api.api
    r = api.client.get(f"/v1/jobs/{s3api.job_id}/archive", headers=api.h(), follow_redirects=False)
    url = _redirect(r)
    q = parse_qs(urlparse(url).query)
    assert q["X-Amz-Expires"] == ["120"] and "X-Amz-Signature" in q
    assert urlparse(url).path.endswith(
        f"/dl-bucket/osdar/jobs/{s3api.job_id}/attempt-1/archive.tar.gz"
    )
    # the store serves it, without the API key
    whole = httpx.get(url)
    assert whole.status_code == 200 and whole.content == DATA
    assert "attachment" in whole.headers["Content-Disposition"]
    # (moto's server does not check signatures, so a forged one cannot be tested here)


def test_a_client_resumes_a_cut_download_with_range_at_the_store(s3api: S3Api) -> None:
    api = s3api.api
    url = _redirect(
        api.client.get(f"/v1/jobs/{s3api.job_id}/archive", headers=api.h(), follow_redirects=False)
    )
    got = b""
    with httpx.stream("GET", url) as r:  # the connection drops after 300 kB
        for chunk in r.iter_bytes(65536):
            got += chunk
            if len(got) >= 300_000:
                break
    rest = httpx.get(url, headers={"Range": f"bytes={len(got)}-"})
    assert rest.status_code == 206
    assert rest.headers["Content-Range"] == f"bytes {len(got)}-{len(DATA) - 1}/{len(DATA)}"
    assert got + rest.content == DATA


def test_the_ownership_and_succeeded_checks_come_before_any_redirect(s3api: S3Api) -> None:
    api = s3api.api
    other = api.client.get(
        f"/v1/jobs/{s3api.job_id}/archive", headers=api.h("bob"), follow_redirects=False
    )
    assert other.status_code == 404 and "Location" not in other.headers
    queued = api.client.get(
        f"/v1/jobs/{s3api.queued_job}/archive", headers=api.h(), follow_redirects=False
    )
    assert queued.status_code == 409 and "Location" not in queued.headers
    anon = api.client.get(f"/v1/jobs/{s3api.job_id}/archive", follow_redirects=False)
    assert anon.status_code == 401


def test_a_campaign_manifest_redirects_too(s3api: S3Api) -> None:
    api = s3api.api
    for name, body in (("manifest.json", b'{"variants": []}'), ("manifest.csv", b"variant,key\n")):
        r = api.client.get(
            f"/v1/campaigns/{s3api.campaign_id}/{name}", headers=api.h(), follow_redirects=False
        )
        assert httpx.get(_redirect(r)).content == body
        bob = api.client.get(
            f"/v1/campaigns/{s3api.campaign_id}/{name}",
            headers=api.h("bob"),
            follow_redirects=False,
        )
        assert bob.status_code == 404
