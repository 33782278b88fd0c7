"""Mounting the dashboard on the app: its pages, static files and the login redirect."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.responses import Response
from fastapi.staticfiles import StaticFiles

from service.dashboard.auth import BASE, LoginRequired, login_required_response
from service.dashboard.router import router

STATIC_DIR = Path(__file__).parent / "static"


def install_dashboard(app: FastAPI) -> None:
    """Mount the pages, their static files and the login redirect on ``app``."""
    app.include_router(router)
    app.mount(f"{BASE}/static", StaticFiles(directory=STATIC_DIR), name="dashboard-static")

    @app.exception_handler(LoginRequired)
    async def _login_required(request: Request, exc: LoginRequired) -> Response:
        return login_required_response(exc)


__all__ = ["install_dashboard"]
