"""GradientDICE: per-member estimators of the density ratio tau_k(s, a) = rho(pi, model k) / rho(data).

All estimators are one batched module (member k = elite k). The saddle point min_tau max_{f, nu} J is approached
with simultaneous gradient steps on the same batch: one backward pass of J, then the f/nu gradients are negated so
their optimiser ascends while tau's descends. Such steps circle the saddle point rather than settle on it, so with
`average` below 1 the penalty reads an exponential (Polyak) average of tau's iterates, as SAC's target critics are.
"""
from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F
from torch import nn

from .config import DiceConfig
from .nn import EnsembleMLP, Standardize, adam, soft_update


class GradientDice(nn.Module):
    def __init__(self, members: int, obs_dim: int, act_dim: int, cfg: DiceConfig, gamma: float):
        super().__init__()
        self.members, self.gamma, self.lam, self.positive = members, gamma, cfg.lam, cfg.positive
        self.norm = Standardize(obs_dim)
        in_dim = obs_dim + act_dim
        self.tau_net = EnsembleMLP(members, in_dim, cfg.hidden, 1)
        self.f_net = EnsembleMLP(members, in_dim, cfg.hidden, 1)
        # Start at tau = 1, the ratio of identical distributions, so an estimator that has not trained yet
        # neither penalises nor rewards anything (softplus(log(e - 1)) = 1).
        nn.init.constant_(self.tau_net.out.bias, math.log(math.e - 1) if cfg.positive else 1.0)
        self.average = cfg.average
        self.tau_avg = copy.deepcopy(self.tau_net).requires_grad_(False) if cfg.average < 1 else None
        self.nu = nn.Parameter(torch.zeros(members, 1))
        self.tau_optim = adam(self.tau_net.parameters(), cfg.lr)
        self.f_optim = adam([*self.f_net.parameters(), self.nu], cfg.lr)

    def _input(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.norm(obs), act], -1)

    def _tau(self, x: torch.Tensor, net: nn.Module | None = None) -> torch.Tensor:
        # A ratio of densities is never negative; the paper's linear output can be, and a negative tau turns the log
        # penalty into its clip floor everywhere. softplus keeps the estimator in the ratio's range.
        raw = (self.tau_net if net is None else net)(x).squeeze(-1)
        return F.softplus(raw) if self.positive else raw

    def tau(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """The estimates the penalty reads (the averaged estimator's, if any), (members, N); inputs (N, d) shared or
        (members, N, d)."""
        return self._tau(self._input(obs, act), self.tau_avg)

    def objective(self, obs, act, next_obs, next_act, obs0, act0, not_done) -> tuple[torch.Tensor, torch.Tensor]:
        """J_k per member, (members,), and tau at the data's (s, a), (members, N).

        next_obs/next_act are per member: (members, N, d)."""
        x, x_next, x0 = self._input(obs, act), self._input(next_obs, next_act), self._input(obs0, act0)
        tau = self._tau(x)
        # f at all three inputs in one pass: three small batched matmuls per layer become one larger one.
        shared = (self.members, -1, -1)
        f_all = self.f_net(torch.cat([x.expand(shared), x_next, x0.expand(shared)], 1)).squeeze(-1)
        f, f_next, f0 = f_all.split([x.shape[-2], x_next.shape[-2], x0.shape[-2]], 1)
        nu = self.nu
        j = (
            (1 - self.gamma) * f0.mean(1)
            + self.gamma * (tau * f_next * not_done).mean(1)
            - (tau * f).mean(1)
            - 0.5 * f.pow(2).mean(1)
            + self.lam * ((nu * tau).mean(1) - nu.squeeze(1) - 0.5 * nu.squeeze(1).pow(2))
        )
        return j, tau

    def update(self, obs, act, next_obs, next_act, obs0, act0, not_done) -> dict[str, torch.Tensor]:
        """One simultaneous step of both players; also reports tau on the data, whose mean must stay near 1."""
        j, tau = self.objective(obs, act, next_obs, next_act, obs0, act0, not_done)
        self.tau_optim.zero_grad(set_to_none=True)
        self.f_optim.zero_grad(set_to_none=True)
        j.sum().backward()
        for group in self.f_optim.param_groups:
            for p in group["params"]:
                if p.grad is not None:
                    p.grad.neg_()
        self.tau_optim.step()
        self.f_optim.step()
        tau = tau.detach()
        metrics = {"dice/objective": j.detach().mean(), "dice/tau_data_mean": tau.mean(),
                   "dice/tau_data_std": tau.std(1).mean(), "dice/tau_data_negative": (tau < 0).float().mean()}
        if self.tau_avg is not None:
            soft_update(self.tau_avg, self.tau_net, self.average)
        return metrics

    def optim_state(self) -> dict:
        return {"tau_optim": self.tau_optim.state_dict(), "f_optim": self.f_optim.state_dict()}

    def load_optim_state(self, state: dict) -> None:
        self.tau_optim.load_state_dict(state["tau_optim"])
        self.f_optim.load_state_dict(state["f_optim"])
