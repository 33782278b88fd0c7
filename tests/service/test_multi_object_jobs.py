"""A direct job takes the multi-object spec a campaign variant uses (``objects``, ``motion``,
``gauge``, a built-in's ``seed``), checked with 422s that name the field, and every
object's uploaded asset is resolved (the owner's only) on the real path: the API
(SQLite, local store), then the job's real stages in this process (run_job_inline).

Known answers: the uploaded tetrahedron (unit legs) placed as the SECOND object at scale 2
comes out 2 m on each side in the job's per-object metrics, beside the built-in cow; a
campaign of a person and that asset two to a variant runs its variant the same way; every
variant a campaign expands into is a valid ``JobCreate`` that the augmentation reads the
same as the variant itself.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from sqlalchemy import update

from osdar_platform.db import session_scope
from osdar_platform.models import Job, JobState
from service.schemas import GaugeOptions, JobCreate
from tests.conftest_service import Api, memory_celery, sqlite_api
from worker.augmentation.gauge import GaugeOutline
from worker.augmentation.spec import AugmentSpec
from worker.campaign.service_expand import expand_campaign_stage
from worker.campaign.service_finalize import finalize_after_job
from worker.orchestration.runner import run_job_inline

pytestmark = pytest.mark.gl

SEQ = {"scene": "fire_site", "frames": 6, "scale": 0.15, "lidar_density": 0.2, "seed": 3}
#: A tetrahedron with unit legs along x, y, z (OBJ).
TETRA_OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
COW = {"object": {"builtin": "cow", "seed": 2}, "placement": {"mode": "track", "s": 15.0}}
WALK = {"mode": "track", "path": [[10.0, -3.0], [10.0, 3.0]], "speed_mps": 1.2}


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Api]:
    with sqlite_api(tmp_path_factory.mktemp("multi_object_api"), SEQ, "fire_multi") as a:
        yield a


def _asset(api: Api, who: str = "alice") -> str:
    r = api.client.post(
        "/v1/assets",
        params={"name": "tetra", "file_type": "obj"},
        content=TETRA_OBJ,
        headers=api.h(who, **{"Content-Type": "application/octet-stream"}),
    )
    assert r.status_code == 201, r.text
    return str(r.json()["id"])


def _many(api: Api, objects: list[dict[str, Any]], **extra: Any) -> dict[str, Any]:
    spec = api.job_spec(objects=objects, **extra)
    del spec["object"], spec["placement"]
    return spec


# ---------------------------------------------------------------------------- 422s
@pytest.mark.parametrize(
    ("body", "loc", "needle"),
    [
        ({"objects": [COW], "object": {"builtin": "rock"}}, ["body", "object"],
         "'object' given beside 'objects'"),
        ({"objects": [COW], "placement": {"mode": "track", "s": 3}}, ["body", "placement"],
         "'placement' given beside 'objects'"),
        ({"objects": [COW], "motion": WALK}, ["body", "motion"], "inside 'objects'"),
        ({"object": None}, ["body", "object"], "give 'object'"),
        ({"placement": None}, ["body", "placement"], "needs a 'placement'"),
        ({"objects": []}, ["body", "objects"], "at least 1"),
        ({"objects": [COW, {"object": {"builtin": "rock"}}]},
         ["body", "objects", 1, "placement"], "needs a 'placement'"),
        ({"objects": [COW, {**COW, "motion": {**WALK, "speed_mps": 0}}]},
         ["body", "objects", 1, "motion", "speed_mps"], "greater than 0"),
        ({"objects": [COW, {**COW, "motion": {**WALK, "path": [[1, 2], [1, 2]]}}]},
         ["body", "objects", 1, "motion"], "coincide"),
        ({"motion": {**WALK, "path": [[1, 2]]}}, ["body", "motion", "path"], "at least 2"),
        ({"objects": [COW, {**COW, "object": {"builtin": "unicorn"}}]},
         ["body", "objects", 1, "object", "builtin"], "cow"),
        ({"gauge": {"margin_m": -1}}, ["body", "gauge", "margin_m"], "greater than or equal"),
        ({"gauge": {"margin": 0.3}}, ["body", "gauge", "margin"], "Extra inputs"),
        ({"object": {"asset_id": "a1", "seed": 3}}, ["body", "object"], "'seed' varies"),
        ({"objects": [COW] * 33}, ["body", "objects"], "at most 32"),
    ],
)  # fmt: skip
def test_a_bad_multi_object_spec_is_a_422_naming_where(
    api: Api, body: dict[str, Any], loc: list[Any], needle: str
) -> None:
    spec = api.job_spec(**body)
    for k in ("object", "placement"):
        if spec.get(k) is None or ("objects" in body and k not in body):
            spec.pop(k, None)
    r = api.client.post("/v1/jobs", json=spec, headers=api.h())
    assert r.status_code == 422, r.text
    match = [e for e in r.json()["detail"] if e["loc"] == loc]
    assert match and needle in match[0]["msg"], r.json()


def test_what_the_sequence_refuses_names_the_object(api: Api) -> None:
    bad = {"object": {"builtin": "rock"},
           "placement": {"mode": "lidar_frame", "xyz": [5, 0, 0], "frame_idx": 9}}  # fmt: skip
    r = api.client.post("/v1/jobs", json=_many(api, [COW, bad]), headers=api.h())
    assert r.status_code == 422, r.text
    (e,) = r.json()["detail"]
    assert e["loc"] == ["body", "objects", 1, "placement", "frame_idx"] and "frame 9" in e["msg"]
    bobs = _asset(api, "bob")
    other = {"object": {"asset_id": bobs}, "placement": {"mode": "track", "s": 20}}
    r = api.client.post("/v1/jobs", json=_many(api, [COW, other]), headers=api.h())
    assert r.status_code == 404, r.text
    assert r.json()["detail"] == f"asset {bobs} not found (body.objects.1.object.asset_id)"


def test_gauge_options_are_the_gauge_outline_fields_with_its_bounds() -> None:
    """The API's light model and the augmentation's outline may not drift apart."""
    light, full = GaugeOptions.model_fields, GaugeOutline.model_fields
    assert set(light) == set(full)
    for name, f in light.items():
        assert f.default is None
        assert [repr(m) for m in f.metadata] == [repr(m) for m in full[name].metadata], name


# ---------------------------------------------------------------------------- real runs
def _metrics(api: Api, job_id: str) -> dict[str, Any]:
    r = api.client.get(f"/v1/jobs/{job_id}", headers=api.h())
    job = r.json()
    assert job["state"] == "SUCCEEDED", job["error"]
    return dict(job["metrics"])


def test_a_job_with_an_asset_as_its_second_object_runs(api: Api) -> None:
    asset = _asset(api)
    tetra = {"object": {"asset_id": asset, "scale": 2.0},
             "placement": {"mode": "track", "s": 20.0, "offset": 2.5}}  # fmt: skip
    walker = {"object": {"builtin": "person"}, "motion": WALK}
    spec = _many(api, [COW, tetra, walker], gauge={"margin_m": 0.4})
    r = api.client.post("/v1/jobs", json=spec, headers=api.h())
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["spec"]["gauge"] == {"margin_m": 0.4}
    assert job["spec"]["objects"][0]["object"]["seed"] == 2
    assert "motion" not in job["spec"]["objects"][0] and "object" not in job["spec"]
    assert api.client.delete(f"/v1/assets/{asset}", headers=api.h()).status_code == 409

    assert run_job_inline(job["id"], settings=api.settings) == JobState.SUCCEEDED
    objects = _metrics(api, job["id"])["augmentation"]["objects"]
    assert [o["class"] for o in objects] == ["cow", "custom", "person"]
    assert objects[1]["size_m"] == pytest.approx([2.0, 2.0, 2.0], abs=1e-6)
    assert [o["moving"] for o in objects] == [False, False, True]


def test_an_asset_not_the_owners_fails_the_job_naming_the_object(api: Api) -> None:
    """The runner checks ownership itself: a spec that names another key's asset (the API
    refuses it; here written straight to the row) fails with the object's path."""
    mine, bobs = _asset(api), _asset(api, "bob")
    spec = _many(api, [COW, {"object": {"asset_id": mine}, "placement": COW["placement"]}])
    r = api.client.post("/v1/jobs", json=spec, headers=api.h())
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    spec["objects"][1]["object"]["asset_id"] = bobs
    with session_scope(api.settings) as s:
        s.execute(update(Job).where(Job.id == job_id).values(spec=spec))
    assert run_job_inline(job_id, settings=api.settings) == JobState.FAILED
    error = api.client.get(f"/v1/jobs/{job_id}", headers=api.h()).json()["error"]
    assert f"objects[1].object: asset {bobs} was deleted" in error, error


