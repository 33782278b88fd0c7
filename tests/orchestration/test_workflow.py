"""How a job's stages are sent (worker/orchestration/tasks.py, queue.py).

- ``run_job`` sends fetch -> prepare -> the chunks (a group; one chunk alone), and no
  ``finish``: the chunk that completes the last one sends it (chunk_join.py). No chord,
  whose end the database result backend finds by polling once a second, and no task
  stores a result.
- A job's first message carries a priority: a direct job 3, a campaign's variant 6, every
  later stage the default 0 (served first on Redis): workers finish what they started, and
  a direct job starts before campaign variants queued earlier.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from celery import group

from osdar_platform.settings import Settings
from tests.conftest_service import Api, memory_celery, sent_tasks, sqlite_api
from worker.campaign.service_expand import expand_campaign_stage
from worker.orchestration import tasks
from worker.orchestration.celery_app import make_celery
from worker.orchestration.chunk_join import send_finish
from worker.orchestration.queue import PRIORITY_CAMPAIGN_VARIANT, PRIORITY_JOB, TASK_RUN_JOB
from worker.orchestration.tasks import workflow

SEQ = {"scene": "fire_site", "frames": 4, "scale": 0.05, "lidar_density": 0.05, "seed": 2}


def _names(canvas: object) -> list[str]:
    out = []
    for t in canvas.tasks:  # type: ignore[attr-defined]
        out.append("group" if isinstance(t, group) else t.task.removeprefix("osdar_ar."))
    return out


def test_the_workflow_ends_with_the_chunks_and_no_chord(tmp_path: object) -> None:
    app = make_celery(Settings(data_dir=str(tmp_path)))
    one = workflow(app, "j", 1, [[0, 1, 2]])
    assert _names(one) == ["fetch", "prepare", "augment_chunk"]
    assert one.tasks[2].args == ("j", 1, 0, [0, 1, 2]) and one.tasks[2].immutable
    two = workflow(app, "j", 1, [[0, 1], [2]])
    assert _names(two) == ["fetch", "prepare", "group"]
    assert [(s.args[2], s.args[3]) for s in two.tasks[2].tasks] == [(0, [0, 1]), (1, [2])]
    # prepare's return value (the preparation key) is no chunk's argument
    assert all(s.immutable for s in [*two.tasks[:2], *two.tasks[2].tasks])
    # no task stores a result: nothing for a chord, nothing polled
    assert app.conf.task_ignore_result
    for name in tasks.TASK_NAMES:
        task = getattr(tasks, name.split(".")[1], None)
        assert task is None or task.ignore_result, name


def test_the_finish_chain_carries_the_token() -> None:
    app = memory_celery()
    sent_tasks()
    send_finish(app, "j", 2, "t" * 32)
    (first,) = sent_tasks()  # the later stages ride in the message's chain
    assert first["task"] == "osdar_ar.finish" and first["args"] == ["j", 2, "t" * 32]
    assert first["priority"] in (None, 0)


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
