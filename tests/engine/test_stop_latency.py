"""A stop takes effect within seconds wherever the run is: inside a dynamics epoch, DICE training, the rollouts or an
evaluation, each made long by its own settings. What is left is right: after a stop in the dynamics phase nothing (no
checkpoint, no cached model), otherwise a checkpoint of the boundary before the phase
(tests/engine/test_trainer.py shows a run resumed from it is exact)."""
from __future__ import annotations

import time

import numpy as np
import pytest

from drop_engine import trainer as trainer_module
from drop_engine.callbacks import Callback
from drop_engine.checkpoint import list_checkpoints, load_latest
from drop_engine.collect import collect_transitions, random_policy
from drop_engine.config import build_config
from drop_engine.data import Dataset, from_arrays
from drop_engine.trainer import Trainer, TrainResult, train

LATE_S = 0.5  # the stop is asked for this long after the phase begins...
WITHIN_S = 10.0  # ...and the run has returned this soon after (slack for a loaded machine); each phase below
# runs for 18-40 s otherwise on an idle one


class StopInside(Callback):
    """Asks to stop from LATE_S after the run entered `owner.name`, which it wraps to see when that happens."""

    def __init__(self, monkeypatch, owner, name: str):
        self.entered: float | None = None
        real = getattr(owner, name)

        def entering(*args, **kwargs):
            self.entered = self.entered or time.monotonic()
            return real(*args, **kwargs)

        monkeypatch.setattr(owner, name, entering)

    def should_stop(self) -> bool:
        return self.entered is not None and time.monotonic() - self.entered >= LATE_S


def _stopped_soon(stop: StopInside, run) -> TrainResult:
    result = run()
    went_on = time.monotonic() - stop.entered - LATE_S
    assert result.status == "stopped" and went_on < WITHIN_S, f"went on for {went_on:.1f} s after the stop was asked"
    return result


def _config(env: str = "hopper", **overrides):
    return build_config("drop", env=env, preset="smoke", task="medium", overrides=overrides)


def _assert_checkpoint_at(result: TrainResult, out, position: tuple[int, int, bool]) -> dict:
    """The run's final checkpoint is the newest, and is at (epoch, step_in_epoch, epoch_started)."""
    assert result.checkpoint == str(list_checkpoints(out / "checkpoints")[-1])
    state = load_latest(out / "checkpoints")
    assert (state["epoch"], state["step_in_epoch"], state["epoch_started"]) == position
    return state


def test_inside_a_dynamics_epoch(tmp_path, hopper_arrays, monkeypatch):
    """An epoch over 150,000 rows takes half a minute; nothing is written, and the model cache stays empty."""
    many = from_arrays({k: np.concatenate([v] * 100) for k, v in hopper_arrays.items()}, {"env_name": "Hopper-v4"},
                       env="hopper")
    cfg = _config(dynamics={"members": 7, "elites": 5, "hidden": 400, "layers": 4, "batch_size": 256,
                            "max_epochs": 100_000, "patience": 1_000})
    stop = StopInside(monkeypatch, trainer_module, "train_dynamics")
    result = _stopped_soon(stop, lambda: train(many, cfg, tmp_path / "run", stop, model_cache=tmp_path / "models"))
    assert result.checkpoint is None and result.dynamics is None
    assert not list_checkpoints(tmp_path / "run" / "checkpoints")
    assert not list((tmp_path / "models").glob("*.pt"))


def test_inside_dice_training(tmp_path, hopper_dataset, monkeypatch):
    stop = StopInside(monkeypatch, Trainer, "train_dice")
    run = Trainer(hopper_dataset, _config(dice={"pretrain_steps": 30_000}), tmp_path, stop)
    _assert_checkpoint_at(_stopped_soon(stop, run.run), tmp_path, (0, 0, False))


def test_inside_the_rollouts(tmp_path, hopper_dataset, monkeypatch):
    """200,000 rollouts of a wide actor; the stopped rollout adds nothing to the model buffer."""
    stop = StopInside(monkeypatch, trainer_module, "model_rollout")
    cfg = _config(sac={"hidden": (2048, 2048)}, rollout={"batch_size": 200_000, "retain_epochs": 1})
    run = Trainer(hopper_dataset, cfg, tmp_path, stop)
    state = _assert_checkpoint_at(_stopped_soon(stop, run.run), tmp_path, (0, 0, False))
    assert state["model_buffer"]["size"] == 0


@pytest.fixture(scope="module")
def cheetah_dataset() -> Dataset:
    """HalfCheetah never terminates: each evaluation episode is 1,000 steps."""
    arrays = collect_transitions("halfcheetah", random_policy(6, seed=0), 1000, seed=0)
    return from_arrays(arrays, {"env_name": "HalfCheetah-v4"}, env="halfcheetah")


def test_inside_an_evaluation(tmp_path, cheetah_dataset, monkeypatch):
    """300 episodes of 1,000 steps; the position stays at the end of the epoch's SAC steps, the evaluation owed."""
    stop = StopInside(monkeypatch, trainer_module, "evaluate")
    cfg = _config("halfcheetah", eval_episodes=300)
    run = Trainer(cheetah_dataset, cfg, tmp_path, stop)
    state = _assert_checkpoint_at(_stopped_soon(stop, run.run), tmp_path, (0, cfg.steps_per_epoch, True))
    assert state["evaluations"] == []
