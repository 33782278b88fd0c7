"""The dashboard (/dashboard): server-rendered pages, browser sessions, live progress.

- with TestClient, on SQLite and PostgreSQL (the ``api`` fixture): pages render for a
  logged-in key, redirect to the login page without one, another key's objects are 404
  pages, login and logout need their form token (and a same-site origin), the cookie is
  HttpOnly + SameSite=Strict and holds no API key;
- the view functions on a real job's metrics shape (tables, preview groups);
- in a real headless Chromium (Debian's /usr/bin/chromium, driven by Playwright) against
  uvicorn on loopback: log in through the page, a job's progress moves in the page
  without a reload as the test updates its row, and a real tiny job's previews load.
"""

from __future__ import annotations

import io
import re
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import update

from osdar_platform.models import ApiKey, Asset, Job, JobEvent, JobState
from tests.conftest_service import Api, memory_celery

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
SCREENSHOT = Path("/tmp/dashboard_job.png")
TOKEN = re.compile(r'name="token" value="([^"]+)"')

#: The shape of a real job's metrics (trimmed from a run on the synthetic fire_site).
METRICS: dict[str, Any] = {
    "evaluation": {
        "strategy": "ins",
        "requested_strategy": "ins",
        "warnings": ["odometry: ICP probably slipped along the track"],
        "ground_truth": {
            "pose_error": {
                "ins": {
                    "translation_m_mean": 0.407,
                    "translation_m_max": 0.414,
                    "rotation_deg_mean": 0.606,
                    "rotation_deg_max": 0.617,
                },
                "odometry": {
                    "translation_m_mean": 0.291,
                    "translation_m_max": 0.411,
                    "rotation_deg_mean": 0.933,
                    "rotation_deg_max": 1.242,
                },
            },
            "landmark_rpe": {
                "rgb_center": {
                    "ins": {
                        "rpe_px": {"mean": 62.571, "std": 15.397, "max": 118.427, "n": 53},
                        "jitter_px": {"mean": 2.012, "std": 1.165, "max": 6.968, "n": 35},
                    },
                    "odometry": {
                        "rpe_px": {"mean": 83.25, "std": 18.3, "max": 118.42, "n": 53},
                        "jitter_px": {"mean": 18.83, "std": 5.56, "max": 24.8, "n": 35},
                    },
                },
                "rgb_highres_center": {
                    "ins": {
                        "rpe_px": {"mean": 91.916, "std": 8.993, "max": 113.203, "n": 48},
                        "jitter_px": {"mean": 2.963, "std": 1.336, "max": 5.569, "n": 32},
                    }
                },
            },
        },
        "per_frame": {"rgb_center": {"frames": [0, 1, 2], "rpe": [65.8, 63.0, 58.7]}},
    },
    "augmentation": {
        "object": {"class": "person"},
        "frames": {"total": 3, "augmented_range": 3, "annotated": 3},
        "cameras": {"rgb_center": {"visible_frames": 3}},
        "lidar": {"object_points_total": 1433},
        "warnings": [],
        "object_errors": {
            "cameras": {
                "rgb_center": {
                    "frames": 3,
                    "anchor_px_mean": 3.278,
                    "anchor_px_max": 5.370,
                    "mask_iou_mean": 0.690,
                    "mask_iou_min": 0.535,
                },
                "rgb_highres_center": {
                    "frames": 0,
                    "anchor_px_mean": None,
                    "anchor_px_max": None,
                    "mask_iou_mean": None,
                    "mask_iou_min": None,
                },
            }
        },
    },
}
PREVIEW_NAMES = [
    "lidar_bev_001.png",
    "rgb_center_000.png",
    "rgb_center_001.png",
    "rgb_center_002.png",
    "rgb_highres_center_000.png",
    "rgb_highres_center_001.png",
    "rgb_highres_center_002.png",
    "rpe_jitter.png",
]
SPEC = {
    "cameras": ["rgb_center", "rgb_highres_center"],
    "lidar": True,
    "object": {"builtin": "person", "scale": 1.0},
    "placement": {"mode": "track", "s": 5.0, "offset": 0.0, "yaw_deg": 90.0},
    "strategy": "ins",
}


# ---------------------------------------------------------------------------- helpers
def _png(width: int = 24, height: int = 16, colour: tuple[int, int, int] = (200, 80, 40)) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (width, height), colour).save(buf, format="PNG")
    return buf.getvalue()


