"""A run's metrics.jsonl and evaluations.csv hold one continuous history, also across a stop and a lost attempt."""
import json

from drop_engine.callbacks import CallbackList
from drop_engine.config import build_config
from drop_engine.run_log import RunLog
from drop_engine.trainer import Trainer

from .recorder import Recorder


def _history(out):
    lines = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    metrics = [(m.pop("step"), {k: v for k, v in m.items() if k != "time" and not k.startswith("time/")})
               for m in lines]
    evaluations = [(int(r["epoch"]), float(r["normalized_score"]))
                   for r in RunLog.read_evaluations(out / "evaluations.csv")]
    return metrics, evaluations


def test_run_log_is_continuous_across_stop_and_lost_writes(tmp_path, hopper_dataset):
    cfg = build_config("drop", env="hopper", preset="smoke", task="medium", overrides={"epochs": 3})
    whole = tmp_path / "whole"
    Trainer(hopper_dataset, cfg, whole, RunLog(whole, cfg.steps_per_epoch)).run()

    split = tmp_path / "split"
    stop = Recorder(stop_in=Trainer._sac_steps, after=35)
    first = Trainer(hopper_dataset, cfg, split, CallbackList(stop, RunLog(split, cfg.steps_per_epoch)))
    assert first.run().status == "stopped"
    # A lost attempt wrote past the checkpoint before dying, at the checkpoint's own step (an epoch start's metrics)
    # and later: none of that may stay in the history.
    with (split / "metrics.jsonl").open("a") as f:
        for step in (first.global_step, first.global_step + 5):
            f.write(json.dumps({"step": step, "time": 0.0, "sac/q_mean": 1e9}) + "\n")
    with (split / "evaluations.csv").open("a") as f:
        f.write(f"{first.epoch + 1},0.0,-999.0,0.0\n")
    Trainer(hopper_dataset, cfg, split, RunLog(split, cfg.steps_per_epoch)).run()

    metrics, evaluations = _history(whole)
    assert [e for e, _ in evaluations] == [1, 2, 3]
    assert any(name == "dynamics/holdout_mse" for _, m in metrics for name in m)
    assert _history(split) == (metrics, evaluations)
