"""A run's history as files beside its checkpoints: `metrics.jsonl` (every metric the service stores, with its step
and wall time) and `evaluations.csv`, so CLI and benchmark runs can be plotted and diagnosed like service jobs."""
from __future__ import annotations

import csv
import io
import json
import time
from pathlib import Path
from typing import Mapping

from .atomic import write_text
from .callbacks import Callback
from .plots import Curve
from .policy_files import FILE_NAMES

EVALUATION_FIELDS = ("epoch", "mean_return", "normalized_score", "time")


class RunLog(Callback):
    """Appends as the run goes; a resumed run first cuts both files back to where they stood when its checkpoint was
    written, so they hold one continuous history, as the service's tables do. Steps cannot tell where to cut: the
    metrics of an epoch's start carry the step of the checkpoint before them."""

    def __init__(self, out_dir: str | Path, steps_per_epoch: int):
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        self.metrics_path, self.evaluations_path = out / "metrics.jsonl", out / "evaluations.csv"
        self.marks_path = out / "run_log_marks.json"  # checkpoint "epoch:step" -> the two files' sizes then
        self.steps_per_epoch = steps_per_epoch

    def on_start(self, resumed: tuple[int, int] | None) -> None:
        mark = self._marks().get(f"{resumed[0]}:{resumed[1]}") if resumed is not None else None
        if mark is not None:
            for path, size in zip((self.metrics_path, self.evaluations_path), mark):
                with path.open("r+b") as f:
                    f.truncate(size)
            return
        if resumed is None:
            self.marks_path.unlink(missing_ok=True)
        # No mark: a fresh run, or a run killed between writing its checkpoint and marking it, when nothing of the
        # next epoch was written yet and the steps do tell.
        last_step = -float("inf") if resumed is None else resumed[0] * self.steps_per_epoch + resumed[1]
        last_epoch = -1 if resumed is None else resumed[0]
        kept = [m for m in self.read_metrics(self.metrics_path)
                if resumed is not None and (m["step"] <= last_step or m["step"] <= 0)]
        write_text(self.metrics_path, "".join(json.dumps(m) + "\n" for m in kept))
        rows = [r for r in self.read_evaluations(self.evaluations_path) if int(r["epoch"]) <= last_epoch]
        table = io.StringIO(newline="")
        writer = csv.DictWriter(table, EVALUATION_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
        write_text(self.evaluations_path, table.getvalue())

    def on_checkpoint(self, path: Path, epoch: int, step: int) -> None:
        sizes = [p.stat().st_size if p.exists() else 0 for p in (self.metrics_path, self.evaluations_path)]
        marks = {**self._marks(), f"{epoch}:{step}": sizes}
        write_text(self.marks_path, json.dumps(marks))

    def _marks(self) -> dict[str, list[int]]:
        return json.loads(self.marks_path.read_text()) if self.marks_path.exists() else {}

    def on_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        line = {"step": step, "time": time.time(), **{k: float(v) for k, v in metrics.items()}}
        with self.metrics_path.open("a") as f:
            f.write(json.dumps(line) + "\n")

    def on_evaluation(self, epoch: int, mean_return: float, normalized_score: float) -> None:
        with self.evaluations_path.open("a", newline="") as f:
            csv.DictWriter(f, EVALUATION_FIELDS).writerow(
                {"epoch": epoch, "mean_return": mean_return, "normalized_score": normalized_score, "time": time.time()})

    @staticmethod
    def read_metrics(path: Path) -> list[dict]:
        if not path.exists():
            return []
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]

    @staticmethod
    def read_evaluations(path: Path) -> list[dict]:
        if not path.exists():
            return []
        with path.open(newline="") as f:
            return list(csv.DictReader(f))


class NotARun(ValueError):
    pass


def run_config(run_dir: Path) -> dict:
    """A run's config: from `summary.json` (drop train), an exported policy's metadata, or else its newest checkpoint
    (slow: the whole state is loaded)."""
    for path in (run_dir / "summary.json", run_dir / "policy" / "last" / FILE_NAMES["metadata"],
                 run_dir / "policy" / FILE_NAMES["metadata"]):
        if path.is_file() and (config := json.loads(path.read_text()).get("config")):
            return config
    from .checkpoint import load_latest

    state = load_latest(run_dir / "checkpoints")
    if state is None:
        raise NotARun(f"{run_dir}: no summary.json, policy metadata or checkpoint says what the run was")
    return state["config"]


def read_curve(run_dir: str | Path) -> Curve:
    """A run directory's learning curve (evaluations.csv) with its algorithm, env and seed."""
    run_dir = Path(run_dir)
    rows = RunLog.read_evaluations(run_dir / "evaluations.csv")
    if not rows:
        raise NotARun(f"{run_dir}: no evaluations.csv, or no evaluation in it yet")
    config = run_config(run_dir)
    return Curve(config["algorithm"], config["env"], int(config["seed"]), [int(r["epoch"]) for r in rows],
                 [float(r["normalized_score"]) for r in rows])
