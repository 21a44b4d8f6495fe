"""Failure-driven θ sampling through the real scheduler (curriculum.mixed.sampling: failure):
each mixed increment draws its (condition, difficulty) cells where the latest scored model
fails, and every θ records why it was drawn."""

from __future__ import annotations

from collections import Counter

from sqlalchemy import select

from db.models import Model, ParameterSet, Split, Stage
from db.session import session_scope
from services.embedded import run_to_completion, start_experiment
from tests.services.flow_helpers import config

MIXED_ONLY = {
    "conditions": ["fb", "sc"],
    "difficulties": ["easy", "hard"],
    "single_condition_stages": False,
    "mixed": {"difficulties": ["easy", "hard"], "conditions_per_image": [1, 1], "draw_from": ["fb", "sc"]},
}
# The model fails on focus blur and is perfect on scale, at every level a mixed image may draw
# (a level the test set lacks would count at the mean failure).
CELLS = {f"{c}/{d}": float(c == "sc") for c in ("fb", "sc") for d in ("easy", "medium", "hard")}


def _training_draws(experiment_id: int) -> list[tuple[int, dict, list[str]]]:
    with session_scope() as session:
        rows = session.scalars(
            select(ParameterSet)
            .where(ParameterSet.experiment_id == experiment_id, ParameterSet.split == Split.train)
            .order_by(ParameterSet.id)
        ).all()
        return [
            (row.increment, row.drawn_for, [c["condition"] + "/" + c["difficulty"] for c in row.theta["components"]])
            for row in rows
        ]


def _run(fakes, sampling: str, share: float = 1.0) -> int:
    fakes.cell_scores = CELLS
    mixed = {**MIXED_ONLY["mixed"], "sampling": sampling, "failure_share": share}
    experiment_id = start_experiment(
        config(curriculum={**MIXED_ONLY, "mixed": mixed}, active_learning={"max_increments": 3, "m": 12})
    )
    assert run_to_completion(experiment_id) == "finished"
    return experiment_id


def test_mixed_stages_alone_train_and_every_cell_is_still_tested(fakes):
    experiment_id = _run(fakes, "uniform")
    with session_scope() as session:
        stages = session.execute(
            select(Stage.condition, Stage.difficulty).where(Stage.experiment_id == experiment_id).order_by(Stage.order)
        ).all()
        tested = set(
            session.execute(
                select(ParameterSet.condition, ParameterSet.difficulty).where(
                    ParameterSet.experiment_id == experiment_id, ParameterSet.split == Split.test
                )
            ).all()
        )
    assert [tuple(stage) for stage in stages] == [("mixed", "easy"), ("mixed", "hard")]
    assert tested == {(c, d) for c in ("fb", "sc", "mixed") for d in ("easy", "hard")}


def test_uniform_draws_both_conditions_and_says_so(fakes):
    draws = _training_draws(_run(fakes, "uniform"))
    assert {reason["sampling"] for _, reason, _ in draws} == {"uniform"}
    conditions = Counter(cell.split("/")[0] for _, _, cells in draws for cell in cells)
    assert conditions["fb"] > 0 and conditions["sc"] > 0


def test_failure_driven_draws_only_where_the_model_fails_once_a_model_is_scored(fakes):
    experiment_id = _run(fakes, "failure", share=1.0)
    draws = _training_draws(experiment_id)
    with session_scope() as session:
        scored = set(session.scalars(select(Model.id).where(Model.experiment_id == experiment_id)))
    before = [(reason, cells) for _, reason, cells in draws if reason["sampling"] == "uniform"]
    after = [(reason, cells) for _, reason, cells in draws if reason["sampling"] == "failure"]
    # Increments 1 and 2 of the first stage are drawn before any model is scored.
    assert before and all(reason["why"] == "no model scored yet" for reason, _ in before)
    assert after, "no increment followed a scored model"
    for reason, cells in after:
        assert reason["model_id"] in scored
        assert all(cell.startswith("fb/") for cell in cells), cells  # scale's AP is 1: never drawn
        assert set(reason["cells"]) == set(cells)
        assert all(entry["ap"] == 0.0 and entry["p"] > 0 for entry in reason["cells"].values())


def test_failure_share_keeps_every_cell_in_the_draw(fakes):
    draws = _training_draws(_run(fakes, "failure", share=0.5))
    followed = Counter(
        cell.split("/")[0] for _, reason, cells in draws if reason["sampling"] == "failure" for cell in cells
    )
    # p(fb) = 0.5 * 1/2 + 0.5 * 1 = 0.75, p(sc) = 0.25.
    assert followed["sc"] > 0
    assert followed["fb"] > 1.5 * followed["sc"]
