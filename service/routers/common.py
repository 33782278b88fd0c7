"""Pieces shared by the resource routers: paging parameters, error responses, bodies,
and the downloads of stored objects (``Range``, presigned redirects)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Header, Query, Request, Response

from osdar_platform.store import ObjectStore
from service.deps import SettingsDep, StoreDep
from service.downloads import download_object, download_responses, stream_object
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


RangeHeader = Annotated[str | None, Header(alias="Range", max_length=200)]


@dataclass(frozen=True)
class Downloads:
    """How a route serves a stored object once its ownership check has passed: the store,
    the request's ``Range`` and the lifetime of a presigned URL."""

    store: ObjectStore
    range_header: str | None
    ttl_s: int

    def send(self, key: str, *, media_type: str, filename: str | None = None) -> Response:
        """:func:`service.downloads.download_object`: 307 to a presigned URL where the store
        signs (S3), else streamed (``Range``: 206, 416)."""
        return download_object(
            self.store,
            key,
            range_header=self.range_header,
            media_type=media_type,
            filename=filename,
            ttl_s=self.ttl_s,
        )

    def stream(self, key: str, *, media_type: str) -> Response:
        """:func:`service.downloads.stream_object`: always streamed by the API."""
        return stream_object(self.store, key, range_header=self.range_header, media_type=media_type)


def _downloads(
    store: StoreDep, settings: SettingsDep, range_header: RangeHeader = None
) -> Downloads:
    return Downloads(store=store, range_header=range_header, ttl_s=settings.download_url_ttl_s)


DownloadsDep = Annotated[Downloads, Depends(_downloads)]


def download_route(media_type: str, *, summary: str, redirect: bool = True) -> dict[str, Any]:
    """Keyword arguments of ``router.get`` for a route answering with :class:`Downloads`:
    a raw response, documented as 200 / 206 / 416 (and 307 with ``redirect``), 404 for
    another key's object and 409 while it has no such file yet."""
    return {
        "response_model": None,
        "response_class": Response,
        "responses": {
            **download_responses(media_type, redirect=redirect),
            **NOT_FOUND,
            **CONFLICT,
        },
        "summary": summary,
    }
