"""The whole API fuzzed from its own OpenAPI document (schemathesis): every operation, with the
token, against the real app on SQLite (and PostgreSQL where one listens). No answer may be a
server error, and every answer must be one the document lists, in the shape it gives.

Kept to a few examples per operation so that the module takes seconds, not minutes; a deeper
run is ``FOLDWISE_FUZZ_EXAMPLES=500 pytest tests/services/api/test_fuzz.py``."""

from __future__ import annotations

import os
import shutil
import warnings

import pytest

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import schemathesis
    from hypothesis import HealthCheck, Phase, settings
    from schemathesis.specs.openapi.checks import (
        content_type_conformance,
        response_schema_conformance,
        status_code_conformance,
    )

from db.migrate import upgrade
from db.session import reset_engines
from foldwise.settings import get_settings
from services.api.app import create_app
from tests.services.api.helpers import AUTH, TOKEN, closed_port

EXAMPLES = int(os.environ.get("FOLDWISE_FUZZ_EXAMPLES", "6"))


def no_unplanned_server_error(ctx, response, case) -> None:
    """A 500 is a bug. Another 5xx (503: the broker is down, the detect queue full; 504: no
    worker answered) is an answer the document promises, which status_code_conformance checks."""
    if response.status_code == 500:
        raise AssertionError(f"500 from {case.method} {case.formatted_path}: {response.text[:500]}")


CHECKS = [no_unplanned_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]


class CurrentApp:
    """The ASGI app the examples go to: the schema is read at collection from an app that
    touches no database, each test swaps in an app on a database of its own."""

    def __init__(self) -> None:
        self.app = create_app()

    async def __call__(self, scope, receive, send) -> None:
        await self.app(scope, receive, send)


current = CurrentApp()
schema = schemathesis.openapi.from_asgi("/openapi.json", current)


@pytest.fixture(params=["sqlite", "postgresql"], autouse=True)
def fuzzed_app(request, tmp_path):
    """The app on a migrated database of its own, tasks in-process (no broker to wait for)."""
    from workers.app import app as celery
    from workers.app import use_eager

    folder = tmp_path
    if request.param == "sqlite":
        shutil.copy(request.getfixturevalue("migrated_sqlite_template"), folder / "api.db")
        url = f"sqlite:///{folder / 'api.db'}"
    else:
        url = request.getfixturevalue("migrated_postgres_url")  # skips, saying why, without a server
    upgrade(url)
    patch = pytest.MonkeyPatch()
    patch.setenv("FOLDWISE_DATA_DIR", str(folder))
    patch.setenv("FOLDWISE_DATABASE_URL", url)
    patch.setenv("FOLDWISE_BROKER_URL", f"redis://127.0.0.1:{closed_port()}/0")
    patch.setenv("FOLDWISE_API_TOKEN", TOKEN)
    patch.setenv("FOLDWISE_EAGER", "1")
    patch.setenv("FOLDWISE_ASSET_ROOTS", str(folder / "assets"))
    get_settings.cache_clear()
    reset_engines()
    previous = celery.conf.task_always_eager
    use_eager(True)
    schema_app = current.app
    current.app = create_app(broker_timeout_s=0.2, ping_timeout_s=0.1)
    try:
        yield current.app
    finally:
        current.app = schema_app
        use_eager(previous)
        patch.undo()
        reset_engines()
        get_settings.cache_clear()


SETTINGS = dict(
    deadline=None,
    derandomize=True,  # the same examples each run: a failure here is reproducible
    suppress_health_check=list(HealthCheck),
    database=None,
)


@schema.exclude(method="POST", path="/experiments").parametrize()
@settings(max_examples=EXAMPLES, **SETTINGS)
def test_no_operation_answers_a_server_error_or_off_its_schema(case):
    case.call_and_validate(headers=AUTH, checks=CHECKS)


@schema.include(method="POST", path="/experiments").parametrize()
@settings(max_examples=EXAMPLES, phases=[Phase.generate], **SETTINGS)
def test_creating_an_experiment_answers_no_server_error_nor_off_its_schema(case):
    # Schemathesis's coverage phase (boundary and invalid values of every field, drawn as
    # explicit examples) takes ~10 s over the whole ExperimentConfig: generated examples only.
    # tests/services/api/test_bad_input.py walks the config's bounds one by one instead.
    case.call_and_validate(headers=AUTH, checks=CHECKS)
