"""`foldwise run` on a config it cannot run: one line on stderr naming the problem, exit code
2, before any work (the database is left as it was, and none is created)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from PIL import Image
from sqlalchemy import create_engine, func, select

from db.migrate import upgrade
from db.models import Experiment
from foldwise.settings import REPO_ROOT

SMOKE = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())


def _png(path: Path, side: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((side, side, 3), 90, np.uint8))


def _folder(tmp_path: Path, name: str, fill) -> Path:
    folder = tmp_path / name
    folder.mkdir()
    fill(folder)
    return folder


def _with(tmp_path: Path, **sections) -> str:
    """configs/smoke.yaml with ``sections`` merged in, as YAML text."""
    config = {**SMOKE, **{key: {**SMOKE.get(key, {}), **value} for key, value in sections.items()}}
    return yaml.safe_dump(config)


# (case, config file's text or a function of tmp_path that writes the file and returns it,
#  the line expected on stderr: its start, then text it must contain)
CASES = [
    ("missing file", lambda d: d / "nowhere.yaml", "error: experiment config '{d}/nowhere.yaml' does not exist", ""),
    (
        "a folder",
        lambda d: (d / "folder.yaml").mkdir() or d / "folder.yaml",
        "error: experiment config '{d}/folder.yaml' is not a file",
        "",
    ),
    ("not UTF-8", b"name: caf\xe9\n", "error: experiment config '{d}/config.yaml' is not UTF-8 text (byte 9)", ""),
    ("empty", "", "error: invalid experiment config: expected a mapping at the top level, got NoneType", ""),
    ("a list", "- a\n- b\n", "error: invalid experiment config: expected a mapping", ""),
    ("not YAML", "name: [unclosed\n", "error: invalid experiment config: not YAML: ", "(line 2, column 1)"),
    ("NUL in the file", "name: a\x00b\n", "error: invalid experiment config: not YAML: ", "#x0000"),
    (
        "a key twice",
        "name: x\nseed: 1\nseed: 2\n",
        "error: invalid experiment config: duplicate key 'seed' (line 3, column 1)",
        "",
    ),
    (
        "10,000 levels",
        "name: x\na: " + "[" * 10_000 + "]" * 10_000 + "\n",
        "error: invalid experiment config: nested deeper than 32 levels",
        "",
    ),
    (
        "unknown key and a bad count",
        lambda d: _with(d, active_learning={"m": "50", "mm": 1}),
        "error: invalid experiment config: active_learning.m: expected a number, got the text '50'; active_learning.mm: unknown key",
        "",
    ),
    (
        "a count as a float",
        lambda d: _with(d, active_learning={"t": 1e3}),
        "error: invalid experiment config: active_learning.t: expected a whole number, got 1000.0",
        "",
    ),
    (
        "too large",
        lambda d: _with(d, detector={"learning_rate": 11}),
        "error: invalid experiment config: detector.learning_rate: Input should be less than or equal to 10",
        "",
    ),
    (
        "control character",
        lambda d: _with(d, assets={"objects": "/srv/a\tb"}),
        "error: invalid experiment config: assets.objects: control character '\\t' in text",
        "",
    ),
    (
        "missing asset folder",
        lambda d: _with(d, assets={"backgrounds": str(d / "none")}),
        "error: assets.backgrounds: folder '{d}/none' does not exist",
        "",
    ),
    (
        "empty asset folder",
        lambda d: _with(d, assets={"occluders": str(_folder(d, "empty", lambda f: None))}),
        "error: assets.occluders: folder '{d}/empty' holds no images",
        "",
    ),
    (
        "not an image",
        lambda d: _with(
            d, assets={"objects": str(_folder(d, "text", lambda f: (f / "notes.png").write_text("hello")))}
        ),
        "error: assets.objects: '{d}/text/notes.png' is not a readable image",
        "",
    ),
    (
        "corrupt PNG",
        lambda d: _with(
            d,
            assets={
                "backgrounds": str(
                    _folder(
                        d,
                        "cut",
                        lambda f: (
                            _png(f / "cut.png", 64),
                            (f / "cut.png").write_bytes((f / "cut.png").read_bytes()[:80]),
                        ),
                    )
                )
            },
        ),
        "error: assets.backgrounds: '{d}/cut/cut.png' is not a readable image",
        "",
    ),
    (
        "1x1 background",
        lambda d: _with(d, assets={"backgrounds": str(_folder(d, "dots", lambda f: _png(f / "dot.png", 1)))}),
        "error: assets.backgrounds: '{d}/dots/dot.png' is 1x1 pixels; backgrounds need at least 16 on each side",
        "",
    ),
    (
        "GIF named .png",
        lambda d: _with(
            d,
            assets={
                "objects": str(
                    _folder(d, "gif", lambda f: Image.new("RGB", (32, 32)).save(f / "flag.png", format="GIF"))
                )
            },
        ),
        "error: assets.objects: '{d}/gif/flag.png' holds a GIF image, not PNG as its name says",
        "",
    ),
    (
        "one class twice",
        lambda d: _with(
            d,
            assets={"objects": str(_folder(d, "twice", lambda f: (_png(f / "mug.png", 32), _png(f / "mug.jpg", 32))))},
        ),
        "error: assets.objects: '{d}/twice/mug.jpg' and '{d}/twice/mug.png' both name the class 'mug'",
        "",
    ),
    (
        "brackets in a path",
        lambda d: _with(d, assets={"objects": str(d / "[bold]x")}),
        "error: assets.objects: folder '{d}/[bold]x' does not exist",
        "",
    ),
]


@pytest.fixture
def database_file(tmp_path, migrated_sqlite_template) -> Path:
    """A migrated SQLite file: a copy of the session's template, brought to head (it is)."""
    path = tmp_path / "foldwise.db"
    shutil.copy(migrated_sqlite_template, path)
    upgrade(f"sqlite:///{path}")
    return path


