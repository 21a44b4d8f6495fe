"""The windowed stopping rule of Algorithm 1, table-driven."""

import math

import pytest

from services.scheduler.stopping import best_index, stopping_rule

NAN = math.nan

# (scores P after increment k, M, N, tau, cap) -> (stop, reason)
CASES = [
    # never before k = M + N, even when flat
    ([0.5, 0.5], 1, 2, 0.02, 99, False, None),
    ([0.5] * 10, 3, 8, 0.02, 99, False, None),
    # k = M + N exactly and flat: plateau
    ([0.5] * 11, 3, 8, 0.02, 99, True, "plateau"),
    # boundary equality is inclusive, float rounding notwithstanding (0.52 - 0.50 > 0.02 in binary)
    ([0.50, 0.50, 0.52], 1, 2, 0.02, 99, True, "plateau"),
    ([0.52, 0.50, 0.50], 1, 2, 0.02, 99, True, "plateau"),
    ([0.50, 0.50, 0.5201], 1, 2, 0.02, 99, False, None),
    # still improving: |P_M - P_N| > tau
    ([0.1, 0.2, 0.3, 0.4], 1, 2, 0.02, 99, False, None),
    # regression: recent window worse than the earlier one by more than tau is not a plateau...
    ([0.9, 0.9, 0.5], 1, 2, 0.02, 99, False, None),
    # ...but a regression within tau is
    ([0.9, 0.9, 0.89], 1, 2, 0.02, 99, True, "plateau"),
    # the windows are maxima: one good recent score is enough
    ([0.6, 0.7, 0.1, 0.69], 2, 2, 0.02, 99, True, "plateau"),
    # only the last M + N scores matter
    ([0.0, 0.0, 0.0, 0.8, 0.8, 0.8], 1, 2, 0.02, 99, True, "plateau"),
    # NaN never counts towards a plateau, in either window
    ([0.5, 0.5, NAN], 1, 2, 0.02, 99, False, None),
    ([NAN, 0.5, 0.5], 1, 2, 0.02, 99, False, None),
    ([0.5, None, 0.5], 1, 2, 0.02, 99, False, None),
    ([NAN, NAN, NAN], 1, 2, 1.0, 99, False, None),
    # once the NaN leaves the windows the rule applies again
    ([NAN, 0.5, 0.5, 0.5], 1, 2, 0.02, 99, True, "plateau"),
    # the cap ends a stage that never plateaus, and only at k = cap
    ([0.1, 0.3, 0.5, 0.7], 1, 2, 0.02, 4, True, "cap"),
    ([0.1, 0.3, 0.5], 1, 2, 0.02, 4, False, None),
    ([NAN] * 4, 1, 2, 0.02, 4, True, "cap"),
    # a cap below M + N still stops
    ([0.1], 3, 8, 0.02, 1, True, "cap"),
    # plateau takes precedence when both hold
    ([0.5, 0.5, 0.5], 1, 2, 0.02, 3, True, "plateau"),
    # tau = 0 needs exact equality
    ([0.5, 0.5, 0.5], 1, 2, 0.0, 99, True, "plateau"),
    ([0.5, 0.5, 0.51], 1, 2, 0.0, 99, False, None),
]


@pytest.mark.parametrize(("scores", "M", "N", "tau", "cap", "stop", "reason"), CASES)
def test_stopping_rule(scores, M, N, tau, cap, stop, reason):
    decision = stopping_rule(scores, M, N, tau, cap)
    assert (decision.stop, decision.reason) == (stop, reason)


def test_windows_report_their_maxima():
    decision = stopping_rule([0.2, 0.4, 0.3, 0.41, 0.1], M=2, N=3, tau=0.02, max_increments=99)
    assert decision.p_m == 0.41 and decision.p_n == 0.4 and decision.stop


@pytest.mark.parametrize(("M", "N", "tau"), [(0, 1, 0.1), (1, 0, 0.1), (1, 1, -0.1)])
def test_invalid_parameters_are_rejected(M, N, tau):
    with pytest.raises(ValueError):
        stopping_rule([0.5], M, N, tau, 10)


@pytest.mark.parametrize(
    ("scores", "best"),
    [([0.1, 0.5, 0.3], 1), ([0.5, 0.5], 0), ([NAN, 0.2, None], 1), ([NAN, None], None), ([], None)],
)
def test_best_index_is_the_earliest_finite_maximum(scores, best):
    assert best_index(scores) == best
