"""`foldwise run` through a pipe (`make run | tee log`): plain progress lines while it runs."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import yaml

from foldwise.settings import REPO_ROOT


def test_run_through_a_pipe_prints_a_line_per_increment_as_it_goes(database, tmp_path):
    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["curriculum"]["difficulties"] = ["easy"]  # one stage: the lines are under test, not learning
    path = tmp_path / "one-stage.yaml"
    path.write_text(yaml.safe_dump(config))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "COLUMNS": "80"}
    env.pop("FORCE_COLOR", None)
    env.pop("TTY_COMPATIBLE", None)
    process = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "run", str(path), "--report-dir", str(tmp_path / "report")],
        cwd=REPO_ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    arrivals = [(time.monotonic(), line.rstrip("\n")) for line in process.stdout]
    assert process.wait(timeout=300) == 0, "\n".join(line for _, line in arrivals)
    ended = time.monotonic()
    text = "\n".join(line for _, line in arrivals)

    assert "\x1b" not in text and "\r" not in text
    progress = [(when, line) for when, line in arrivals if " planned iterations (" in line and "ETA" in line]
    increments = [line for _, line in progress if "fb/easy k=" in line]
    # k = 0 (the stage starts), 1 and 2 (smoke: M + N = 2 increments)
    assert {line.split("k=")[1].split()[0].rstrip(":") for line in increments} >= {"0", "1", "2"}, text
    # lines arrive while it runs, not in one block at the end
    assert ended - progress[0][0] > 1.0, text
    assert progress[-1][1].startswith("finished") and "(100%)" in progress[-1][1]
    # no wrapping at 80 columns (COLUMNS=80 is ignored off a terminal): the header stays one line
    header = next(line for _, line in arrivals if line.startswith("foldwise: experiment"))
    assert len(header) > 80 and f"database {database}" in header
    assert any("plateau" in line and line.count("│") == 9 for line in text.splitlines())  # 8 columns, one row


def test_progress_counts_planned_training_iterations_not_stages():
    from foldwise.config import parse_config
    from services.cli import training_progress

    # Four single-condition stages of 8 iterations, capped at 1; a mixed stage of 240, capped at 5.
    config = parse_config(
        {
            "name": "progress",
            "curriculum": {
                "conditions": ["fb", "sc"],
                "difficulties": ["easy", "hard"],
                "mixed": {"active_learning": {"t": 240, "max_increments": 5}},
            },
            "active_learning": {"t": 8, "max_increments": 1},
        }
    )
    singles, mixed = 4 * 1 * 8, 5 * 240  # cap x t per stage
    assert training_progress(config, []) == (0, singles + mixed)
    rows = [{"condition": c, "difficulty": d, "status": "done", "increments": 1} for c, d in config.stage_order()[:4]]
    rows.append({"condition": "mixed", "difficulty": "hard", "status": "running", "increments": 2})
    done, planned = training_progress(config, rows)
    # 4 of 5 stages are done, but most of the training is still ahead.
    assert (done, planned) == (singles + 2 * 240, singles + mixed) and done / planned < 0.55
    rows[-1] = {**rows[-1], "status": "done", "increments": 3}  # ended early by the stopping rule
    assert training_progress(config, rows) == (planned, planned)


def test_progress_plans_the_canonical_stage_of_a_canonical_start_at_its_own_increments():
    from foldwise.config import load_config
    from services.cli import training_progress

    config = load_config(REPO_ROOT / "configs/learnability_canonical_quick.yaml")
    canonical, kappa, t = config.learnability.canonical_increments, config.learnability.kappa, config.active_learning.t
    assert training_progress(config, []) == (0, (canonical + 21 * kappa) * t)
    rows = [{"condition": "canonical", "difficulty": "canonical", "status": "running", "increments": 2}]
    assert training_progress(config, rows) == (2 * t, (canonical + 21 * kappa) * t)