def _foldwise_run(config: Path, data_dir: Path, database_url: str | None) -> subprocess.CompletedProcess:
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "FOLDWISE_DATA_DIR": str(data_dir), "COLUMNS": "60"}
    if database_url:
        env["FOLDWISE_DATABASE_URL"] = database_url
    return subprocess.run(
        [sys.executable, "-m", "services.cli", "run", str(config)],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )


@pytest.mark.parametrize(("case", "config", "starts", "contains"), CASES, ids=[case for case, *_ in CASES])
def test_a_config_it_cannot_run_is_one_line_on_stderr_and_exit_2(
    tmp_path, database_file, case, config, starts, contains
):
    work = tmp_path / "work"
    work.mkdir()
    if callable(config):
        config = config(work)
    if isinstance(config, Path):
        path = config
    else:
        path = work / "config.yaml"
        path.write_bytes(config if isinstance(config, bytes) else config.encode())
    before = database_file.read_bytes()

    done = _foldwise_run(path, tmp_path / "data", f"sqlite:///{database_file}")

    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stdout == ""
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr  # one line, however long (COLUMNS=60 does not wrap it)
    assert lines[0].startswith(starts.format(d=work)), lines[0]
    assert contains.format(d=work) in lines[0]
    assert "Traceback" not in done.stderr
    assert database_file.read_bytes() == before  # nothing recorded, not even a session opened on it
    assert not (tmp_path / "data").exists()  # no images, no report, no store


def test_without_a_database_none_is_created(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("name: x\nseed: -1\n")
    done = _foldwise_run(path, tmp_path / "data", None)  # the default: SQLite in the data dir
    assert (done.returncode, done.stdout) == (2, "")
    assert done.stderr == "error: invalid experiment config: seed: Input should be greater than or equal to 0\n"
    assert not (tmp_path / "data").exists()


def test_a_bad_config_leaves_experiments_untouched(tmp_path, database_file):
    # The database already holds a run: a refused config adds no row beside it.
    engine = create_engine(f"sqlite:///{database_file}")
    with engine.begin() as connection:
        connection.execute(Experiment.__table__.insert().values(name="earlier", config={}, seed=0, status="finished"))
    path = tmp_path / "bad.yaml"
    path.write_text("name: x\nactive_learning: {m: 5, m: 6}\n")
    done = _foldwise_run(path, tmp_path / "data", f"sqlite:///{database_file}")
    assert done.returncode == 2 and done.stderr.startswith("error: invalid experiment config: duplicate key 'm'")
    with engine.connect() as connection:
        assert connection.scalar(select(func.count()).select_from(Experiment)) == 1
    engine.dispose()


@pytest.mark.parametrize("experiment_id", ["0", "2147483648", "99999999999999999999"])
def test_foldwise_report_of_an_id_past_the_columns_is_one_line(tmp_path, database_file, experiment_id):
    # Past 2**63 - 1 SQLite raised OverflowError (a 197-line traceback); past 2**31 - 1 PostgreSQL a DataError.
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "FOLDWISE_DATA_DIR": str(tmp_path / "data"),
           "FOLDWISE_DATABASE_URL": f"sqlite:///{database_file}"}  # fmt: skip
    done = subprocess.run(
        [sys.executable, "-m", "services.cli", "report", experiment_id, "--figures"], cwd=REPO_ROOT, capture_output=True,
        text=True, env=env, timeout=120,
    )  # fmt: skip
    assert (done.returncode, done.stdout, done.stderr) == (2, "", f"error: experiment {experiment_id} does not exist\n")
