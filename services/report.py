"""``foldwise report``: error (1 − mAP) against cumulative wall time, as a PNG and a CSV.

One colour per stage (c/δ). The lower panel tells render, train and evaluation time apart:
the seconds each has consumed so far, so a reader sees what the accuracy cost and where the
time went (in distributed mode renders overlap training, so their sum can exceed wall time).

A learnability experiment (Algorithm 2) also gets ``learnability-{id}.csv``: each condition's
learnability score, its rank, the paper's rank and Spearman's ρ (services/learnability.py).
A canonical baseline gets ``table2-{id}.csv``: its model's mAP per condition and difficulty
beside the paper's Table 2 (services/baseline.py).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, replace
from pathlib import Path

from db.session import session_scope
from foldwise.config import ExperimentConfig
from services import queries
from services.baseline import Table2, experiment_table2, write_table2_csv
from services.learnability import LearnabilityOrder, experiment_learnability, write_learnability_csv

CSV_COLUMNS = [
    "stage",
    "condition",
    "difficulty",
    "k",
    "model_id",
    "parent_id",
    "map",
    "error",
    "wall_seconds",
    "render_seconds",
    "train_seconds",
    "eval_seconds",
    "cumulative_render_seconds",
    "cumulative_train_seconds",
    "cumulative_eval_seconds",
]


@dataclass(frozen=True)
class ReportFiles:
    png: Path
    csv: Path
    rows: list[dict]
    # kind: learnability only: the learnability order beside the paper's, and its CSV.
    learnability: LearnabilityOrder | None = None
    learnability_csv: Path | None = None
    # kind: canonical_baseline only: the paper's Table 2 from its model, and its CSV.
    table2: Table2 | None = None
    table2_csv: Path | None = None


def report_rows(experiment_id: int) -> list[dict]:
    with session_scope() as session:
        entries = queries.history(session, experiment_id)
        render_total = queries.test_set_render_seconds(session, experiment_id)
    train_total = eval_total = 0.0
    rows = []
    for entry in entries:
        render_total += entry["render_seconds"] or 0.0
        train_total += entry["train_seconds"] or 0.0
        eval_total += entry["eval_seconds"] or 0.0
        score = entry["map"]
        rows.append(
            {
                **{
                    key: entry[key] for key in ("stage", "condition", "difficulty", "k", "model_id", "parent_id", "map")
                },
                "error": None if score is None else 1.0 - score,
                "wall_seconds": entry["wall_seconds"],
                "render_seconds": entry["render_seconds"],
                "train_seconds": entry["train_seconds"],
                "eval_seconds": entry["eval_seconds"],
                "cumulative_render_seconds": render_total,
                "cumulative_train_seconds": train_total,
                "cumulative_eval_seconds": eval_total,
            }
        )
    return rows


def write_report(experiment_id: int, out_dir: Path) -> ReportFiles:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with session_scope() as session:
        experiment = queries.get_experiment(session, experiment_id)
        name = experiment.name
        kind = ExperimentConfig.model_validate(experiment.config).kind
        learnability = experiment_learnability(session, experiment_id) if kind == "learnability" else None
        table2 = experiment_table2(session, experiment_id) if kind == "canonical_baseline" else None
    rows = report_rows(experiment_id)
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = out_dir / f"experiment-{experiment_id}.csv"
    with open(csv_path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)

    figure, (top, bottom) = plt.subplots(
        2, 1, figsize=(9, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 2]}, constrained_layout=True
    )
    colours = plt.get_cmap("tab20")
    stages = sorted({(r["stage"], r["condition"], r["difficulty"]) for r in rows})
    for i, (order, condition, difficulty) in enumerate(stages):
        points = [(r["wall_seconds"], r["error"]) for r in rows if r["stage"] == order and r["error"] is not None]
        if points:
            xs, ys = zip(*points)
            top.plot(xs, ys, "o-", color=colours(i % 20), label=f"{order}: {condition}/{difficulty}", markersize=4)
    top.set_ylabel("error  (1 − mAP@0.5)")
    top.set_ylim(-0.02, 1.02)
    top.grid(alpha=0.3)
    top.set_title(f"experiment {experiment_id}: {name}")
    if stages:
        top.legend(fontsize=7, ncol=max(1, len(stages) // 12 + 1), loc="upper right")

    walls = [r["wall_seconds"] for r in rows]
    for key, label, colour in (
        ("cumulative_render_seconds", "render", "tab:blue"),
        ("cumulative_train_seconds", "train", "tab:orange"),
        ("cumulative_eval_seconds", "evaluation", "tab:green"),
    ):
        bottom.step(walls, [r[key] for r in rows], where="post", label=label, color=colour)
    bottom.set_xlabel("wall time since the experiment started (s)")
    bottom.set_ylabel("seconds spent so far")
    bottom.grid(alpha=0.3)
    bottom.legend(fontsize=8, loc="upper left")

    png_path = out_dir / f"experiment-{experiment_id}.png"
    figure.savefig(png_path, dpi=120)
    plt.close(figure)
    files = ReportFiles(png=png_path, csv=csv_path, rows=rows)
    if learnability is not None:
        learnability_csv = write_learnability_csv(learnability, out_dir / f"learnability-{experiment_id}.csv")
        files = replace(files, learnability=learnability, learnability_csv=learnability_csv)
    if table2 is not None:
        table2_csv = write_table2_csv(table2.rows, table2.difficulties, out_dir / f"table2-{experiment_id}.csv")
        files = replace(files, table2=table2, table2_csv=table2_csv)
    return files
