"""Resource limits over real HTTP: 413 past the body cap with bounded bytes read, 429s.

- A sequence upload and a mesh upload far over their caps, streamed chunked (no
  Content-Length): 413, and the bytes the app pulled from the connection (counted by an
  ASGI wrapper around the app) stay within the cap plus one body message (uvicorn hands
  the body over as the socket delivers it: at most one read, 256 KiB).
- The same with a declared Content-Length over the cap: 413 before any body byte is read.
- A burst of requests over the per-key rate limit: 429 with Retry-After; another key and
  /v1/health are unaffected.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import httpx
import uvicorn
from celery import Celery

from scripts.reliability import common as c
from service.app import create_app

NAME = "limits"
MiB = 2**20


class CountingApp:
    """ASGI wrapper: bytes of request bodies the app pulled, per path."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self.pulled: dict[str, int] = {}
        self.largest_message = 0  # uvicorn hands the body over as the socket delivers it
        self.state = app.state

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        path = scope["path"]
        self.pulled[path] = 0

        async def counted() -> Any:
            msg = await receive()
            n = len(msg.get("body", b""))
            self.pulled[path] += n
            self.largest_message = max(self.largest_message, n)
            return msg

        return await self.app(scope, counted, send)


def run(workdir: Path, *, quick: bool = False, seed: int = 0) -> dict[str, Any]:

    body_mib = 32 if quick else 256
    burst = 10
    with c.pg_database() as db:
        settings = c.reliability_settings(
            workdir / "var",
            database_url=db,
            broker_url="memory://",
            max_sequence_upload_bytes=4 * MiB,
            max_asset_upload_bytes=1 * MiB,
            rate_limit_per_s=2.0,
            rate_limit_burst=burst,
        )
        alice, bob = c.new_api_key(settings, "alice"), c.new_api_key(settings, "bob")
        figures: dict[str, Any] = {}
        server = _CountingServer(settings, counting_factory=CountingApp)
        with server:
            counting = server.counting
            chunk = b"\0" * (64 * 1024)
            sent = {"n": 0}

            def gen() -> Any:
                for _ in range(body_mib * MiB // len(chunk)):
                    sent["n"] += len(chunk)
                    yield chunk

            cases = {
                "sequence_upload": ("/v1/sequences/upload", {}, settings.max_sequence_upload_bytes),
                "asset_upload": (
                    "/v1/assets",
                    {"name": "big", "file_type": "obj"},
                    settings.max_asset_upload_bytes,
                ),
            }
            for name, (path, params, limit) in cases.items():
                sent["n"] = 0
                with httpx.Client(
                    base_url=server.url, timeout=60, headers={"Authorization": f"Bearer {alice}"}
                ) as h:
                    try:
                        r = h.post(path, params=params, content=gen())
                        status = r.status_code
                    except httpx.HTTPError as exc:  # server closed while we were sending
                        status = f"closed ({type(exc).__name__})"
                figures[f"{name}_status"] = status
                figures[f"{name}_limit_bytes"] = limit
                figures[f"{name}_bytes_read_by_app"] = counting.pulled.get(path, -1)
                figures[f"{name}_bytes_client_sent"] = sent["n"]
                # declared too large: refused before reading
                with httpx.Client(
                    base_url=server.url, timeout=60, headers={"Authorization": f"Bearer {alice}"}
                ) as h:
                    r = h.post(path, params=params, content=b"\0" * (limit + 1))
                figures[f"{name}_declared_status"] = r.status_code
                figures[f"{name}_declared_bytes_read_by_app"] = counting.pulled.get(path, -1)
            figures["largest_body_message_bytes"] = counting.largest_message
            tmp_left = list((Path(settings.data_dir) / "tmp").glob("upload-*"))
            figures["partial_upload_files_left"] = len(tmp_left)
            # rate limit: burst + 20 requests as fast as possible
            with server.client(alice) as a, server.client(bob) as b:
                codes = [a.get("/v1/sequences").status_code for _ in range(burst + 20)]
                r = a.get("/v1/sequences")
                figures["rate_burst"] = burst
                figures["rate_requests"] = len(codes) + 1
                figures["rate_200"] = codes.count(200)
                figures["rate_429"] = codes.count(429) + (r.status_code == 429)
                figures["rate_retry_after_s"] = r.headers.get("retry-after")
                figures["rate_other_key_status"] = b.get("/v1/sequences").status_code
                figures["rate_health_status"] = a.get("/v1/health").status_code
                figures["rate_5xx"] = sum(1 for x in codes if x >= 500)
    return figures


class _CountingServer(c.ApiServer):
    def __init__(self, settings: Any, counting_factory: Any) -> None:

        super().__init__(settings, celery_app=Celery("l", broker="memory://", set_as_current=False))
        self.counting_factory = counting_factory
        self.counting: Any = None

    def __enter__(self) -> _CountingServer:

        self.app = create_app(self.settings, celery_app=self.celery_app)
        self.counting = self.counting_factory(self.app)
        config = uvicorn.Config(self.counting, host="127.0.0.1", port=self.port, log_level="error")
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._server.run, daemon=True)
        self._thread.start()
        c.wait_for(lambda: self._server.started, 30, "the API", every=0.05)
        return self


def ok(f: dict[str, Any]) -> bool:
    good = f["rate_429"] >= 1 and f["rate_other_key_status"] == 200 and f["rate_5xx"] == 0
    good &= f["rate_health_status"] == 200 and f["rate_200"] <= f["rate_burst"] + 1
    good &= f["partial_upload_files_left"] == 0
    for name in ("sequence_upload", "asset_upload"):
        status = f[f"{name}_status"]
        good &= status == 413 or str(status).startswith("closed")
        bound = f[f"{name}_limit_bytes"] + f["largest_body_message_bytes"]
        good &= 0 <= f[f"{name}_bytes_read_by_app"] <= bound
        good &= f[f"{name}_declared_status"] == 413
        good &= f[f"{name}_declared_bytes_read_by_app"] == 0
    return bool(good)


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
