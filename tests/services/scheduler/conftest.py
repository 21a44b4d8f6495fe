"""No broker in the scheduler's unit tests: the broker view is off (as in eager mode) unless a
test sets its own, so no test reads the queues of, or broadcasts to, a Redis on this machine."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def no_broker_view(monkeypatch):
    from services.scheduler import reconcile

    monkeypatch.setattr(reconcile, "_broker_view", lambda snapshot: None)


@pytest.fixture
def sent(monkeypatch, database):
    """The scheduler's messages, recorded and never delivered (as if every worker were down)."""
    from services.scheduler import reconcile

    messages: list[reconcile.Send] = []
    monkeypatch.setattr(reconcile, "_send", messages.append)
    return messages
