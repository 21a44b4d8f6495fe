"""`foldwise run` of a learnability experiment (Algorithm 2) on a smoke-sized config, end to end
in one process: κ increments per stage, no stopping rule, each difficulty from the last model
of the one before, each condition from the initial weights and scored on its own test set,
and a report with the learnability order and Spearman's ρ; with ``learnability.start: canonical``,
a canonical stage first and every condition from its last model."""

from __future__ import annotations

import csv

from sqlalchemy import select

from db.models import Evaluation, Experiment, Model, Stage, StageEndReason
from db.session import session_scope
from tests.services.kinds import assert_scored_on_own_condition, report, run_in_process, smoke_kind_config

KAPPA = 2


def _learnability_config(tmp_path, **settings):
    return smoke_kind_config(tmp_path, "learnability", {"kappa": KAPPA, **settings})


def test_a_learnability_run_trains_kappa_increments_from_the_last_model(database, tmp_path):
    report_dir = tmp_path / "report"
    result = run_in_process(_learnability_config(tmp_path), report_dir)
    assert "Spearman" in result.output and "kappa" in result.output

    with session_scope() as session:
        (experiment,) = session.scalars(select(Experiment)).all()
        stages = session.scalars(select(Stage).order_by(Stage.order)).all()
        models = session.scalars(select(Model).order_by(Model.id)).all()
        evaluations = {e.model_id: e for e in session.scalars(select(Evaluation))}
        assert experiment.status.value == "finished"
        assert [(s.condition, s.difficulty) for s in stages] == [
            ("fb", "easy"), ("fb", "hard"), ("po", "easy"), ("po", "hard"),
        ]  # fmt: skip
        by_stage = {s.id: sorted((m for m in models if m.stage_id == s.id), key=lambda m: m.increment) for s in stages}
        for stage in stages:
            # exactly κ increments, ended by κ and not by a stopping rule
            assert [m.increment for m in by_stage[stage.id]] == list(range(1, KAPPA + 1))
            assert stage.end_reason == StageEndReason.kappa
            # within a stage each increment starts from the one before (ω_in ← ω_k)
            first, *rest = by_stage[stage.id]
            assert first.parent_id == stage.init_model_id
            assert [m.parent_id for m in rest] == [m.id for m in by_stage[stage.id][:-1]]
        fb_easy, fb_hard, po_easy, po_hard = stages
        # a condition's first difficulty starts from the initial weights, not another condition's model
        assert fb_easy.init_model_id is None and po_easy.init_model_id is None
        # the next difficulty starts from the previous difficulty's LAST model ω_κ
        assert fb_hard.init_model_id == by_stage[fb_easy.id][-1].id
        assert po_hard.init_model_id == by_stage[po_easy.id][-1].id
        # every model is scored on its own condition's test set only
        assert_scored_on_own_condition(stages, by_stage, evaluations)

    with open(report_dir / f"learnability-{experiment.id}.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert sorted(row["condition"] for row in rows) == ["fb", "po"]
    assert all(int(row["increments"]) == 2 * KAPPA for row in rows)
    assert {row["paper_rank"] for row in rows} == {"1", "6"}
    # with two conditions ρ is ±1 unless the scores tie (then it is undefined and left empty)
    rho = {row["spearman_rho"] for row in rows}
    assert len(rho) == 1 and rho.pop() in {"1.0000", "-1.0000", ""}
    fb, po = sorted(rows, key=lambda row: row["condition"])
    if fb["score"] != po["score"]:
        assert rows[0]["spearman_rho"] == ("1.0000" if float(fb["score"]) > float(po["score"]) else "-1.0000")

    # Fig. 4 and 5 of the learnability experiment are drawn
    result = report(str(experiment.id), "--out", str(report_dir), "--figures")
    assert "the paper's: fb > po; Spearman's ρ" in result.output  # both orders, so that ρ can be read
    for name in ("fig4", "fig5"):
        png = report_dir / f"{name}-experiments-{experiment.id}.png"
        assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"

    # ... and the API serves the same order; an Algorithm 1 experiment has none (409)
    from fastapi.testclient import TestClient

    from foldwise.config import parse_config
    from services import queries
    from services.api.app import create_app

    with session_scope() as session:
        other = queries.create_experiment(session, parse_config({"name": "active"})).id
    client = TestClient(create_app(broker_timeout_s=0.5, ping_timeout_s=0.3))
    answer = client.get(f"/experiments/{experiment.id}/learnability")
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert [row["condition"] for row in body["conditions"]] == [row["condition"] for row in rows]
    assert body["compared"] == [row["condition"] for row in rows] and body["paper_order"][0] == "fb"
    assert client.get(f"/experiments/{other}/learnability").status_code == 409


CANONICAL_INCREMENTS = 2


def test_a_canonical_start_trains_the_canonical_stage_first_and_every_condition_from_its_last_model(database, tmp_path):
    path = _learnability_config(tmp_path, start="canonical", canonical_increments=CANONICAL_INCREMENTS)
    report_dir = tmp_path / "report"
    run_in_process(path, report_dir)

    with session_scope() as session:
        (experiment,) = session.scalars(select(Experiment)).all()
        stages = session.scalars(select(Stage).order_by(Stage.order)).all()
        models = session.scalars(select(Model).order_by(Model.id)).all()
        evaluations = {e.model_id: e for e in session.scalars(select(Evaluation))}
        assert experiment.status.value == "finished"
        assert [(s.condition, s.difficulty) for s in stages] == [
            ("canonical", "canonical"), ("fb", "easy"), ("fb", "hard"), ("po", "easy"), ("po", "hard"),
        ]  # fmt: skip
        by_stage = {s.id: sorted((m for m in models if m.stage_id == s.id), key=lambda m: m.increment) for s in stages}
        canonical, fb_easy, fb_hard, po_easy, po_hard = stages
        # the canonical stage trains first, from the initial weights, for its fixed increments
        canonical_models = by_stage[canonical.id]
        assert [m.increment for m in canonical_models] == list(range(1, CANONICAL_INCREMENTS + 1))
        assert canonical.end_reason == StageEndReason.increments and canonical.init_model_id is None
        assert canonical_models[0].parent_id is None
        assert max(m.id for m in canonical_models) < min(m.id for m in models if m.stage_id != canonical.id)
        assert canonical.finished_at <= min(s.started_at for s in stages[1:])
        # ... scored on the whole test set, every condition of the curriculum
        for model in canonical_models:
            groups = set(evaluations[model.id].details["breakdown"]["condition/difficulty"])
            assert groups == {"fb/easy", "fb/hard", "po/easy", "po/hard"}
        # every condition's first difficulty starts from the canonical stage's LAST model
        last_canonical = canonical_models[-1].id
        for first in (fb_easy, po_easy):
            assert first.init_model_id == last_canonical
            assert by_stage[first.id][0].parent_id == last_canonical
        # later difficulties still start from the condition's previous difficulty's last model
        assert fb_hard.init_model_id == by_stage[fb_easy.id][-1].id
        assert po_hard.init_model_id == by_stage[po_easy.id][-1].id
        for stage in stages[1:]:
            assert [m.increment for m in by_stage[stage.id]] == list(range(1, KAPPA + 1))
            assert stage.end_reason == StageEndReason.kappa
        assert_scored_on_own_condition(stages[1:], by_stage, evaluations)

    # the canonical stage is no condition of the learnability order
    with open(report_dir / f"learnability-{experiment.id}.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert sorted(row["condition"] for row in rows) == ["fb", "po"]
    assert all(int(row["increments"]) == 2 * KAPPA for row in rows)

    # ... and the figures and the report still draw
    assert "Spearman" in report(str(experiment.id), "--out", str(report_dir), "--figures").output
    for name in ("fig4", "fig5", "fig7", "fig8"):
        png = report_dir / f"{name}-experiments-{experiment.id}.png"
        assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    # Fig. 5 gives the canonical stage one bar of its own, not a difficulty slot in every group
    with open(report_dir / f"fig5-experiments-{experiment.id}.csv") as handle:
        bars = list(csv.DictReader(handle))
    assert [(b["condition"], b["difficulty"]) for b in bars if "canonical" in (b["condition"], b["difficulty"])] == [
        ("canonical", "canonical")
    ]
    assert {b["difficulty"] for b in bars if b["condition"] != "canonical"} == {"easy", "hard"}
