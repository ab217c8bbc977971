"""Reward penalties, one per algorithm, so DROP, MOPO and MBPO share a single rollout loop."""
from __future__ import annotations

import math

import torch

from .config import PenaltyConfig


def ratio_penalty(tau: torch.Tensor, cfg: PenaltyConfig) -> torch.Tensor:
    """DROP's g(tau): large where the policy visits model states the data rarely covers (tau >> 1)."""
    if cfg.g == "log":
        low, high = cfg.clip if cfg.clip is not None else (1e-8, math.inf)
        g = torch.log(1e-8 + tau.clamp(low, high))
    elif cfg.g == "tanh":
        g = torch.tanh(tau - 1.0)
    else:  # tanh_shift
        g = torch.tanh(tau) - math.tanh(1.0)
    return g if cfg.bonus else g.clamp_min(0.0)


def uncertainty_penalty(logvar: torch.Tensor) -> torch.Tensor:
    """MOPO's u(s, a): the largest predicted std norm over all members, (N,) from logvar (B, N, D)."""
    return torch.exp(0.5 * logvar).norm(dim=-1).max(0).values


def penalized_reward(
    algorithm: str, reward: torch.Tensor, cfg: PenaltyConfig, tau: torch.Tensor | None, logvar: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(penalised reward, penalty) for one rollout step."""
    if algorithm == "drop":
        penalty = cfg.eta * ratio_penalty(tau, cfg)
    elif algorithm == "mopo":
        penalty = cfg.mopo_lambda * uncertainty_penalty(logvar)
    else:
        penalty = torch.zeros_like(reward)
    return reward - penalty, penalty
