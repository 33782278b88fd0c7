"""Fuzz every dashboard route: hostile path, query, form, cookie and header values.

The dashboard is not in the OpenAPI document, so schemathesis does not reach it. Here the
app runs on PostgreSQL with a Redis broker and a prefork worker that finishes one real job
(metrics, previews, archive) while a second stays queued; then hypothesis draws requests
for every route the app mounts under ``/dashboard`` (the list is read from the app, so a
new route is fuzzed without editing this file): ids that exist, belong to another key or
are any unicode, offsets and indices far out of range, unknown states, login forms with
forged tokens and ``next`` values aiming off-site, forged session cookies, odd methods and
Range headers, as Alice, as Bob, and without a session.

Every response is checked: no 5xx; an HTML page carries its Content-Security-Policy;
input is never reflected unescaped (a ``<script>`` marker sent in any field never comes
back raw); a redirect never leaves the dashboard (``Location`` on the same host, under
``/dashboard``); a 405 says what is allowed (``Allow``). Figures: routes fuzzed of routes
mounted, requests, status codes, and each violation count with up to ten examples.
"""

from __future__ import annotations

import re
import string
import urllib.parse
from collections import Counter
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import seed as hypothesis_seed
from hypothesis import strategies as st
from starlette.routing import Mount, Route

from scripts.reliability import common as c
from service.app import create_app
from service.dashboard.auth import BASE, LOGIN_COOKIE, SESSION_COOKIE
from worker.orchestration.celery_app import make_celery

NAME = "dashboard_fuzz"
MARKER = "<script>osdar_fuzz()</script>"
METHODS = ["GET", "POST", "PUT", "DELETE", "PATCH", "HEAD", "OPTIONS"]
#: Values a careless page mishandles, beside what hypothesis draws.
NASTY = [
    "", " ", "0", "-1", "1e309", "NaN", "18446744073709551617", "%00", "\x00", "../../etc/passwd",
    "..%2F..%2Fetc%2Fpasswd", "//evil.example/x", "https://evil.example/", "javascript:alert(1)",
    "/dashboard/../v1/jobs", "\\\\evil.example", MARKER, '"><img src=x onerror=alert(1)>',
    "x" * 5000, "é" * 300, "\ud7ff\ue000", "SUCCEEDED", "succeeded",
]  # fmt: skip


def _text() -> st.SearchStrategy[str]:
    return st.one_of(
        st.sampled_from(NASTY),
        st.text(max_size=80),
        st.text(alphabet=string.ascii_letters + string.digits + "-_", max_size=70),
    )


