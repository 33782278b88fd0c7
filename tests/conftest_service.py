"""Fixtures of the job-service tests: a synthetic sequence, databases, the API client.

``api`` is parametrised over SQLite and PostgreSQL: every API test runs on both. The
PostgreSQL side gets a fresh schema in the ``test`` database per session, migrated with
Alembic and dropped afterwards (``OSDAR_AR_TEST_PG_URL`` overrides the server; without a
server the PostgreSQL cases skip, except under CI where they fail).
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

PG_CANDIDATES = (
    "postgresql+psycopg://postgres@127.0.0.1:5432/test",
    "postgresql+psycopg://root@127.0.0.1:5432/test",
)
SYNTH = {"scene": "fire_site", "frames": 3, "scale": 0.05, "lidar_density": 0.05}


@pytest.fixture(scope="session")
def synth_sequence_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3-frame synthetic OSDaR23 sequence (generated once per session)."""
    from worker.synth.generator import SynthConfig, generate

    folder = tmp_path_factory.mktemp("service_seq") / "fire_site_tiny"
    generate(folder, SynthConfig(**SYNTH))
    return folder


def _admin_pg_url() -> Any:
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    candidates = (
        [os.environ["OSDAR_AR_TEST_PG_URL"]] if "OSDAR_AR_TEST_PG_URL" in os.environ else []
    )
    errors = []
    for raw in [*candidates, *PG_CANDIDATES]:
        url = make_url(raw)
        engine = create_engine(url, connect_args={"connect_timeout": 3})
        try:
            with engine.connect() as conn:
                conn.execute(text("SELECT 1"))
            return url
        except Exception as exc:
            errors.append(f"{url.render_as_string()}: {exc}")
        finally:
            engine.dispose()
    msg = "PostgreSQL not reachable: " + "; ".join(errors)
    if os.environ.get("CI"):
        pytest.fail(msg)
    pytest.skip(msg)


@dataclass
class PgSchema:
    url: str  # with search_path set to the schema
    schema: str
    admin_url: Any


def make_pg_schema(prefix: str = "osdar_test") -> Iterator[PgSchema]:
    """A fresh schema in the test database, migrated; dropped at the end."""
    from sqlalchemy import create_engine, text

    from osdar_platform.migrate import upgrade

    admin = _admin_pg_url()
    schema = f"{prefix}_{uuid.uuid4().hex[:10]}"
    engine = create_engine(admin, pool_pre_ping=True)  # db_restart restarts the server
    with engine.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    url = admin.update_query_dict({"options": f"-csearch_path={schema}"})
    rendered = url.render_as_string(hide_password=False)
    try:
        upgrade(database_url=rendered)
        yield PgSchema(url=rendered, schema=schema, admin_url=admin)
    finally:
        with engine.begin() as conn:
            conn.execute(text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
        engine.dispose()


@pytest.fixture(scope="session")
def pg_schema() -> Iterator[PgSchema]:
    yield from make_pg_schema()


def memory_celery() -> Any:
    """A Celery app on kombu's in-memory broker (messages readable with ``sent_tasks``)."""
    from celery import Celery

    return Celery("osdar-ar-test", broker="memory://", set_as_current=False)


def sent_tasks() -> list[dict[str, Any]]:
    """Drain the in-memory 'celery' queue: [{"task", "id", "args", "priority"}]."""
    from kombu import Connection

    out = []
    with Connection("memory://") as conn:
        queue = conn.SimpleQueue("celery")
        try:
            while True:
                try:
                    msg = queue.get(block=False)
                except queue.Empty:
                    break
                h, pri = msg.headers, msg.properties.get("priority")
                out.append({"task": h["task"], "id": h["id"], "args": msg.payload[0],
                            "priority": pri})  # fmt: skip
                msg.ack()
        finally:
            queue.close()
    return out


@dataclass
class Api:
    """An app on one backend with two API keys and the synthetic sequence registered."""

    backend: str
    client: Any
    settings: Any
    sessions: Any
    keys: dict[str, str] = field(default_factory=dict)  # name -> secret
    sequence_id: str = ""

    def h(self, who: str = "alice", **extra: str) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.keys[who]}", **extra}

    def job_spec(self, **overrides: Any) -> dict[str, Any]:
        spec: dict[str, Any] = {
            "sequence_id": self.sequence_id,
            "cameras": ["rgb_center"],
            "lidar": True,
            "object": {"builtin": "cow", "scale": 1.0},
            "placement": {"mode": "track", "s": 30.0, "offset": 0.0, "yaw_deg": 90},
            "strategy": "ins",
            "frame_range": [0, 2],
        }
        spec.update(overrides)
        return spec

    def new_key(self, name: str) -> str:
        from osdar_platform.keys import create_api_key

        with self.sessions.begin() as session:
            _, secret = create_api_key(
                session=session,
                name=name,
                pepper=self.settings.api_key_pepper.get_secret_value(),
            )
        self.keys[name] = secret
        return secret


