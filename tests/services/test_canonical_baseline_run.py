"""`foldwise run` of a canonical baseline (the paper's Table 2) on a smoke-sized config, end to
end in one process: one stage of canonical images for a fixed number of increments, its last
model scored on every (condition, difficulty) of the test set, the scores stored with the
evaluation, and Table 2 beside the paper's in the report's CSV and the API."""

from __future__ import annotations

import csv

from sqlalchemy import select

from db.models import Evaluation, Experiment, Model, ParameterSet, Split, Stage, StageEndReason
from db.session import session_scope
from tests.services.kinds import DIFFICULTIES, report, run_in_process, smoke_kind_config

INCREMENTS = 2
# fb is in the paper's curriculum; wr (wrinkles) only in its Table 2, as a condition added since.
CONDITIONS = ["fb", "wr"]


def test_a_canonical_baseline_run_stores_every_conditions_score_and_reports_table_2(database, tmp_path):
    report_dir = tmp_path / "report"
    path = smoke_kind_config(tmp_path, "canonical_baseline", {"increments": INCREMENTS}, conditions=CONDITIONS)
    result = run_in_process(path, report_dir)
    assert "Table 2: trained on canonical images only (faster_rcnn, model" in result.output

    pairs = {f"{c}/{d}" for c in CONDITIONS for d in DIFFICULTIES}
    with session_scope() as session:
        (experiment,) = session.scalars(select(Experiment)).all()
        (stage,) = session.scalars(select(Stage)).all()
        models = session.scalars(select(Model).order_by(Model.increment)).all()
        evaluations = {e.model_id: e for e in session.scalars(select(Evaluation))}
        train = session.scalars(select(ParameterSet).where(ParameterSet.split == Split.train)).all()
        assert experiment.status.value == "finished"
        assert (stage.condition, stage.difficulty, stage.end_reason) == (
            "canonical",
            "canonical",
            StageEndReason.increments,
        )
        # a fixed number of increments from the initial weights, each from the one before
        assert [m.increment for m in models] == list(range(1, INCREMENTS + 1))
        assert stage.init_model_id is None and [m.parent_id for m in models] == [None, models[0].id]
        # the final model is the last one trained, the one Table 2 scores
        assert experiment.final_model_id == models[-1].id
        # it trained on canonical images only ...
        assert {row.theta["difficulty"] for row in train} == {"canonical"}
        # ... and every model is scored on every (condition, difficulty) of the test set, stored in P
        for model in models:
            assert set(evaluations[model.id].details["breakdown"]["condition/difficulty"]) == pairs
        stored = evaluations[models[-1].id].details["breakdown"]

    with open(report_dir / f"table2-{experiment.id}.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [row["condition"] for row in rows] == CONDITIONS
    assert [row["name"] for row in rows] == ["focus blur", "wrinkles"]
    assert [row["paper_fast_rcnn"] for row in rows] == ["0.3377", "0.9434"]
    for row in rows:
        assert float(row["map"]) == round(stored["condition"][row["condition"]]["map"], 4)
        for difficulty in DIFFICULTIES:
            expected = stored["condition/difficulty"][f"{row['condition']}/{difficulty}"]["map"]
            assert float(row[difficulty]) == round(expected, 4)

    # `foldwise report` writes and prints the same table
    again = tmp_path / "again"
    assert "Table 2" in report(str(experiment.id), "--out", str(again)).output
    assert (again / f"table2-{experiment.id}.csv").read_text() == (
        report_dir / f"table2-{experiment.id}.csv"
    ).read_text()

    # ... and the API serves it; an Algorithm 1 experiment has none (409), an unknown id is 404
    from fastapi.testclient import TestClient

    from foldwise.config import parse_config
    from services import queries
    from services.api.app import create_app

    with session_scope() as session:
        other = queries.create_experiment(session, parse_config({"name": "active"})).id
    client = TestClient(create_app(broker_timeout_s=0.5, ping_timeout_s=0.3))
    answer = client.get(f"/experiments/{experiment.id}/table2")
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert (body["model_id"], body["increment"], body["final"]) == (models[-1].id, INCREMENTS, True)
    assert body["difficulties"] == DIFFICULTIES
    assert [row["condition"] for row in body["conditions"]] == CONDITIONS
    for row in body["conditions"]:
        assert row["paper"] == float(next(r["paper_fast_rcnn"] for r in rows if r["condition"] == row["condition"]))
        assert row["by_difficulty"] == {
            d: stored["condition/difficulty"][f"{row['condition']}/{d}"]["map"] for d in DIFFICULTIES
        }
    assert client.get(f"/experiments/{other}/table2").status_code == 409
    assert client.get(f"/experiments/{other + 1}/table2").status_code == 404
