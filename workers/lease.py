"""Leases: a worker renews its claim on the rows it works on while it works (a heartbeat), so the
scheduler can tell a long task from a dead worker: a claim not renewed for ``lease_s`` has lost
its worker, and its work is sent again."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)


class Heartbeat:
    """Calls ``renew`` every ``interval_s`` in a thread of its own while the ``with`` block runs."""

    def __init__(self, name: str, renew: Callable[[], None], interval_s: float) -> None:
        self.name, self.renew, self.interval_s = name, renew, interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat-{name}", daemon=True)

    def _beat(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.renew()
            except Exception as error:  # a missed beat is not fatal; a lapsed lease re-sends the work
                log.warning("heartbeat of %s failed: %s", self.name, error)

    def __enter__(self) -> Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *_exc) -> None:
        self._stop.set()
        self._thread.join()
