"""The paper's figures from the database: every figure written as PNG, SVG and CSV, its numbers
equal to the record, its text naming the axes, the score cut and the conditions in full."""

from __future__ import annotations

import csv

from typer.testing import CliRunner

from db.session import session_scope
from services import queries
from services.cli import app
from services.embedded import run_to_completion, start_experiment
from services.figures import FIGURES, write_figures
from tests.services.flow_helpers import config


def _two_runs(fakes):  # noqa: F811
    fakes.scores = {(0, 1): 0.2, (0, 2): 0.61, (0, 3): 0.6}
    first = start_experiment(config())
    assert run_to_completion(first) == "finished"
    fakes.scores = {(0, 1): 0.4, (0, 2): 0.4, (1, 1): 0.9}
    second = start_experiment(config(detector={"family": "yolo"}))
    assert run_to_completion(second) == "finished"
    return first, second


def test_every_figure_is_written_with_its_numbers(fakes, tmp_path):  # noqa: F811
    first, second = _two_runs(fakes)
    written = write_figures([first, second], tmp_path)
    assert set(written) == set(FIGURES)
    for paths in written.values():
        assert [p.suffix for p in paths] == [".png", ".svg", ".csv"] and all(p.stat().st_size > 0 for p in paths)

    with session_scope() as session:
        history = queries.history(session, first)
        stages = queries.stages(session, second)
    fig7 = [row for row in csv.DictReader(open(written["fig7"][2])) if row["experiment"] == str(first)]
    assert [float(row["map"]) for row in fig7] == [entry["map"] for entry in history]
    fig8 = {
        (row["condition"], row["difficulty"]): row
        for row in csv.DictReader(open(written["fig8"][2]))
        if row["experiment"] == str(second)
    }
    for stage in stages:
        assert float(fig8[(stage["condition"], stage["difficulty"])]["best_map"]) == stage["best_map"]
    fig6 = [row for row in csv.DictReader(open(written["fig6"][2])) if row["experiment"] == str(first)]
    assert float(fig6[-1]["cumulative_train_seconds"]) == sum(entry["train_seconds"] for entry in history)
    fig5 = {(row["condition"], row["difficulty"]): row["best_map"] for row in csv.DictReader(open(written["fig5"][2]))
            if row["experiment"] == str(second)}  # fmt: skip
    for stage in stages:  # a bar per condition and difficulty: each stage's best
        assert float(fig5[(stage["condition"], stage["difficulty"])]) == stage["best_map"]
    assert "difficulty trained" in written["fig5"][1].read_text()

    svg = written["fig4"][1].read_text()
    for text in (
        "focus blur, easy",
        "scale, hard",
        "increment k",
        "score ≥ 0.8, IoU ≥ 0.5",
        "faster_rcnn (experiment",
        "yolo (experiment",
    ):
        assert text in svg, text
    assert "the best model of each stage" in written["fig8"][1].read_text()


def test_foldwise_report_draws_the_figures_of_several_experiments(fakes, tmp_path):  # noqa: F811
    first, second = _two_runs(fakes)
    result = CliRunner().invoke(app, ["report", str(first), str(second), "--figures", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / f"fig4-experiments-{first}-{second}.svg").is_file()
    assert (tmp_path / f"experiment-{second}.png").is_file()
    missing = CliRunner().invoke(app, ["report", "999", "--figures", "--out", str(tmp_path)])
    assert missing.exit_code == 2 and "experiment 999 does not exist" in missing.output
