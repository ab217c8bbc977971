"""Probabilistic dynamics ensemble (MOPO/MBPO): B Gaussian networks over [r, s' - s], trained once on the data."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .config import DynamicsConfig
from .data import Dataset, Normalizer, split_sizes
from .nn import EnsembleLinear, adam
from .stopping import StopFlag, check, never


class GaussianEnsemble(nn.Module):
    """Members share one batched module; log-variance is soft-bounded by learned limits."""

    def __init__(self, obs_dim: int, act_dim: int, cfg: DynamicsConfig):
        super().__init__()
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.members, self.num_elites = cfg.members, cfg.elites
        in_dim, out_dim = obs_dim + act_dim, obs_dim + 1
        sizes = [in_dim] + [cfg.hidden] * cfg.layers
        self.body = nn.ModuleList(EnsembleLinear(cfg.members, a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        self.mean_head = EnsembleLinear(cfg.members, cfg.hidden, out_dim)
        self.logvar_head = EnsembleLinear(cfg.members, cfg.hidden, out_dim)
        self.max_logvar = nn.Parameter(torch.full((1, 1, out_dim), 0.5))
        self.min_logvar = nn.Parameter(torch.full((1, 1, out_dim), -10.0))
        self.register_buffer("in_mean", torch.zeros(in_dim))
        self.register_buffer("in_std", torch.ones(in_dim))
        self.register_buffer("elites", torch.arange(cfg.elites))
        decays = list(cfg.weight_decay)
        # One decay per hidden layer (the second-to-last value repeats if there are more layers), then the last value
        # for both heads (1e-4 by default, as the official code).
        self.decays = [decays[min(i, len(decays) - 2)] for i in range(cfg.layers)] + [decays[-1], decays[-1]]

    def set_normalizer(self, norm: Normalizer) -> None:
        self.in_mean.copy_(torch.as_tensor(norm.mean))
        self.in_std.copy_(torch.as_tensor(norm.std))

    def forward(
        self, obs: torch.Tensor, act: torch.Tensor, members: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-variance, (B, N, 1 + obs_dim); inputs (N, d) shared or (B, N, d) per member.

        With `members` only those members run, and the leading dimension is len(members)."""
        x = (torch.cat([obs, act], -1) - self.in_mean) / self.in_std
        for layer in self.body:
            x = F.silu(layer(x, members))
        mean = self.mean_head(x, members)
        logvar = self.logvar_head(x, members)
        logvar = self.max_logvar - F.softplus(self.max_logvar - logvar)
        logvar = self.min_logvar + F.softplus(logvar - self.min_logvar)
        return mean, logvar

    def member_state_keys(self) -> list[str]:
        """State-dict entries that hold one slice per member (snapshotted member by member)."""
        return [k for k in self.state_dict() if k.startswith(("body.", "mean_head.", "logvar_head."))]

    def decay_loss(self) -> torch.Tensor:
        layers = [*self.body, self.mean_head, self.logvar_head]
        return sum(d * 0.5 * layer.weight.pow(2).sum() for d, layer in zip(self.decays, layers))

    def loss(self, obs: torch.Tensor, act: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Gaussian NLL, mean over dims and batch, summed over members, plus the logvar bound and decay terms."""
        mean, logvar = self(obs, act)
        nll = ((mean - target).pow(2) * torch.exp(-logvar) + logvar).mean((1, 2)).sum()
        bounds = 0.01 * self.max_logvar.sum() - 0.01 * self.min_logvar.sum()
        return nll + bounds + self.decay_loss()

    @torch.no_grad()
    def mse(self, obs: torch.Tensor, act: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Per-member holdout MSE of the mean."""
        mean, _ = self(obs, act)
        return (mean - target).pow(2).mean((1, 2))


def build_ensemble(obs_dim: int, act_dim: int, cfg: DynamicsConfig, seed: int,
                   device: torch.device) -> GaussianEnsemble:
    """Initial weights from `seed` alone, drawn in a fork of the CPU generator: the run's torch stream is left where
    it was, so it is the same whether this ensemble is then trained or replaced by a cached one."""
    with torch.random.fork_rng(devices=[]):
        torch.default_generator.manual_seed(seed)
        return GaussianEnsemble(obs_dim, act_dim, cfg).to(device)


def dynamics_rng(seed: int) -> np.random.Generator:
    """The ensemble's own number stream (splits, bootstraps, shuffles), apart from the run's."""
    return np.random.default_rng([seed, 1])


@dataclass
class DynamicsReport:
    epochs: int
    holdout_mse: list[float]
    elites: list[int]
    seconds: float
    stopped_by: str  # "patience", "max_epochs" or "max_seconds"


def _targets(data: Dataset) -> np.ndarray:
    return np.concatenate([data.rewards[:, None], data.next_observations - data.observations], 1)


def train_dynamics(
    model: GaussianEnsemble,
    data: Dataset,
    cfg: DynamicsConfig,
    rng: np.random.Generator,
    device: torch.device,
    on_epoch: Callable[[int, float], None] | None = None,
    should_stop: StopFlag = never,
) -> DynamicsReport:
    """Fit the ensemble with holdout early stopping; `on_epoch(epoch, holdout)` hears of each epoch. `should_stop` is
    asked before every batch (an epoch over a large dataset takes minutes) and raises `Stopped`, leaving the model
    half-trained: the caller discards it."""
    start = time.perf_counter()
    n = len(data)
    perm = rng.permutation(n)
    n_train, n_hold = split_sizes(n, cfg.holdout_ratio, cfg.max_holdout)
    train_idx, hold_idx = perm[:n_train], perm[n_train:]
    inputs = np.concatenate([data.observations, data.actions], 1)
    model.set_normalizer(Normalizer.fit(inputs[train_idx]))
    t = lambda a: torch.as_tensor(a, device=device)  # noqa: E731
    obs, act, target = t(data.observations), t(data.actions), t(_targets(data))
    if n_hold == 0:  # tiny datasets: judge on the training rows
        hold_idx = train_idx
    h_obs, h_act, h_tgt = obs[hold_idx], act[hold_idx], target[hold_idx]
    optim = adam(model.parameters(), cfg.lr)
    B = model.members
    boot = torch.as_tensor(train_idx[rng.integers(0, n_train, size=(B, n_train))], device=device)

    best = model.mse(h_obs, h_act, h_tgt).cpu().numpy()
    member_keys = model.member_state_keys()
    snapshots = {k: v.detach().clone() for k, v in model.state_dict().items() if k in member_keys}
    epochs_since, epoch, stopped_by = 0, 0, "patience"
    while True:
        order = torch.as_tensor(np.argsort(rng.random((B, n_train)), axis=1), device=device)
        shuffled = torch.gather(boot, 1, order)
        for lo in range(0, n_train, cfg.batch_size):
            check(should_stop)
            idx = shuffled[:, lo : lo + cfg.batch_size]
            loss = model.loss(obs[idx], act[idx], target[idx])
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
        epoch += 1
        hold = model.mse(h_obs, h_act, h_tgt).cpu().numpy()
        improved = (best - hold) / np.maximum(np.abs(best), 1e-12) > 0.01
        if improved.any():
            state = model.state_dict()
            for k in np.flatnonzero(improved):
                best[k] = hold[k]
                for name in member_keys:
                    snapshots[name][k] = state[name][k]
            epochs_since = 0
        else:
            epochs_since += 1
        if on_epoch is not None:
            on_epoch(epoch, float(hold.mean()))
        if epochs_since >= cfg.patience:
            break
        if cfg.max_epochs is not None and epoch >= cfg.max_epochs:
            stopped_by = "max_epochs"
            break
        if cfg.max_seconds is not None and time.perf_counter() - start >= cfg.max_seconds:
            stopped_by = "max_seconds"
            break
    # Restore each member's best snapshot; shared parameters (logvar bounds, normaliser) keep their latest values.
    model.load_state_dict(snapshots, strict=False)
    hold = model.mse(h_obs, h_act, h_tgt).cpu().numpy()
    elites = np.argsort(hold, kind="stable")[: model.num_elites]
    model.elites.copy_(torch.as_tensor(np.sort(elites), device=device))
    return DynamicsReport(epoch, hold.tolist(), sorted(int(e) for e in elites), time.perf_counter() - start, stopped_by)