def _owner_id(sessions: Any, pepper: str, secret: str) -> int:
    from osdar_platform.keys import find_api_key

    with sessions() as s:
        key = find_api_key(session=s, secret=secret, pepper=pepper)
        assert key is not None
        return key.id


def _insert_job(sessions: Any, owner_id: int, sequence_id: str | None, **values: Any) -> str:
    """A job row as a worker would leave it (defaults: RUNNING, 0 of 10 frames)."""
    row: dict[str, Any] = {
        "owner_id": owner_id,
        "sequence_id": sequence_id,
        "spec": {"sequence_id": sequence_id, **SPEC},
        "state": JobState.RUNNING,
        "stage": "prepare",
        "progress_done": 0,
        "progress_total": 10,
        "attempt": 1,
        "started_at": datetime.now(UTC),
    }
    row.update(values)
    with sessions.begin() as s:
        job = Job(**row)
        job.events.append(JobEvent(kind="created"))
        s.add(job)
        s.flush()
        return job.id


def _set_job(sessions: Any, job_id: str, **values: Any) -> None:
    with sessions.begin() as s:
        s.execute(update(Job).where(Job.id == job_id).values(**values))


def _login(client: Any, secret: str, next_path: str = "/dashboard/jobs") -> Any:
    page = client.get("/dashboard/login", params={"next": next_path})
    assert page.status_code == 200
    token = TOKEN.search(page.text)
    assert token is not None, page.text
    return client.post(
        "/dashboard/login",
        data={"api_key": secret, "token": token.group(1), "next": next_path},
        follow_redirects=False,
    )


@dataclass
class Dash:
    """Two keys of their own on the ``api`` app, a sequence and jobs of the first."""

    api: Api
    alice: str
    bob: str
    alice_id: int
    bob_id: int
    sequence_id: str
    done_job: str  # SUCCEEDED, metrics, previews, archive
    live_job: str  # RUNNING
    bob_job: str

    def client(self) -> Any:
        from fastapi.testclient import TestClient

        return TestClient(self.api.client.app)

    def logged_in(self, who: str = "alice") -> Any:
        client = self.client()
        r = _login(client, self.alice if who == "alice" else self.bob)
        assert r.status_code == 303, r.text
        return client


@pytest.fixture(scope="module")
def dash(api: Api, synth_sequence_dir: Path) -> Dash:
    alice, bob = api.new_key("dash-alice"), api.new_key("dash-bob")
    pepper = api.settings.api_key_pepper.get_secret_value()
    alice_id = _owner_id(api.sessions, pepper, alice)
    bob_id = _owner_id(api.sessions, pepper, bob)
    r = api.client.post(
        "/v1/sequences",
        json={"path": str(synth_sequence_dir), "name": "dash tiny"},
        headers={"Authorization": f"Bearer {alice}"},
    )
    assert r.status_code == 201, r.text
    seq_id = r.json()["id"]
    store = api.client.app.state.store
    done = _insert_job(
        api.sessions,
        alice_id,
        seq_id,
        state=JobState.SUCCEEDED,
        stage="publish",
        progress_done=3,
        progress_total=3,
        metrics=METRICS,
        timings={"fetch": 0.25, "prepare": 0.33, "evaluate": 0.1, "package": 1.0},
        finished_at=datetime.now(UTC),
    )
    keys = [f"jobs/{done}/previews/attempt-1/{name}" for name in PREVIEW_NAMES]
    for i, key in enumerate(keys):
        store.put_bytes(key, _png(24 + i, 16))
    store.put_bytes(f"jobs/{done}/attempt-1/archive.tar.gz", b"archive bytes")
    _set_job(api.sessions, done, previews=keys, result_key=f"jobs/{done}/attempt-1/archive.tar.gz")
    live = _insert_job(api.sessions, alice_id, seq_id, progress_done=4)
    with api.sessions.begin() as s:
        s.add(
            Asset(
                owner_id=alice_id,
                name="dash-rock.glb",
                file_type="glb",
                store_key="assets/dash-rock.glb",
                size=123_456,
                vertices=812,
                faces=1620,
            )
        )
    bob_job = _insert_job(api.sessions, bob_id, None, state=JobState.QUEUED, stage=None)
    return Dash(api, alice, bob, alice_id, bob_id, seq_id, done, live, bob_job)


