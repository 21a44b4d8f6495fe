"""The learnability score, order and Spearman's ρ (services/learnability.py) on hand-made P."""

from __future__ import annotations

import csv

import pytest

from services.learnability import (
    PAPER_ORDER,
    average_ranks,
    learnability_order,
    spearman_rho,
    write_learnability_csv,
)


def _history(maps_by_condition: dict[str, list[float | None]]) -> list[dict]:
    return [{"condition": c, "map": m} for c, maps in maps_by_condition.items() for m in maps]


def test_the_score_is_the_mean_map_over_every_increment():
    order = learnability_order(_history({"fb": [0.2, 0.4, 0.9], "po": [0.0, None, 0.3]}))
    fb, po = order.rows
    assert (fb.condition, fb.score, fb.best_map, fb.increments, fb.rank) == ("fb", pytest.approx(0.5), 0.9, 3, 1)
    # a non-finite mAP counts as nothing learned; the best is over the finite ones
    assert (po.condition, po.score, po.best_map, po.rank) == ("po", pytest.approx(0.1), 0.3, 2)


def test_the_shared_canonical_stage_is_no_condition_of_the_order():
    # learnability.start: canonical trains a canonical stage first; it scores highest of all
    order = learnability_order(_history({"canonical": [0.9, 0.95], "fb": [0.2, 0.4], "po": [0.1, 0.3]}))
    assert [row.condition for row in order.rows] == ["fb", "po"]
    assert [row.rank for row in order.rows] == [1, 2]
    assert order.compared == ("fb", "po") and order.spearman_rho == pytest.approx(1.0)


def test_a_condition_learned_early_beats_one_that_only_ends_as_high():
    order = learnability_order(_history({"de": [0.1, 0.1, 0.8], "sc": [0.6, 0.7, 0.8]}))
    assert [row.condition for row in order.rows] == ["sc", "de"]
    assert order.rows[0].best_map == order.rows[1].best_map


def test_the_papers_order_gives_rho_one_and_its_reverse_minus_one():
    paper = _history({code: [1.0 - i / 10] for i, code in enumerate(PAPER_ORDER)})
    order = learnability_order(paper)
    assert [row.condition for row in order.rows] == list(PAPER_ORDER)
    assert [row.paper_rank for row in order.rows] == [1, 2, 3, 4, 5, 6]
    assert order.spearman_rho == pytest.approx(1.0)
    reverse = _history({code: [i / 10] for i, code in enumerate(PAPER_ORDER)})
    assert learnability_order(reverse).spearman_rho == pytest.approx(-1.0)


def test_lighting_is_ranked_but_left_out_of_rho():
    maps = {code: [1.0 - i / 10] for i, code in enumerate(PAPER_ORDER)}
    order = learnability_order(_history({"li": [0.95], **maps}))
    li = next(row for row in order.rows if row.condition == "li")
    assert li.rank == 2 and li.paper_rank is None
    assert order.compared == PAPER_ORDER and order.spearman_rho == pytest.approx(1.0)


def test_one_swap_of_neighbours_in_six():
    # fb and mb swapped: Σd² = 2, ρ = 1 − 6·2 / (6·35) = 1 − 2/35
    swapped = ["mb", "fb", "sc", "eo", "de", "po"]
    order = learnability_order(_history({code: [1.0 - i / 10] for i, code in enumerate(swapped)}))
    assert order.spearman_rho == pytest.approx(1 - 2 / 35)


def test_rho_is_undefined_without_two_ranked_conditions_or_without_spread():
    assert learnability_order(_history({"fb": [0.5], "li": [0.2]})).spearman_rho is None
    assert learnability_order(_history({"fb": [0.0, 0.0], "po": [0.0, 0.0]})).spearman_rho is None
    assert spearman_rho([], []) is None
    with pytest.raises(ValueError):
        spearman_rho([1.0], [1.0, 2.0])


def test_ties_share_their_mean_rank():
    assert average_ranks([0.3, 0.5, 0.3, 0.1]) == [2.5, 1.0, 2.5, 4.0]
    assert average_ranks([0.3, 0.5, 0.3, 0.1], descending=False) == [2.5, 4.0, 2.5, 1.0]


def test_the_csv_holds_score_rank_paper_rank_and_rho(tmp_path):
    order = learnability_order(_history({"fb": [0.9], "po": [0.1], "li": [0.5]}), {"fb": "focus blur"})
    path = write_learnability_csv(order, tmp_path / "learnability.csv")
    with open(path) as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["condition"], r["name"], r["rank"], r["paper_rank"]) for r in rows] == [
        ("fb", "focus blur", "1", "1"), ("li", "li", "2", ""), ("po", "po", "3", "6"),
    ]  # fmt: skip
    assert {r["spearman_rho"] for r in rows} == {"1.0000"}
    assert rows[0]["score"] == "0.9000" and rows[0]["best_map"] == "0.9000"


def test_the_order_reads_the_score_the_loop_read():
    # At the cut both conditions read 0 (a young detector's boxes score below 0.8); the
    # unthresholded mAP still tells them apart.
    history = [
        {"condition": "fb", "map": 0.0, "map_unthresholded": 0.9},
        {"condition": "po", "map": 0.0, "map_unthresholded": 0.3},
    ]
    assert learnability_order(history).spearman_rho is None
    order = learnability_order(history, score="map_unthresholded")
    assert [row.condition for row in order.rows] == ["fb", "po"]
    assert order.spearman_rho == pytest.approx(1.0)
