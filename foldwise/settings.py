"""Process settings from the environment (prefix ``FOLDWISE_``), one class for every role."""

from __future__ import annotations

import os
import tempfile
from functools import lru_cache
from pathlib import Path

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

REPO_ROOT = Path(__file__).resolve().parent.parent


def default_cache_dir() -> Path:
    """$XDG_CACHE_HOME/foldwise, else ~/.cache/foldwise; a folder under the system's temporary one
    where there is no home to find (a container run as a user without one)."""
    try:
        return Path(os.environ.get("XDG_CACHE_HOME") or "~/.cache").expanduser() / "foldwise"
    except RuntimeError:  # Path.expanduser: no $HOME and no password entry
        return Path(tempfile.gettempdir()) / "foldwise-cache"


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="FOLDWISE_", extra="ignore")

    data_dir: Path = Field(default=Path("var"), description="artifact store: images and checkpoints")
    database_url: str | None = Field(default=None, description="SQLAlchemy URL; SQLite in data_dir if unset")
    broker_url: str = "redis://127.0.0.1:6379/0"
    eager: bool = Field(default=False, description="run Celery tasks in-process (embedded mode, tests)")
    api_token: str | None = Field(default=None, description="token for POST/DELETE on the API")
    configs_dir: Path = REPO_ROOT / "configs"
    scheduler_poll_s: float = 1.0
    # A task redelivered by the broker after this long is assumed lost with its worker.
    visibility_timeout_s: int = 6 * 3600
    # Where the broker cannot be seen (RabbitMQ, which redelivers what a dead worker held by
    # itself; or Redis unreachable), queued work not started after this long is sent again.
    # On Redis, sent work that shows no sign of life for lease_s / 2 and that neither a queue nor
    # a live worker holds is sent again (services/scheduler/broker_view.py).
    requeue_after_s: float = 3600.0
    # A train worker renews its claim on a model (a heartbeat) every lease_s / 4 while it works;
    # a claim not renewed for lease_s has lost its worker, and the model is sent again. A task
    # that runs for hours stays claimed as long as its worker lives.
    lease_s: float = Field(default=60.0, gt=0)
    # Folders (os.pathsep-separated) under which an experiment POSTed to the API may name its
    # asset folders; unset, the API accepts none (workers would read any folder a token holder
    # names). `foldwise run`, a user's own process, is not limited.
    asset_roots: str = ""
    # The most torch threads this process trains and detects with (0: as the detector config
    # says). Processes that share a machine each take a part of it: `foldwise run --members 2`
    # gives each of its two curricula one of two cores.
    threads: int = Field(default=0, ge=0)
    # What a process can make again but would rather not: the texture check's keypoints and
    # trees, seconds to make (workers/train/texture_check.py). Empty: nothing is kept.
    cache_dir: Path | None = Field(default_factory=default_cache_dir)

    @field_validator("cache_dir", mode="before")
    @classmethod
    def _empty_is_none(cls, value):
        return None if isinstance(value, str) and not value.strip() else value

    @property
    def asset_root_paths(self) -> list[Path]:
        return [Path(part).expanduser().resolve() for part in self.asset_roots.split(os.pathsep) if part.strip()]

    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'foldwise.db').resolve()}"


@lru_cache
def get_settings() -> Settings:
    return Settings()
