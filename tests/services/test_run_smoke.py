"""`foldwise run configs/smoke.yaml`: the real renderer and detector, in one process.

The whole of Algorithm 1 on the embedded default (SQLite, eager Celery): afterwards the
database holds every θ, every ω with its parent, and every P entry, and the report exists.
"""

from __future__ import annotations

import csv

from sqlalchemy import select
from typer.testing import CliRunner

from db.models import Evaluation, Experiment, Model, ParameterSet, RenderStatus, Stage
from db.session import session_scope
from foldwise import store
from foldwise.settings import REPO_ROOT


def test_smoke_run_records_everything(database, tmp_path):
    from services.cli import _register_worker_commands, app

    _register_worker_commands()
    result = CliRunner().invoke(app, ["run", str(REPO_ROOT / "configs/smoke.yaml"), "--report-dir", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "fb" in result.output and "plateau" in result.output
    assert "final model: " in result.output and "views (sizes" not in result.output  # one view: nothing to add

    with session_scope() as session:
        (experiment,) = session.scalars(select(Experiment)).all()
        stages = session.scalars(select(Stage).order_by(Stage.order)).all()
        thetas = session.scalars(select(ParameterSet)).all()
        models = session.scalars(select(Model).order_by(Model.id)).all()
        evaluations = session.scalars(select(Evaluation)).all()
        assert experiment.status.value == "finished"
        assert [(s.condition, s.difficulty) for s in stages] == [("fb", "easy"), ("fb", "hard")]
        assert all(s.end_reason is not None and s.best_model_id for s in stages)

        # every θ rendered once, to its id-derived file, with a valid box inside the image
        assert thetas and all(t.status == RenderStatus.rendered for t in thetas)
        assert len({t.image_path for t in thetas}) == len(thetas)
        for theta in thetas:
            assert theta.image_path == store.image_path(experiment.id, theta.id)
            assert store.resolve(theta.image_path).is_file()
            x0, y0, x1, y1 = theta.box
            assert 0 <= x0 < x1 <= 64 and 0 <= y0 < y1 <= 64
            assert 0 < theta.visible_fraction <= 1

        # every ω has its checkpoint and its parent ω_in; every P entry is there
        assert len(evaluations) == len(models) == sum(1 for _ in models)
        by_id = {m.id: m for m in models}
        for model in models:
            assert store.resolve(model.checkpoint_path).is_file()
            assert model.attempts == 1
            if model.increment > 1:
                assert by_id[model.parent_id].increment == model.increment - 1
        assert models[0].parent_id is None
        second_stage_first = next(m for m in models if m.stage_id == stages[1].id and m.increment == 1)
        assert second_stage_first.parent_id == stages[0].best_model_id
        assert all(e.map is None or 0.0 <= e.map <= 1.0 for e in evaluations)
        # the paper's breakdown per (c, δ) and pycocotools' metrics travel with every P entry
        assert all({"fb/easy", "fb/hard"} <= set(e.details["breakdown"]["condition/difficulty"]) for e in evaluations)
        assert all(e.details["coco"] and "AP50" in e.details["coco"] for e in evaluations)

    png = tmp_path / f"experiment-{experiment.id}.png"
    with open(tmp_path / f"experiment-{experiment.id}.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert len(rows) == len(evaluations)
    assert float(rows[-1]["cumulative_train_seconds"]) > 0


def test_a_mixed_stage_records_every_object_and_trains_on_images_without_one(database, tmp_path):
    import yaml

    from services.cli import _register_worker_commands, app

    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["name"] = "smoke-mixed"
    config["curriculum"] = {
        "conditions": ["fb"],
        "difficulties": ["easy"],
        "mixed": {
            "conditions_per_image": [2, 2],
            "draw_from": ["mo", "cl", "or"],
            "negatives": 0.4,
            "active_learning": {"max_increments": 2, "tau": 0.0, "training_set": "grow"},
        },
    }
    path = tmp_path / "mixed.yaml"
    path.write_text(yaml.safe_dump(config))
    _register_worker_commands()
    result = CliRunner().invoke(app, ["run", str(path), "--report-dir", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "mixed" in result.output

    with session_scope() as session:
        stages = session.scalars(select(Stage).order_by(Stage.order)).all()
        assert [(s.condition, s.difficulty) for s in stages] == [("fb", "easy"), ("mixed", "hard")]
        mixed = session.scalars(select(ParameterSet).where(ParameterSet.condition == "mixed")).all()
        assert mixed and all(t.status == RenderStatus.rendered for t in mixed)
        counts = [len(t.objects) for t in mixed]
        assert 0 in counts and max(counts) >= 2  # images without the object, and with several
        for theta in mixed:
            assert len(theta.theta["components"]) == 2
            assert (theta.box is None) == (theta.objects == [])
            if theta.objects:
                assert theta.objects[0]["box"] == theta.box and theta.objects[0]["label"] == theta.label
        evaluation = session.scalars(select(Evaluation).order_by(Evaluation.id.desc())).first()
        assert "mixed/hard" in evaluation.details["breakdown"]["condition/difficulty"]
        # The mixed stage grows its training set (its own setting); the fb stage resets it.
        m = config["active_learning"]["m"]
        sizes = {
            (model.stage_id, model.increment): model.train_stats["training_images"]
            for model in session.scalars(select(Model)).all()
        }
        assert sizes[(stages[1].id, 1)] == m and sizes[(stages[1].id, 2)] == 2 * m
        assert all(size == m for (stage_id, _), size in sizes.items() if stage_id == stages[0].id)


def test_the_loop_scores_at_the_trained_view_when_told_and_the_checkpoint_keeps_its_views(
    database, tmp_path, monkeypatch
):
    """evaluation.views: trained — every increment's P comes from the network at one view (the
    detector's own size, upright, no texture check), recorded with the evaluation, while the
    checkpoint still detects at the views its config names, its texture check on (what
    `foldwise detect`, REST and bench/wild.py get)."""
    import yaml

    import workers.train.checkpoint as checkpoint
    from services.cli import _register_worker_commands, app

    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["name"] = "smoke-views"
    config["curriculum"]["difficulties"] = ["easy"]
    config["active_learning"]["max_increments"] = 2
    config["detector"].update(
        {"test_sizes": [64, 96], "test_turns": [0, 1], "view_vote": 0.7, "texture_check": True, "texture_search": True}
    )
    config["evaluation"]["views"] = "trained"
    path = tmp_path / "views.yaml"
    path.write_text(yaml.safe_dump(config))

    asked = []
    real_detect = checkpoint.detect_object

    def recording_detect(detector, images, *args, **kwargs):
        asked.append((kwargs.get("test_sizes"), kwargs.get("test_turns"), kwargs.get("texture_check", True)))
        return real_detect(detector, images, *args, **kwargs)

    monkeypatch.setattr(checkpoint, "detect_object", recording_detect)
    _register_worker_commands()
    result = CliRunner().invoke(app, ["run", str(path), "--report-dir", str(tmp_path)])
    assert result.exit_code == 0, result.output

    with session_scope() as session:
        evaluations = session.scalars(select(Evaluation)).all()
        model = session.scalars(select(Model).order_by(Model.id.desc())).first()
        assert evaluations and asked == [((), (), False)] * len(evaluations)
        assert all(
            e.details["views"]
            == {"test_sizes": [], "test_turns": [], "view_vote": None, "texture_check": False, "texture_search": False}
            for e in evaluations
        )
        loaded = checkpoint.load_detector(store.resolve(model.checkpoint_path))
        final = session.get(Model, session.scalars(select(Experiment)).one().final_model_id)
        final_path = store.resolve(final.checkpoint_path)
    assert (loaded.model.test_sizes, loaded.model.test_turns, loaded.model.view_vote) == ((64, 96), (0, 1), 0.7)
    # ... and its texture check, with the experiment's textures (the loop scored the network alone).
    assert loaded.texture_check().search and sorted(loaded.textures) == sorted(loaded.classes)
    # The run names the detector it hands over, and says its table's mAP is one view's, not the detector's.
    assert f"final model: {final_path} (model {final.id})" in result.output
    assert (
        "the final model detects at 4 views (sizes [64, 96], quarter turns [0, 1]; they vote at 0.7; its texture "
        "checks the boxes and searches the image for sheets they miss)" in " ".join(result.output.split())
    )


def test_a_final_model_whose_checkpoint_is_gone_is_named_as_missing(database, capsys):
    """The run's last lines name the detector; a checkpoint missing from the store is said, not printed as a path."""
    from foldwise.config import parse_config
    from services.cli import _print_final_model

    _print_final_model(parse_config({"name": "gone"}), 999)
    assert "final model: model 999 does not exist" in capsys.readouterr().out


def test_members_run_side_by_side_and_hand_over_one_ensemble(database, tmp_path):
    """foldwise run --members 2: two curricula (seeds seed and seed+1), each in its own process
    with its share of the threads, under one study; their final models, joined whole into one
    ensemble file, are what the run hands over."""
    import torch
    import yaml

    from foldwise.settings import get_settings
    from services.artifacts import checkpoint_file
    from services.cli import _register_worker_commands, app
    from workers.train.checkpoint import load_detector, read_checkpoint

    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["curriculum"]["difficulties"] = ["easy"]
    path = tmp_path / "one-stage.yaml"
    path.write_text(yaml.safe_dump(config))
    _register_worker_commands()
    result = CliRunner().invoke(app, ["run", str(path), "--members", "2"])
    assert result.exit_code == 0, result.output
    assert "2 curricula side by side (seeds 1, 2; 1 thread each)" in result.output

    with session_scope() as session:
        experiments = session.scalars(select(Experiment).order_by(Experiment.id)).all()
        assert [(e.name, e.seed, e.status.value) for e in experiments] == [
            ("smoke-seed1", 1, "finished"),
            ("smoke-seed2", 2, "finished"),
        ]
        (study,) = {e.study for e in experiments}
        finals = [checkpoint_file(session, e.final_model_id) for e in experiments]
    ensemble_path = get_settings().data_dir / "studies" / study / "ensemble.pt"
    assert f"final model: {ensemble_path}, an ensemble of model" in result.output.replace("\n", "")
    ensemble = load_detector(ensemble_path)
    assert len(ensemble.meta["members"]) == 2
    # Its runtime graph beside it: detection runs the network through onnxruntime.
    assert f"runtime graph: {ensemble_path}.onnx" in result.output.replace("\n", "")
    assert ensemble.runtime is not None and ensemble.runtime.classes == ensemble.classes
    for member, final in zip(ensemble.model.members, finals):
        for name, tensor in read_checkpoint(final)["state_dict"].items():
            assert torch.equal(member.state_dict()[name], tensor), name
    assert not all(
        torch.equal(a, b)
        for a, b in zip(
            ensemble.model.members[0].state_dict().values(), ensemble.model.members[1].state_dict().values()
        )
    )  # two seeds, two networks


def test_members_need_a_kind_that_hands_over_a_final_model(database):
    from services.cli import app

    result = CliRunner().invoke(app, ["run", str(REPO_ROOT / "configs/learnability_quick.yaml"), "--members", "2"])
    assert result.exit_code == 2 and "--members: only kind active_learning" in result.output
    with session_scope() as session:
        assert session.scalars(select(Experiment)).all() == []


def test_an_experiment_whose_process_died_is_marked_failed_and_an_ended_one_keeps_its_status(database):
    from foldwise.config import parse_config
    from services import queries

    with session_scope() as session:
        running = queries.create_experiment(session, parse_config({"name": "a"}))
        finished = queries.create_experiment(session, parse_config({"name": "b"}))
        finished.status = finished.status.__class__.finished
        session.flush()
        assert queries.fail_experiment(session, running.id, "its process ended with exit code -9")
        assert not queries.fail_experiment(session, finished.id, "too late")
    with session_scope() as session:
        assert queries.get_experiment(session, running.id).status.value == "failed"
        assert queries.get_experiment(session, running.id).error == "its process ended with exit code -9"
        assert queries.get_experiment(session, finished.id).status.value == "finished"
