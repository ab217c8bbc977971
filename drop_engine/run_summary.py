"""A run's diagnostics in blocks of epochs: the mean of each metric of `metrics.jsonl` over epochs 1-10, 11-20, ...,
the table bench/QUALITY.md reads to tell a learning run from one that collapses or exploits its model."""
from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path
from typing import Iterable

from .run_log import NotARun, RunLog, run_config

# tau on the data should stay near 1; Q on model rows running away from Q on data rows, or model rewards above the
# data's, is model exploitation; the penalty's share says how much of the reward DROP's or MOPO's penalty takes.
DEFAULT_KEYS = ("dice/tau_data_mean", "rollout/penalty_share", "sac/q_data", "sac/q_model", "sac/target_clipped",
                "sac/bc_mse", "sac/bc_nll", "sac/alpha", "sac/entropy", "diag/reward_data", "diag/reward_model",
                "diag/uncertainty_data", "diag/uncertainty_model")


def by_epochs(metrics: Iterable[dict], steps_per_epoch: int, every: int,
              keys: Iterable[str]) -> tuple[list[str], dict[str, list[float | None]]]:
    """Block labels ("1-10", ...) and, per key, its mean in each block (None where it was never reported). A line
    belongs to the epoch its step falls in; lines of step 0 or less (dynamics, DICE pretraining) are left out."""
    sums: dict[tuple[str, int], list[float]] = defaultdict(lambda: [0.0, 0])
    keys, last = tuple(keys), -1
    for line in metrics:
        if line["step"] <= 0:
            continue
        block = (int(line["step"]) - 1) // steps_per_epoch // every
        last = max(last, block)
        for key in keys:
            value = line.get(key)
            if value is not None and math.isfinite(value):
                acc = sums[key, block]
                acc[0] += value
                acc[1] += 1
    labels = [f"{b * every + 1}-{(b + 1) * every}" for b in range(last + 1)]
    table = {key: [sums[key, b][0] / sums[key, b][1] if (key, b) in sums else None for b in range(last + 1)]
             for key in keys}
    return labels, table


def diagnostics_markdown(run_dir: str | Path, every: int = 10, keys: Iterable[str] = DEFAULT_KEYS) -> str:
    """The markdown table of `by_epochs` for one run directory (drop train's or the paper table's)."""
    run_dir = Path(run_dir)
    path = run_dir / "metrics.jsonl"
    if not path.is_file():
        raise NotARun(f"{run_dir}: no metrics.jsonl")
    labels, table = by_epochs(RunLog.read_metrics(path), int(run_config(run_dir)["steps_per_epoch"]), every, keys)
    out = [f"| metric (mean by epochs) | {' | '.join(labels)} |", "|---" * (len(labels) + 1) + "|"]
    out += [f"| {key} | {' | '.join('-' if v is None else f'{v:.3g}' for v in values)} |"
            for key, values in table.items() if any(v is not None for v in values)]
    return "\n".join(out)
