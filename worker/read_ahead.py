"""Work a few items ahead of a sequential consumer, on one worker thread.

Lidar odometry is sequential: frame k must be registered before frame k + 1. Reading and
parsing the next cloud (file I/O, numpy) does not depend on that, so :func:`read_ahead`
runs ``fn(item)`` for the next ``depth`` items on a worker thread while the consumer works
on the current one. KISS-ICP releases the GIL while it registers, and the reading waits on
the disk, so the two overlap on a 2-core machine.

The results come in the items' order; an exception raised by ``fn`` is raised to the
consumer when it reaches that item. Leaving the loop early cancels what has not started.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from typing import TypeVar

In = TypeVar("In")
Out = TypeVar("Out")

#: Items prepared ahead of the consumer: enough to hide one slow read, few enough that the
#: clouds held in memory stay a handful.
DEFAULT_DEPTH = 2


def read_ahead(
    fn: Callable[[In], Out],
    items: Iterable[In],
    depth: int = DEFAULT_DEPTH,
    pool: Executor | None = None,
) -> Iterator[Out]:
    """``fn(item)`` for every item, in order, computed up to ``depth`` items ahead.

    Parameters
    ----------
    fn : the work per item (run on the worker thread).
    items : the items, consumed lazily.
    depth : how many items may be ready or in progress ahead of the consumer (>= 1).
    pool : an executor to share with other background work (its own one-thread pool
        otherwise, shut down when the iteration ends).
    """
    if depth < 1:
        raise ValueError(f"depth must be >= 1, got {depth}")
    own = pool is None
    ex = ThreadPoolExecutor(1, thread_name_prefix="read-ahead") if own else pool
    it = iter(items)
    pending: deque[Future[Out]] = deque()
    try:
        for item in it:
            pending.append(ex.submit(fn, item))
            if len(pending) >= depth:
                break
        while pending:
            head = pending.popleft()
            # queue the next item before waiting, so the worker never idles
            for item in it:
                pending.append(ex.submit(fn, item))
                break
            yield head.result()
    finally:
        for fut in pending:
            fut.cancel()
        if own:
            ex.shutdown(wait=True, cancel_futures=True)
