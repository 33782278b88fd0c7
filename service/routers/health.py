"""GET /v1/health: no auth; checks the database."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Request
from sqlalchemy import text

from service.schemas import Health

router = APIRouter(tags=["health"])
log = logging.getLogger(__name__)


@router.get("/health", response_model=Health, summary="Liveness and database check")
def health(request: Request) -> Health:
    try:
        with request.app.state.sessions() as session:
            session.execute(text("SELECT 1"))
        db = "ok"
    except Exception as exc:  # reported, not raised: health must answer
        log.warning("health: database: %s", exc)
        db = "unreachable"
    return Health(
        status="ok" if db == "ok" else "degraded", database=db, version=request.app.version
    )