# ---------------------------------------------------------------------------- (1) server
def test_pages_redirect_to_the_login_page_without_a_session(dash: Dash) -> None:
    client = dash.client()
    for path in (
        "/dashboard/jobs",
        f"/dashboard/jobs/{dash.done_job}",
        f"/dashboard/jobs/{dash.done_job}/previews/0",
        f"/dashboard/jobs/{dash.done_job}/archive",
        "/dashboard/sequences",
        f"/dashboard/sequences/{dash.sequence_id}",
        "/dashboard/assets",
    ):
        r = client.get(path, follow_redirects=False)
        assert r.status_code == 303, path
        assert r.headers["location"] == f"/dashboard/login?next={path}", path
    r = client.get("/dashboard", follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/dashboard/jobs"
    r = client.get("/dashboard/api/jobs", params={"id": dash.live_job})
    assert r.status_code == 401
    # a forged or foreign cookie is no session
    client.cookies.set("osdar_dash", "eyJrIjoxfQ.forged.sig", path="/dashboard")
    assert client.get("/dashboard/jobs", follow_redirects=False).status_code == 303


def test_login_sets_a_strict_httponly_cookie_without_the_key(dash: Dash) -> None:
    client = dash.client()
    page = client.get("/dashboard/login")
    assert page.status_code == 200 and 'name="api_key"' in page.text
    assert "frame-ancestors 'none'" in page.headers["content-security-policy"]
    login_cookie = page.headers["set-cookie"].lower()
    assert "httponly" in login_cookie and "samesite=strict" in login_cookie
    r = _login(client, dash.alice, next_path=f"/dashboard/jobs/{dash.done_job}")
    assert r.status_code == 303
    assert r.headers["location"] == f"/dashboard/jobs/{dash.done_job}"
    cookie = next(c for c in r.headers.get_list("set-cookie") if c.startswith("osdar_dash="))
    low = cookie.lower()
    assert "httponly" in low and "samesite=strict" in low and "path=/dashboard" in low
    assert dash.alice not in cookie and dash.alice[4:20] not in cookie
    # a logged-in browser asking for the login page goes on
    again = client.get("/dashboard/login", follow_redirects=False)
    assert again.status_code == 303 and again.headers["location"] == "/dashboard/jobs"


def test_pages_render_the_keys_objects(dash: Dash) -> None:
    client = dash.logged_in("alice")
    jobs = client.get("/dashboard/jobs")
    assert jobs.status_code == 200
    assert dash.done_job in jobs.text and dash.live_job in jobs.text
    assert dash.bob_job not in jobs.text
    assert "dash tiny" in jobs.text and "4 / 10 (40%)" in jobs.text
    assert 'data-percent="40.0"' in jobs.text and "dash-alice" in jobs.text
    running = client.get("/dashboard/jobs", params={"state": "RUNNING"}).text
    assert dash.live_job in running and dash.done_job not in running

    page = client.get(f"/dashboard/jobs/{dash.done_job}")
    assert page.status_code == 200
    text = page.text
    # spec, timings, metrics tables
    assert "person" in text and "track: s = 5.00 m" in text
    assert "package" in text and "1.68" in text  # timings and their total
    assert "62.57 ± 15.40" in text and "91.92 ± 8.99" in text  # RPE per camera, ins
    assert "83.25 ± 18.30" in text  # the other strategy
    assert "2.01 ± 1.17" in text  # jitter
    assert "0.407" in text and "0.933" in text  # pose errors
    assert "3.28" in text and "0.690" in text  # object errors
    assert "ICP probably slipped" in text
    # previews: 3 frames x 2 cameras, the lidar from above, the RPE/jitter plot
    srcs = re.findall(rf'src="(/dashboard/jobs/{dash.done_job}/previews/\d+)"', text)
    assert len(srcs) == 8
    for pos in ("first", "middle", "last"):
        assert f"{pos} · frame" in text
    assert "lidar from above · frame 1" in text and "RPE and jitter per frame" in text
    assert f'href="/dashboard/jobs/{dash.done_job}/archive"' in text
    for src in srcs:
        img = client.get(src)
        assert img.status_code == 200 and img.headers["content-type"] == "image/png"
        assert img.content.startswith(b"\x89PNG")
        assert img.headers["cache-control"].startswith("private")
    archive = client.get(f"/dashboard/jobs/{dash.done_job}/archive")
    assert archive.status_code == 200 and archive.content == b"archive bytes"
    assert "attachment" in archive.headers["content-disposition"]
    part = client.get(f"/dashboard/jobs/{dash.done_job}/archive", headers={"Range": "bytes=0-6"})
    assert part.status_code == 206 and part.content == b"archive"
    # a running job: no archive yet (409 page), no previews
    live = client.get(f"/dashboard/jobs/{dash.live_job}")
    assert live.status_code == 200 and "No archive yet." in live.text
    assert client.get(f"/dashboard/jobs/{dash.live_job}/archive").status_code == 409
    assert client.get(f"/dashboard/jobs/{dash.done_job}/previews/8").status_code == 404

    seqs = client.get("/dashboard/sequences")
    assert seqs.status_code == 200 and "dash tiny" in seqs.text
    seq = client.get(f"/dashboard/sequences/{dash.sequence_id}")
    assert seq.status_code == 200
    assert "rgb_center, rgb_highres_center" in seq.text and dash.live_job in seq.text
    assets = client.get("/dashboard/assets")
    assert assets.status_code == 200
    assert "dash-rock.glb" in assets.text and "123.5 KB" in assets.text and "1620" in assets.text


def test_live_status_json(dash: Dash) -> None:
    client = dash.logged_in("alice")
    r = client.get("/dashboard/api/jobs", params=[("id", dash.live_job), ("id", dash.done_job)])
    assert r.status_code == 200 and r.headers["cache-control"] == "no-store"
    by_id = {j["id"]: j for j in r.json()["jobs"]}
    assert by_id[dash.live_job]["state"] == "RUNNING" and by_id[dash.live_job]["percent"] == 40
    assert by_id[dash.live_job]["terminal"] is False
    assert by_id[dash.done_job]["terminal"] is True and by_id[dash.done_job]["percent"] == 100
    one = client.get(f"/dashboard/api/jobs/{dash.live_job}").json()
    assert (one["done"], one["total"], one["stage"]) == (4, 10, "prepare")


def test_another_keys_objects_are_404_pages(dash: Dash) -> None:
    client = dash.logged_in("bob")
    jobs = client.get("/dashboard/jobs").text
    assert dash.bob_job in jobs and dash.done_job not in jobs and dash.live_job not in jobs
    for path, what in (
        (f"/dashboard/jobs/{dash.done_job}", "job"),
        (f"/dashboard/jobs/{dash.done_job}/previews/0", "preview"),
        (f"/dashboard/jobs/{dash.done_job}/archive", "job"),
        (f"/dashboard/sequences/{dash.sequence_id}", "sequence"),
        ("/dashboard/jobs/no-such-job", "job"),
    ):
        r = client.get(path)
        assert r.status_code == 404, path
        assert r.headers["content-type"].startswith("text/html")
        assert f"There is no {what}" in r.text
        assert "62.57" not in r.text and "dash tiny" not in r.text
    r = client.get("/dashboard/api/jobs", params={"id": dash.live_job})
    assert r.json() == {"jobs": []}
    assert client.get(f"/dashboard/api/jobs/{dash.live_job}").status_code == 404
    assert "dash tiny" not in client.get("/dashboard/sequences").text
    assert "dash-rock.glb" not in client.get("/dashboard/assets").text


def test_login_needs_its_form_token_and_the_same_origin(dash: Dash) -> None:
    client = dash.client()
    form = {"api_key": dash.alice, "next": "/dashboard/jobs"}
    # no token, and no login cookie
    assert client.post("/dashboard/login", data=form).status_code == 403
    token = TOKEN.search(client.get("/dashboard/login").text).group(1)  # type: ignore[union-attr]
    # a token that is not the one of this browser's login cookie
    r = client.post("/dashboard/login", data={**form, "token": token[::-1]})
    assert r.status_code == 403
    r = client.post("/dashboard/login", data={**form, "token": "ü" + token[1:]})  # not ASCII
    assert r.status_code == 403
    # a cross-site form (Origin of another site), even with the right token
    r = client.post(
        "/dashboard/login",
        data={**form, "token": token},
        headers={"Origin": "https://evil.example"},
        follow_redirects=False,
    )
    assert r.status_code == 403
    # a wrong key: the form again, with an error
    r = client.post("/dashboard/login", data={**form, "api_key": "oar_nope", "token": token})
    assert r.status_code == 401 and "Unknown or revoked API key" in r.text
    # the right key, the same origin: in, and never redirected off the dashboard
    token = TOKEN.search(r.text).group(1)  # type: ignore[union-attr]
    r = client.post(
        "/dashboard/login",
        data={**form, "token": token, "next": "//evil.example/x"},
        headers={"Origin": "http://testserver"},
        follow_redirects=False,
    )
    assert r.status_code == 303 and r.headers["location"] == "/dashboard/jobs"


def test_logout_needs_the_sessions_form_token(dash: Dash) -> None:
    client = dash.logged_in("alice")
    page = client.get("/dashboard/jobs").text
    token = TOKEN.search(page).group(1)  # type: ignore[union-attr]
    assert client.post("/dashboard/logout", data={}).status_code == 403
    assert client.post("/dashboard/logout", data={"token": "x" * 20}).status_code == 403
    assert client.post("/dashboard/logout", data={"token": "é" * 20}).status_code == 403
    r = client.post(
        "/dashboard/logout", data={"token": token}, headers={"Origin": "https://evil.example"}
    )
    assert r.status_code == 403
    assert client.get("/dashboard/jobs", follow_redirects=False).status_code == 200  # still in
    r = client.post("/dashboard/logout", data={"token": token}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/dashboard/login"
    assert client.get("/dashboard/jobs", follow_redirects=False).status_code == 303


def test_a_revoked_key_ends_its_sessions(dash: Dash) -> None:
    from osdar_platform.keys import revoke_api_key

    secret = dash.api.new_key("dash-carol")
    client = dash.client()
    assert _login(client, secret).status_code == 303
    assert client.get("/dashboard/jobs", follow_redirects=False).status_code == 200
    pepper = dash.api.settings.api_key_pepper.get_secret_value()
    key_id = _owner_id(dash.api.sessions, pepper, secret)
    with dash.api.sessions.begin() as s:
        assert revoke_api_key(session=s, key_id=key_id)
    assert client.get("/dashboard/jobs", follow_redirects=False).status_code == 303


def test_safe_next_stays_inside_the_dashboard() -> None:
    from service.dashboard.auth import safe_next

    assert safe_next("/dashboard/jobs/abc?x=1") == "/dashboard/jobs/abc?x=1"
    for bad in (None, "", "https://evil.example/", "//evil.example", "/v1/jobs", "/dash\\x"):
        assert safe_next(bad) == "/dashboard/jobs"


# ---------------------------------------------------------------------------- views
def test_preview_groups_follow_the_runners_names() -> None:
    from service.services.dashboard import preview_groups

    keys = [f"jobs/j/previews/attempt-1/{n}" for n in PREVIEW_NAMES]
    g = preview_groups(keys, ["rgb_center", "rgb_highres_center"])
    assert [c["camera"] for c in g["cameras"]] == ["rgb_center", "rgb_highres_center"]
    frames = g["cameras"][0]["frames"]
    assert [(f["position"], f["frame"], f["index"]) for f in frames] == [
        ("first", 0, 1),
        ("middle", 1, 2),
        ("last", 2, 3),
    ]
    assert g["lidar"] == [{"frame": 1, "index": 0}] and g["plot"] == 7 and g["other"] == []
    two = preview_groups(["a/rgb_center_000.png", "a/rgb_center_004.png", "a/x.png"], [])
    assert [f["position"] for f in two["cameras"][0]["frames"]] == ["first", "last"]
    assert two["other"] == [{"name": "x.png", "index": 2}] and two["plot"] is None


def test_metrics_view_tables() -> None:
    from service.services.dashboard import metrics_view, timings_rows

    assert metrics_view(None) is None
    m = metrics_view(METRICS)
    assert m is not None and m["strategy"] == "ins"
    rpe = {(r["camera"], r["strategy"]): r for r in m["rpe"]}
    assert rpe[("rgb_center", "ins")]["chosen"] and not rpe[("rgb_center", "odometry")]["chosen"]
    assert rpe[("rgb_center", "ins")]["rpe"] == {
        "mean_std": "62.57 ± 15.40",
        "max": "118.43",
        "n": "53",
    }
    assert [p["strategy"] for p in m["pose"]] == ["ins", "odometry"]
    objects = {o["camera"]: o for o in m["objects"]}
    assert objects["rgb_highres_center"]["anchor_mean"] == "-"
    assert objects["rgb_center"]["iou_min"] == "0.535"
    clicked = metrics_view({"evaluation": {"strategy": "rail", "rpe": {"rgb_center": {}}}})
    assert clicked is not None and clicked["rpe"][0]["source"] == "clicked landmark"
    assert timings_rows({"a": 1.0, "b": 0.5})[-1] == ("total", "1.50")


# ---------------------------------------------------------------------------- (2) browser
@dataclass
class Live:
    url: str
    settings: Any
    sessions: Any
    secret: str
    owner_id: int
    sequence_id: str
    real_job: str


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory, synth_sequence_dir: Path) -> Iterator[Live]:
    """uvicorn on 127.0.0.1 (SQLite + a local store in tmp) with one real finished job."""
    import uvicorn

    from osdar_platform.db import session_scope
    from osdar_platform.keys import create_api_key
    from osdar_platform.migrate import upgrade
    from service.app import create_app
    from service.schemas import JobCreate
    from service.services.sequences import register_sequence
    from worker.orchestration.embedded import embedded_settings, free_port
    from worker.orchestration.runner import run_job_inline

    data = tmp_path_factory.mktemp("dashboard_live")
    settings = embedded_settings(data, rate_limit_per_s=10_000, rate_limit_burst=100_000)
    upgrade(database_url=str(settings.database_url))
    with session_scope(settings) as s:
        key, secret = create_api_key(
            session=s, name="browser", pepper=settings.api_key_pepper.get_secret_value()
        )
        owner = s.get(ApiKey, key.id)
        seq = register_sequence(
            session=s, owner=owner, path=str(synth_sequence_dir), name=None, settings=settings
        )
        owner_id, seq_id = key.id, seq.id
        frames = len(seq.validation["frame_indices"])
        spec = JobCreate.model_validate({"sequence_id": seq_id, **SPEC}).model_dump(mode="json")
        job = Job(
            owner_id=owner_id,
            sequence_id=seq_id,
            spec=spec,
            state=JobState.QUEUED,
            progress_total=frames,
        )
        s.add(job)
        s.flush()
        real_job = job.id
    state = run_job_inline(real_job, settings=settings)  # a few seconds on 3 tiny frames
    assert state == JobState.SUCCEEDED

    app = create_app(settings, celery_app=memory_celery())
    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on")
    )
    thread = threading.Thread(target=server.run, name="dashboard-api", daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.05)
    try:
        yield Live(
            url=f"http://127.0.0.1:{port}",
            settings=settings,
            sessions=app.state.sessions,
            secret=secret,
            owner_id=owner_id,
            sequence_id=seq_id,
            real_job=real_job,
        )
    finally:
        server.should_exit = True
        thread.join(10)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if not CHROMIUM.is_file():
        pytest.skip(f"{CHROMIUM} is missing: run scripts/install_system_deps.sh (apt chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()


def _text(page: Any, selector: str) -> str:
    return page.locator(selector).first.inner_text().strip()


def test_browser_login_live_progress_and_previews(
    browser: Any, live: Live, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the pages poll every 0.25 s instead of 1 s: the same script, the waits shorter
    monkeypatch.setattr("service.dashboard.router.POLL_MS", 250)
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("response", lambda r: errors.append(f"{r.status} {r.url}") if r.status >= 400 else None)
    try:
        # -- log in through the page
        page.goto(f"{live.url}/dashboard/jobs")
        assert "/dashboard/login" in page.url
        page.fill("#api_key", live.secret)
        page.click("form button[type=submit]")
        page.wait_for_url(f"{live.url}/dashboard/jobs")
        assert live.real_job in page.content()

        # -- a job's progress moves in the list without a reload
        job = _insert_job(live.sessions, live.owner_id, live.sequence_id)
        page.reload()
        row = f'tr[data-job-id="{job}"]'
        assert _text(page, f"{row} .js-progress-text") == "0 / 10 (0%)"
        assert _text(page, f"{row} .js-state") == "RUNNING"
        page.evaluate("window.__sameDocument = true")
        fill = f"{row} .js-fill"
        _set_job(live.sessions, job, progress_done=5, stage="augment[0]")
        page.wait_for_function(
            "sel => document.querySelector(sel).textContent.trim() === '5 / 10 (50%)'",
            arg=f"{row} .js-progress-text",
            timeout=10_000,
        )
        assert page.locator(fill).evaluate("e => e.style.width") == "50%"
        assert _text(page, f"{row} .js-stage") == "augment[0]"
        page.wait_for_function(  # the CSS transition ends near half of the bar
            "sel => { const f = document.querySelector(sel);"
            " const r = f.getBoundingClientRect().width / f.parentElement.clientWidth;"
            " return r > 0.45 && r < 0.55; }",
            arg=fill,
            timeout=5_000,
        )
        _set_job(
            live.sessions,
            job,
            progress_done=10,
            state=JobState.SUCCEEDED,
            stage=None,
            finished_at=datetime.now(UTC),
        )
        page.wait_for_function(
            "sel => document.querySelector(sel + ' .js-state').textContent === 'SUCCEEDED'"
            " && document.querySelector(sel + ' .js-progress-text').textContent.trim()"
            " === '10 / 10 (100%)'",
            arg=row,
            timeout=10_000,
        )
        assert page.locator(fill).evaluate("e => e.style.width") == "100%"
        assert page.evaluate("window.__sameDocument") is True  # no reload happened
        page.wait_for_function(
            "sel => { const f = document.querySelector(sel);"
            " return f.getBoundingClientRect().width >= f.parentElement.clientWidth - 1; }",
            arg=fill,
            timeout=5_000,
        )
        page.screenshot(path="/tmp/dashboard_jobs.png")

        # -- the job page follows a running job too, and reloads once it is done
        job2 = _insert_job(live.sessions, live.owner_id, live.sequence_id, progress_done=2)
        page.goto(f"{live.url}/dashboard/jobs/{job2}")
        head = ".job-head"
        assert _text(page, f"{head} .js-progress-text") == "2 / 10 (20%)"
        page.evaluate("window.__sameDocument = true")
        _set_job(live.sessions, job2, progress_done=7, stage="package")
        page.wait_for_function(
            "sel => document.querySelector(sel).textContent.trim() === '7 / 10 (70%)'",
            arg=f"{head} .js-progress-text",
            timeout=10_000,
        )
        assert _text(page, f"{head} .js-stage") == "package"
        assert page.evaluate("window.__sameDocument") is True
        _set_job(live.sessions, job2, state=JobState.FAILED, error="package: disk full")
        page.wait_for_function(
            "() => window.__sameDocument === undefined"
            " && document.querySelector('.job-head .js-state').textContent === 'FAILED'",
            timeout=10_000,
        )
        assert "package: disk full" in _text(page, f"{head} .js-error")

        # -- a real job's page: previews loaded, metrics, plot; a screenshot to look at
        page.goto(f"{live.url}/dashboard/jobs/{live.real_job}")
        page.wait_for_load_state("load")
        page.wait_for_function(
            "() => Array.from(document.querySelectorAll('img.preview')).every(i => i.complete)",
            timeout=10_000,
        )
        images = page.eval_on_selector_all(
            "img.preview",
            "els => els.map(e => ({alt: e.alt, w: e.naturalWidth, h: e.naturalHeight}))",
        )
        alts = [i["alt"] for i in images]
        assert len(images) == 8, alts  # 2 cameras x first/middle/last, lidar, plot
        assert all(i["w"] > 0 and i["h"] > 0 for i in images), images
        for cam in ("rgb_center", "rgb_highres_center"):
            for pos in ("first", "middle", "last"):
                assert any(a.startswith(f"{cam}, {pos} frame") for a in alts), alts
        assert any(a.startswith("lidar cloud from above") for a in alts)
        assert any(a.startswith("RPE and jitter") for a in alts)
        assert _text(page, ".job-head .js-state") == "SUCCEEDED"
        assert page.locator("table.rpe tbody tr").count() >= 2
        assert page.locator("table.pose tbody tr").count() >= 1
        assert page.locator("a.button", has_text="Download the archive").count() == 1
        page.screenshot(path=str(SCREENSHOT), full_page=True)
        assert SCREENSHOT.stat().st_size > 10_000

        # -- log out through the page
        page.click("header form.logout button")
        page.wait_for_url(f"{live.url}/dashboard/login")
        page.goto(f"{live.url}/dashboard/jobs")
        assert "/dashboard/login" in page.url
        assert errors == [], errors
    finally:
        context.close()
