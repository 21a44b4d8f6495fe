"""``foldwise``: the command line of every role.

Sub-commands of the render and train workers live beside their code
(``workers/render/cli.py``, ``workers/train/cli.py``) and are registered here; every command
keeps its heavy imports (bpy, torch) inside its body so that ``foldwise api`` never loads them.
"""

from __future__ import annotations

import logging
import os
import sys
from datetime import UTC
from pathlib import Path

import typer
from rich.markup import escape
from rich.table import Table

from foldwise import store
from foldwise.progress import CommandProgress, command_console

app = typer.Typer(no_args_is_help=True, add_completion=False, help="foldwise: teach a detector one deformable object.")
db_app = typer.Typer(no_args_is_help=True, help="Database migrations.")
app.add_typer(db_app, name="db")
console = command_console()
error_console = command_console(stderr=True)


def one_line(message: str) -> str:
    """A message of several lines (a config error lists each bad key) as one line."""
    first, *rest = [line.strip() for line in message.strip().splitlines() if line.strip()] or [""]
    if not rest:
        return first
    return f"{first} {'; '.join(rest)}" if first.endswith(":") else " ".join([first, *rest])


def _fail(message: str, code: int = 2) -> None:
    # One line on stderr, never wrapped (a script greps it, a person reads it whole); the
    # message is text, not markup: a path may hold brackets.
    error_console.print(f"[bold red]error:[/] {escape(one_line(message))}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def _check_photographs(config) -> None:
    """test_set.photographs read as the train worker will read it, or an AssetError naming why."""
    from foldwise.asset_check import AssetError, check_photographs

    path = check_photographs(config.test_set)
    if path is None:
        return
    from workers.train.data import DatasetError, load_dataset

    try:
        samples, classes = load_dataset(path)
    except (DatasetError, KeyError, TypeError, ValueError) as error:
        detail = f"missing field {error}" if isinstance(error, KeyError) else str(error)
        raise AssetError(f"test_set.photographs: cannot read {path}: {detail}") from None
    if not samples:
        raise AssetError(f"test_set.photographs: {path} lists no image")


def _load(config_path: Path, preflight: bool = False):
    """The config, or a one-line error (exit 2); with ``preflight`` its asset folders and
    ImageNet weights (when it asks for them) are checked too, before any work starts."""
    from foldwise.asset_check import AssetError, validate_assets
    from foldwise.config import ConfigError, load_config
    from foldwise.weights import missing_imagenet_weights

    try:
        config = load_config(config_path)
        if preflight:
            validate_assets(config.assets)
            _check_photographs(config)
            if config.detector.pretrained == "imagenet" and (
                problem := missing_imagenet_weights(config.detector.backbone)
            ):
                raise ConfigError(problem)
        return config
    except (ConfigError, AssetError) as error:
        _fail(str(error))


@app.command()
def run(
    config_path: Path = typer.Argument(..., metavar="CONFIG", help="experiment YAML, e.g. configs/quick.yaml"),
    report_dir: Path | None = typer.Option(None, "--report-dir", help="where to write the PNG/CSV report"),
    members: int = typer.Option(
        1,
        "--members",
        min=1,
        max=8,
        help="curricula to run side by side, one process each, with the seeds seed, seed+1, ...; "
        "their final models are handed over as one ensemble (make run: 2 for configs/quick.yaml)",
    ),
) -> None:
    """Run an experiment end to end in this process (SQLite by default, eager Celery)."""
    config = _load(config_path, preflight=True)
    handed_over = (
        _run_members(config, members, report_dir)
        if members > 1
        else _run_experiment(config, report_dir)[1] == "finished"
    )
    if not handed_over:
        raise typer.Exit(1)


def _write_runtime_graph(checkpoint: Path) -> None:
    """The handed-over model's runtime graph beside it, so that detection runs its network through
    onnxruntime (workers/train/export.py); a family that cannot export says so and runs in torch."""
    from workers.train.export import write_runtime_graph_told

    console.print(escape(write_runtime_graph_told(checkpoint)), highlight=False)


def _print_final_model(config, model_id: int) -> None:
    """Where the detector the run hands over is, and, when the loop scored at one view, that the
    table's mAP is not the detector's own (it detects at all of its views)."""
    from db.session import session_scope
    from services.artifacts import checkpoint_file
    from services.queries import NotFound

    try:
        with session_scope() as session:
            checkpoint = checkpoint_file(session, model_id)
    except NotFound as missing:
        console.print(f"final model: {escape(str(missing))}", highlight=False)
        return
    path = escape(str(checkpoint))  # a path may hold brackets: text, not markup
    console.print(f"final model: {path} (model {model_id}); foldwise detect --model {path} IMAGE...", highlight=False)
    _print_views(config, path)


def _print_views(config, path: str) -> None:
    """When the loop scored at one view, that the table's mAP is not the final model's own."""
    from foldwise.config import view_count

    detector = config.detector
    views = view_count(detector.test_sizes, detector.test_turns)
    if config.evaluation.views == "trained" and views > 1:
        console.print(
            f"best mAP above: each model at the one view it trained at (evaluation.views: trained); the final "
            f"model detects at {views} views (sizes {list(detector.test_sizes) or [detector.input_size]}, "
            f"quarter turns {list(detector.test_turns) or [0]}"
            f"{f'; they vote at {detector.view_vote}' if detector.view_vote else ''}"
            f"{_texture_words(detector)}): "
            f"python bench/wild.py --model {path} scores it there",
            highlight=False,
        )


def _texture_words(detector) -> str:
    """What the detector's texture check adds to its views, for ``_print_views``."""
    if not detector.texture_check:
        return ""
    return "; its texture checks the boxes" + (
        " and searches the image for sheets they miss" if detector.texture_search else ""
    )


def _run_experiment(config, report_dir: Path | None, study: str | None = None) -> tuple[int, str]:
    """Record and run one experiment in this process with progress, then print its stage table
    and write its report; returns its id and final status."""
    from db.session import session_scope
    from foldwise.settings import get_settings
    from services import queries
    from services.embedded import run_to_completion, start_experiment
    from services.report import write_report

    settings = get_settings()
    console.print(
        f"foldwise: experiment [bold]{config.name}[/] — {len(config.stage_order())} stages, "
        f"detector {config.detector.family}/{config.detector.backbone}, renderer {config.render.backend}, "
        f"database {settings.resolved_database_url}" + (f", study {study}" if study else ""),
        highlight=False,
    )
    experiment_id = start_experiment(config, study=study)
    _, planned = training_progress(config, [])
    # A line per increment when the output is not a terminal (make run | tee log).
    with CommandProgress(console, "starting", total=planned, unit="planned iterations") as progress:

        def on_step(_experiment_id: int, _decisions) -> None:
            with session_scope() as session:
                info = queries.summary(session, experiment_id)
                stage_rows = queries.stages(session, experiment_id)
                done, _ = training_progress(config, stage_rows)
            current = info["current_stage"]
            best = info["best"]["map"] if info["best"] else None
            description = (
                f"{current['condition']}/{current['difficulty']} k={current['k'] or 0}" if current else info["status"]
            )
            stage = next((row for row in stage_rows if current and row["order"] == current.get("order")), None)
            if stage is not None and stage["best_p"] is not None:
                description += f"  P {stage['best_p']:.3f}"
            if best is not None:
                description += f"  best mAP {best:.3f}"
            progress.update(done, description=description)

        try:
            status = run_to_completion(experiment_id, on_step)
        except KeyboardInterrupt:
            _fail(f"interrupted; experiment {experiment_id} stays recorded and can be inspected", code=130)

    info = _print_stages(experiment_id, config.name, status)
    if info["final_model_id"] is not None:
        _print_final_model(config, info["final_model_id"])
    files = write_report(experiment_id, report_dir or settings.data_dir / f"experiments/{experiment_id}/report")
    console.print(f"report: {files.png}  {files.csv}", highlight=False)
    _print_learnability(experiment_id, files)
    _print_table2(files)
    return experiment_id, status


def _print_stages(experiment_id: int, name: str, status: str) -> dict:
    """An ended experiment's stage table, failed renders and error; returns its summary."""
    from db.session import session_scope
    from services import queries

    with session_scope() as session:
        info = queries.summary(session, experiment_id)
        stage_rows = queries.stages(session, experiment_id)
    table = Table(title=f"experiment {experiment_id} ({name}): {status}")
    p_column = "P start → best" + (" (unthresholded)" if stage_rows and stage_rows[0]["loop_score"] != "map" else "")
    for column in ("c", "δ", "increments", "end reason", p_column, "best mAP", "failed images", "time (s)"):
        table.add_column(column, justify="right" if column not in ("c", "δ", "end reason") else "left")

    def score(value: float | None) -> str:
        return "—" if value is None else f"{value:.3f}"

    for row in stage_rows:
        table.add_row(
            row["condition"],
            row["difficulty"],
            str(row["increments"]),
            row["end_reason"] or row["status"],
            f"{score(row['start_p'])} → {score(row['best_p'])}",
            score(row["best_map"]),
            str(row["failed_images"]),
            "—" if row["seconds"] is None else f"{row['seconds']:.1f}",
        )
    console.print(table)
    if info["failed_by_reason"]:
        reasons = ", ".join(f"{count} {reason}" for reason, count in info["failed_by_reason"].items())
        console.print(f"images that could not be rendered: {reasons}", highlight=False)
    if info["error"]:
        console.print(f"[red]failed:[/] {escape(info['error'])}", highlight=False)
    return info


def member_configs(config, members: int) -> list:
    """The curricula of ``foldwise run --members``: ``config`` with the seeds seed, seed+1, ...,
    each named after its seed."""
    from foldwise.config import parse_config

    variants = []
    for index in range(members):
        data = config.model_dump(mode="json")
        data["seed"] = config.seed + index
        data["name"] = f"{config.name}-seed{config.seed + index}"
        variants.append(parse_config(data))
    return variants


def _run_members(config, members: int, report_dir: Path | None) -> bool:
    """Run ``members`` curricula of ``config`` (seeds seed, seed+1, ...) side by side, one process
    each with an equal share of the threads, under one study id; then hand over their final models
    as one ensemble file. Their models detect better as one than the average member alone; on 2
    cores two curricula of quick.yaml took 1.0-1.17x one curriculum's time (bench/README.md, "Two
    curricula"). Returns whether every curriculum finished and the ensemble was written."""
    import multiprocessing
    import time
    from datetime import datetime

    from db.session import session_scope
    from foldwise.settings import get_settings
    from services import queries
    from services.artifacts import checkpoint_file
    from services.embedded import run_member, start_experiment
    from services.queries import NotFound
    from services.report import write_report
    from services.scheduler.service import experiment_status

    if config.kind != "active_learning":
        _fail(
            f"--members: only kind active_learning hands over a final model to join (this config's kind is {config.kind})"
        )
    settings = get_settings()
    variants = member_configs(config, members)
    share = config.detector.num_threads or os.cpu_count() or 1
    threads = max(1, share // members)
    study_id = f"{config.name}-members-{datetime.now(UTC):%Y%m%dT%H%M%S}"
    console.print(
        f"foldwise: experiment [bold]{config.name}[/] — {members} curricula side by side (seeds "
        f"{', '.join(str(v.seed) for v in variants)}; {threads} thread{'s' if threads > 1 else ''} each), "
        f"{len(config.stage_order())} stages each, detector {config.detector.family}/{config.detector.backbone}, "
        f"renderer {config.render.backend}, database {settings.resolved_database_url}, study {study_id}",
        highlight=False,
    )
    ids = [start_experiment(variant, study=study_id) for variant in variants]
    context = multiprocessing.get_context("spawn")  # a fresh interpreter: no torch threads or DB connections shared
    processes = [context.Process(target=run_member, args=(i, threads), name=f"foldwise-experiment-{i}") for i in ids]
    planned = sum(training_progress(variant, [])[1] for variant in variants)

    def progress_now() -> tuple[int, str]:
        done, parts = 0, []
        with session_scope() as session:
            for experiment_id, variant in zip(ids, variants):
                info = queries.summary(session, experiment_id)
                done += training_progress(variant, queries.stages(session, experiment_id))[0]
                current = info["current_stage"]
                part = (
                    f"{current['condition']}/{current['difficulty']} k={current['k'] or 0}"
                    if current
                    else info["status"]
                )
                if info["best"]:
                    part += f" best {info['best']['map']:.3f}"
                parts.append(f"seed {variant.seed}: {part}")
        return done, " · ".join(parts)

    with CommandProgress(console, "starting", total=planned, unit="planned iterations") as bar:
        try:
            for process in processes:
                process.start()
            while any(process.is_alive() for process in processes):
                time.sleep(2.0)  # the database is read for progress alone: 1-2% of a core
                done, description = progress_now()
                bar.update(done, description=description)
        except KeyboardInterrupt:
            for process in processes:
                process.terminate()
            _fail(f"interrupted; experiments {', '.join(map(str, ids))} stay recorded and can be inspected", code=130)
        for process in processes:
            process.join()

    statuses, finals = [], []  # per member
    for experiment_id, variant, process in zip(ids, variants, processes):
        status = experiment_status(experiment_id).value
        if status not in ("finished", "failed", "cancelled"):  # its process died before it could say so
            with session_scope() as session:
                queries.fail_experiment(session, experiment_id, f"its process ended with exit code {process.exitcode}")
            status = "failed"
        info = _print_stages(experiment_id, variant.name, status)
        out = (
            report_dir / f"experiment-{experiment_id}"
            if report_dir
            else settings.data_dir / f"experiments/{experiment_id}/report"
        )
        files = write_report(experiment_id, out)
        console.print(f"report: {files.png}  {files.csv}", highlight=False)
        statuses.append(status)
        finals.append(info["final_model_id"])
    if all(status == "finished" for status in statuses) and None not in finals:
        from workers.train.checkpoint import CheckpointError, save_ensemble  # torch: only now

        try:
            with session_scope() as session:
                checkpoints = [checkpoint_file(session, model_id) for model_id in finals]
            path = save_ensemble(checkpoints, settings.data_dir / store.ensemble_path(study_id))
        except (NotFound, CheckpointError) as error:
            console.print(f"[red]no ensemble written:[/] {escape(str(error))}", highlight=False)
            return False
        models = ", ".join(f"model {m} (experiment {e})" for m, e in zip(finals, ids))
        shown = escape(str(path))
        console.print(
            f"final model: {shown}, an ensemble of {models}; foldwise detect --model {shown} IMAGE...", highlight=False
        )
        _print_views(config, shown)
        _write_runtime_graph(path)
        return True
    console.print("no ensemble written: not every curriculum finished", highlight=False)
    return False


def training_progress(config, stage_rows: list[dict]) -> tuple[int, int]:
    """(training iterations done, planned) for the progress bar and its ETA.

    Training is most of a run's time, and stages may differ in it by two orders of magnitude
    (a few iterations in a single-condition stage, a thousand in a mixed one), so a count of
    stages would make the ETA wrong by minutes. Each stage plans its cap (κ for
    learnability) times its t; a stage that ended early counts as planned, so the bar ends at
    100% and the ETA is an upper bound while a stopping rule can still end stages early."""
    rows = {(row["condition"], row["difficulty"]): row for row in stage_rows}
    done = planned = 0
    for condition, difficulty in config.stage_order():
        iterations = config.stage_active_learning(condition).t
        budget = config.stage_increments_cap(condition) * iterations
        planned += budget
        row = rows.get((condition, difficulty))
        if row is not None and row["status"] == "done":
            done += budget
        elif row is not None:
            done += min(row["increments"] * iterations, budget)
    return done, planned


def _print_learnability(experiment_id: int, files) -> None:
    """A learnability experiment's order of conditions beside the paper's, with Spearman's ρ."""
    order = files.learnability
    if order is None:
        return
    table = Table(
        title=f"experiment {experiment_id}: learnability (mean mAP over every increment), most learnable first"
    )
    for column in ("rank", "condition", "score", "best mAP", "increments", "paper rank"):
        table.add_column(column, justify="left" if column == "condition" else "right")
    for row in order.rows:
        table.add_row(
            f"{row.rank:g}",
            row.name,
            f"{row.score:.3f}",
            "—" if row.best_map is None else f"{row.best_map:.3f}",
            str(row.increments),
            "—" if row.paper_rank is None else str(row.paper_rank),
        )
    console.print(table)
    rho = order.spearman_rho
    rho = "undefined (fewer than two ranked conditions, or all tied)" if rho is None else f"{rho:.3f}"
    # Both orders over the conditions both rank, most learnable first, so that ρ can be read.
    ranked = sorted((row for row in order.rows if row.condition in order.compared), key=lambda row: row.rank)
    ours = " > ".join(row.condition for row in ranked) or "no condition in common"
    papers = " > ".join(row.condition for row in sorted(ranked, key=lambda row: row.paper_rank)) or "-"
    console.print(f"order here: {ours}; the paper's: {papers}; Spearman's ρ: {rho}", highlight=False)
    console.print(f"learnability: {files.learnability_csv}", highlight=False)


def _table2(title: str, rows, difficulties: list[str]) -> Table:
    """The paper's Table 2 as a terminal table: mAP per condition at each difficulty and over all,
    beside the paper's Fast R-CNN figure."""

    def cell(value) -> str:
        return "—" if value is None else f"{value:.3f}"

    table = Table(title=title)
    for column in ("condition", *difficulties, "all", "paper (Fast R-CNN)"):
        table.add_column(column, justify="left" if column == "condition" else "right")
    for row in rows:
        table.add_row(row.name, *(cell(row.by_difficulty[d]) for d in difficulties), cell(row.map), cell(row.paper))
    return table


def _table2_title(detector: str, score_threshold: float, iou_threshold: float, model: str = "") -> str:
    return (
        f"Table 2: trained on canonical images only ({detector}{model}); mAP, score ≥ {score_threshold:g}, "
        f"IoU ≥ {iou_threshold:g}"
    )


def _print_table2(files) -> None:
    """A canonical baseline's Table 2 beside the paper's."""
    table2 = files.table2
    if table2 is None:
        return
    if table2.model_id is None:
        model = ", no model evaluated yet"
    else:
        model = f", model {table2.model_id} at k={table2.increment}" + ("" if table2.final else ", not final")
    title = _table2_title(table2.detector, table2.score_threshold, table2.iou_threshold, model)
    console.print(_table2(title, table2.rows, table2.difficulties))
    console.print(f"table 2: {files.table2_csv}", highlight=False)


def _choices(option: str, text: str, known: tuple[str, ...]) -> list[str]:
    values = [part.strip() for part in text.split(",") if part.strip()]
    if len(set(values)) != len(values):
        _fail(f"{option}: {text!r} names a value twice")
    for value in values:
        if value not in known:
            _fail(f"{option}: unknown value {value!r}; known: {', '.join(known)}")
    return values


@app.command()
def study(
    config_path: Path = typer.Argument(..., metavar="CONFIG", help="experiment YAML, e.g. configs/quick.yaml"),
    detectors: str = typer.Option(
        "", "--detectors", help="comma list of faster_rcnn, fast_rcnn, yolo (default: the config's)"
    ),
    training_set: str = typer.Option("", "--training-set", help="comma list of reset, grow (default: the config's)"),
    name: str | None = typer.Option(None, "--name", help="the study id (default: the config's name and the time)"),
    out: Path | None = typer.Option(None, "--out", help="where the figures go (default: DATA_DIR/studies/NAME)"),
) -> None:
    """Run CONFIG once per detector and per training-set choice, one after another in this
    process, under one study id; then draw the paper's figures with the runs side by side.

    In the distributed stack, POST the variants with ?study=NAME and the workers run them
    side by side; `foldwise report E1 E2 ... --figures` draws them."""
    from datetime import datetime
    from typing import get_args

    from foldwise.config import ActiveLearningConfig, ConfigError, DetectorConfig, parse_config
    from foldwise.settings import get_settings
    from services.figures import write_figures
    from services.queries import STUDY_NAME

    if name is not None and not STUDY_NAME.match(name):
        _fail(f"--name: a study name is one line of 1 to 200 printable characters, got {name!r}")
    config = _load(config_path, preflight=True)
    known_families = get_args(DetectorConfig.model_fields["family"].annotation)
    known_sets = get_args(ActiveLearningConfig.model_fields["training_set"].annotation)
    families = _choices("--detectors", detectors, known_families) or [config.detector.family]
    choices = _choices("--training-set", training_set, known_sets) or [config.active_learning.training_set]
    study_id = name or f"{config.name}-{datetime.now(UTC):%Y%m%dT%H%M%S}"
    variants = []
    for family in families:
        for choice in choices:
            data = config.model_dump(mode="json")
            data["name"] = f"{config.name}-{family}-{choice}"
            data["detector"] = {**data["detector"], "family": family}
            data["active_learning"] = {**data["active_learning"], "training_set": choice}
            try:
                variants.append(parse_config(data))
            except ConfigError as error:
                _fail(str(error))
    console.print(f"study {study_id}: {len(variants)} experiments", highlight=False)
    finished = []
    for variant in variants:
        finished.append(_run_experiment(variant, None, study=study_id))
    out = out or get_settings().data_dir / "studies" / study_id
    for figure, paths in write_figures([experiment_id for experiment_id, _ in finished], out).items():
        console.print(f"{figure} → {'  '.join(str(p) for p in paths)}", highlight=False)
    summary = ", ".join(f"{experiment_id} {status}" for experiment_id, status in finished)
    console.print(f"study {study_id}: experiments {summary}", highlight=False)
    if any(status != "finished" for _, status in finished):
        raise typer.Exit(1)


@app.command()
def baseline(
    config_path: Path = typer.Argument(..., metavar="CONFIG", help="detector, renderer, image size, assets and seed"),
    out: Path = typer.Option(..., "--out", help="folder for the images, the model and table2.csv"),
    train_images: int = typer.Option(500, "--train-images", min=1, max=100_000, help="canonical training images"),
    iterations: int = typer.Option(2000, "--iterations", min=1, max=1_000_000),
    test_per_pair: int = typer.Option(
        30, "--test-per-pair", min=1, max=100_000, help="test images per (condition, difficulty)"
    ),
    conditions: str = typer.Option(
        "", "--conditions", help="comma list of condition codes (default: every one of the table)"
    ),
) -> None:
    """The paper's Table 2: train on canonical images only, score every condition (each
    difficulty and all together) beside the paper's Fast R-CNN figures."""
    from foldwise.conditions import load_condition_table
    from services.baseline import canonical_baseline

    config = _load(config_path, preflight=True)
    codes = _choices("--conditions", conditions, load_condition_table().codes)
    rows = canonical_baseline(
        config, out, train_images, iterations, test_per_pair, codes or None, echo=lambda line: console.print(line, highlight=False)
    )  # fmt: skip

    difficulties = list(rows[0].by_difficulty) if rows else []
    title = _table2_title(config.detector.family, config.evaluation.score_threshold, config.evaluation.iou_threshold)
    console.print(_table2(title, rows, difficulties))
    console.print(f"table: {out / 'table2.csv'}", highlight=False)


@app.command()
def report(
    experiment_ids: list[int] = typer.Argument(..., metavar="EXPERIMENT...", help="one or more experiment ids"),
    out: Path | None = typer.Option(
        None, "--out", help="output directory (default: the first experiment's report dir)"
    ),
    figures: bool = typer.Option(
        False, "--figures", help="also the paper's Fig. 4 to 8 (PNG, SVG, CSV), a line per experiment"
    ),
) -> None:
    """Plot error (1 − mAP) against cumulative wall time, render/train/eval apart; write PNG and CSV.

    With --figures, the paper's figures too, the experiments side by side (one per detector
    compares detectors)."""
    from foldwise.settings import get_settings
    from services.figures import write_figures
    from services.queries import NotFound
    from services.report import write_report

    out = out or get_settings().data_dir / f"experiments/{experiment_ids[0]}/report"
    try:
        for experiment_id in experiment_ids:
            files = write_report(experiment_id, out)
            console.print(f"{len(files.rows)} evaluations → {files.png}  {files.csv}", highlight=False)
            _print_learnability(experiment_id, files)
            _print_table2(files)
        if figures:
            for name, paths in write_figures(experiment_ids, out).items():
                console.print(f"{name} → {'  '.join(str(p) for p in paths)}", highlight=False)
    except NotFound as error:
        _fail(str(error))


@db_app.command("upgrade")
def db_upgrade(revision: str = typer.Argument("head")) -> None:
    """Apply database migrations (FOLDWISE_DATABASE_URL, default SQLite in FOLDWISE_DATA_DIR)."""
    from db.migrate import upgrade
    from foldwise.settings import get_settings

    upgrade(revision=revision)
    console.print(f"database at {revision}: {get_settings().resolved_database_url}", highlight=False)


@app.command()
def scheduler(
    poll: float | None = typer.Option(None, help="seconds between passes (FOLDWISE_SCHEDULER_POLL_S)"),
    once: bool = typer.Option(False, help="one pass over live experiments, then exit"),
) -> None:
    """Run the scheduler service: reconcile every live experiment until stopped."""
    from services.scheduler.service import serve

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    serve(poll_s=poll, once=once)


@app.command()
def api(
    host: str = typer.Option("127.0.0.1", help="bind address (0.0.0.0 in a container)"),
    port: int = typer.Option(8000),
) -> None:
    """Serve the REST API (status for everyone; creating or cancelling needs FOLDWISE_API_TOKEN)."""
    import uvicorn

    uvicorn.run("services.api.app:app", host=host, port=port, log_level="info")


@app.command()
def worker(
    role: str = typer.Argument(..., metavar="render|train|detect"),
    concurrency: int = typer.Option(1, help="processes of this worker"),
    loglevel: str = typer.Option("info"),
) -> None:
    """Start a Celery worker on the role's queue (a thin wrapper over `celery worker -Q ROLE`).

    `detect` answers POST /models/{id}/detect; it needs the train extra (torch), like `train`.
    """
    from workers.app import DETECT_QUEUE, RENDER_QUEUE, TRAIN_QUEUE

    queues = {"render": RENDER_QUEUE, "train": TRAIN_QUEUE, "detect": DETECT_QUEUE}
    if role not in queues:
        _fail(f"unknown worker role {role!r}; expected one of: {', '.join(queues)}")
    argv = [
        sys.executable, "-m", "celery", "-A", "workers.app:app", "worker",
        "-Q", queues[role], "--concurrency", str(concurrency), "--loglevel", loglevel,
        # Unique per process: several workers of a role may share a host (compose --scale, tests).
        "-n", f"{role}-{os.getpid()}@%h",
    ]  # fmt: skip
    os.execv(sys.executable, argv)


def _register_worker_commands() -> None:
    from workers.render import cli as render_cli
    from workers.train import cli as train_cli

    render_cli.register(app)
    train_cli.register(app)


def main() -> None:
    _register_worker_commands()
    app()


if __name__ == "__main__":
    main()