def make_settings(data_dir: Path, database_url: str, **extra: Any) -> Any:
    from osdar_platform.settings import Settings

    return Settings(
        data_dir=data_dir,
        database_url=database_url,
        broker_url="memory://",
        rate_limit_per_s=10_000,
        rate_limit_burst=100_000,
        max_concurrent_jobs_per_key=10_000,
        max_sequence_upload_bytes=5 * 1024 * 1024,
        max_asset_upload_bytes=1024 * 1024,
        **extra,
    )


@pytest.fixture(scope="session", params=["sqlite", "postgres"])
def api(
    request: pytest.FixtureRequest,
    tmp_path_factory: pytest.TempPathFactory,
    synth_sequence_dir: Path,
) -> Iterator[Api]:
    from fastapi.testclient import TestClient

    from osdar_platform.migrate import upgrade
    from service.app import create_app

    data_dir = tmp_path_factory.mktemp(f"api_{request.param}")
    if request.param == "sqlite":
        url = f"sqlite:///{data_dir}/osdar-ar.db"
        upgrade(database_url=url)
    else:
        url = request.getfixturevalue("pg_schema").url
    settings = make_settings(data_dir, url)
    app = create_app(settings, celery_app=memory_celery())
    with TestClient(app) as client:
        api = Api(request.param, client, settings, app.state.sessions)
        api.new_key("alice")
        api.new_key("bob")
        r = client.post("/v1/sequences", json={"path": str(synth_sequence_dir)}, headers=api.h())
        assert r.status_code == 201, r.text
        api.sequence_id = r.json()["id"]
        sent_tasks()  # start from an empty queue
        yield api
    app.state.engine.dispose()


@contextmanager
def sqlite_api(data: Path, seq: dict[str, Any], name: str) -> Iterator[Api]:
    """An app on SQLite (environment "test", the memory broker) with keys ``alice`` and
    ``bob`` and a synthetic sequence ``data/name`` (SynthConfig ``seq``) registered by
    alice: the campaign and multi-object tests, whose jobs run inline."""
    from fastapi.testclient import TestClient

    from osdar_platform.migrate import upgrade
    from service.app import create_app
    from worker.synth.generator import SynthConfig, generate

    generate(data / name, SynthConfig(**seq))
    url = f"sqlite:///{data}/osdar-ar.db"
    upgrade(database_url=url)
    settings = make_settings(data, url, environment="test", campaign_dry_run_wait_s=0.0)
    app = create_app(settings, celery_app=memory_celery())
    with TestClient(app) as client:
        a = Api("sqlite", client, settings, app.state.sessions)
        a.new_key("alice")
        a.new_key("bob")
        r = client.post("/v1/sequences", json={"path": str(data / name)}, headers=a.h())
        assert r.status_code == 201, r.text
        a.sequence_id = r.json()["id"]
        sent_tasks()
        yield a
    app.state.engine.dispose()
