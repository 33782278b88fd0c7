"""GET /v1/health: no auth; checks the database."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse
from sqlalchemy import text

from service.errors import DATABASE_RETRY_AFTER_S
from service.schemas import Health

router = APIRouter(tags=["health"])
log = logging.getLogger(__name__)


@router.get(
    "/health",
    response_model=Health,
    responses={503: {"model": Health, "description": "The database is unreachable"}},
    summary="Liveness and database check",
)
def health(request: Request) -> Health | JSONResponse:
    try:
        with request.app.state.sessions() as session:
            session.execute(text("SELECT 1"))
    except Exception as exc:  # reported, not raised: health must answer
        log.warning("health: database: %s", exc)
        body = Health(status="degraded", database="unreachable", version=request.app.version)
        return JSONResponse(
            body.model_dump(),
            status_code=503,
            headers={"Retry-After": str(DATABASE_RETRY_AFTER_S)},
        )
    return Health(status="ok", database="ok", version=request.app.version)
