"""Typed training configuration, presets and overrides.

A run is fully described by one `TrainConfig`; `build_config` composes it from the per-dataset settings of the official
code (penalty, horizon, DICE), a preset (`paper` as published; `cpu`, smaller and with the stabilisers of
bench/QUALITY.md; `smoke` for tests) and user overrides, in that order, and validates
the result, so a bad override is rejected before any work starts.
"""
from __future__ import annotations

import json
from typing import Annotated, Any, Iterable, Literal, Mapping, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .envs import EnvVersion
from .errors import ConfigError

Algorithm = Literal["drop", "mopo", "mbpo"]
PenaltyFn = Literal["log", "tanh", "tanh_shift"]
Preset = Literal["paper", "cpu", "smoke"]
PRESETS: tuple[Preset, ...] = get_args(Preset)
# The dataset kinds with settings of their own (the official table's rows); a run without one takes medium's.
Task = Literal["random", "medium", "medium-replay", "medium-expert"]
TASKS: tuple[Task, ...] = get_args(Task)


class _Strict(BaseModel):
    """Unknown keys and non-finite numbers are refused: a NaN or infinite setting would only surface as a NaN loss."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


# Upper bounds: generous enough for a power user of the CLI, finite so that no value asks for the impossible. The
# service refuses jobs over its own, tighter limits on the whole run (app/jobs/limits.py).
Width = Annotated[int, Field(ge=1, le=4096)]
Hidden = Annotated[tuple[Width, ...], Field(max_length=8)]
BatchSize = Annotated[int, Field(ge=1, le=65_536)]
LearningRate = Annotated[float, Field(gt=0, le=1)]
Epochs = Annotated[int, Field(ge=1, le=100_000)]
Steps = Annotated[int, Field(ge=0, le=1_000_000)]
Weight = Annotated[float, Field(ge=0, le=1_000)]
Horizon = Annotated[int, Field(ge=1, le=1_000)]
ClipBound = Annotated[float, Field(le=1e6)]


class DynamicsConfig(_Strict):
    members: int = Field(7, ge=1, le=64)
    elites: int = Field(5, ge=1, le=64)
    hidden: Width = 200
    layers: int = Field(4, ge=1, le=8)
    lr: LearningRate = 1e-3
    batch_size: BatchSize = 256
    holdout_ratio: float = Field(0.2, ge=0, lt=1)
    max_holdout: int = Field(1000, ge=1, le=1_000_000)
    patience: int = Field(5, ge=1, le=1_000, description="epochs with no member improving by >1% before stopping")
    max_epochs: Epochs | None = None
    max_seconds: float | None = Field(None, gt=0, le=30 * 24 * 3600, description="wall-clock cap; makes the model, "
                                      "and so the run, depend on how busy the machine is (no preset sets it)")
    weight_decay: tuple[Annotated[float, Field(ge=0, le=1)], ...] = Field(
        (2.5e-5, 5e-5, 7.5e-5, 7.5e-5, 1e-4), min_length=1, max_length=16,
        description="per hidden layer (the second-to-last repeats), the last for the heads")

    @model_validator(mode="after")
    def _check(self) -> DynamicsConfig:
        if self.elites > self.members:
            raise ValueError(f"elites ({self.elites}) cannot exceed members ({self.members})")
        return self


class SACConfig(_Strict):
    hidden: Hidden = (256, 256)
    actor_lr: LearningRate = 3e-4
    critic_lr: LearningRate = 3e-4
    alpha_lr: LearningRate = 3e-4
    gamma: float = Field(0.99, gt=0, lt=1)
    tau: float = Field(5e-3, gt=0, le=1)
    batch_size: BatchSize = 256
    real_ratio: float = Field(0.05, ge=0, le=1)
    target_entropy: Annotated[float, Field(ge=-1_000, le=1_000)] | Literal["data"] | None = Field(
        None, description="the entropy the temperature holds the policy at; default -|A|. 'data': the lower of -|A| "
                          "and the data's behaviour entropy, estimated before training by a maximum-likelihood fit "
                          "(`behaviour_fit_steps`): a policy broader than the data samples actions the data does not "
                          "have, and the density ratio on the data is then small (bench/QUALITY.md E28); -|A| where "
                          "too few rows have every action inside the bounds (`bc.MIN_FIT_ROWS`), as in a bang-bang "
                          "policy's data")
    behaviour_fit_steps: int = Field(5_000, ge=1, le=100_000, description="steps of the fit that estimates the "
                                     "data's behaviour entropy, with target_entropy='data'")
    alpha_min: float | None = Field(
        None, gt=0, le=1, description="a floor under the temperature: the entropy term keeps at least this weight "
                                      "when the policy's entropy stays above the target, where the temperature "
                                      "would otherwise decay without end (to about 1e-8 on halfcheetah-medium-replay "
                                      "and hopper-medium-expert, bench/QUALITY.md E67, E68; one pilot run, E69); "
                                      "None is the paper's")
    bc_weight: Weight = Field(0.0, description="behaviour term of the actor loss, as TD3+BC: with w > 0 the "
                             "actor minimises (alpha logp - Q)/mean|Q| + w * the term `bc_action` picks, on a real "
                             "batch; 0 is plain SAC (the paper)")
    bc_action: Literal["mean", "sample", "likelihood"] = Field(
        "mean", description="what the behaviour term pulls to the data's action: the deterministic action tanh(mu(s)), "
                            "as TD3+BC; a reparameterised sample of the policy, which also narrows its spread (the "
                            "stochastic policy is what rollouts and DICE see); or the policy's whole density, by the "
                            "data action's negative log-likelihood per dimension, which spreads the policy over the "
                            "data's actions (bench/QUALITY.md E3, E23)")
    actor_lr_schedule: Literal["constant", "cosine"] = Field(
        "constant", description="cosine: the actor's learning rate falls from actor_lr to 0 along a half cosine over "
                                "the run, set per epoch, as OfflineRL-Kit's MOPO, MOBILE and COMBO; the last "
                                "evaluations then see a settled actor instead of one still swinging between epochs "
                                "(bench/QUALITY.md E25); constant is the paper's")
    critic_layer_norm: bool = Field(
        False, description="layer norm after each hidden layer of the critics: it bounds how far Q can extrapolate "
                           "beyond the values it was fitted on, the over-estimation that made hopper collapse "
                           "(bench/QUALITY.md E5); False is the paper's plain MLP")
    actor_average: float = Field(1.0, gt=0, le=1, description=(
        "Polyak weight of the newest actor iterate in the policy that is evaluated and exported: 1 is the latest "
        "iterate (the paper); below 1 the running mean of the iterates until it spans 1/actor_average updates, then "
        "their exponential average, as weight averaging steadies deep RL (Nikishin et al. 2018). The rollouts, DICE "
        "and the updates still use the latest iterate, so training is unchanged, and each of a training run's "
        "evaluations also records that iterate's score as live_* (bench/QUALITY.md E41)"))
    value_bound: bool = Field(
        False, description="clip the bootstrapped Q in the critics' target at the largest soft Q possible if no "
                           "step earns more than the data's largest reward, (r_max + gamma alpha |A| log 2) / "
                           "(1 - gamma): a Q above it is extrapolation feeding on itself (bench/QUALITY.md E30). A "
                           "model reward above r_max is the model's extrapolation, so on rollouts the clip is "
                           "pessimism, not a bound the model obeys. False is the paper's")


class RolloutConfig(_Strict):
    batch_size: int = Field(50_000, ge=1, le=1_000_000, description="start states per epoch")
    horizon: Horizon = 5
    retain_epochs: int = Field(5, ge=1, le=1_000)


class DiceConfig(_Strict):
    hidden: Hidden = (64, 64)
    lr: LearningRate = 1e-4
    lam: Weight = Field(0.1, description="normalisation constraint weight (lambda)")
    batch_size: BatchSize = 256
    pretrain_steps: Steps = 400
    steps_per_epoch: Steps = 400
    positive: bool = Field(False, description="tau = softplus(net), never negative; False is the paper's linear tau")
    discount: Annotated[float, Field(ge=0, lt=1)] | Literal["sac", "horizon"] = Field(
        "sac", description="the occupancy's discount: 'sac' uses SAC's gamma (the paper); 'horizon' uses (h-1)/(h+1), "
                           "whose mean step (h-1)/2 is that of the h-step model rollouts the penalty is applied to")
    average: float = Field(1.0, gt=0, le=1, description=(
        "Polyak weight of the newest iterate in the tau the penalty reads: 1 reads the latest iterate (the paper); "
        "below 1 an exponential average of the iterates, which sits at the saddle point while single iterates "
        "circle it (bench/QUALITY.md E10, E15). The average remembers about 1/average steps, so it also lags the "
        "policy by that much: keep 1/average near dice.steps_per_epoch"))


class PenaltyConfig(_Strict):
    eta: Weight = Field(1.0, description="DROP penalty coefficient")
    g: PenaltyFn = "log"
    clip: tuple[ClipBound, ClipBound] | None = (0.01, 10.0)
    bonus: bool = Field(True, description="let a ratio below 1 raise the reward, as the official code does")
    mopo_lambda: Weight = 1.0
    mopo_horizon: Horizon = 5

    @model_validator(mode="after")
    def _check(self) -> PenaltyConfig:
        if self.clip is not None and not 0 < self.clip[0] < self.clip[1]:
            raise ValueError(f"clip must satisfy 0 < low < high, got {self.clip}")
        return self


class TrainConfig(_Strict):
    algorithm: Algorithm = "drop"
    env: str = "hopper"
    env_version: EnvVersion | None = Field(None, description="the gymnasium env version evaluations run in; default: "
                                           "the version of the env id the dataset records (Minari's MuJoCo datasets "
                                           "record v5), else v4")
    task: str | None = Field(None, description="dataset kind, e.g. 'medium', selects the per-dataset settings "
                             "(build_config admits only TASKS; a stored config keeps what it was built with)")
    preset: Preset = "cpu"
    seed: int = Field(0, ge=0, lt=2**32)
    device: str = "cpu"
    threads: int | None = Field(None, ge=1, le=256)
    epochs: Epochs = 200
    steps_per_epoch: int = Field(1000, ge=1, le=1_000_000)
    eval_every: Epochs = 10
    eval_episodes: int = Field(10, ge=1, le=1_000)
    checkpoint_every: Epochs = 10
    keep_checkpoints: int = Field(2, ge=1, le=100)
    normalize_obs: bool = True
    log_every: int = Field(250, ge=1, le=1_000_000, description="SAC steps between metric reports")
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
    """The official per-dataset settings as nested overrides; `medium` stands in for no task."""
    key = f"{env}-{task}" if f"{env}-{task}" in _TABLE else f"{env}-medium"
    if key not in _TABLE:
        return {}
    h, eta, g, clip, lam, dice_lr, dice_steps, mopo_h, mopo_lam = _TABLE[key]
    return {
        "rollout": {"horizon": h},
        "penalty": {"eta": eta, "g": g, "clip": clip, "mopo_lambda": mopo_lam, "mopo_horizon": mopo_h},
        "dice": {"lam": lam, "lr": dice_lr, "steps_per_epoch": dice_steps, "pretrain_steps": dice_steps},
    }


# The cpu preset's behaviour-term weight per dataset kind (bench/QUALITY.md): a floor at the data's policy that leaves
# the model room to lift the policy above it. The term is the data actions' likelihood (E23): it keeps the stochastic
# policy, which the rollouts and DICE see, spread over the data's actions, so the ratio on the data stays normalised.
# Revision 4 weighted one competent policy's data (medium, medium-expert) at 0.4: at 0.1 alone the critics ran away on
# hopper-medium (E46: DROP 42.9 -> 15.8, MBPO 37.4 -> 2.8). With the value bound on (revision 5), 0.1 there gave DROP
# 51.1 +- 0.4 over two seeds against 39.5 (E47-E48) and walker2d-medium 42.7 against 34.9 (E51), neutral on
# halfcheetah-medium; MBPO at seed 0 swung down (21.5 against 36.0). On halfcheetah-medium-expert it gave DROP 45.5
# against 44.1 (E56). Each kind's weight is measured, and each came out 0.1 once the bound was on.
# The likelihood term cannot narrow the policy below the temperature's entropy target, so that target is the data's
# where the data is narrower than -|A| (E28).
CPU_BC_WEIGHT = {"random": 0.1, "medium": 0.1, "medium-replay": 0.1, "medium-expert": 0.1}


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
            "sac": {"bc_weight": CPU_BC_WEIGHT.get(task or "medium", CPU_BC_WEIGHT["medium"]),
                    "bc_action": "likelihood", "target_entropy": "data", "value_bound": True},
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
    """Turn {"dice.lr": 1e-3} into {"dice": {"lr": 1e-3}}; nested dicts merge in. A field given twice (`dice.lr` and
    `dice: {lr}`) is refused by name rather than one of them silently winning."""
    nested: dict = {}

    def put(path: tuple[str, ...], value: Any) -> None:
        node = nested
        for depth, part in enumerate(path[:-1], 1):
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{'.'.join(path[:depth])}: set as a value and as a group of fields in overrides")
        last = path[-1]
        if isinstance(value, Mapping):
            if not isinstance(node.setdefault(last, {}), dict):
                raise ConfigError(f"{'.'.join(path)}: set as a value and as a group of fields in overrides")
            for key, inner in value.items():
                put((*path, str(key)), inner)
        elif last in node:
            twice = "set as a value and as a group of fields" if isinstance(node[last], dict) else "given twice"
            raise ConfigError(f"{'.'.join(path)}: {twice} in overrides")
        else:
            node[last] = value

    for key, value in overrides.items():
        put(tuple(str(key).split(".")), value)
    return nested


def parse_override(text: str) -> tuple[str, Any]:
    """KEY=VALUE with VALUE parsed as JSON when it is JSON (numbers, lists, booleans, null), else kept as a string:
    the one reading of an override on every command line."""
    if "=" not in text:
        raise ConfigError(f"{text!r} is not KEY=VALUE")
    key, raw = text.split("=", 1)
    try:
        return key, json.loads(raw)
    except json.JSONDecodeError:
        return key, raw


def override_dict(pairs: Iterable[tuple[str, Any]]) -> dict[str, Any]:
    """KEY=VALUE pairs (`--set`) as one mapping; a key given twice is refused, not the last silently kept."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ConfigError(f"{key}: given twice in overrides")
        out[key] = value
    return out


