"""The FastAPI application: ``create_app(settings)`` and the module-level ``app``.

Run: ``osdar-ar migrate && uvicorn service.app:app``. Building the app opens no
connection; the database and the store are reached per request.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import APIRouter, FastAPI

from osdar_platform.db import make_engine, make_sessionmaker
from osdar_platform.migrate import upgrade
from osdar_platform.settings import Settings, get_settings
from osdar_platform.store import store_from_url
from service.dashboard.mount import install_dashboard
from service.deps import Dispatcher
from service.errors import install_handlers
from service.ratelimit import TokenBuckets
from service.routers import assets, campaigns, health, jobs, sequences

log = logging.getLogger(__name__)
VERSION = "0.1.0"

DESCRIPTION = """\
Augmented railway perception data: place a virtual obstacle into an OSDaR23 sequence
(both front cameras and the lidar), get the augmented sequence, annotations and AR-quality
metrics back.

Every route but `/v1/health` needs an API key (`Authorization: Bearer <key>` or
`X-API-Key`). Another key's objects answer 404. Errors are `{"detail": ...}`; 422 lists
`{"loc", "msg", "type"}` items naming the field at fault.
"""


def create_app(
    settings: Settings | None = None, *, celery_app: Any = None, migrate: bool = False
) -> FastAPI:
    """Build the API for ``settings`` (default: the environment's).

    ``celery_app`` replaces ``worker.orchestration.celery_app`` for sending jobs (tests use one on
    an in-memory broker); ``migrate=True`` runs ``alembic upgrade head`` at startup (the
    embedded one-machine mode; deployments run ``osdar-ar migrate`` as a prestart step).
    """
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if migrate:
            upgrade(database_url=str(settings.database_url))
        yield
        app.state.engine.dispose()

    app = FastAPI(
        title="osdar-ar",
        version=VERSION,
        description=DESCRIPTION,
        lifespan=lifespan,
        openapi_url="/v1/openapi.json",
        docs_url="/v1/docs",
        redoc_url=None,
    )
    engine = make_engine(str(settings.database_url))
    app.state.settings = settings
    app.state.engine = engine
    app.state.sessions = make_sessionmaker(engine)
    app.state.store = store_from_url(str(settings.store_url), settings)
    app.state.limiter = TokenBuckets(settings.rate_limit_per_s, settings.rate_limit_burst)
    app.state.dispatcher = Dispatcher(sessions=app.state.sessions, celery_app=celery_app)
    install_handlers(app)
    v1 = APIRouter(prefix="/v1")
    for module in (health, sequences, assets, jobs, campaigns):
        v1.include_router(module.router)
    app.include_router(v1)
    install_dashboard(app)
    return app


app = create_app()
