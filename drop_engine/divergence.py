"""Divergence: a loss or statistic that has become NaN or infinite never recovers, and every later number is
meaningless, so the run fails at once with `TrainingDiverged` instead of carrying NaNs into its record. Checked on
what the trainer reports, which it has already brought to the CPU: no extra synchronisation."""
from __future__ import annotations

import math
from typing import Mapping


class TrainingDiverged(ArithmeticError):
    """`metric` was `value` in the report at `step` (a global SAC step; minus the epoch in the dynamics phase)."""

    def __init__(self, metric: str, value: float, step: int):
        self.metric, self.value, self.step = metric, value, step
        where = f"dynamics epoch {-step}" if step < 0 else f"step {step}"
        super().__init__(f"training diverged: {metric} was {value} at {where}")


def check_finite(metrics: Mapping[str, float], step: int) -> None:
    """Raise `TrainingDiverged` for the first metric that is not a finite number."""
    for name, value in metrics.items():
        if not math.isfinite(value):
            raise TrainingDiverged(name, value, step)