def test_a_campaign_variant_with_an_asset_second_runs(api: Api) -> None:
    asset = _asset(api)
    body = {
        "name": "asset_second",
        "seed": 5,
        "sequences": [{"id": api.sequence_id}],
        "obstacles": [
            {"builtin": "person", "motion": {"pattern": "cross", "span_m": 6}},
            {"asset_id": asset, "scale": 2.0},
        ],
        "placements": [{"zone": "beside", "distance_m": [15, 40]}],
        "objects_per_sequence": 2,
        "job": {"cameras": ["rgb_center"], "strategy": "ins", "gauge": {"margin_m": 0.3}},
    }
    r = api.client.post("/v1/campaigns", json=body, headers=api.h())
    assert r.status_code in (201, 202), r.text
    campaign_id = r.json()["id"]
    expand_campaign_stage(campaign_id, settings=api.settings, app=memory_celery())
    detail = api.client.get(f"/v1/campaigns/{campaign_id}", headers=api.h()).json()
    (variant,) = detail["variants"]
    spec = api.client.get(f"/v1/jobs/{variant['job_id']}", headers=api.h()).json()["spec"]
    # the variant's job is a valid direct job, read by the augmentation as the variant
    direct = JobCreate.model_validate(spec).model_dump(mode="json")
    assets = {asset: (TETRA_OBJ, "obj")}
    assert AugmentSpec.from_job_spec(direct, assets=assets) == AugmentSpec.from_job_spec(
        spec, assets=assets
    )
    assert [o["object"].get("asset_id") for o in spec["objects"]] == [None, asset]
    assert "motion" in spec["objects"][0] and spec["gauge"] == {"margin_m": 0.3}
    r = api.client.post("/v1/jobs", json=direct, headers=api.h())
    assert r.status_code == 201, r.text  # the same spec submitted as a job

    assert run_job_inline(variant["job_id"], settings=api.settings) == JobState.SUCCEEDED
    objects = _metrics(api, variant["job_id"])["augmentation"]["objects"]
    assert [o["class"] for o in objects] == ["person", "custom"]
    assert objects[1]["size_m"] == pytest.approx([2.0, 2.0, 2.0], abs=1e-6)
    finalize_after_job(variant["job_id"], settings=api.settings)  # what the task does next
    final = api.client.get(f"/v1/campaigns/{campaign_id}", headers=api.h()).json()
    assert final["state"] == "SUCCEEDED", final
