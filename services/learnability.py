"""The learnability of each imaging condition (paper §5.2, Algorithm 2), and its order against
the paper's.

The paper ranks the conditions from its Fig. 4 (mAP per increment) and Fig. 5 (best mAP) without
giving a formula. foldwise's score of a condition is the mean of its mAP over every increment of
every difficulty (3κ values, each on the condition's own test set): the area under its Fig. 4
curve, divided by the number of increments. It rewards a condition learned early as well as one
learned well, and, unlike the best mAP alone, one lucky increment does not decide it. The best
mAP (Fig. 5) is reported beside it. The shared canonical stage of ``learnability.start:
canonical`` trains no condition and is left out.

The paper's order, most to least learnable: focus blur, motion blur, scale, occlusion,
deformation, pose. Lighting is in the curriculum (Table 3) but not in that sentence, so it has
no paper rank and stays out of Spearman's ρ.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

# §5.2: "the most learnable to the least learnable ... focus blur, motion blur, scale changes,
# occlusions, deformations and pose changes", by foldwise's condition codes.
PAPER_ORDER = ("fb", "mb", "sc", "eo", "de", "po")

CSV_COLUMNS = ["condition", "name", "score", "best_map", "increments", "rank", "paper_rank", "spearman_rho"]


@dataclass(frozen=True)
class ConditionLearnability:
    condition: str
    name: str
    score: float  # mean mAP over the condition's increments (a non-finite mAP counts as 0)
    best_map: float | None
    increments: int
    rank: float  # 1 = most learnable; tied scores share their mean rank
    paper_rank: int | None  # position in PAPER_ORDER, None for a condition the paper does not rank


@dataclass(frozen=True)
class LearnabilityOrder:
    rows: list[ConditionLearnability]  # most learnable first
    # Spearman's ρ between the scores and the paper's order over the conditions both rank;
    # None below two such conditions or when either side has no spread (all tied).
    spearman_rho: float | None
    compared: tuple[str, ...]


def average_ranks(values: Sequence[float], descending: bool = True) -> list[float]:
    """Ranks from 1, the largest first when ``descending``; ties share their mean rank."""
    from scipy.stats import rankdata

    return [float(rank) for rank in rankdata([-v if descending else v for v in values], method="average")]


def spearman_rho(x: Sequence[float], y: Sequence[float]) -> float | None:
    """Spearman's rank correlation (scipy.stats.spearmanr); None when it is undefined (fewer
    than two pairs, or no spread on one side)."""
    if len(x) != len(y):
        raise ValueError(f"spearman_rho: {len(x)} values against {len(y)}")
    if len(x) < 2 or len(set(x)) < 2 or len(set(y)) < 2:
        return None
    from scipy.stats import spearmanr

    return float(spearmanr(x, y).statistic)


def learnability_order(
    history: Sequence[dict], names: dict[str, str] | None = None, score: str = "map"
) -> LearnabilityOrder:
    """Score and rank every condition of P (``queries.history`` entries: condition and the
    ``score`` key, the experiment's ``evaluation.loop_score``)."""
    from foldwise.theta import CANONICAL

    by_condition: dict[str, list[float | None]] = {}
    for entry in history:
        if entry["condition"] == CANONICAL:
            # start: canonical's shared stage, where every condition starts: not a condition.
            continue
        by_condition.setdefault(entry["condition"], []).append(entry[score])
    conditions = list(by_condition)
    # A model whose mAP is not finite (diverged) detected nothing usable: it scores 0.
    scores = [sum(m if m is not None else 0.0 for m in maps) / len(maps) for maps in by_condition.values()]
    ranks = average_ranks(scores)
    rows = sorted(
        (
            ConditionLearnability(
                condition=condition,
                name=(names or {}).get(condition, condition),
                score=score,
                best_map=max((m for m in by_condition[condition] if m is not None), default=None),
                increments=len(by_condition[condition]),
                rank=rank,
                paper_rank=PAPER_ORDER.index(condition) + 1 if condition in PAPER_ORDER else None,
            )
            for condition, score, rank in zip(conditions, scores, ranks)
        ),
        key=lambda row: (row.rank, row.condition),
    )
    compared = [row for row in rows if row.paper_rank is not None]
    # A high score is a low (good) paper rank: correlate the score with the negated rank.
    rho = spearman_rho([row.score for row in compared], [-row.paper_rank for row in compared])
    return LearnabilityOrder(rows=rows, spearman_rho=rho, compared=tuple(row.condition for row in compared))


def experiment_learnability(session, experiment_id: int) -> LearnabilityOrder:
    """The order of an experiment's conditions, from its P as ``session`` reads it."""
    from foldwise.conditions import load_condition_table
    from foldwise.config import ExperimentConfig
    from services import queries

    table = load_condition_table()
    experiment = queries.get_experiment(session, experiment_id)
    score = ExperimentConfig.model_validate(experiment.config).evaluation.loop_score
    names = {code: table.name(code) for code in table.codes}
    return learnability_order(queries.history(session, experiment_id), names, score)


def write_learnability_csv(order: LearnabilityOrder, path: Path) -> Path:
    """One row per condition, most learnable first; ρ repeats on every row so that a reader of
    any one row (or a spreadsheet filter) still sees it."""
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for row in order.rows:
            writer.writerow(
                {
                    "condition": row.condition,
                    "name": row.name,
                    "score": f"{row.score:.4f}",
                    "best_map": "" if row.best_map is None else f"{row.best_map:.4f}",
                    "increments": row.increments,
                    "rank": f"{row.rank:g}",
                    "paper_rank": "" if row.paper_rank is None else row.paper_rank,
                    "spearman_rho": "" if order.spearman_rho is None else f"{order.spearman_rho:.4f}",
                }
            )
    return path
