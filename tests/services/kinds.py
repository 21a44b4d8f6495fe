"""The experiments of the two kinds beside Algorithm 1 (``learnability``, Algorithm 2, and
``canonical_baseline``, the paper's Table 2), set up once for the plan tests
(tests/services/scheduler/test_plan_*.py) and the end-to-end runs (tests/services/*_run.py),
which used to repeat the same lines; and what the end-to-end runs share: ``foldwise run`` of a
smoke-sized config in one process, and the check that each model is scored on its own test set."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from typer.testing import CliRunner

from foldwise.settings import REPO_ROOT

# Two conditions the paper ranks far apart (1st and 6th), so a learnability order has two
# entries and a ρ; a canonical baseline is scored on the same pairs.
CONDITIONS, DIFFICULTIES = ["fb", "po"], ["easy", "hard"]


def kind_config(
    kind: str, name: str, settings: dict[str, Any], conditions=CONDITIONS, difficulties=DIFFICULTIES, **sections
) -> dict[str, Any]:
    """A config of ``kind`` whose own section (``learnability:`` or ``canonical_baseline:``) is
    ``settings``, on ``conditions`` × ``difficulties``; ``sections`` are added as they are."""
    return {
        "name": name,
        "kind": kind,
        kind: dict(settings),
        "curriculum": {"conditions": list(conditions), "difficulties": list(difficulties)},
        **sections,
    }


def smoke_kind_config(tmp_path: Path, kind: str, settings: dict[str, Any], conditions=CONDITIONS) -> Path:
    """configs/smoke.yaml as an experiment of ``kind``, written under ``tmp_path``.

    smoke.yaml's stopping rule (M, N, τ, cap) is refused by both kinds (and its τ = 1 would end
    every Algorithm 1 stage at k = M + N = 2): m and t only. Two training images per increment
    and two test images per (condition, difficulty) are all these runs check the records of.
    """
    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config.update(
        kind_config(
            kind, f"smoke-{kind.replace('_', '-')}", settings, conditions,
            active_learning={"m": 2, "t": 2}, test_set={**config["test_set"], "per_stage": 2},
        )
    )  # fmt: skip
    path = tmp_path / f"{kind}.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def run_in_process(config_path: Path, report_dir: Path):
    """``foldwise run CONFIG --report-dir DIR`` in this process (eager tasks); its CLI result."""
    from services.cli import _register_worker_commands, app

    _register_worker_commands()
    result = CliRunner().invoke(app, ["run", str(config_path), "--report-dir", str(report_dir)])
    assert result.exit_code == 0, result.output
    return result


def report(*arguments: str):
    """``foldwise report ARGUMENTS`` in this process; its CLI result."""
    from services.cli import app

    result = CliRunner().invoke(app, ["report", *arguments])
    assert result.exit_code == 0, result.output
    return result


def assert_scored_on_own_condition(stages, by_stage, evaluations, difficulties=DIFFICULTIES) -> None:
    """Every model of a condition's stages is scored on that condition's test set only."""
    for stage in stages:
        for model in by_stage[stage.id]:
            groups = set(evaluations[model.id].details["breakdown"]["condition/difficulty"])
            assert groups == {f"{stage.condition}/{d}" for d in difficulties}, (stage.condition, groups)
