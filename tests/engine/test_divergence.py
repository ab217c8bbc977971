"""A run whose losses become NaN or infinite fails at once with TrainingDiverged, naming the metric and the step, and
no non-finite number reaches the callback: SAC diverging for real, DICE and the dynamics fit through broken losses."""
from __future__ import annotations

import math

import pytest
import torch

from drop_engine.callbacks import Callback
from drop_engine.config import build_config
from drop_engine.dice import GradientDice
from drop_engine.divergence import TrainingDiverged
from drop_engine.dynamics import GaussianEnsemble
from drop_engine.trainer import train

# The temperature's target entropy far above any policy's, at the largest learning rate: log alpha climbs by about one
# per step, and the critic's squared error overflows within the first epoch.
RUNAWAY_ALPHA = {"sac.alpha_lr": 1.0, "sac.target_entropy": 1000.0, "epochs": 3, "steps_per_epoch": 50}


class Metrics(Callback):
    def __init__(self):
        self.values: list[float] = []

    def on_metrics(self, metrics, step):
        self.values += list(metrics.values())


def _diverged(tmp_path, dataset, overrides: dict) -> TrainingDiverged:
    seen = Metrics()
    config = build_config("drop", env="hopper", preset="smoke", task="medium", overrides=overrides)
    with pytest.raises(TrainingDiverged) as caught:
        train(dataset, config, tmp_path, seen)
    assert all(math.isfinite(v) for v in seen.values)
    return caught.value


def test_sac_diverging(tmp_path, hopper_dataset):
    exc = _diverged(tmp_path, hopper_dataset, RUNAWAY_ALPHA)
    assert exc.metric.startswith("sac/") and exc.step == 50 and not math.isfinite(exc.value)
    assert str(exc) == f"training diverged: {exc.metric} was {exc.value} at step 50"


def test_dice_diverging(tmp_path, hopper_dataset, monkeypatch):
    real = GradientDice.objective

    def broken(self, *args):
        j, tau = real(self, *args)
        return j * math.nan, tau

    monkeypatch.setattr(GradientDice, "objective", broken)
    exc = _diverged(tmp_path, hopper_dataset, {})
    assert (exc.metric, exc.step) == ("dice/objective", 0)  # pretraining, reported with the first rollouts


def test_dynamics_diverging(tmp_path, hopper_dataset, monkeypatch):
    real = GaussianEnsemble.loss
    monkeypatch.setattr(GaussianEnsemble, "loss", lambda self, *a: real(self, *a) * torch.tensor(math.nan))
    exc = _diverged(tmp_path, hopper_dataset, {})
    assert (exc.metric, exc.step) == ("dynamics/holdout_mse", -1)
    assert str(exc) == "training diverged: dynamics/holdout_mse was nan at dynamics epoch 1"
