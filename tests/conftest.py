"""Shared fixtures: an isolated artifact store and a migrated SQLite database per test."""

from __future__ import annotations

import pytest


@pytest.fixture
def database(tmp_path, monkeypatch):
    """A fresh SQLite database and data dir; yields the URL. Settings and engines are reset."""
    from db.migrate import upgrade
    from db.session import reset_engines
    from foldwise.settings import get_settings

    url = f"sqlite:///{tmp_path / 'foldwise.db'}"
    monkeypatch.setenv("FOLDWISE_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("FOLDWISE_DATABASE_URL", url)
    get_settings.cache_clear()
    reset_engines()
    upgrade(url)
    yield url
    reset_engines()
    get_settings.cache_clear()


@pytest.fixture
def eager():
    from workers.app import app, use_eager

    previous = app.conf.task_always_eager
    use_eager(True)
    yield
    use_eager(previous)
