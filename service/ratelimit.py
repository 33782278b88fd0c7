"""A per-key token bucket, in process (one API process; behind several, each has its own).

``rate`` tokens per second refill a bucket of ``burst``; a request takes one token or is
refused with the seconds until the next token (Retry-After).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class TokenBuckets:
    def __init__(
        self, rate: float, burst: int, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.rate = float(rate)
        self.burst = float(burst)
        self.clock = clock
        self._lock = threading.Lock()
        self._state: dict[object, tuple[float, float]] = {}  # key -> (tokens, last time)

    def take(self, key: object) -> float:
        """Take a token; 0.0 if granted, else the seconds to wait for one."""
        now = self.clock()
        with self._lock:
            tokens, last = self._state.get(key, (self.burst, now))
            tokens = min(self.burst, tokens + (now - last) * self.rate)
            if tokens >= 1.0:
                self._state[key] = (tokens - 1.0, now)
                return 0.0
            self._state[key] = (tokens, now)
            return (1.0 - tokens) / self.rate
