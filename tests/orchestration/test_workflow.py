"""How a job's stages are sent (worker/orchestration/tasks.py, queue.py).

- One chunk of frames is a plain link to ``finish``: no chord, whose end the database
  result backend finds by polling once a second.
- A job's first message carries a priority: a direct job 3, a campaign's variant 6, every
  later stage the default 0 (served first on Redis): workers finish what they started, and
  a direct job starts before campaign variants queued earlier.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from celery import chord

from osdar_platform.settings import Settings
from tests.conftest_service import Api, memory_celery, sent_tasks, sqlite_api
from worker.campaign.service_expand import expand_campaign_stage
from worker.orchestration.celery_app import make_celery
from worker.orchestration.queue import PRIORITY_CAMPAIGN_VARIANT, PRIORITY_JOB, TASK_RUN_JOB
from worker.orchestration.tasks import finish, workflow

SEQ = {"scene": "fire_site", "frames": 4, "scale": 0.05, "lidar_density": 0.05, "seed": 2}


def _names(canvas: object) -> list[str]:
    out = []
    for t in canvas.tasks:  # type: ignore[attr-defined]
        out.append("chord" if isinstance(t, chord) else t.task.removeprefix("osdar_ar."))
    return out


def test_one_chunk_is_a_link_and_several_a_chord(tmp_path: object) -> None:
    app = make_celery(Settings(data_dir=str(tmp_path)))
    one = workflow(app, "j", 1, [[0, 1, 2]])
    assert _names(one) == ["fetch", "prepare", "augment_chunk", "finish", "evaluate",
                           "package", "publish"]  # fmt: skip
    assert one.tasks[2].immutable and not one.tasks[3].immutable  # finish gets the chunk
    two = workflow(app, "j", 1, [[0, 1], [2]])
    # the stages after the chord are its body (Celery folds them in)
    assert _names(two) == ["fetch", "prepare", "chord"]
    assert [s.args[2] for s in two.tasks[2].tasks] == [0, 1]
    assert _names(two.tasks[2].body) == ["finish", "evaluate", "package", "publish"]


def test_finish_takes_one_chunk_or_the_chords_list(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[object] = []
    monkeypatch.setattr(
        "worker.orchestration.runner.finish_job",
        lambda job_id, chunks, attempt: seen.append(chunks) or {"frames": len(chunks)},
    )
    chunk = {"index": 0, "frames": [0], "files": "f", "records": "r"}
    assert finish.run(chunk, "j", 1) == {"frames": 1}
    assert finish.run([chunk, chunk], "j", 1) == {"frames": 2}
    assert seen == [[chunk], [chunk, chunk]]


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Api]:
    with sqlite_api(tmp_path_factory.mktemp("workflow"), SEQ, "fire_flow") as a:
        yield a


@pytest.mark.gl
def test_a_direct_job_outranks_campaign_variants(api: Api) -> None:
    body = {
        "name": "ranked",
        "sequences": [{"id": api.sequence_id}],
        "obstacles": [{"builtin": "person"}, {"builtin": "rock"}],
        "placements": [{"explicit": {"mode": "track", "s": 5.0, "yaw_deg": 90}}],
        "job": {"cameras": ["rgb_center"], "strategy": "ins"},
    }
    r = api.client.post("/v1/campaigns", json=body, headers=api.h())
    assert r.status_code in (201, 202), r.text
    sent_tasks()
    expand_campaign_stage(r.json()["id"], settings=api.settings, app=memory_celery())
    r = api.client.post("/v1/jobs", json=api.job_spec(frame_range=[0, 1]), headers=api.h())
    assert r.status_code == 201, r.text
    runs = [(t["id"], t["priority"]) for t in sent_tasks() if t["task"] == TASK_RUN_JOB]
    assert [p for _, p in runs] == [PRIORITY_CAMPAIGN_VARIANT] * 2 + [PRIORITY_JOB]
    assert runs[-1][0] == r.json()["id"]
    assert 0 < PRIORITY_JOB < PRIORITY_CAMPAIGN_VARIANT  # later stages: 0, served first
