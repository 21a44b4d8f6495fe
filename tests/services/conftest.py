"""Fixtures of the services' tests: the scheduler's curriculum run against worker stand-ins."""

from __future__ import annotations

import pytest

from tests.services.flow_helpers import Fakes


@pytest.fixture
def fakes(monkeypatch, database, eager):
    import workers.render.tasks
    import workers.train.tasks

    fake = Fakes()
    monkeypatch.setattr(workers.render.tasks, "render_parameter_set", fake.render)
    monkeypatch.setattr(workers.train.tasks, "run_increment", fake.train)
    return fake
