"""/dashboard: server-rendered pages of a key's jobs, sequences and assets.

Pages (HTML, Jinja2)::

    GET  /dashboard                       -> /dashboard/jobs
    GET  /dashboard/login                 paste an API key
    POST /dashboard/login                 start a session (form token)
    POST /dashboard/logout                end it (form token)
    GET  /dashboard/jobs                  jobs, live state/stage/progress (?state=, ?sequence_id=)
    GET  /dashboard/jobs/{id}             spec, live progress, timings, metrics, previews
    GET  /dashboard/jobs/{id}/previews/N  one preview image (streamed from the store)
    GET  /dashboard/jobs/{id}/archive     the published archive (streamed, Range)
    GET  /dashboard/campaigns             campaigns, with their progress
    GET  /dashboard/campaigns/{id}        a campaign: progress, quality histogram (inline
                                          SVG), its variants with a preview each
    GET  /dashboard/sequences             sequences
    GET  /dashboard/sequences/{id}        one sequence and its jobs
    GET  /dashboard/assets                uploaded meshes

JSON for the pages' poller (``static/dashboard.js``)::

    GET  /dashboard/api/jobs?id=..&id=..  live status of those jobs
    GET  /dashboard/api/jobs/{id}         live status of one job

Every route but login shows only the logged-in key's objects; another key's object is a
404 page. An operator key (``osdar-ar keys create NAME --operator``) sees every key's jobs
and campaigns, and the jobs page shows it the workers alive, the queue depth and the
failure rate. Routes stay thin: the data comes from ``service/services/*.py``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import urlencode

import jinja2
from fastapi import APIRouter, Form, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.templating import Jinja2Templates

from osdar_platform.models import CampaignState, JobState
from service.dashboard import auth
from service.dashboard.auth import BASE, ApiUser, DashSession, PageUser
from service.deps import DispatcherDep, SessionDep, SettingsDep, StoreDep
from service.downloads import archive_media_type, image_media_type, stream_object
from service.errors import Conflict, NotFound
from service.schemas import ID_PATTERN
from service.services import assets as svc_assets
from service.services import campaign_view
from service.services import campaigns as svc_campaigns
from service.services import dashboard as view
from service.services import jobs as svc_jobs
from service.services import operator as svc_operator
from service.services import sequences as svc_sequences

HERE = Path(__file__).parent
PAGE_SIZE = 50
#: How often the pages ask for live progress (milliseconds).
POLL_MS = 1000
#: Pages load only their own scripts, styles and images; nothing may frame them.
SECURITY_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'self'; img-src 'self'; style-src 'self'; script-src 'self'; "
        "connect-src 'self'; form-action 'self'; frame-ancestors 'none'; base-uri 'none'"
    ),
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "same-origin",
    "Cache-Control": "no-store",
}

_env = jinja2.Environment(
    loader=jinja2.FileSystemLoader(HERE / "templates"),
    autoescape=True,
    undefined=jinja2.StrictUndefined,
    trim_blocks=True,
    lstrip_blocks=True,
)
_env.filters["when"] = view.when
_env.filters["size"] = view.size
templates = Jinja2Templates(env=_env)

router = APIRouter(prefix=BASE, include_in_schema=False)

JobId = Annotated[str, PathParam(max_length=64, pattern=ID_PATTERN)]
Offset = Annotated[int, Query(ge=0, le=10_000_000)]
FormToken = Annotated[str, Form(max_length=200)]


# ---------------------------------------------------------------------------- helpers
def render(
    request: Request,
    name: str,
    user: DashSession | None,
    status_code: int = 200,
    **context: Any,
) -> HTMLResponse:
    ctx = {
        "base": BASE,
        "user": user,
        "key_name": None if user is None else user.key.name,
        "key_prefix": None if user is None else user.key.prefix,
        "csrf": None if user is None else user.csrf,
        "poll_ms": POLL_MS,
        "nav": context.pop("nav", None),
        **context,
    }
    response = templates.TemplateResponse(request, name, ctx, status_code=status_code)
    response.headers.update(SECURITY_HEADERS)
    return response


def not_found(request: Request, user: DashSession, what: str, ident: str) -> HTMLResponse:
    return render(request, "not_found.html", user, 404, what=what, ident=ident)


def forbidden(request: Request) -> HTMLResponse:
    """A POST without a valid form token or from another origin."""
    response = HTMLResponse(
        "<!doctype html><title>403</title><p>Forbidden: the form has expired or came from "
        f'another site. <a href="{BASE}/login">Log in again</a>.</p>',
        status_code=403,
    )
    response.headers.update(SECURITY_HEADERS)
    return response


def _pages(total: int, offset: int, limit: int, **query: Any) -> dict[str, str | None]:
    keep = {k: v for k, v in query.items() if v}

    def link(off: int) -> str:
        return "?" + urlencode({**keep, "offset": off}) if off else "?" + urlencode(keep)

    return {
        "prev": link(max(0, offset - limit)) if offset > 0 else None,
        "next": link(offset + limit) if offset + limit < total else None,
        "range": f"{min(total, offset + 1)}–{min(total, offset + limit)} of {total}",
    }


def _everyone(user: DashSession) -> bool:
    """An operator key sees every key's jobs and campaigns."""
    return bool(user.key.operator)


