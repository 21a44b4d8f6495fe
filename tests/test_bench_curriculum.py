"""bench/curriculum.py: a run's stages read back from its own database, and the goals judged on
what each stage did (learned, and why it ended), not on its letter."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import curriculum  # noqa: E402


def _stage(start, best, best_map, reason):
    return {"start_p": start, "best_p": best, "best_map": best_map, "end_reason": reason}


def test_a_stage_that_learns_nothing_fails_the_goals():
    good = [_stage(None, 0.8, 0.3, "cap"), _stage(0.8, 0.9, 0.7, "plateau"), _stage(0.9, 0.92, 0.75, "plateau")]
    assert all(value is True for key, value in curriculum.goals(good, 600).items() if key != "stages_ended_by_the_rule")
    flat = [*good[:2], _stage(0.9, 0.9, 0.75, "plateau")]  # best P no higher than where it started
    assert curriculum.goals(flat, 600)["every_stage_raised_p"] is False
    zero = [_stage(None, 0.5, 0.0, "plateau"), *good[1:]]
    assert curriculum.goals(zero, 600)["no_stage_best_map_zero"] is False
    capped = [_stage(None, 0.8, 0.3, "cap"), _stage(0.8, 0.9, 0.7, "cap"), good[2]]
    assert curriculum.goals(capped, 600)["half_ended_by_the_rule"] is False
    assert curriculum.goals(good, 901)["within_15_minutes"] is False


def test_stages_are_read_from_the_runs_record(tmp_path, database, eager, monkeypatch):
    import workers.render.tasks
    import workers.train.tasks
    from services.embedded import run_to_completion, start_experiment
    from tests.services.flow_helpers import Fakes, config

    fakes = Fakes(scores={(0, 1): 0.2, (0, 2): 0.6, (0, 3): 0.61, (1, 1): 0.7, (1, 2): 0.9})
    monkeypatch.setattr(workers.render.tasks, "render_parameter_set", fakes.render)
    monkeypatch.setattr(workers.train.tasks, "run_increment", fakes.train)
    curriculum_config = {
        "conditions": ["fb"],
        "difficulties": ["easy", "hard"],
        "single_condition_stages": False,
        "mixed": {"difficulties": ["easy", "hard"], "conditions_per_image": [1, 1]},
    }
    active = {"M": 1, "N": 1, "tau": 0.02, "max_increments": 2}
    experiment_id = start_experiment(config(curriculum=curriculum_config, active_learning=active))
    assert run_to_completion(experiment_id) == "finished"

    easy, hard = curriculum.read_stages(tmp_path / "foldwise.db")
    assert (easy["stage"], easy["end_reason"], easy["start_p"], easy["best_p"]) == ("mixed/easy", "cap", None, 0.6)
    assert [entry["p"] for entry in easy["increments"]] == [0.2, 0.6]
    assert (hard["start_p"], hard["best_p"], hard["end_reason"]) == (0.6, 0.9, "cap")
