"""bench/render.py on a tiny setting: it runs end to end and its JSON holds what the render
issue's goals are read from (rates of both backends, their ratios, box agreement, the machine)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run_bench(tmp_path: Path, *args: str) -> dict:
    out = tmp_path / "render.json"
    command = [
        sys.executable,
        str(ROOT / "bench" / "render.py"),
        "--n-per-stage",
        "1",
        "--size",
        "32",
        "--own-pass-repeats",
        "1",
        "--parallel-repeats",
        "1",
        "--quiet",
        "--out",
        str(out),
        *args,
    ]
    finished = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert finished.returncode == 0, finished.stderr[-3000:]
    assert json.loads(finished.stdout) == json.loads(out.read_text())
    return json.loads(out.read_text())


def test_both_backends_give_rates_ratios_and_box_agreement(tmp_path):
    pytest.importorskip("bpy", reason="the blender backend needs bpy (the render extra)")
    report = _run_bench(tmp_path, "--samples", "1", "--processes", "1")
    thetas = report["settings"]["thetas"]
    assert thetas == 22  # canonical and 7 conditions x 3 difficulties, one θ each
    for backend in ("raster", "blender"):
        speed = report["speed"][backend]
        assert speed["images"] + speed["rejected"] == thetas and not speed["errors"]
        assert speed["images_per_second"] > 0
    own = report["speed"]["raster"]["own_passes"]
    assert len(own["passes"]) == 2 and all(p["errors"] == 0 for p in own["passes"])
    ratios = report["speed_ratio"]
    for value in (
        ratios["value"],
        ratios["interleaved"]["value"],
        ratios["render_stage"],
        ratios["all_cores"]["value"],
    ):
        assert math.isfinite(value) and value > 0
    assert ratios["value"] == pytest.approx(own["images_per_second"] / report["speed"]["blender"]["images_per_second"])
    assert report["box_iou"]["n"] > 0 and 0.0 <= report["box_iou"]["min"] <= report["box_iou"]["mean"] <= 1.0
    assert set(report["targets"]) >= {"mean_box_iou_at_least_0.98", "raster_at_least_100x_blender_whole_pipeline"}
    assert report["machine"]["cpu"] and report["machine"]["cpus_allowed"] >= 1


def test_raster_alone_needs_no_blender(tmp_path):
    report = _run_bench(tmp_path, "--backends", "raster", "--processes", "0")
    assert report["speed"]["raster"]["images"] > 0 and "speed_ratio" not in report


def test_bad_arguments_are_named(tmp_path):
    finished = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "render.py"), "--backends", "raster,povray"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert finished.returncode == 2 and "--backends" in finished.stderr and "povray" in finished.stderr
