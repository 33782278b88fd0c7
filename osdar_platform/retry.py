"""The one retry layer of the object store: bounded retries with exponential backoff.

A store that fails for a while (S3 endpoint restarting, network blip) must not fail the
job: every store call a job makes goes through :class:`RetryingStore`, which retries a
:class:`~osdar_platform.store.StoreError` (the store's "unreachable or refused") up to
``retries`` times, sleeping ``base * 2**i`` seconds (capped at ``cap``, with +-25 %
jitter so that many workers do not retry in step), within a total time ``budget_s`` from
the first try. botocore makes one attempt per call (osdar_platform/store.py): retries on
top of its own (5 each) made one call up to 35 tries and an outage took minutes to
surface. Past the budget the call raises :class:`StoreUnavailable`, whose message says
how long the store was away against which budget, and the job fails with it.
:class:`~osdar_platform.store.ObjectNotFound` and bad keys are answers, not failures:
never retried. Writes are atomic in both stores,
so a retried upload never leaves a partial object visible.
"""

from __future__ import annotations

import logging
import math
import random
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

from osdar_platform.store import ObjectStore, StoreError

log = logging.getLogger(__name__)
T = TypeVar("T")

#: on_retry(operation, key, retry number (1..), delay s, exception)
RetryHook = Callable[[str, str, int, float, BaseException], None]


def backoff_delays(retries: int, base: float, cap: float) -> list[float]:
    """The nominal delays (s) before retry 1..retries: base, 2 base, 4 base... <= cap."""
    return [min(cap, base * 2**i) for i in range(retries)]


class StoreUnavailable(StoreError):
    """The store stayed unavailable past the retry budget (attempts or time)."""


def call_with_retries(
    fn: Callable[[], T],
    *,
    what: str,
    key: str = "",
    retries: int,
    base: float,
    cap: float,
    budget_s: float = math.inf,
    on_retry: RetryHook | None = None,
    retry_on: tuple[type[BaseException], ...] = (StoreError,),
    sleep: Callable[[float], None] | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> T:
    """``fn()``; on ``retry_on`` errors up to ``retries`` more tries with backoff, as long
    as the next try starts within ``budget_s`` of the first; then
    :class:`StoreUnavailable` (from the last error)."""
    delays = backoff_delays(retries, base, cap)
    started = clock()
    for i in range(retries + 1):
        try:
            return fn()
        except retry_on as exc:
            elapsed = clock() - started
            delay = delays[i] * random.uniform(0.75, 1.25) if i < retries else 0.0
            if i >= retries or elapsed + delay > budget_s:
                raise StoreUnavailable(
                    f"object store unavailable for {elapsed:.0f} s (budget {budget_s:g} s, "
                    f"{retries + 1} attempts; {i + 1} made) on {what} {key}: {exc}"
                ) from exc
            log.warning(
                "store %s %s failed (%s); retry %d/%d in %.1fs (%.0f s of the %g s budget left)",
                what,
                key,
                exc,
                i + 1,
                retries,
                delay,
                budget_s - elapsed,
                budget_s,
            )
            if on_retry is not None:
                try:
                    on_retry(what, key, i + 1, delay, exc)
                except Exception:  # a hook must never turn a retry into a failure
                    log.exception("retry hook failed")
            (sleep or time.sleep)(delay)
    raise AssertionError("unreachable")  # pragma: no cover


class RetryingStore:
    """An :class:`ObjectStore` whose calls are retried (module docstring)."""

    def __init__(
        self,
        inner: ObjectStore,
        *,
        retries: int,
        base: float,
        cap: float,
        budget_s: float = math.inf,
        on_retry: RetryHook | None = None,
    ) -> None:
        self.inner = inner
        self.retries = retries
        self.base = base
        self.cap = cap
        self.budget_s = budget_s
        self.on_retry = on_retry

    def __repr__(self) -> str:
        return f"RetryingStore({self.inner!r}, retries={self.retries})"

    def _do(self, what: str, key: str, fn: Callable[[], T]) -> T:
        return call_with_retries(
            fn,
            what=what,
            key=key,
            retries=self.retries,
            base=self.base,
            cap=self.cap,
            budget_s=self.budget_s,
            on_retry=self.on_retry,
        )

    def put_file(self, key: str, path: str | Path, *, consume: bool = False) -> None:
        self._do("put_file", key, lambda: self.inner.put_file(key, path, consume=consume))

    def put_bytes(self, key: str, data: bytes) -> None:
        self._do("put_bytes", key, lambda: self.inner.put_bytes(key, data))

    def open_read(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        # the request is retried; a failure while streaming the body is the caller's
        return self._do("open_read", key, lambda: self.inner.open_read(key, start, end))

    def get_file(self, key: str, path: str | Path) -> None:
        self._do("get_file", key, lambda: self.inner.get_file(key, path))

    def size(self, key: str) -> int:
        return self._do("size", key, lambda: self.inner.size(key))

    def exists(self, key: str) -> bool:
        return self._do("exists", key, lambda: self.inner.exists(key))

    def delete(self, key: str) -> None:
        self._do("delete", key, lambda: self.inner.delete(key))

    def list(self, prefix: str = "") -> list[str]:
        return self._do("list", prefix, lambda: self.inner.list(prefix))

    def __getattr__(self, name: str) -> Any:  # create_bucket, root, client...
        return getattr(self.inner, name)


__all__ = ["RetryingStore", "StoreUnavailable", "backoff_delays", "call_with_retries"]