def _job_rows(session: Any, user: DashSession, jobs: list[Any]) -> list[dict[str, Any]]:
    everyone = _everyone(user)
    names = view.sequence_names(
        session=session, owner=user.key, ids={j.sequence_id for j in jobs}, everyone=everyone
    )
    owners = view.key_names(session=session, ids={j.owner_id for j in jobs}) if everyone else {}
    return [
        {
            **view.job_status(j),
            "short": j.id[:8],
            "created": j.created_at,
            "sequence_id": j.sequence_id,
            "sequence": names.get(j.sequence_id or "", "(deleted)"),
            "object": view.object_label(j.spec or {}),
            "campaign_id": j.campaign_id,
            "owner": owners.get(j.owner_id),
        }
        for j in jobs
    ]


# ---------------------------------------------------------------------------- login
@router.get("")
def home() -> RedirectResponse:
    return RedirectResponse(f"{BASE}/jobs", status_code=303)


@router.get("/login", response_class=HTMLResponse)
def login_page(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    next: Annotated[str | None, Query(max_length=2000)] = None,
) -> Response:
    if auth.read_session(request, session, settings) is not None:
        return RedirectResponse(auth.safe_next(next), status_code=303)
    return _login_form(request, settings, next=auth.safe_next(next))


def _login_form(
    request: Request, settings: Any, *, next: str, error: str | None = None, status: int = 200
) -> HTMLResponse:
    token, signed = auth.new_login_token(settings)
    response = render(request, "login.html", None, status, next=next, error=error, token=token)
    auth.set_login_cookie(response, request, signed)
    return response


@router.post("/login", response_class=HTMLResponse)
def login(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    api_key: Annotated[str, Form(max_length=256)],
    token: FormToken = "",
    next: Annotated[str, Form(max_length=2000)] = "",
) -> Response:
    if not auth.same_origin(request) or not auth.login_token_ok(request, settings, token):
        return forbidden(request)
    target = auth.safe_next(next)
    key = auth.login_check(request, session, settings, api_key)
    if key is None:
        return _login_form(
            request, settings, next=target, error="Unknown or revoked API key.", status=401
        )
    response = RedirectResponse(target, status_code=303)
    auth.start_session(response, request, settings, key)
    return response


@router.post("/logout")
def logout(request: Request, user: PageUser, token: FormToken = "") -> Response:
    if not auth.same_origin(request) or not auth.csrf_ok(user, token):
        return forbidden(request)
    response = RedirectResponse(f"{BASE}/login", status_code=303)
    auth.end_session(response)
    return response


# ---------------------------------------------------------------------------- jobs
@router.get("/jobs", response_class=HTMLResponse)
def jobs_page(
    request: Request,
    user: PageUser,
    session: SessionDep,
    dispatcher: DispatcherDep,
    offset: Offset = 0,
    state: JobState | None = None,
    sequence_id: Annotated[str | None, Query(max_length=64, pattern=ID_PATTERN)] = None,
) -> HTMLResponse:
    rows, total = svc_jobs.list_jobs(
        session=session,
        owner=user.key,
        limit=PAGE_SIZE,
        offset=offset,
        state=[state] if state else None,
        sequence_id=sequence_id or None,
        everyone=_everyone(user),
    )
    ops = svc_operator.overview(session, dispatcher.broker) if _everyone(user) else None
    return render(
        request,
        "jobs.html",
        user,
        nav="jobs",
        ops=ops,
        jobs=_job_rows(session, user, rows),
        total=total,
        states=[s.value for s in JobState],
        state=state.value if state else None,
        sequence_id=sequence_id,
        pages=_pages(
            total,
            offset,
            PAGE_SIZE,
            state=state.value if state else None,
            sequence_id=sequence_id,
        ),
    )


