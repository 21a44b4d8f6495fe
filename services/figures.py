"""The paper's figures from the database, for one experiment or several side by side.

`foldwise report E [E ...] --figures` (and ``GET /experiments/{id}/figures/{name}.{png,svg,csv}``)
draw, each as PNG and SVG with its numbers as CSV:

* ``fig4``: mAP against increment k for every (condition, difficulty) stage, a line per
  experiment (run one experiment per detector to compare detectors, as the paper's Fig. 4);
* ``fig5``: the best mAP each experiment reached per condition and difficulty, a panel per
  experiment (Fig. 5);
* ``fig6``: mAP against cumulative training time, a line per experiment (a reset run beside a
  grow run of the same config is the paper's Fig. 6), with each run's total training time;
* ``fig7``: the standard test set's mAP across the whole curriculum, increment after
  increment, stages marked (Fig. 7);
* ``fig8``: the mAP of each stage's best model ω_be (Fig. 8).

Every figure names its axes and units, the protocol's score cut and IoU threshold, and the
conditions by their full names.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

from db.session import session_scope
from foldwise.conditions import load_condition_table
from foldwise.config import ExperimentConfig
from foldwise.theta import CANONICAL
from services import queries

FIGURES = ("fig4", "fig5", "fig6", "fig7", "fig8")
MAP_LABEL = "mAP (score ≥ {cut:g}, IoU ≥ {iou:g})"


@dataclass(frozen=True)
class Run:
    """One experiment's record, as the figures read it."""

    experiment_id: int
    label: str  # legend: "faster_rcnn (experiment 3)"
    score_threshold: float
    iou_threshold: float
    history: list[dict]
    stages: list[dict]
    kind: str = "active_learning"  # learnability: each model is scored on its condition's own test set


def load_runs(experiment_ids: list[int]) -> list[Run]:
    runs = []
    with session_scope() as session:
        for experiment_id in experiment_ids:
            experiment = queries.get_experiment(session, experiment_id)
            config = ExperimentConfig.model_validate(experiment.config)
            runs.append(
                Run(
                    experiment_id=experiment_id,
                    label=f"{config.detector.family} (experiment {experiment_id}: {experiment.name})",
                    score_threshold=config.evaluation.score_threshold,
                    iou_threshold=config.evaluation.iou_threshold,
                    history=queries.history(session, experiment_id),
                    stages=queries.stages(session, experiment_id),
                    kind=config.kind,
                )
            )
    return runs


def _protocol(runs: list[Run]) -> str:
    cuts = sorted({(run.score_threshold, run.iou_threshold) for run in runs})
    return "; ".join(MAP_LABEL.format(cut=cut, iou=iou) for cut, iou in cuts)


def _test_set(runs: list[Run]) -> str:
    """Which test set the runs' mAP is on, for the titles."""
    kinds = {run.kind for run in runs}
    if kinds == {"learnability"}:
        return "the condition's own test set (learnability)"
    if "learnability" in kinds:
        return "the standard test set (learnability runs: the condition's own)"
    return "the standard test set"


def _stage_keys(runs: list[Run]) -> list[tuple[str, str]]:
    """(condition, difficulty) in curriculum order, the union over the runs."""
    keys: list[tuple[str, str]] = []
    for run in runs:
        for stage in run.stages:
            key = (stage["condition"], stage["difficulty"])
            if key not in keys:
                keys.append(key)
    return keys


def _write_csv(path: Path, columns: list[str], rows: list[dict]) -> None:
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)


