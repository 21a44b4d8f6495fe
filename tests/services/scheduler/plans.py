"""Hand-made scheduler states for ``plan``'s tests: a config, its stages, snapshots and models."""

from collections import Counter
from datetime import UTC, datetime, timedelta

from db.models import ExperimentStatus, ModelStatus, RenderStatus, StageStatus
from foldwise.config import parse_config
from services.scheduler.snapshot import ModelView, Snapshot, StageView

NOW = datetime(2026, 1, 1, tzinfo=UTC)
CONFIG = parse_config(
    {
        "name": "p",
        "curriculum": {"conditions": ["fb"], "difficulties": ["easy", "hard"]},
        "active_learning": {"M": 1, "N": 1, "tau": 0.05, "max_increments": 3},
    }
)
STAGES = (
    StageView(10, 0, "fb", "easy", StageStatus.running, None, None),
    StageView(11, 1, "fb", "hard", StageStatus.pending, None, None),
)
RENDERED = Counter({RenderStatus.rendered: 4})


def snapshot(status=ExperimentStatus.running, stages=STAGES, models=(), counts=None, pending=(), stale=()):
    return Snapshot(
        experiment_id=1, status=status, seed=0, config=CONFIG, stages=stages, models=tuple(models),
        theta_counts={("test", None, None): RENDERED, **(counts or {})},
        pending_theta_ids=tuple(pending), stale_theta_ids=tuple(stale), now=NOW, requeue_after=timedelta(hours=1),
    )  # fmt: skip


def model(id, k, status=ModelStatus.evaluated, score=0.5, stage_id=10, enqueued=NOW, error=None):
    return ModelView(id, stage_id, k, id - 1 if k > 1 else None, status, score, error, enqueued, None)
