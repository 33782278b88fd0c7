"""service.services.ownership: another key's job, campaign or sequence is a 404 (as if it
did not exist); an operator key's dashboard (``everyone``) reads every key's."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy.orm import Session

from osdar_platform.db import make_engine, make_sessionmaker
from osdar_platform.keys import create_api_key
from osdar_platform.migrate import upgrade
from osdar_platform.models import ApiKey, Campaign, Job, Sequence
from service.errors import NotFound
from service.services import campaigns as svc_campaigns
from service.services import jobs as svc_jobs
from service.services.ownership import owned_or_404


@dataclass
class World:
    session: Session
    alice: ApiKey
    bob: ApiKey
    ops: ApiKey  # an operator key
    rows: dict[str, Any]  # what -> alice's row


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Iterator[World]:
    url = f"sqlite:///{Path(tmp_path_factory.mktemp('ownership')) / 'o.db'}"
    upgrade(database_url=url)
    engine = make_engine(url)
    with make_sessionmaker(engine)() as session:
        keys = {
            name: create_api_key(session=session, name=name, pepper="p", operator=name == "ops")[0]
            for name in ("alice", "bob", "ops")
        }
        alice = keys["alice"]
        seq = Sequence(owner_id=alice.id, name="s", source="path", path="/nowhere")
        session.add(seq)
        session.flush()
        campaign = Campaign(owner_id=alice.id, name="c", spec={})
        job = Job(owner_id=alice.id, sequence_id=seq.id, spec={})
        session.add_all([campaign, job])
        session.commit()
        rows = {"sequence": seq, "campaign": campaign, "job": job}
        yield World(session, alice, keys["bob"], keys["ops"], rows)
    engine.dispose()


WHAT = ["sequence", "campaign", "job"]


@pytest.mark.parametrize("what", WHAT)
def test_the_owner_gets_its_object(world: World, what: str) -> None:
    row = world.rows[what]
    got = owned_or_404(world.session, type(row), row.id, owner=world.alice, what=what)
    assert got is row


@pytest.mark.parametrize("what", WHAT)
def test_another_keys_object_is_a_404_as_if_it_did_not_exist(world: World, what: str) -> None:
    row = world.rows[what]
    with pytest.raises(NotFound) as exc:
        owned_or_404(world.session, type(row), row.id, owner=world.bob, what=what)
    with pytest.raises(NotFound) as missing:
        owned_or_404(world.session, type(row), "no-such-id", owner=world.alice, what=what)
    assert exc.value.status_code == missing.value.status_code == 404
    assert exc.value.message == f"{what} {row.id} not found"
    # the operator role counts only where the caller says everyone may be read (the API
    # never does: an operator's API key reads its own objects like any other)
    with pytest.raises(NotFound):
        owned_or_404(world.session, type(row), row.id, owner=world.ops, what=what)


@pytest.mark.parametrize("what", WHAT)
def test_an_operator_sees_every_keys_object_but_not_a_missing_one(world: World, what: str) -> None:
    row = world.rows[what]
    ops = world.ops
    got = owned_or_404(
        world.session, type(row), row.id, owner=ops, what=what, everyone=ops.operator
    )
    assert got is row
    with pytest.raises(NotFound):
        owned_or_404(world.session, type(row), "no-such-id", owner=ops, what=what, everyone=True)
    assert not world.bob.operator  # an ordinary key's dashboard passes everyone=False


def test_the_job_and_campaign_services_follow_the_rule(world: World) -> None:
    job, campaign = world.rows["job"], world.rows["campaign"]
    s = world.session
    assert svc_jobs.get_job(session=s, owner=world.ops, job_id=job.id, everyone=True) is job
    got = svc_campaigns.get_campaign(
        session=s, owner=world.ops, campaign_id=campaign.id, everyone=True
    )
    assert got is campaign
    with pytest.raises(NotFound, match=f"job {job.id} not found"):
        svc_jobs.get_job(session=s, owner=world.bob, job_id=job.id)
    with pytest.raises(NotFound, match=f"campaign {campaign.id} not found"):
        svc_campaigns.get_campaign(session=s, owner=world.bob, campaign_id=campaign.id)
