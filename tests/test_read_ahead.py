"""read_ahead: results in order, computed ahead of the consumer, errors at their item."""

from __future__ import annotations

import threading

import pytest

from worker.read_ahead import read_ahead


def test_results_come_in_order_and_work_runs_ahead_of_the_consumer() -> None:
    started = [threading.Event() for _ in range(6)]

    def work(k: int) -> int:
        started[k].set()
        return k * k

    out = []
    for k, value in enumerate(read_ahead(work, range(6), depth=2)):
        # while the consumer holds item k, the worker has taken up item k + 1 (it would
        # never start without read-ahead: this loop would wait out the timeout)
        if k + 1 < 6:
            assert started[k + 1].wait(timeout=10.0)
        out.append(value)
    assert out == [k * k for k in range(6)]


def test_never_more_than_depth_items_ahead() -> None:
    taken = []
    consumed = []

    def work(k: int) -> int:
        taken.append(k)
        return k

    for k in read_ahead(work, range(20), depth=3):
        consumed.append(k)
        # items submitted: those consumed plus at most ``depth`` ahead
        assert len(taken) <= len(consumed) + 3
    assert consumed == list(range(20))


def test_an_error_reaches_the_consumer_at_its_item() -> None:
    def work(k: int) -> int:
        if k == 3:
            raise ValueError("cloud 3 unreadable")
        return k

    seen = []
    with pytest.raises(ValueError, match="cloud 3 unreadable"):
        for k in read_ahead(work, range(10)):
            seen.append(k)
    assert seen == [0, 1, 2]


def test_leaving_early_stops_the_worker() -> None:
    calls = []
    gen = read_ahead(calls.append, iter(range(1000)), depth=2)
    next(gen)
    gen.close()  # what a ``break`` does: the pending work is cancelled, the pool shut down
    assert len(calls) <= 3
    with pytest.raises(ValueError):
        next(read_ahead(abs, [1], depth=0))
