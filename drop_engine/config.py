"""Typed training configuration, presets and overrides.

A run is fully described by one `TrainConfig`; `build_config` composes it from the per-dataset settings of the official
code (penalty, horizon, DICE), a size preset (`paper`, `cpu`, `smoke`) and user overrides, in that order, and validates
the result, so a bad override is rejected before any work starts.
"""
from __future__ import annotations

from typing import Any, Literal, Mapping

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

Algorithm = Literal["drop", "mopo", "mbpo"]
PenaltyFn = Literal["log", "tanh", "tanh_shift"]
PRESETS = ("paper", "cpu", "smoke")


class ConfigError(ValueError):
    """A configuration that cannot be built; the message names the field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class DynamicsConfig(_Strict):
    members: int = Field(7, ge=1)
    elites: int = Field(5, ge=1)
    hidden: int = Field(200, ge=1)
    layers: int = Field(4, ge=1)
    lr: float = Field(1e-3, gt=0)
    batch_size: int = Field(256, ge=1)
    holdout_ratio: float = Field(0.2, ge=0, lt=1)
    max_holdout: int = Field(1000, ge=1)
    patience: int = Field(5, ge=1, description="epochs with no member improving by >1% before stopping")
    max_epochs: int | None = Field(None, ge=1)
    max_seconds: float | None = Field(None, gt=0, description="wall-clock cap; makes the model, and so the run, "
                                      "depend on how busy the machine is (no preset sets it)")
    weight_decay: tuple[float, ...] = (2.5e-5, 5e-5, 7.5e-5, 7.5e-5, 1e-4)

    @model_validator(mode="after")
    def _check(self) -> "DynamicsConfig":
        if self.elites > self.members:
            raise ValueError(f"elites ({self.elites}) cannot exceed members ({self.members})")
        return self


class SACConfig(_Strict):
    hidden: tuple[int, ...] = (256, 256)
    actor_lr: float = Field(3e-4, gt=0)
    critic_lr: float = Field(3e-4, gt=0)
    alpha_lr: float = Field(3e-4, gt=0)
    gamma: float = Field(0.99, gt=0, lt=1)
    tau: float = Field(5e-3, gt=0, le=1)
    batch_size: int = Field(256, ge=1)
    real_ratio: float = Field(0.05, ge=0, le=1)
    target_entropy: float | None = Field(None, description="default -|A|")
    bc_weight: float = Field(0.0, ge=0, description="behaviour term of the actor loss, as TD3+BC: with w > 0 the "
                             "actor minimises (alpha logp - Q)/mean|Q| + w * mean (tanh(mu(s)) - a)^2 on a real batch; "
                             "0 is plain SAC (the paper)")


class RolloutConfig(_Strict):
    batch_size: int = Field(50_000, ge=1, description="start states per epoch")
    horizon: int = Field(5, ge=1)
    retain_epochs: int = Field(5, ge=1)


class DiceConfig(_Strict):
    hidden: tuple[int, ...] = (64, 64)
    lr: float = Field(1e-4, gt=0)
    lam: float = Field(0.1, ge=0, description="normalisation constraint weight (lambda)")
    batch_size: int = Field(256, ge=1)
    pretrain_steps: int = Field(400, ge=0)
    steps_per_epoch: int = Field(400, ge=0)
    positive: bool = Field(False, description="tau = softplus(net), never negative; False is the paper's linear tau")
    discount: float | Literal["sac", "horizon"] = Field(
        "sac", description="the occupancy's discount: 'sac' uses SAC's gamma (the paper); 'horizon' uses (h-1)/(h+1), "
                           "whose mean step (h-1)/2 is that of the h-step model rollouts the penalty is applied to")

    @model_validator(mode="after")
    def _check(self) -> "DiceConfig":
        if isinstance(self.discount, float) and not 0 <= self.discount < 1:
            raise ValueError(f"discount must be in [0, 1), got {self.discount}")
        return self


class PenaltyConfig(_Strict):
    eta: float = Field(1.0, ge=0, description="DROP penalty coefficient")
    g: PenaltyFn = "log"
    clip: tuple[float, float] | None = (0.01, 10.0)
    bonus: bool = Field(True, description="let a ratio below 1 raise the reward, as the official code does")
    mopo_lambda: float = Field(1.0, ge=0)
    mopo_horizon: int = Field(5, ge=1)

    @model_validator(mode="after")
    def _check(self) -> "PenaltyConfig":
        if self.clip is not None and not 0 < self.clip[0] < self.clip[1]:
            raise ValueError(f"clip must satisfy 0 < low < high, got {self.clip}")
        return self


class TrainConfig(_Strict):
    algorithm: Algorithm = "drop"
    env: str = "hopper"
    env_version: Literal["v4", "v5"] = "v4"
    task: str | None = Field(None, description="dataset kind, e.g. 'medium', selects the per-dataset settings")
    preset: Literal["paper", "cpu", "smoke"] = "cpu"
    seed: int = Field(0, ge=0)
    device: str = "cpu"
    threads: int | None = Field(None, ge=1)
    epochs: int = Field(200, ge=1)
    steps_per_epoch: int = Field(1000, ge=1)
    eval_every: int = Field(10, ge=1)
    eval_episodes: int = Field(10, ge=1)
    checkpoint_every: int = Field(10, ge=1)
    keep_checkpoints: int = Field(2, ge=1)
    normalize_obs: bool = True
    log_every: int = Field(250, ge=1, description="SAC steps between metric reports")
    dynamics: DynamicsConfig = DynamicsConfig()
    sac: SACConfig = SACConfig()
    rollout: RolloutConfig = RolloutConfig()
    dice: DiceConfig = DiceConfig()
    penalty: PenaltyConfig = PenaltyConfig()

    @property
    def horizon(self) -> int:
        return self.penalty.mopo_horizon if self.algorithm == "mopo" else self.rollout.horizon

    @property
    def dice_discount(self) -> float:
        if self.dice.discount == "sac":
            return self.sac.gamma
        if self.dice.discount == "horizon":
            return (self.horizon - 1) / (self.horizon + 1)
        return self.dice.discount


# Per-dataset settings of the official code: h, eta, g, clip, lambda, dice lr, dice steps, MOPO h, MOPO lambda.
_LOG10, _LOG50 = ("log", (0.01, 10.0)), ("log", (0.01, 50.0))
_TABLE: dict[str, tuple] = {
    "halfcheetah-random": (5, 0.5, *_LOG10, 0.1, 1e-4, 400, 5, 0.5),
    "halfcheetah-medium": (5, 1.0, *_LOG10, 0.1, 1e-4, 400, 1, 1.0),
    "halfcheetah-medium-replay": (5, 1.0, *_LOG10, 1.0, 1e-4, 400, 5, 1.0),
    "halfcheetah-medium-expert": (5, 0.1, *_LOG50, 0.5, 1e-4, 200, 5, 5.0),
    "hopper-random": (5, 1.0, "tanh", None, 0.1, 1e-4, 400, 5, 1.0),
    "hopper-medium": (5, 5.0, *_LOG10, 0.1, 1e-4, 400, 5, 5.0),
    "hopper-medium-replay": (5, 1.0, *_LOG10, 0.1, 1e-4, 400, 5, 1.0),
    "hopper-medium-expert": (5, 5.0, *_LOG10, 0.1, 1e-4, 400, 5, 1.0),
    "walker2d-random": (1, 1.0, *_LOG50, 0.1, 1e-3, 600, 1, 1.0),
    "walker2d-medium": (5, 0.1, "tanh_shift", None, 0.1, 1e-4, 400, 5, 5.0),
    "walker2d-medium-replay": (1, 2.0, *_LOG50, 0.1, 1e-4, 600, 1, 1.0),
    "walker2d-medium-expert": (1, 5.0, "tanh_shift", None, 0.1, 1e-4, 500, 1, 2.0),
}
PAPER_EPOCHS = {"hopper": 1500, "halfcheetah": 500, "walker2d": 3000}


def dataset_settings(env: str, task: str | None) -> dict[str, Any]:
    """The official per-dataset settings as nested overrides; `medium` stands in for an unknown task."""
    key = f"{env}-{task}" if f"{env}-{task}" in _TABLE else f"{env}-medium"
    if key not in _TABLE:
        return {}
    h, eta, g, clip, lam, dice_lr, dice_steps, mopo_h, mopo_lam = _TABLE[key]
    return {
        "rollout": {"horizon": h},
        "penalty": {"eta": eta, "g": g, "clip": clip, "mopo_lambda": mopo_lam, "mopo_horizon": mopo_h},
        "dice": {"lam": lam, "lr": dice_lr, "steps_per_epoch": dice_steps, "pretrain_steps": dice_steps},
    }


# The cpu preset's behaviour-term weight per dataset kind (bench/QUALITY.md): strong where the data is one competent
# policy, weak where it is a mix of many (medium-replay) or no policy at all (random), so the model can lift the
# policy above the data there.
CPU_BC_WEIGHT = {"random": 0.1, "medium": 0.4, "medium-replay": 0.1, "medium-expert": 0.4}


def preset_settings(preset: str, env: str, task: str | None = None) -> dict[str, Any]:
    """Sizes, and for `cpu` the stabilisers of bench/QUALITY.md, applied alike to DROP, MOPO and MBPO."""
    if preset == "paper":
        return {"epochs": PAPER_EPOCHS.get(env, 1000), "sac": {"target_entropy": -3.0}}
    if preset == "cpu":
        # Dynamics bounded by epochs and early stopping, never by the clock, so a seed gives the same model on a busy
        # machine; then 90 epochs of 1000 SAC updates, the DICE steps and 10,000 x h rollouts (bench/QUALITY.md).
        return {
            "epochs": 90, "eval_every": 10, "eval_episodes": 10, "checkpoint_every": 10,
            "dynamics": {"max_epochs": 60},
            "rollout": {"batch_size": 10_000},
            "sac": {"bc_weight": CPU_BC_WEIGHT.get(task or "medium", CPU_BC_WEIGHT["medium"])},
            "dice": {"positive": True, "discount": "horizon"},
            "penalty": {"bonus": False},
        }
    if preset == "smoke":
        return {
            "epochs": 2, "steps_per_epoch": 20, "eval_every": 1, "eval_episodes": 2, "checkpoint_every": 1,
            "log_every": 10,
            "dynamics": {"members": 3, "elites": 2, "hidden": 32, "layers": 2, "max_epochs": 3, "batch_size": 64},
            "sac": {"hidden": (32, 32), "batch_size": 64},
            "rollout": {"batch_size": 64, "retain_epochs": 2},
            "dice": {"hidden": (16, 16), "batch_size": 64, "pretrain_steps": 10, "steps_per_epoch": 5},
        }
    raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")


def _merge(base: dict, extra: Mapping) -> dict:
    out = dict(base)
    for key, value in extra.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _nest(overrides: Mapping[str, Any]) -> dict:
    """Turn {"dice.lr": 1e-3} into {"dice": {"lr": 1e-3}}; nested dicts pass through."""
    nested: dict = {}
    for key, value in overrides.items():
        parts = str(key).split(".")
        node = nested
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {key!r} conflicts with another override")
        node[parts[-1]] = value
    return nested


def build_config(
    algorithm: str = "drop",
    env: str = "hopper",
    preset: str = "cpu",
    task: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    seed: int = 0,
    device: str = "cpu",
) -> TrainConfig:
    """Compose dataset settings, preset and overrides into one validated config."""
    base = {"algorithm": algorithm, "env": env, "preset": preset, "task": task, "seed": seed, "device": device}
    layers = [dataset_settings(env, task), preset_settings(preset, env, task), _nest(overrides or {})]
    merged: dict = base
    for layer in layers:
        merged = _merge(merged, layer)
    try:
        return TrainConfig.model_validate(merged)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc']) or 'config'}: {err['msg']}" for err in exc.errors()
        )
        raise ConfigError(problems) from None
