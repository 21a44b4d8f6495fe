"""Waiting in tests without guessing a duration: poll a condition until it holds or a deadline
passes, and a clock that moves only when the test says so.

``poll`` returns the last value it read, so that the caller's assertion shows what was there;
``wait_until`` asserts itself. ``FakeClock`` stands in for ``db.models.utcnow`` wherever product
code reads the time through a module attribute or takes a ``now`` (a lease, a claim): the test
moves it past a lease with ``advance`` instead of sleeping through one.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import TypeVar

T = TypeVar("T")


def poll(read: Callable[[], T], until: Callable[[T], bool] = bool, timeout: float = 10.0, interval: float = 0.01) -> T:
    """``read()`` again every ``interval`` seconds until ``until(value)`` holds or ``timeout``
    seconds have passed; the last value read either way."""
    deadline = time.monotonic() + timeout
    while True:
        value = read()
        if until(value) or time.monotonic() > deadline:
            return value
        time.sleep(interval)


def wait_until(condition: Callable[[], T], timeout: float = 10.0, interval: float = 0.01, message: str = "") -> T:
    """The first truthy value of ``condition()``, polled as ``poll`` does; AssertionError (with
    ``message``) when it is still falsy after ``timeout`` seconds."""
    value = poll(condition, bool, timeout, interval)
    assert value, message or f"not met within {timeout} s"
    return value


class FakeClock:
    """Timezone-aware UTC time that stands still until ``advance`` moves it; safe to read from
    other threads (a heartbeat's). Call it as ``utcnow`` is called."""

    def __init__(self, start: datetime | None = None) -> None:
        self._now = start or datetime.now(UTC)
        self._lock = threading.Lock()

    def __call__(self) -> datetime:
        with self._lock:
            return self._now

    def advance(self, seconds: float) -> datetime:
        """Move the clock ``seconds`` on; the new time."""
        with self._lock:
            self._now += timedelta(seconds=seconds)
            return self._now
