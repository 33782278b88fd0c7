"""Browser sessions of the dashboard: an API key pasted once, a signed cookie after it.

- **Login**: the login form posts the key and a form token; the key is checked as the API
  checks it (``find_api_key``). The session cookie then holds the key's id, a fingerprint
  of its stored hash and a CSRF token, signed and timestamped with
  ``settings.dashboard_secret`` (itsdangerous). The key's secret itself is never in it.
- **Every request** verifies the signature and the age, reloads the key and compares the
  fingerprint: a revoked key, or a changed secret, logs the browser out.
- **Cookies** are ``HttpOnly``, ``SameSite=Strict``, scoped to ``/dashboard`` (and
  ``Secure`` over https).
- **CSRF**: besides SameSite, every POST carries a form token (the session's, or for the
  login form a token double-submitted in a short-lived signed cookie) and a cross-site
  ``Origin`` is refused.
"""

from __future__ import annotations

import hmac
import secrets
from dataclasses import dataclass
from typing import Annotated, Any
from urllib.parse import quote, urlsplit

from fastapi import Depends, Request
from fastapi.responses import JSONResponse, RedirectResponse, Response
from itsdangerous import BadSignature, URLSafeTimedSerializer

from osdar_platform.keys import find_api_key
from osdar_platform.models import ApiKey
from osdar_platform.settings import Settings
from service.deps import SessionDep, SettingsDep
from service.errors import TooManyRequests
from service.ratelimit import TokenBuckets

BASE = "/dashboard"
SESSION_COOKIE = "osdar_dash"
LOGIN_COOKIE = "osdar_dash_login"
SESSION_MAX_AGE_S = 12 * 3600
LOGIN_MAX_AGE_S = 3600
FINGERPRINT_CHARS = 16
_SESSION_SALT = "osdar-ar.dashboard.session"
_LOGIN_SALT = "osdar-ar.dashboard.login"


@dataclass
class DashSession:
    """The logged-in API key and the session's form token."""

    key: ApiKey
    csrf: str


class LoginRequired(Exception):
    """No valid session: pages redirect to the login page, the JSON routes answer 401."""

    def __init__(self, next_path: str, *, api: bool) -> None:
        super().__init__("login required")
        self.next_path = next_path
        self.api = api


def _serializer(settings: Settings, salt: str) -> URLSafeTimedSerializer:
    return URLSafeTimedSerializer(settings.dashboard_secret.get_secret_value(), salt=salt)


def fingerprint(key: ApiKey) -> str:
    return key.key_hash[:FINGERPRINT_CHARS]


def _cookie_args(request: Request, max_age: int) -> dict[str, Any]:
    return {
        "max_age": max_age,
        "path": BASE,
        "httponly": True,
        "samesite": "strict",
        "secure": request.url.scheme == "https",
    }


# ---------------------------------------------------------------------------- session
def start_session(response: Response, request: Request, settings: Settings, key: ApiKey) -> None:
    """Set the session cookie for ``key`` (a fresh CSRF token) on ``response``."""
    payload = {"k": key.id, "f": fingerprint(key), "t": secrets.token_urlsafe(24)}
    value = _serializer(settings, _SESSION_SALT).dumps(payload)
    response.set_cookie(SESSION_COOKIE, value, **_cookie_args(request, SESSION_MAX_AGE_S))
    response.delete_cookie(LOGIN_COOKIE, path=BASE)


def end_session(response: Response) -> None:
    response.delete_cookie(SESSION_COOKIE, path=BASE)


def read_session(request: Request, session: Any, settings: Settings) -> DashSession | None:
    """The session of the request's cookie, or None (absent, forged, expired, revoked)."""
    raw = request.cookies.get(SESSION_COOKIE)
    if not raw:
        return None
    try:
        data = _serializer(settings, _SESSION_SALT).loads(raw, max_age=SESSION_MAX_AGE_S)
        key_id, fp, csrf = int(data["k"]), str(data["f"]), str(data["t"])
    except (BadSignature, KeyError, TypeError, ValueError):
        return None
    key = session.get(ApiKey, key_id)
    if key is None or key.revoked or not same_text(fingerprint(key), fp):
        return None
    return DashSession(key=key, csrf=csrf)


def _requester(*, api: bool) -> Any:
    def current(request: Request, session: SessionDep, settings: SettingsDep) -> DashSession:
        user = read_session(request, session, settings)
        if user is None:
            path = request.url.path
            if request.url.query:
                path += "?" + request.url.query
            raise LoginRequired(path, api=api)
        limiter: TokenBuckets = request.app.state.limiter
        wait = limiter.take(user.key.id)
        if wait > 0:
            raise TooManyRequests("rate limit exceeded for this API key", retry_after_s=wait)
        return user

    return current


#: A dashboard page's logged-in key (else a redirect to the login page).
PageUser = Annotated[DashSession, Depends(_requester(api=False))]
#: A dashboard JSON route's logged-in key (else 401).
ApiUser = Annotated[DashSession, Depends(_requester(api=True))]


# ---------------------------------------------------------------------------- login
def login_check(request: Request, session: Any, settings: Settings, secret: str) -> ApiKey | None:
    """The active key of ``secret`` (as the API finds it), or None."""
    return find_api_key(
        session=session, secret=secret.strip(), pepper=settings.api_key_pepper.get_secret_value()
    )


def new_login_token(settings: Settings) -> tuple[str, str]:
    """A form token for the login form and its signed copy for the login cookie."""
    token = secrets.token_urlsafe(24)
    return token, _serializer(settings, _LOGIN_SALT).dumps(token)


def set_login_cookie(response: Response, request: Request, signed: str) -> None:
    response.set_cookie(LOGIN_COOKIE, signed, **_cookie_args(request, LOGIN_MAX_AGE_S))


def login_token_ok(request: Request, settings: Settings, form_token: str) -> bool:
    raw = request.cookies.get(LOGIN_COOKIE)
    if not raw or not form_token:
        return False
    try:
        token = _serializer(settings, _LOGIN_SALT).loads(raw, max_age=LOGIN_MAX_AGE_S)
    except BadSignature:
        return False
    return isinstance(token, str) and same_text(token, form_token)


def same_text(a: str, b: str) -> bool:
    """Constant-time equality of two strings of any characters (``hmac.compare_digest``
    raises TypeError on a str with non-ASCII characters: a form field is user input)."""
    return hmac.compare_digest(
        a.encode("utf-8", "surrogatepass"), b.encode("utf-8", "surrogatepass")
    )


def csrf_ok(user: DashSession, form_token: str) -> bool:
    return bool(form_token) and same_text(user.csrf, form_token)


def same_origin(request: Request) -> bool:
    """False when the browser says the request comes from another origin."""
    origin = request.headers.get("origin")
    if origin is None:
        return True  # not sent: SameSite and the form token decide
    host = request.headers.get("host", "")
    return origin != "null" and urlsplit(origin).netloc == host


def safe_next(value: str | None) -> str:
    """A redirect target inside the dashboard (never another site)."""
    if (
        not value
        or not value.startswith(BASE)
        or value.startswith("//")
        or "\\" in value
        or any(ord(c) < 0x20 for c in value)
    ):
        return f"{BASE}/jobs"
    return value


def login_required_response(exc: LoginRequired) -> Response:
    if exc.api:
        return JSONResponse({"detail": "not logged in"}, status_code=401)
    target = f"{BASE}/login?next={quote(exc.next_path, safe='/')}"
    response = RedirectResponse(target, status_code=303)
    end_session(response)
    return response
