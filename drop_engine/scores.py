"""How a run's evaluations are summarised, and which policies a run exports, in one place so the trainer, its exports
and the service agree (torch-free, so the API can import it).

"Best" is the earliest evaluation with the highest normalised score (a later tie does not replace it). "Final" is the
mean of the last `FINAL_WINDOW` evaluations rather than the last one alone, because a single evaluation is noisy.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence

FINAL_WINDOW = 3
Which = Literal["last", "best"]  # the policy after the last epoch, or the one of the best evaluation


@dataclass(frozen=True)
class ScoreSummary:
    last_score: float | None
    best_score: float | None
    best_epoch: int | None
    final_score: float | None


def summarize(evaluations: Sequence[tuple[int, float]]) -> ScoreSummary:
    """(epoch, normalised score) pairs in evaluation order to the run's last, best and final scores."""
    if not evaluations:
        return ScoreSummary(None, None, None, None)
    best_epoch, best_score = max(evaluations, key=lambda e: e[1])  # max keeps the first of ties
    window = [score for _, score in evaluations[-FINAL_WINDOW:]]
    return ScoreSummary(evaluations[-1][1], best_score, best_epoch, sum(window) / len(window))
