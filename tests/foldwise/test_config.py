"""Experiment configs: every shipped config loads, and errors name the offending key."""

from pathlib import Path

import pytest

from foldwise.config import ConfigError, load_config, parse_config, parse_config_text
from foldwise.settings import REPO_ROOT

CONFIGS = sorted((REPO_ROOT / "configs").glob("*.yaml"))


@pytest.mark.parametrize("path", [p for p in CONFIGS if p.name != "conditions.yaml"], ids=lambda p: p.name)
def test_shipped_configs_are_valid(path):
    config = load_config(path)
    assert config.stage_order()
    assert config.active_learning.M >= 1


def test_paper_config_has_the_papers_values():
    config = load_config(REPO_ROOT / "configs/paper.yaml")
    al = config.active_learning
    assert (al.M, al.N, al.tau, al.m, al.t) == (3, 8, 0.02, 50, 1000)
    assert config.test_set.per_stage == 150 and len(config.test_pairs()) == 21  # 3,150 test images
    assert {c for c, _ in config.test_pairs()} == set(config.curriculum.conditions)
    assert config.evaluation.score_threshold == 0.8


@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({"name": "x", "active_learning": {"tua": 0.1}}, "active_learning.tua: unknown key"),
        ({"name": "x", "active_learning": {"M": 0}}, "active_learning.M"),
        ({"name": "x", "active_learning": {"tau": -1}}, "active_learning.tau"),
        ({"name": "x", "curriculum": {"conditions": ["fb", "xx"]}}, "unknown condition 'xx'"),
        ({"name": "x", "curriculum": {"difficulties": ["easy", "extreme"]}}, "unknown difficulty 'extreme'"),
        ({"name": "x", "curriculum": {"conditions": ["fb", "fb"]}}, "listed twice"),
        ({"name": "x", "detector": {"family": "ssd"}}, "detector.family"),
        ({"name": "x", "render": {"backend": "eevee"}}, "render.backend"),
        ({"name": "x", "render": {"image_size": 8}}, "render.image_size"),
        ({"name": "x", "bogus": 1}, "bogus: unknown key"),
        ({"name": "x", "detector": {"learning_rate": float("inf")}}, "detector.learning_rate"),
        ({"seed": 1}, "name: Field required"),
        ({"name": "   "}, "name"),
    ],
)
def test_errors_name_the_offending_key(data, key):
    with pytest.raises(ConfigError) as error:
        parse_config(data)
    assert key in str(error.value)


def test_non_mapping_and_non_yaml_are_rejected_clearly():
    with pytest.raises(ConfigError, match="mapping"):
        parse_config_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="not YAML"):
        parse_config_text("name: [unclosed")
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(Path("/nonexistent/config.yaml"))


def test_json_is_accepted_as_yaml():
    config = parse_config_text('{"name": "j", "active_learning": {"M": 2}}')
    assert config.active_learning.M == 2


def test_config_round_trips_through_json():
    config = load_config(REPO_ROOT / "configs/smoke.yaml")
    assert parse_config(config.model_dump(mode="json")) == config


def test_a_mixed_stage_ends_the_curriculum_with_its_own_settings():
    config = load_config(REPO_ROOT / "configs/quick.yaml")
    stages = config.stage_order()
    assert stages[:21] == [(c, d) for c in ("fb", "mb", "po", "de", "eo", "sc", "li") for d in ("easy", "medium", "hard")]
    assert stages[21:] == [("mixed", "hard")]
    assert ("mixed", "hard") in config.test_pairs()
    mixed = config.stage_active_learning("mixed")
    assert (mixed.m, mixed.t, mixed.max_increments, mixed.tau) == (150, 110, 5, 0.02)
    assert mixed.training_set == "grow" and config.active_learning.training_set == "reset"
    assert (mixed.M, mixed.N) == (2, 2) != (config.active_learning.M, config.active_learning.N)
    assert config.stage_active_learning("fb") == config.active_learning
    draw = config.mixed_draw()
    assert draw.conditions_per_image == (3, 6) and draw.negatives == 0.1 and draw.draw_from == ()


@pytest.mark.parametrize(
    ("mixed", "key"),
    [
        ({"conditions_per_image": [3, 2]}, "conditions_per_image: needs 1 <= low <= high"),
        ({"conditions_per_image": [1, 40]}, "only 17 to draw from"),
        ({"draw_from": ["fb", "zz"]}, "draw_from[1]: unknown condition 'zz'"),
        ({"difficulties": ["brutal"]}, "unknown difficulty 'brutal'"),
        ({"negatives": 0.95}, "curriculum.mixed.negatives"),
        ({"active_learning": {"t": 0}}, "curriculum.mixed.active_learning.t"),
        ({"active_learning": {"q": 1}}, "curriculum.mixed.active_learning.q: unknown key"),
    ],
)
def test_bad_mixed_stages_name_the_key(mixed, key):
    with pytest.raises(ConfigError) as caught:
        parse_config({"name": "x", "curriculum": {"mixed": mixed}})
    assert key in str(caught.value)


def test_covers_table3_all_and_curriculum():
    base = {"name": "x", "curriculum": {"conditions": ["fb"], "difficulties": ["easy"], "mixed": {}}}
    pairs = {covers: parse_config({**base, "test_set": {"covers": covers}}).test_pairs() for covers in ("table3", "all", "curriculum")}
    assert len(pairs["table3"]) == 21 and len(pairs["all"]) == 51
    assert pairs["curriculum"] == [("fb", "easy"), ("mixed", "hard")]


def test_a_mixed_stage_may_grow_its_training_set_while_the_others_reset():
    config = parse_config({"name": "g", "curriculum": {"mixed": {"active_learning": {"training_set": "grow"}}}})
    assert config.stage_active_learning("mixed").training_set == "grow"
    assert config.stage_active_learning("fb").training_set == "reset"
    with pytest.raises(ConfigError, match="training_set"):
        parse_config({"name": "g", "curriculum": {"mixed": {"active_learning": {"training_set": "keep"}}}})
