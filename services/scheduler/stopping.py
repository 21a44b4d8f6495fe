"""The windowed stopping rule of Algorithm 1 (Sankar & Bartoli 2018, §4.2).

Once k ≥ M + N: P_M = max of the last M scores, P_N = max of the N scores before them;
the stage has learned its condition when |P_M − P_N| ≤ τ (inclusive). A score that is not a
finite number (a diverged model, an empty evaluation) never counts towards a plateau: a
window holding one cannot stop the stage. A cap on increments ends a stage that never
plateaus, and the reason is recorded.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

# |P_M − P_N| is a difference of floats: 0.52 − 0.50 is 0.020000000000000018, which must
# still count as "equal to τ = 0.02" for the rule to be inclusive as the paper states.
_TOLERANCE = 1e-9


def _finite(value: float | None) -> bool:
    return value is not None and math.isfinite(value)


@dataclass(frozen=True)
class StopDecision:
    stop: bool
    reason: str | None  # "plateau" | "cap" | None
    p_m: float | None = None
    p_n: float | None = None


def stopping_rule(scores: Sequence[float | None], M: int, N: int, tau: float, max_increments: int) -> StopDecision:
    """Decide after increment k = len(scores) whether the stage stops."""
    if M < 1 or N < 1:
        raise ValueError(f"window sizes must be at least 1, got M={M}, N={N}")
    if tau < 0:
        raise ValueError(f"tau must be non-negative, got {tau}")
    k = len(scores)
    p_m = p_n = None
    if k >= M + N:
        recent = scores[k - M :]
        earlier = scores[k - M - N : k - M]
        if all(_finite(s) for s in recent) and all(_finite(s) for s in earlier):
            p_m, p_n = max(recent), max(earlier)
            if abs(p_m - p_n) <= tau + _TOLERANCE:
                return StopDecision(True, "plateau", p_m, p_n)
    if k >= max_increments:
        return StopDecision(True, "cap", p_m, p_n)
    return StopDecision(False, None, p_m, p_n)


def best_index(scores: Sequence[float | None]) -> int | None:
    """argmax over finite scores (the earliest on ties); None when no score is finite."""
    best = None
    for i, score in enumerate(scores):
        if _finite(score) and (best is None or score > scores[best]):
            best = i
    return best
