"""The broker's sentinel: a key of ours in the Redis broker's database.

A Redis that restarts without persistence, is flushed or fails over to an empty replica
loses every message and this key with them. Whoever hands a job to the broker records the
sentinel's token on the job (:func:`worker.orchestration.queue.enqueue_job`); the reaper
re-sends a job whose message was handed under a token that is gone
(:mod:`worker.orchestration.reaper`). The first caller to find the key missing writes it.
"""

from __future__ import annotations

import json
import uuid
from dataclasses import dataclass
from datetime import datetime

import redis

from osdar_platform.models import utcnow

SENTINEL_KEY = "osdar_ar:broker_epoch"


@dataclass(frozen=True)
class BrokerEpoch:
    """Since when the Redis broker's data is known intact: the sentinel's token and time."""

    token: str
    since: datetime
    #: This call wrote the sentinel: the previous one was gone (data lost, or first run).
    written: bool = False


def is_redis_url(url: str) -> bool:
    """A Redis broker URL (the only broker whose data can vanish under a running job)."""
    return url.startswith(("redis://", "rediss://"))


def sentinel_epoch(url: str) -> BrokerEpoch | None:
    """The sentinel of the Redis broker at ``url`` (written now if it is gone); None for
    other brokers. Raises if Redis is not reachable or the sentinel is not ours."""
    if not is_redis_url(url):
        return None
    client = redis.Redis.from_url(url, socket_timeout=10, socket_connect_timeout=5)
    raw = None
    try:
        raw = client.get(SENTINEL_KEY)
        written = False
        if raw is None:
            value = {"token": uuid.uuid4().hex, "since": utcnow().isoformat()}
            written = bool(client.set(SENTINEL_KEY, json.dumps(value), nx=True))
            raw = client.get(SENTINEL_KEY)  # another caller's, if it was faster
        data = json.loads(raw or "null")
        since = datetime.fromisoformat(data["since"])
    except (ValueError, TypeError, KeyError) as exc:
        raise ValueError(f"broker sentinel {SENTINEL_KEY!r} unreadable: {raw!r}") from exc
    finally:
        client.close()
    return BrokerEpoch(str(data["token"]), since, written)
