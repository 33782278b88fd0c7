"""Pieces shared by the resource routers: paging parameters, error responses, bodies."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Query, Request

from service.schemas import Problem, ValidationProblem

Limit = Annotated[int, Query(ge=1, le=100, description="page size")]
Offset = Annotated[int, Query(ge=0, le=10_000_000, description="items to skip")]

AUTH_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": Problem, "description": "Missing or invalid API key"},
    429: {"model": Problem, "description": "Rate limit or concurrent-job limit"},
}
NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {"model": Problem, "description": "No such object for this API key"}
}
INVALID: dict[int | str, dict[str, Any]] = {
    422: {"model": ValidationProblem, "description": "What is wrong, and where"}
}
CONFLICT: dict[int | str, dict[str, Any]] = {409: {"model": Problem, "description": "Conflict"}}
FORBIDDEN: dict[int | str, dict[str, Any]] = {
    403: {"model": Problem, "description": "Outside what this service may read"}
}
BAD_REQUEST: dict[int | str, dict[str, Any]] = {
    400: {"model": Problem, "description": "A body that cannot be read (empty, not JSON)"}
}
TOO_LARGE: dict[int | str, dict[str, Any]] = {
    413: {"model": Problem, "description": "Body over the size limit"}
}


def binary_body(media_types: list[str], description: str) -> dict[str, Any]:
    """``openapi_extra`` for a route that streams the raw request body."""
    schema = {"type": "string", "format": "binary", "minLength": 1}
    return {
        "requestBody": {
            "required": True,
            "description": description,
            "content": {mt: {"schema": schema} for mt in media_types},
        }
    }


def content_length(request: Request) -> int | None:
    raw = request.headers.get("content-length")
    try:
        return int(raw) if raw is not None else None
    except ValueError:
        return None
