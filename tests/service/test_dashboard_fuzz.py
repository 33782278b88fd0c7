"""The dashboard fuzz scenario (``scripts/reliability/dashboard_fuzz.py``).

Its checker is first shown to catch what it looks for on a deliberately broken app (a
500, an unescaped reflection, an off-site redirect, an HTML page without its CSP, a 405
without Allow); then the reduced scenario runs against the real dashboard on PostgreSQL
and Redis with a real finished job.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from fastapi.testclient import TestClient

from scripts.reliability.dashboard_fuzz import MARKER, Checker, dashboard_routes


def _broken_app() -> FastAPI:
    app = FastAPI()

    @app.get("/dashboard/echo")
    def echo(q: str = "") -> HTMLResponse:
        return HTMLResponse(
            f"<p>{q}</p>", headers={"Content-Security-Policy": "default-src 'self'"}
        )

    @app.get("/dashboard/boom")
    def boom() -> Response:
        raise RuntimeError("boom")

    @app.get("/dashboard/away")
    def away() -> RedirectResponse:
        return RedirectResponse("https://evil.example/x", status_code=303)

    @app.get("/dashboard/bare")
    def bare() -> HTMLResponse:
        return HTMLResponse("<p>no policy</p>")

    @app.get("/dashboard/no-allow")
    def no_allow() -> Response:
        return Response(status_code=405)

    return app


def test_the_checker_catches_each_violation() -> None:
    app = _broken_app()
    checker = Checker(app)
    with TestClient(app, raise_server_exceptions=False) as client:
        checker.send(client, "echo", "GET", "/dashboard/echo", params={"q": MARKER})
        checker.send(client, "echo", "GET", "/dashboard/echo", params={"q": "harmless"})
        checker.send(client, "boom", "GET", "/dashboard/boom")
        checker.send(client, "away", "GET", "/dashboard/away")
        checker.send(client, "bare", "GET", "/dashboard/bare")
        checker.send(client, "no-allow", "GET", "/dashboard/no-allow")
    counts = {k: len(v) for k, v in checker.violations.items()}
    assert counts == {
        "server_errors_5xx": 1,
        "missing_csp_on_html": 1,
        "unescaped_reflections": 1,
        "offsite_redirects": 1,
        "method_not_allowed_without_allow": 1,
        "transport_errors": 0,
    }
    assert [p for p, _ in dashboard_routes(app)] == sorted(
        f"/dashboard/{n}" for n in ("away", "bare", "boom", "echo", "no-allow")
    )


@pytest.mark.slow
def test_dashboard_fuzz_finds_no_server_error_or_leak(tmp_path: Path) -> None:
    from tests.orchestration.test_reliability import _scenario

    f = _scenario("dashboard_fuzz", tmp_path)
    assert f["routes_fuzzed"] == f["routes_mounted"] >= 13
    assert f["requests"] >= 40 * f["routes_mounted"]
    assert f["status_codes"].get(200, 0) > 0  # the logged-in pages were reached


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("OSDAR_FULL"), reason="full form: OSDAR_FULL=1")
def test_dashboard_fuzz_full_form(tmp_path: Path) -> None:
    from tests.orchestration.test_reliability import _scenario

    f = _scenario("dashboard_fuzz", tmp_path, quick=False)
    assert f["requests"] >= 400 * f["routes_mounted"]
