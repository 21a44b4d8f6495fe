"""`foldwise study`: one experiment per detector and per reset/grow choice under one study id,
then the figures side by side; the API lists a study's experiments."""

from __future__ import annotations

import pytest
import yaml
from fastapi.testclient import TestClient
from sqlalchemy import select
from typer.testing import CliRunner

from db.models import Experiment
from db.session import session_scope
from services.cli import app
from tests.services.flow_helpers import config


def _config_file(tmp_path):
    path = tmp_path / "study.yaml"
    path.write_text(yaml.safe_dump(config().model_dump(mode="json")))
    return path


def test_a_study_runs_each_variant_under_one_id_and_draws_them_together(fakes, tmp_path):  # noqa: F811
    result = CliRunner().invoke(app, [
        "study", str(_config_file(tmp_path)), "--detectors", "faster_rcnn,yolo", "--training-set", "reset,grow",
        "--name", "detectors-and-sets", "--out", str(tmp_path / "figures"),
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    with session_scope() as session:
        experiments = session.scalars(select(Experiment).order_by(Experiment.id)).all()
        variants = [(e.study, e.name, e.config["detector"]["family"], e.config["active_learning"]["training_set"], e.status.value)
                    for e in experiments]  # fmt: skip
    assert variants == [
        ("detectors-and-sets", f"flow-{family}-{choice}", family, choice, "finished")
        for family in ("faster_rcnn", "yolo") for choice in ("reset", "grow")
    ]  # fmt: skip
    ids = "-".join(str(e.id) for e in experiments)
    assert (tmp_path / "figures" / f"fig4-experiments-{ids}.svg").is_file()
    assert "study detectors-and-sets: experiments" in result.output

    from services.api.app import create_app

    listed = TestClient(create_app()).get("/experiments", params={"study": "detectors-and-sets"}).json()
    assert [item["id"] for item in listed] == [e.id for e in experiments]
    assert TestClient(create_app()).get("/experiments", params={"study": "other"}).json() == []


def test_an_unknown_detector_is_one_line_before_any_work(fakes, tmp_path):  # noqa: F811
    result = CliRunner().invoke(app, ["study", str(_config_file(tmp_path)), "--detectors", "faster_rcnn,ssd"])
    assert result.exit_code == 2
    assert result.output.strip() == "error: --detectors: unknown value 'ssd'; known: faster_rcnn, fast_rcnn, yolo"
    with session_scope() as session:
        assert session.scalars(select(Experiment)).all() == []


@pytest.mark.parametrize("name", ["", "a\x00b", "two\nlines", "x" * 201])
def test_a_study_name_that_cannot_be_stored_is_one_line_before_any_work(fakes, tmp_path, name):  # noqa: F811
    # The API refuses these names; the CLI recorded them (a NUL only reaches it from Python: argv has none).
    result = CliRunner().invoke(app, ["study", str(_config_file(tmp_path)), "--name", name])
    assert result.exit_code == 2
    assert result.output == f"error: --name: a study name is one line of 1 to 200 printable characters, got {name!r}\n"
    with session_scope() as session:
        assert session.scalars(select(Experiment)).all() == []