class Checker:
    """Sends requests and counts statuses and violations."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self.codes: Counter[int] = Counter()
        self.by_route: Counter[str] = Counter()
        self.violations: dict[str, list[str]] = {
            "server_errors_5xx": [],
            "missing_csp_on_html": [],
            "unescaped_reflections": [],
            "offsite_redirects": [],
            "method_not_allowed_without_allow": [],
            "transport_errors": [],
        }

    def _bad(self, kind: str, what: str) -> None:
        self.violations[kind].append(what[:300])

    def send(self, client: TestClient, route: str, method: str, url: str, **kw: Any) -> None:
        self.by_route[route] += 1
        what = f"{method} {url[:200]}"
        try:
            r = client.request(method, url, follow_redirects=False, **kw)
        except Exception as exc:  # the app raised through the transport
            self._bad("transport_errors", f"{what}: {type(exc).__name__}: {exc}")
            self.codes[599] += 1
            return
        self.codes[r.status_code] += 1
        if r.status_code >= 500:
            self._bad("server_errors_5xx", f"{what} -> {r.status_code}")
        if r.status_code == 405 and "allow" not in r.headers:
            self._bad("method_not_allowed_without_allow", what)
        ctype = r.headers.get("content-type", "")
        if ctype.startswith("text/html"):
            if "content-security-policy" not in r.headers:
                self._bad("missing_csp_on_html", what)
            if MARKER in r.text:
                self._bad("unescaped_reflections", what)
        if 300 <= r.status_code < 400:
            loc = urllib.parse.urlsplit(r.headers.get("location", ""))
            own_host = loc.netloc in ("", urllib.parse.urlsplit(str(r.request.url)).netloc)
            inside = loc.path == BASE or loc.path.startswith(f"{BASE}/")
            if not (own_host and inside) or loc.path.startswith("//"):
                self._bad("offsite_redirects", f"{what} -> {loc.geturl()}")


def dashboard_routes(app: Any) -> list[tuple[str, set[str]]]:
    """(path template, methods) of every route mounted under the dashboard."""
    out: list[tuple[str, set[str]]] = []

    def walk(routes: list[Any]) -> None:
        for r in routes:
            if isinstance(r, Route) and r.path.startswith(BASE):
                out.append((r.path, set(r.methods or ())))
            elif isinstance(r, Mount) and r.path.startswith(BASE):
                out.append((f"{r.path}/{{path}}", {"GET"}))
            elif hasattr(r, "original_router"):  # FastAPI >= 0.165 wraps included routers
                walk(list(r.original_router.routes))

    walk(list(app.routes))
    merged: dict[str, set[str]] = {}
    for path, methods in out:  # GET and POST /login are two routes of one path
        merged.setdefault(path, set()).update(methods)
    return sorted(merged.items())


def _ascii(text: str) -> str:
    """What an HTTP client can put in a header or cookie (printable ASCII, no CR/LF)."""
    return "".join(ch for ch in text if 32 <= ord(ch) < 127)


def _fill(template: str, values: dict[str, str]) -> str:
    path = template
    for name, value in values.items():
        path = path.replace("{" + name + "}", urllib.parse.quote(value, safe=""))
    return path


def _params(template: str) -> list[str]:
    return [p.split("}")[0].split(":")[0] for p in template.split("{")[1:]]


def run(workdir: Path, *, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    examples = 40 if quick else 400
    seq = c.synth_sequence(workdir / "seq" / "fire_site_rel")
    with c.pg_database() as db, c.redis_db() as broker:
        cfg = c.reliability_settings(workdir / "var", database_url=db, broker_url=broker)
        alice, bob = c.new_api_key(cfg, "alice"), c.new_api_key(cfg, "bob")
        app = create_app(cfg, celery_app=make_celery(cfg))
        workers = c.Workers(cfg, workdir / "worker.log", concurrency=1)
        h = {"Authorization": f"Bearer {alice}"}
        with TestClient(app, raise_server_exceptions=False) as api:
            sid = api.post("/v1/sequences", json={"path": str(seq)}, headers=h).json()["id"]
            spec = c.job_spec(sid, cameras=["rgb_center"])
            with workers:
                done = api.post("/v1/jobs", json=spec, headers=h).json()["id"]
                rows = c.wait_terminal(cfg, [done], 300)
            queued = api.post("/v1/jobs", json=spec, headers=h).json()["id"]
            state = rows[done].state.value
            ids = {"job_id": [done, queued], "sequence_id": [sid], "index": ["0", "1", "7"]}
            checker = Checker(app)
            clients = {"alice": _session(app, alice), "bob": _session(app, bob), "none": None}
            routes = dashboard_routes(app)
            try:
                for template, methods in routes:
                    _fuzz_route(checker, clients, template, methods, ids, examples, seed)
            finally:
                for cl in clients.values():
                    if cl is not None:
                        cl.close()
        app.state.engine.dispose()
    v = checker.violations
    return {
        "first_job_state": state,
        "routes_mounted": len(routes),
        "routes_fuzzed": len(checker.by_route),
        "examples_per_route": examples,
        "requests": sum(checker.codes.values()),
        "status_codes": dict(sorted(checker.codes.items())),
        **{k: len(x) for k, x in v.items()},
        "examples": {k: x[:10] for k, x in v.items() if x},
    }


def _session(app: Any, secret: str) -> TestClient:
    """A client logged in through the login form (token, same origin)."""
    cl = TestClient(app, raise_server_exceptions=False)
    page = cl.get(f"{BASE}/login")
    token = re.search(r'name="token" value="([^"]+)"', page.text)
    if token is None:
        raise RuntimeError(f"no login token on the login page ({page.status_code})")
    r = cl.post(
        f"{BASE}/login",
        data={"api_key": secret, "token": token.group(1), "next": f"{BASE}/jobs"},
        follow_redirects=False,
    )
    if r.status_code != 303:
        raise RuntimeError(f"login failed: {r.status_code}")
    return cl


def _fuzz_route(
    checker: Checker,
    clients: dict[str, TestClient | None],
    template: str,
    methods: set[str],
    ids: dict[str, list[str]],
    examples: int,
    seed: int,
) -> None:
    names = _params(template)
    value = {n: st.one_of(st.sampled_from(ids.get(n, ["x"])), _text()) for n in names}
    fields = st.dictionaries(
        st.sampled_from(["api_key", "token", "next", "offset", "state", "extra"]), _text(),
        max_size=4,
    )  # fmt: skip
    query = st.dictionaries(
        st.sampled_from(["offset", "state", "sequence_id", "id", "next", "x"]),
        st.one_of(_text(), st.integers(-(2**70), 2**70).map(str)),
        max_size=4,
    )
    cookies = st.one_of(
        st.none(),
        st.dictionaries(st.sampled_from([SESSION_COOKIE, LOGIN_COOKIE]), _text(), max_size=2),
    )
    headers = st.dictionaries(
        st.sampled_from(["Origin", "Referer", "Range", "Accept", "Content-Type"]),
        st.one_of(_text().map(_ascii),
                  st.sampled_from(["bytes=0-0", "bytes=-1", "bytes=5-2", "bytes=0-99999999999"])),
        max_size=3,
    )  # fmt: skip
    own = sorted(methods)

    @settings(
        max_examples=examples,
        database=None,
        deadline=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(
        who=st.sampled_from(sorted(clients)),
        method=st.one_of(st.sampled_from(own), st.sampled_from(METHODS)),
        path_values=st.fixed_dictionaries(value),
        q=query,
        form=fields,
        jar=cookies,
        hdr=headers,
        form_as_json=st.booleans(),
    )
    def one(
        who: str,
        method: str,
        path_values: dict[str, str],
        q: dict[str, str],
        form: dict[str, str],
        jar: dict[str, str] | None,
        hdr: dict[str, str],
        form_as_json: bool,
    ) -> None:
        client = clients[who]
        anonymous = client is None
        if client is None:
            client = TestClient(checker.app, raise_server_exceptions=False)
        if jar:  # forged cookies replace the session's for this request
            client.cookies.clear()
            for k, v in jar.items():
                client.cookies.set(k, _ascii(v) or "x")
        url = _fill(template, path_values)
        kw: dict[str, Any] = {"params": q, "headers": hdr}
        if method in ("POST", "PUT", "PATCH"):
            kw["json" if form_as_json else "data"] = form
        try:
            checker.send(client, template, method, url, **kw)
        finally:
            if anonymous:
                client.close()
            elif jar:
                _restore(client, who)

    restore_sessions = {w: dict(cl.cookies) for w, cl in clients.items() if cl is not None}

    def _restore(client: TestClient, who: str) -> None:
        client.cookies.clear()
        for k, v in restore_sessions[who].items():
            client.cookies.set(k, v)

    hypothesis_seed(seed)(one)()


def ok(f: dict[str, Any]) -> bool:
    bad = (
        "server_errors_5xx", "missing_csp_on_html", "unescaped_reflections",
        "offsite_redirects", "method_not_allowed_without_allow", "transport_errors",
    )  # fmt: skip
    return (
        all(f[k] == 0 for k in bad)
        and f["routes_fuzzed"] == f["routes_mounted"] > 10
        and f["first_job_state"] == "SUCCEEDED"
    )


if __name__ == "__main__":
    raise SystemExit(c.main(NAME, run, __doc__, ok))
