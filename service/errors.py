"""Errors the service functions raise, and how the API turns them into responses.

Service functions raise :class:`ServiceError` subclasses (no HTTP knowledge in them
beyond a status code); the handlers installed by :func:`install_handlers` write
``{"detail": "..."}`` or, for 422, FastAPI's ``{"detail": [{"loc", "msg", "type"}]}``.
Anything else becomes a plain 500 without a stack trace (logged on the server).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DisconnectionError, OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

log = logging.getLogger(__name__)


class ServiceError(Exception):
    status_code = 400

    def __init__(self, message: str, *, headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.headers = headers

    def body(self) -> dict[str, Any]:
        return {"detail": self.message}


class BadRequest(ServiceError):
    status_code = 400


class Forbidden(ServiceError):
    """The request is understood and authenticated, but this service may not do it (a
    folder outside the configured sequence roots)."""

    status_code = 403


class NotFound(ServiceError):
    status_code = 404


class Conflict(ServiceError):
    status_code = 409


class PayloadTooLarge(ServiceError):
    status_code = 413


class TooManyRequests(ServiceError):
    status_code = 429

    def __init__(self, message: str, *, retry_after_s: float) -> None:
        super().__init__(message, headers={"Retry-After": str(max(1, round(retry_after_s + 0.5)))})


class Invalid(ServiceError):
    """422 naming the field: ``loc`` as in FastAPI's validation errors."""

    status_code = 422

    def __init__(self, message: str, *, loc: tuple[str | int, ...] = ("body",)) -> None:
        super().__init__(message)
        self.errors = [{"loc": list(loc), "msg": message, "type": "value_error"}]

    @classmethod
    def many(cls, errors: list[tuple[tuple[str | int, ...], str]]) -> Invalid:
        exc = cls(errors[0][1], loc=errors[0][0])
        exc.errors = [{"loc": list(loc), "msg": msg, "type": "value_error"} for loc, msg in errors]
        return exc

    def body(self) -> dict[str, Any]:
        return {"detail": self.errors}


class Unauthorized(ServiceError):
    status_code = 401

    def __init__(self, message: str) -> None:
        super().__init__(message, headers={"WWW-Authenticate": "Bearer"})


def _plain_errors(errors: Any) -> list[dict[str, Any]]:
    """loc/msg/type of each validation error; the input is not echoed back (it may be huge,
    or hold NaN, which JSON cannot carry)."""
    out = []
    for e in errors:
        loc = [x if isinstance(x, int) else str(x) for x in e.get("loc", ())]
        out.append({"loc": loc, "msg": str(e.get("msg", "invalid")), "type": str(e.get("type"))})
    return out


#: Retry-After (s) of a 503 while the database is away (a restart takes seconds).
DATABASE_RETRY_AFTER_S = 5

#: The methods a 405's Allow header may name.
HTTP_METHODS = ("DELETE", "GET", "HEAD", "OPTIONS", "PATCH", "POST", "PUT")


def allowed_methods(app: FastAPI, scope: Mapping[str, Any]) -> list[str]:
    """Every method some route of ``app`` fully matches the request's path with (the
    routers' own matching, nested routers included), sorted."""
    out = []
    for method in HTTP_METHODS:
        probe = {**scope, "method": method}
        if any(route.matches(probe)[0] == Match.FULL for route in app.router.routes):
            out.append(method)
    return out


def install_handlers(app: FastAPI) -> None:
    @app.exception_handler(RequestValidationError)
    async def _invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": _plain_errors(exc.errors())}, status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            # Starlette's Allow names the methods of the first route on this path only;
            # a path served by several routes (GET and POST /v1/jobs) allows them all.
            headers["Allow"] = ", ".join(allowed_methods(request.app, request.scope))
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=headers)

    @app.exception_handler(OperationalError)
    @app.exception_handler(DisconnectionError)
    async def _database_away(request: Request, exc: Exception) -> JSONResponse:
        # The database restarting or unreachable: the request was fine, try again shortly
        # (never a 500; nothing was half-done: every write is one transaction).
        log.warning("database unavailable on %s %s: %s", request.method, request.url.path, exc)
        return JSONResponse(
            {"detail": "the database is unavailable; retry shortly"},
            status_code=503,
            headers={"Retry-After": str(DATABASE_RETRY_AFTER_S)},
        )

    @app.exception_handler(ServiceError)
    async def _service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse(exc.body(), status_code=exc.status_code, headers=exc.headers)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return JSONResponse({"detail": "internal error"}, status_code=500)