def build_config(
    algorithm: str = "drop",
    *,
    env: str = "hopper",
    preset: str = "cpu",
    task: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    seed: int = 0,
    device: str = "cpu",
) -> TrainConfig:
    """Compose dataset settings, preset and overrides into one validated config."""
    if task is not None and task not in TASKS:  # a typo (medium_replay) would silently take medium's settings
        raise ConfigError(f"task: {task!r} is not one of {', '.join(TASKS)}; leave it out for medium's settings")
    base = {"algorithm": algorithm, "env": env, "preset": preset, "task": task, "seed": seed, "device": device}
    layers = [dataset_settings(env, task), preset_settings(preset, env, task), _nest(overrides or {})]
    merged: dict = base
    for layer in layers:
        merged = _merge(merged, layer)
    try:
        return TrainConfig.model_validate(merged)
    except ValidationError as exc:
        problems = "; ".join(f"{_field_path(err['loc']) or 'config'}: {err['msg']}" for err in exc.errors())
        raise ConfigError(problems) from None


def _field_path(loc: tuple[int | str, ...]) -> str:
    """The dotted field an error is about, e.g. `dice.discount` or `sac.hidden.0`: pydantic's loc also holds the tags
    of the union branches it tried (`dice.discount.float`), which name no field."""
    model: type[BaseModel] | None = TrainConfig
    parts = []
    for part in loc:
        if model is not None:
            parts.append(str(part))
            field = model.model_fields.get(str(part))
            annotation = field.annotation if field is not None else None
            model = annotation if isinstance(annotation, type) and issubclass(annotation, BaseModel) else None
        elif isinstance(part, int):
            parts.append(str(part))
    return ".".join(parts)
