"""bench/sampling.py: both rules train the same work (the stopping rule off, the same cap), and
the run's record is read back as P against the CPU spent."""

from __future__ import annotations

import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import sampling  # noqa: E402
from foldwise.config import parse_config  # noqa: E402


def test_both_rules_train_every_stage_to_the_same_cap():
    base = yaml.safe_load((ROOT / "configs/quick.yaml").read_text())
    configs = {rule: parse_config(sampling.rule_config(base, rule, 3, 0.5)) for rule in sampling.RULES}
    for rule, config in configs.items():
        assert config.curriculum.mixed.sampling == rule
        for condition, _ in config.stage_order():
            al = config.stage_active_learning(condition)
            # M + N > the cap: the windowed rule can never end a stage early.
            assert al.max_increments == 3 and al.M + al.N > al.max_increments
    uniform, failure = (configs[rule].model_dump() for rule in sampling.RULES)
    for config in (uniform, failure):
        config.pop("name")
        config["curriculum"]["mixed"].pop("sampling")
    assert uniform == failure  # nothing else differs


def test_seconds_to_a_target_is_the_first_point_reaching_it():
    curve = [{"cpu_seconds": 10.0, "p": 0.4}, {"cpu_seconds": 25.0, "p": None}, {"cpu_seconds": 40.0, "p": 0.8}]
    assert sampling.seconds_to(curve, 0.5) == 40.0
    assert sampling.seconds_to(curve, 0.4) == 10.0
    assert sampling.seconds_to(curve, 0.9) is None


def test_failure_and_uniform_runs_are_read_from_their_records(tmp_path, database, eager, monkeypatch):
    """A small failure-driven run through the real scheduler (stand-in workers) reads back as a
    curve whose CPU seconds add up and whose θ say why they were drawn."""
    import workers.render.tasks
    import workers.train.tasks
    from services.embedded import run_to_completion, start_experiment
    from tests.services.flow_helpers import Fakes, config

    fakes = Fakes(cell_scores={"fb/easy": 0.2, "fb/medium": 0.5, "fb/hard": 0.9})
    monkeypatch.setattr(workers.render.tasks, "render_parameter_set", fakes.render)
    monkeypatch.setattr(workers.train.tasks, "run_increment", fakes.train)
    curriculum = {
        "conditions": ["fb", "sc"],
        "difficulties": ["easy", "hard"],
        "single_condition_stages": False,
        "mixed": {"difficulties": ["easy", "hard"], "sampling": "failure", "conditions_per_image": [1, 2]},
    }
    experiment_id = start_experiment(config(curriculum=curriculum, active_learning={"max_increments": 2}))
    assert run_to_completion(experiment_id) == "finished"

    from foldwise.settings import get_settings

    run = sampling.read_run(get_settings().data_dir, database=tmp_path / "foldwise.db")
    assert run["status"] == "finished"
    assert [point["stage"] for point in run["curve"]] == ["mixed/easy"] * 2 + ["mixed/hard"] * 2
    seconds = [point["cpu_seconds"] for point in run["curve"]]
    assert seconds == sorted(seconds) and run["cpu_seconds"] == seconds[-1]
    assert set(run["theta_drawn"]) == {"uniform", "failure"}
