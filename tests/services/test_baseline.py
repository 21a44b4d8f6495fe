"""`foldwise baseline`: the paper's Table 2 from canonical training images, every condition
scored at each difficulty beside the paper's figures."""

from __future__ import annotations

import csv

import yaml
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
    result = CliRunner().invoke(app, ["baseline", str(REPO_ROOT / "configs/smoke.yaml"), "--out", str(tmp_path), "--conditions", "fb,zz"])
    assert result.exit_code == 2 and "--conditions: unknown value 'zz'; known: fb, mb" in result.output
