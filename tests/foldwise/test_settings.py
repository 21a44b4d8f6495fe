"""Process settings: where a process keeps what it can make again (FOLDWISE_CACHE_DIR)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

from foldwise import settings as settings_module
from foldwise.settings import Settings


@pytest.fixture
def no_cache_setting(monkeypatch):
    monkeypatch.delenv("FOLDWISE_CACHE_DIR", raising=False)  # the test session sets one of its own
    return monkeypatch


def test_the_cache_folder_follows_xdg_then_home(no_cache_setting, tmp_path):
    no_cache_setting.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert Settings().cache_dir == tmp_path / "xdg" / "foldwise"
    no_cache_setting.delenv("XDG_CACHE_HOME")
    no_cache_setting.setenv("HOME", str(tmp_path / "home"))
    assert Settings().cache_dir == tmp_path / "home" / ".cache" / "foldwise"


def test_without_a_home_the_cache_goes_to_the_temporary_folder_and_settings_still_load(no_cache_setting):
    """A container run as a user with no $HOME and no password entry: Path.expanduser raises, and
    every command would fail at reading its settings."""
    no_cache_setting.delenv("XDG_CACHE_HOME", raising=False)

    def no_home(self):
        raise RuntimeError("Could not determine home directory.")

    no_cache_setting.setattr(settings_module.Path, "expanduser", no_home)
    assert Settings().cache_dir == Path(tempfile.gettempdir()) / "foldwise-cache"


@pytest.mark.parametrize("value, expected", [("", None), ("   ", None), ("/srv/cache", Path("/srv/cache"))])
def test_an_empty_cache_setting_keeps_nothing(no_cache_setting, value, expected):
    no_cache_setting.setenv("FOLDWISE_CACHE_DIR", value)
    assert Settings().cache_dir == expected
