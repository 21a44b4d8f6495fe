"""`foldwise baseline`: the paper's Table 2 from canonical training images, every condition
scored at each difficulty beside the paper's figures."""

from __future__ import annotations

import csv

import yaml
from sqlalchemy import select
from typer.testing import CliRunner

from foldwise.settings import REPO_ROOT
from services.cli import app


def test_table2_scores_each_condition_at_each_difficulty_beside_the_paper(tmp_path):
    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["detector"] = {**config.get("detector", {}), "family": "yolo", "input_size": 64, "num_threads": 1}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(config))
    result = CliRunner().invoke(app, [
        "baseline", str(path), "--out", str(tmp_path / "b"), "--train-images", "4", "--iterations", "2",
        "--test-per-pair", "1", "--conditions", "fb,cl,wr",
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(open(tmp_path / "b" / "table2.csv")))
    assert [row["condition"] for row in rows] == ["fb", "cl", "wr"]
    assert [row["name"] for row in rows] == ["focus blur", "clutter", "wrinkles"]
    assert [row["paper_fast_rcnn"] for row in rows] == ["0.3377", "0.9521", "0.9434"]
    for row in rows:
        assert all(row[d] != "" and 0.0 <= float(row[d]) <= 1.0 for d in ("easy", "medium", "hard", "map"))
    assert "Table 2: trained on canonical images only (yolo)" in result.output


def test_an_unknown_condition_is_one_line(tmp_path):
    result = CliRunner().invoke(
        app, ["baseline", str(REPO_ROOT / "configs/smoke.yaml"), "--out", str(tmp_path), "--conditions", "fb,zz"]
    )
    assert result.exit_code == 2 and "--conditions: unknown value 'zz'; known: fb, mb" in result.output


def test_table2_rows_take_each_condition_from_the_breakdown_and_leave_a_missing_score_empty(tmp_path):
    from services.baseline import table2_rows, write_table2_csv

    # an evaluation's breakdown where sc/hard had no rendered test image, and sn none at all
    breakdown = {
        "condition": {"sc": {"map": 0.25}},
        "condition/difficulty": {"sc/easy": {"map": 0.5}, "sc/medium": {"map": 0.125}},
    }
    rows = table2_rows(breakdown, ["sc", "sn"], ["easy", "medium", "hard"])
    assert [(r.condition, r.name, r.map, r.paper) for r in rows] == [
        ("sc", "scale", 0.25, 0.5947),
        ("sn", "sensor noise and compression", None, 0.8349),
    ]
    assert rows[0].by_difficulty == {"easy": 0.5, "medium": 0.125, "hard": None}
    path = write_table2_csv(rows, ["easy", "medium", "hard"], tmp_path / "t.csv")
    assert path.read_text().splitlines() == [
        "condition,name,map,easy,medium,hard,paper_fast_rcnn",
        "sc,scale,0.2500,0.5000,0.1250,,0.5947",
        "sn,sensor noise and compression,,,,,0.8349",
    ]


def test_an_experiments_table2_reads_its_latest_score_while_it_runs_and_its_final_model_once_finished(database):
    from db.models import Evaluation, ExperimentStatus, Model, ModelStatus, Stage
    from db.session import session_scope
    from foldwise.config import parse_config
    from services import queries
    from services.baseline import experiment_table2

    config = parse_config(
        {"name": "b", "kind": "canonical_baseline", "curriculum": {"conditions": ["fb"], "difficulties": ["easy"]}}
    )
    with session_scope() as session:
        experiment = queries.create_experiment(session, config)
        experiment.status = ExperimentStatus.running
        stage = Stage(experiment=experiment, order=0, condition="canonical", difficulty="canonical")
        session.add(stage)
        session.flush()
        for k, score in ((1, 0.75), (2, 0.25)):
            model = Model(experiment_id=experiment.id, stage_id=stage.id, increment=k, detector="faster_rcnn",
                          iterations=1, status=ModelStatus.evaluated)  # fmt: skip
            session.add(model)
            session.flush()
            breakdown = {"condition": {"fb": {"map": score}}, "condition/difficulty": {"fb/easy": {"map": score}}}
            session.add(Evaluation(model_id=model.id, map=score, details={"breakdown": breakdown}, eval_seconds=0.0))
        experiment_id = experiment.id
    with session_scope() as session:
        running = experiment_table2(session, experiment_id)
        assert (running.increment, running.final, running.rows[0].by_difficulty) == (2, False, {"easy": 0.25})
        experiment = queries.get_experiment(session, experiment_id)
        first = session.scalar(select(Model).where(Model.increment == 1))
        experiment.status, experiment.final_model_id = ExperimentStatus.finished, first.id
    with session_scope() as session:
        final = experiment_table2(session, experiment_id)
        assert (final.model_id, final.final, final.rows[0].map) == (first.id, True, 0.75)
