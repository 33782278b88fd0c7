"""Dependencies of the routes, as ``Annotated`` aliases: settings, DB session, store,
the job dispatcher and the authenticated API key (with its rate limit)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session, sessionmaker

from osdar_platform.keys import find_api_key
from osdar_platform.models import ApiKey, JobState
from osdar_platform.settings import Settings
from osdar_platform.store import ObjectStore
from service.errors import TooManyRequests, Unauthorized
from service.ratelimit import TokenBuckets
from worker.orchestration.queue import (
    TASK_EXPAND_CAMPAIGN,
    TASK_FINALIZE_CAMPAIGN,
    broker_overview,
    enqueue_job,
    request_cancel,
    send_task,
)


@dataclass
class Dispatcher:
    """Hands committed jobs to the workers and cancels them (``worker.orchestration.queue``)."""

    sessions: sessionmaker[Session]
    celery_app: Any = None  # None: worker.orchestration.celery_app, imported on first use

    def enqueue(self, job_id: str) -> None:
        enqueue_job(job_id, sessions=self.sessions, app=self.celery_app)

    def cancel(self, job_id: str) -> JobState | None:
        return request_cancel(job_id, sessions=self.sessions, app=self.celery_app)

    def send_expand(self, campaign_id: str) -> None:
        """A campaign's expansion (worker/campaign/service_expand.py)."""
        send_task(TASK_EXPAND_CAMPAIGN, [campaign_id], app=self.celery_app)

    def broker(self) -> dict[str, Any]:
        """Workers answering a ping and the job queue's depth (an operator's dashboard)."""
        return broker_overview(app=self.celery_app, timeout_s=1.0)

    def send_finalize(self, campaign_id: str) -> None:
        """A campaign's manifest and end state (worker/campaign/service_finalize.py)."""
        send_task(TASK_FINALIZE_CAMPAIGN, [campaign_id], app=self.celery_app)


def _settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


def _session(request: Request) -> Iterator[Session]:
    with request.app.state.sessions() as session:
        yield session


def _store(request: Request) -> ObjectStore:
    store: ObjectStore = request.app.state.store
    return store


def _dispatcher(request: Request) -> Dispatcher:
    dispatcher: Dispatcher = request.app.state.dispatcher
    return dispatcher


SettingsDep = Annotated[Settings, Depends(_settings)]
SessionDep = Annotated[Session, Depends(_session)]
StoreDep = Annotated[ObjectStore, Depends(_store)]
DispatcherDep = Annotated[Dispatcher, Depends(_dispatcher)]

_bearer = HTTPBearer(auto_error=False, description="API key as `Authorization: Bearer <key>`")
_header = APIKeyHeader(name="X-API-Key", auto_error=False, description="API key")


def _current_key(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)] = None,
    header_key: Annotated[str | None, Security(_header)] = None,
) -> ApiKey:
    secret = bearer.credentials if bearer is not None else header_key
    if not secret:
        raise Unauthorized("missing API key: send 'Authorization: Bearer <key>' or 'X-API-Key'")
    key = find_api_key(
        session=session, secret=secret, pepper=settings.api_key_pepper.get_secret_value()
    )
    if key is None:
        raise Unauthorized("invalid or revoked API key")
    limiter: TokenBuckets = request.app.state.limiter
    wait = limiter.take(key.id)
    if wait > 0:
        raise TooManyRequests("rate limit exceeded for this API key", retry_after_s=wait)
    return key


CurrentKey = Annotated[ApiKey, Depends(_current_key)]