def write_figures(experiment_ids: list[int], out_dir: Path, names: tuple[str, ...] = FIGURES) -> dict[str, list[Path]]:
    """Draw the named figures of these experiments into ``out_dir``; returns the files per figure."""
    import matplotlib

    matplotlib.use("Agg")
    matplotlib.rcParams["svg.fonttype"] = "none"  # text stays text in the SVG: searchable, editable
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    unknown = sorted(set(names) - set(FIGURES))
    if unknown:
        raise ValueError(f"unknown figure(s) {unknown}; known: {', '.join(FIGURES)}")
    runs = load_runs(experiment_ids)
    table = load_condition_table()
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = "experiments-" + "-".join(str(i) for i in experiment_ids)
    protocol = _protocol(runs)
    colours = plt.get_cmap("tab10")
    written: dict[str, list[Path]] = {}

    def save(name: str, figure, columns: list[str], rows: list[dict]) -> None:
        paths = [out_dir / f"{name}-{stem}.{suffix}" for suffix in ("png", "svg", "csv")]
        figure.savefig(paths[0], dpi=120)
        figure.savefig(paths[1])
        plt.close(figure)
        _write_csv(paths[2], columns, rows)
        written[name] = paths

    keys = _stage_keys(runs)
    if "fig4" in names and not keys:
        # No stage has started: one panel that says so (matplotlib draws no grid of 0 x 0).
        figure, ax = plt.subplots(figsize=(4.8, 2.4), constrained_layout=True)
        ax.set_axis_off()
        ax.text(0.5, 0.5, "no stage has started yet", ha="center", va="center")
        figure.suptitle(f"Fig. 4: mAP on {_test_set(runs)} after each increment; {protocol}", fontsize=9)
        save("fig4", figure, ["experiment", "condition", "difficulty", "k", "map"], [])
    elif "fig4" in names:
        conditions = list(dict.fromkeys(c for c, _ in keys))
        difficulties = list(dict.fromkeys(d for _, d in keys))
        figure, axes = plt.subplots(
            len(conditions), len(difficulties), figsize=(3.2 * len(difficulties), 2.3 * len(conditions)),
            squeeze=False, sharey=True, constrained_layout=True,
        )  # fmt: skip
        rows = []
        for i, condition in enumerate(conditions):
            for j, difficulty in enumerate(difficulties):
                ax = axes[i][j]
                if (condition, difficulty) not in keys:  # not a stage of any run (the mixed stage's easy)
                    ax.set_visible(False)
                    continue
                ax.xaxis.set_major_locator(MaxNLocator(integer=True))
                for r, run in enumerate(runs):
                    points = [
                        (e["k"], e["map"])
                        for e in run.history
                        if (e["condition"], e["difficulty"]) == (condition, difficulty)
                    ]
                    rows += [{"experiment": run.experiment_id, "condition": condition, "difficulty": difficulty, "k": k, "map": m}
                             for k, m in points]  # fmt: skip
                    finite = [(k, m) for k, m in points if m is not None]
                    if finite:
                        ax.plot(*zip(*finite), "o-", markersize=3, color=colours(r % 10), label=run.label)
                ax.set_title(f"{table.name(condition)}, {difficulty}", fontsize=8)
                ax.set_ylim(-0.02, 1.02)
                ax.grid(alpha=0.3)
                if i == len(conditions) - 1:
                    ax.set_xlabel("increment k")
                if j == 0:
                    ax.set_ylabel("mAP")
        # One legend for every run, wherever it has points (a run of one condition plots in
        # its own row only, and the first panel's legend would leave it out).
        handles = {}
        for ax in axes.flat:
            for handle, label in zip(*ax.get_legend_handles_labels()):
                handles.setdefault(label, handle)
        # Below the panels, where it hides no curve.
        figure.legend(
            handles.values(), handles.keys(), fontsize=7, loc="outside lower center", ncol=min(3, len(handles) or 1)
        )
        figure.suptitle(f"Fig. 4: mAP on {_test_set(runs)} after each increment; {protocol}", fontsize=9)
        save("fig4", figure, ["experiment", "condition", "difficulty", "k", "map"], rows)

    if "fig5" in names:
        # The paper's Fig. 5: per condition, a bar per difficulty (its mAP rises once the
        # detector trains on hard cases), a panel per detector.
        conditions = list(dict.fromkeys(c for c, _ in keys))
        # A canonical stage (the baseline's, or a learnability run's shared start) has no
        # difficulty: one grey bar across its group instead of a slot beside every difficulty.
        difficulties = list(dict.fromkeys(d for _, d in keys if d != CANONICAL))
        shades = plt.get_cmap("Blues")
        width = 0.8 / max(1, len(difficulties))
        figure, axes = plt.subplots(
            max(1, len(runs)), 1, figsize=(max(6, 0.9 * len(conditions) * max(1, len(difficulties)) / 2 + 2), 3.2 * max(1, len(runs))),
            constrained_layout=True, squeeze=False,
        )  # fmt: skip
        rows = []
        for r, (run, ax) in enumerate(zip(runs, axes[:, 0])):
            best = {(s["condition"], s["difficulty"]): s["best_map"] for s in run.stages if s["best_map"] is not None}
            if (CANONICAL, CANONICAL) in best:
                value = best[(CANONICAL, CANONICAL)]
                rows.append({"experiment": run.experiment_id, "condition": CANONICAL, "name": table.name(CANONICAL),
                             "difficulty": CANONICAL, "best_map": value})  # fmt: skip
                ax.bar([conditions.index(CANONICAL) + width * (len(difficulties) - 1) / 2], [value], 0.8, color="0.7",
                       edgecolor="black", linewidth=0.4, label="canonical images")  # fmt: skip
            for d, difficulty in enumerate(difficulties):
                heights = [
                    None if condition == CANONICAL else best.get((condition, difficulty)) for condition in conditions
                ]
                for condition, value in zip(conditions, heights):
                    if condition == CANONICAL:
                        continue
                    rows.append({"experiment": run.experiment_id, "condition": condition, "name": table.name(condition),
                                 "difficulty": difficulty, "best_map": value})  # fmt: skip
                ax.bar([c + d * width for c in range(len(conditions))], [h or 0.0 for h in heights], width, label=difficulty,
                       color=shades(0.35 + 0.55 * d / max(1, len(difficulties) - 1)), edgecolor="black", linewidth=0.4)  # fmt: skip
            ax.set_xticks([c + width * (len(difficulties) - 1) / 2 for c in range(len(conditions))])
            ax.set_xticklabels([table.name(c) for c in conditions], rotation=30, ha="right", fontsize=8)
            ax.set_ylabel(f"best {MAP_LABEL.format(cut=run.score_threshold, iou=run.iou_threshold)}", fontsize=8)
            ax.set_ylim(0, 1.02)
            ax.set_title(run.label, fontsize=8)
            # Beside the panel: inside, it would cover the tallest bars.
            if ax.get_legend_handles_labels()[0]:  # an experiment with no stage yet has no bar to name
                ax.legend(
                    title="difficulty trained",
                    fontsize=7,
                    title_fontsize=7,
                    loc="upper left",
                    bbox_to_anchor=(1.0, 1.0),
                )
            ax.grid(axis="y", alpha=0.3)
        figure.suptitle(f"Fig. 5: the best mAP per condition and difficulty (any increment); {protocol}", fontsize=9)
        save("fig5", figure, ["experiment", "condition", "name", "difficulty", "best_map"], rows)

    if "fig6" in names:
        figure, ax = plt.subplots(figsize=(9, 4.5), constrained_layout=True)
        rows = []
        for r, run in enumerate(runs):
            seconds, points = 0.0, []
            for entry in run.history:
                seconds += entry["train_seconds"] or 0.0
                points.append((seconds, entry["map"]))
                rows.append({"experiment": run.experiment_id, "condition": entry["condition"], "difficulty": entry["difficulty"],
                             "k": entry["k"], "cumulative_train_seconds": seconds, "map": entry["map"]})  # fmt: skip
            finite = [(x, y) for x, y in points if y is not None]
            if finite:
                ax.plot(*zip(*finite), ".-", color=colours(r % 10), label=f"{run.label}: {seconds:.0f} s of training")
        ax.set_xlabel("cumulative training time (s)")
        ax.set_ylabel("mAP on the standard test set")
        ax.set_ylim(-0.02, 1.02)
        ax.set_title(f"Fig. 6: mAP against training time (reset against grow: one run each); {protocol}", fontsize=9)
        if ax.get_legend_handles_labels()[0]:  # no run has a finite mAP yet: nothing to name
            ax.legend(fontsize=7, loc="lower right")
        ax.grid(alpha=0.3)
        save("fig6", figure, ["experiment", "condition", "difficulty", "k", "cumulative_train_seconds", "map"], rows)

    if "fig7" in names:
        figure, ax = plt.subplots(figsize=(11, 5), constrained_layout=True)
        rows = []
        for r, run in enumerate(runs):
            xs = list(range(1, len(run.history) + 1))
            ys = [e["map"] for e in run.history]
            rows += [{"experiment": run.experiment_id, "increment": x, "condition": e["condition"], "difficulty": e["difficulty"],
                      "k": e["k"], "map": e["map"]} for x, e in zip(xs, run.history)]  # fmt: skip
            ax.plot(
                xs, [y if y is not None else float("nan") for y in ys], ".-", color=colours(r % 10), label=run.label
            )
        if runs:  # stage bands of the first run
            start = 1
            for n, (condition, difficulty) in enumerate(_bands(runs[0].history)):
                end = start + condition[2]
                ax.axvspan(start - 0.5, end - 0.5, color="grey", alpha=0.12 if n % 2 else 0.0)
                ax.text((start + end - 1) / 2, 1.03, f"{table.name(condition[0])}, {difficulty}", ha="center", va="top",
                        fontsize=6, rotation=90)  # fmt: skip
                start = end
        ax.set_xlabel("increment, counted across the whole curriculum")
        ax.set_ylabel("mAP on the standard test set")
        ax.set_ylim(-0.02, 1.05)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_title(f"Fig. 7: standard test set mAP across the curriculum; {protocol}", fontsize=9)
        ax.legend(fontsize=7, loc="lower right")
        ax.grid(alpha=0.3)
        save("fig7", figure, ["experiment", "increment", "condition", "difficulty", "k", "map"], rows)

    if "fig8" in names:
        labels = [f"{table.name(c)}, {d}" for c, d in keys]
        figure, ax = plt.subplots(figsize=(max(6, 0.45 * len(keys) * max(1, len(runs))), 4.5), constrained_layout=True)
        width = 0.8 / max(1, len(runs))
        rows = []
        for r, run in enumerate(runs):
            by_key = {(s["condition"], s["difficulty"]): s for s in run.stages}
            values = [by_key.get(key, {}).get("best_map") for key in keys]
            rows += [{"experiment": run.experiment_id, "condition": c, "difficulty": d,
                      "best_model_id": by_key.get((c, d), {}).get("best_model_id"), "best_map": v}
                     for (c, d), v in zip(keys, values)]  # fmt: skip
            ax.bar([i + r * width for i in range(len(keys))], [v or 0.0 for v in values], width, label=run.label,
                   color=colours(r % 10))  # fmt: skip
        ax.set_xticks([i + width * (len(runs) - 1) / 2 for i in range(len(keys))])
        ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
        ax.set_ylabel("mAP of the stage's best model ω_be")
        ax.set_ylim(0, 1.02)
        ax.set_title(f"Fig. 8: the best model of each stage; {protocol}", fontsize=9)
        ax.legend(fontsize=7)
        ax.grid(axis="y", alpha=0.3)
        save("fig8", figure, ["experiment", "condition", "difficulty", "best_model_id", "best_map"], rows)
    return written


def _bands(history: list[dict]):
    """Consecutive runs of one stage in P: ((condition, difficulty, length), difficulty)."""
    bands: list[list] = []
    for entry in history:
        key = (entry["condition"], entry["difficulty"])
        if bands and bands[-1][0] == key:
            bands[-1][1] += 1
        else:
            bands.append([key, 1])
    return [((key[0], key[1], length), key[1]) for key, length in bands]
