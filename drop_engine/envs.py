"""Environments drop-rl knows: gymnasium ids, dims, D4RL reference scores and termination functions.

Termination functions work on torch tensors of any leading shape so model rollouts never leave the device.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable

import torch

TerminationFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def _hopper_done(obs: torch.Tensor, act: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    # gymnasium's healthy check; the official MOPO code misplaces a parenthesis here.
    height, angle = next_obs[..., 0], next_obs[..., 1]
    healthy = (
        torch.isfinite(next_obs).all(-1)
        & (next_obs[..., 1:].abs() < 100).all(-1)
        & (height > 0.7)
        & (angle.abs() < 0.2)
    )
    return ~healthy


def _walker2d_done(obs: torch.Tensor, act: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    height, angle = next_obs[..., 0], next_obs[..., 1]
    healthy = (height > 0.8) & (height < 2.0) & (angle > -1.0) & (angle < 1.0)
    return ~healthy


def _never_done(obs: torch.Tensor, act: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    return torch.zeros(next_obs.shape[:-1], dtype=torch.bool, device=next_obs.device)


@dataclass(frozen=True)
class EnvSpec:
    name: str
    gym_name: str
    obs_dim: int
    act_dim: int
    random_score: float
    expert_score: float
    termination: TerminationFn

    def gym_id(self, version: str = "v4") -> str:
        if version not in ("v4", "v5"):
            raise ValueError(f"unknown env version {version!r}; use 'v4' or 'v5'")
        return f"{self.gym_name}-{version}"

    def normalized_score(self, ret: float) -> float:
        """D4RL normalised score: 0 is a random policy, 100 an expert."""
        return 100.0 * (ret - self.random_score) / (self.expert_score - self.random_score)


ENVS: dict[str, EnvSpec] = {
    "hopper": EnvSpec("hopper", "Hopper", 11, 3, -20.272305, 3234.3, _hopper_done),
    "walker2d": EnvSpec("walker2d", "Walker2d", 17, 6, 1.629008, 4592.3, _walker2d_done),
    "halfcheetah": EnvSpec("halfcheetah", "HalfCheetah", 17, 6, -280.178953, 12135.0, _never_done),
}


def get_env(name: str) -> EnvSpec:
    """Look up by short name ('hopper') or gymnasium id ('Hopper-v4')."""
    key = name.lower().split("-")[0]
    if key not in ENVS:
        raise KeyError(f"unknown env {name!r}; known: {', '.join(sorted(ENVS))}")
    return ENVS[key]


def termination_fn(name: str) -> TerminationFn:
    """The env's termination function; unknown envs never terminate (with a warning)."""
    try:
        return get_env(name).termination
    except KeyError:
        warnings.warn(f"no termination function for {name!r}: model rollouts never terminate", stacklevel=2)
        return _never_done


def envs_matching(obs_dim: int, act_dim: int) -> list[str]:
    return [spec.name for spec in ENVS.values() if (spec.obs_dim, spec.act_dim) == (obs_dim, act_dim)]


def make_env(name: str, version: str = "v4"):
    """A real gymnasium MuJoCo env for `name`."""
    import gymnasium as gym

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return gym.make(get_env(name).gym_id(version))