@router.get("/jobs/{job_id}", response_class=HTMLResponse)
def job_page(request: Request, job_id: JobId, user: PageUser, session: SessionDep) -> Response:
    try:
        job = svc_jobs.get_job(
            session=session, owner=user.key, job_id=job_id, everyone=_everyone(user)
        )
    except NotFound:
        return not_found(request, user, "job", job_id)
    spec = job.spec or {}
    seq = None
    if job.sequence_id:
        names = view.sequence_names(
            session=session, owner=user.key, ids={job.sequence_id}, everyone=_everyone(user)
        )
        seq = {"id": job.sequence_id, "name": names.get(job.sequence_id, job.sequence_id)}
    events = svc_jobs.list_events(
        session=session, owner=user.key, job_id=job.id, everyone=_everyone(user)
    )
    return render(
        request,
        "job.html",
        user,
        nav="jobs",
        job=job,
        status=view.job_status(job),
        sequence=seq,
        spec=view.spec_summary(spec),
        timings=view.timings_rows(job.timings),
        duration=view.duration(job.started_at, job.finished_at),
        metrics=view.metrics_view(job.metrics),
        previews=view.preview_groups(
            [str(k) for k in job.previews or []], list(spec.get("cameras") or [])
        ),
        events=events[-20:],
    )


@router.get("/jobs/{job_id}/previews/{index}")
def job_preview(
    request: Request,
    job_id: JobId,
    index: Annotated[int, PathParam(ge=0, le=10_000)],
    user: PageUser,
    session: SessionDep,
    store: StoreDep,
) -> Response:
    try:
        key = svc_jobs.preview_key(
            session=session, owner=user.key, job_id=job_id, index=index, everyone=_everyone(user)
        )
        response = stream_object(store, key, range_header=None, media_type=image_media_type(key))
    except (NotFound, Conflict):  # no such preview, or the job has not SUCCEEDED
        return not_found(request, user, "preview", f"{job_id}/{index}")
    response.headers["Cache-Control"] = "private, max-age=3600"
    response.headers["X-Content-Type-Options"] = "nosniff"
    return response


@router.get("/jobs/{job_id}/archive")
def job_archive(
    request: Request,
    job_id: JobId,
    user: PageUser,
    session: SessionDep,
    store: StoreDep,
) -> Response:
    try:
        key = svc_jobs.archive_key(
            session=session, owner=user.key, job_id=job_id, everyone=_everyone(user)
        )
        name = key.rsplit("/", 1)[-1]
        return stream_object(
            store,
            key,
            range_header=request.headers.get("range"),
            media_type=archive_media_type(name),
            filename=f"osdar-ar-{job_id}-{name}",
        )
    except NotFound:
        return not_found(request, user, "job", job_id)
    except Conflict as exc:
        return render(request, "not_found.html", user, 409, what="archive", ident=exc.message)


# ---------------------------------------------------------------------------- live JSON
@router.get("/api/jobs")
def jobs_status(
    user: ApiUser,
    session: SessionDep,
    id: Annotated[list[str] | None, Query(max_length=view.MAX_POLL_IDS)] = None,
) -> JSONResponse:
    ids = [i for i in id or [] if re.fullmatch(ID_PATTERN, i)]  # others name no job
    items = view.jobs_status(session=session, owner=user.key, ids=ids, everyone=_everyone(user))
    return JSONResponse({"jobs": items}, headers={"Cache-Control": "no-store"})


@router.get("/api/jobs/{job_id}")
def job_status(job_id: JobId, user: ApiUser, session: SessionDep) -> JSONResponse:
    items = view.jobs_status(
        session=session, owner=user.key, ids=[job_id], everyone=_everyone(user)
    )
    if not items:
        return JSONResponse({"detail": f"job {job_id} not found"}, status_code=404)
    return JSONResponse(items[0], headers={"Cache-Control": "no-store"})


# ---------------------------------------------------------------------------- campaigns
@router.get("/campaigns", response_class=HTMLResponse)
def campaigns_page(
    request: Request,
    user: PageUser,
    session: SessionDep,
    offset: Offset = 0,
    state: CampaignState | None = None,
) -> HTMLResponse:
    everyone = _everyone(user)
    rows, total = svc_campaigns.list_campaigns(
        session=session, owner=user.key, limit=PAGE_SIZE, offset=offset,
        state=[state] if state else None, everyone=everyone,
    )  # fmt: skip
    progress = svc_campaigns.progress_of(session, [c.id for c in rows])
    owners = view.key_names(session=session, ids={c.owner_id for c in rows}) if everyone else {}
    items = [{"c": c, "p": progress.get(c.id), "owner": owners.get(c.owner_id)} for c in rows]
    return render(
        request,
        "campaigns.html",
        user,
        nav="campaigns",
        campaigns=items,
        total=total,
        states=[s.value for s in CampaignState],
        state=state.value if state else None,
        pages=_pages(total, offset, PAGE_SIZE, state=state.value if state else None),
    )


@router.get("/campaigns/{campaign_id}", response_class=HTMLResponse)
def campaign_page(
    request: Request,
    campaign_id: Annotated[str, PathParam(max_length=64, pattern=ID_PATTERN)],
    user: PageUser,
    session: SessionDep,
    offset: Offset = 0,
) -> Response:
    try:
        c = svc_campaigns.get_campaign(
            session=session, owner=user.key, campaign_id=campaign_id, everyone=_everyone(user)
        )
    except NotFound:
        return not_found(request, user, "campaign", campaign_id)
    cameras = list(((c.spec or {}).get("job") or {}).get("cameras") or [])
    rows = svc_campaigns.variant_rows(session, c.id, limit=PAGE_SIZE, offset=offset)
    every = svc_campaigns.variant_rows(session, c.id, limit=100_000, offset=0)
    camera = cameras[0] if cameras else ""
    _measure, label, values = campaign_view.quality_values([v.row for v, _ in every], camera)
    return render(
        request,
        "campaign.html",
        user,
        nav="campaigns",
        c=c,
        prog=svc_campaigns.progress_of(session, [c.id]).get(c.id),
        variants=[campaign_view.variant_row(v, j, cameras) for v, j in rows],
        histogram=campaign_view.histogram(values),
        measure=label,
        camera=camera,
        pages=_pages(c.variants_total, offset, PAGE_SIZE),
    )


# ---------------------------------------------------------------------------- sequences
@router.get("/sequences", response_class=HTMLResponse)
def sequences_page(
    request: Request, user: PageUser, session: SessionDep, offset: Offset = 0
) -> HTMLResponse:
    rows, total = svc_sequences.list_sequences(
        session=session, owner=user.key, limit=PAGE_SIZE, offset=offset
    )
    return render(
        request,
        "sequences.html",
        user,
        nav="sequences",
        sequences=rows,
        total=total,
        pages=_pages(total, offset, PAGE_SIZE),
    )


@router.get("/sequences/{sequence_id}", response_class=HTMLResponse)
def sequence_page(
    request: Request,
    sequence_id: Annotated[str, PathParam(max_length=64, pattern=ID_PATTERN)],
    user: PageUser,
    session: SessionDep,
) -> Response:
    try:
        seq = svc_sequences.get_sequence(session=session, owner=user.key, sequence_id=sequence_id)
    except NotFound:
        return not_found(request, user, "sequence", sequence_id)
    jobs, total = svc_jobs.list_jobs(
        session=session, owner=user.key, limit=PAGE_SIZE, offset=0, sequence_id=seq.id
    )
    v = dict(seq.validation or {})
    facts = [
        ("Frames", f"{seq.frames} ({v.get('first_frame', '-')} – {v.get('last_frame', '-')})"),
        ("Cameras", ", ".join(seq.cameras or []) or "-"),
        ("Lidar", str(v.get("lidar") or "none")),
        ("Time span", f"{seq.time_span_s:.2f} s"),
        ("INS rows", str(v.get("ins_rows", "-"))),
        ("Points (first frame)", str(v.get("points_first_frame", "-"))),
        ("Source", seq.source),
        ("Folder", seq.path),
        ("State", seq.state),
        ("Registered", view.when(seq.created_at)),
    ]
    return render(
        request,
        "sequence.html",
        user,
        nav="sequences",
        seq=seq,
        facts=facts,
        warnings=[str(w) for w in v.get("warnings") or []],
        jobs=_job_rows(session, user, jobs),
        jobs_total=total,
    )


# ---------------------------------------------------------------------------- assets
@router.get("/assets", response_class=HTMLResponse)
def assets_page(
    request: Request, user: PageUser, session: SessionDep, offset: Offset = 0
) -> HTMLResponse:
    rows, total = svc_assets.list_assets(
        session=session, owner=user.key, limit=PAGE_SIZE, offset=offset
    )
    return render(
        request,
        "assets.html",
        user,
        nav="assets",
        assets=rows,
        total=total,
        pages=_pages(total, offset, PAGE_SIZE),
    )
