"""Soft actor-critic: tanh-Gaussian actor, twin critics as one two-member batched network, learned temperature."""
from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F
from torch import nn

from .config import SACConfig
from .nn import EnsembleMLP, IterateAverage, Standardize, adam, mlp, soft_update

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
ACTION_EDGE = 1 - 1e-6  # float32: atanh of it is 7.25, of 1 infinite


class Actor(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...]):
        super().__init__()
        self.norm = Standardize(obs_dim)
        self.net = mlp(obs_dim, hidden, 2 * act_dim)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, log_std = self.net(self.norm(obs)).chunk(2, -1)
        return mu, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised tanh-squashed action and its log-probability."""
        mu, log_std = self(obs)
        u = mu + log_std.exp() * torch.randn_like(mu)
        return torch.tanh(u), _squashed_log_prob(u, mu, log_std)

    def log_prob(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """The log-density of given actions, as behaviour cloning by maximum likelihood needs; an action on a tanh
        bound (a saturated sample) is read just inside it."""
        mu, log_std = self(obs)
        return _squashed_log_prob(torch.atanh(act.clamp(-ACTION_EDGE, ACTION_EDGE)), mu, log_std)

    def act(self, obs: torch.Tensor, deterministic: bool = False) -> torch.Tensor:
        if deterministic:
            return torch.tanh(self(obs)[0])
        return self.sample(obs)[0]


def _squashed_log_prob(u: torch.Tensor, mu: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log pi(tanh(u)) of the tanh-squashed diagonal Gaussian N(mu, exp(log_std)^2)."""
    log_prob = (-0.5 * ((u - mu) / log_std.exp()).pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
    # log|d tanh(u)/du| = 2 (log 2 - u - softplus(-2u)), the numerically stable form.
    return log_prob - (2 * (math.log(2) - u - F.softplus(-2 * u))).sum(-1)


class TwinCritic(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...], layer_norm: bool = False):
        super().__init__()
        self.norm = Standardize(obs_dim)
        self.net = EnsembleMLP(2, obs_dim + act_dim, hidden, 1, layer_norm=layer_norm)

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """Q-values of both critics, (2, N)."""
        return self.net(torch.cat([self.norm(obs), act], -1)).squeeze(-1)


class SAC(nn.Module):
    """Holds the networks, target critic, temperature and optimisers; `update` is one gradient step of all three."""

    def __init__(self, obs_dim: int, act_dim: int, cfg: SACConfig):
        super().__init__()
        self.cfg = cfg
        self.actor = Actor(obs_dim, act_dim, cfg.hidden)
        self.critic = TwinCritic(obs_dim, act_dim, cfg.hidden, cfg.critic_layer_norm)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.zeros(()))
        # 'data' starts at -|A| too; the trainer lowers it to the data's estimated entropy before the first update.
        self.target_entropy = float(-act_dim if cfg.target_entropy in (None, "data") else cfg.target_entropy)
        self.actor_optim = adam(self.actor.parameters(), cfg.actor_lr)
        self.critic_optim = adam(self.critic.parameters(), cfg.critic_lr)
        self.alpha_optim = adam([self.log_alpha], cfg.alpha_lr)
        self.max_reward = math.inf  # the data's largest reward (set_reward_bound), read with value_bound
        self.max_entropy = act_dim * math.log(2.0)  # of the uniform distribution on [-1, 1]^|A|
        self.actor_average = IterateAverage(self.actor, cfg.actor_average) if cfg.actor_average < 1 else None

    @property
    def policy(self) -> Actor:
        """The actor that is evaluated and exported: the average of the iterates with `actor_average` < 1."""
        return self.actor if self.actor_average is None else self.actor_average.module

    def anneal(self, progress: float) -> None:
        """Set the actor's learning rate for the point `progress` in [0, 1) of the run. It is a function of where the
        run is, not of an optimiser's step count, so a resumed run sets the same rate as one never stopped."""
        if self.cfg.actor_lr_schedule == "cosine":
            for group in self.actor_optim.param_groups:
                group["lr"] = self.cfg.actor_lr * 0.5 * (1 + math.cos(math.pi * progress))

    def set_obs_normalizer(self, mean, std) -> None:
        for module in (self.actor.norm, self.policy.norm, self.critic.norm, self.critic_target.norm):
            module.set(mean, std)

    def set_reward_bound(self, max_reward: float) -> None:
        self.max_reward = float(max_reward)

    def value_ceiling(self, alpha: torch.Tensor) -> torch.Tensor:
        """The largest soft Q any policy can have if no step earns more than `max_reward`. Each step adds at most
        that reward and, from the next step on, alpha times the largest entropy of a distribution on [-1, 1]^|A|:
        Q_max = r_max + gamma (Q_max + alpha H_max). A terminal step earns r_max alone, above Q_max when r_max is
        below -alpha H_max."""
        bootstrapped = (self.max_reward + self.cfg.gamma * alpha * self.max_entropy) / (1.0 - self.cfg.gamma)
        return torch.clamp_min(bootstrapped, self.max_reward)

    def update(self, obs, act, rew, next_obs, done, real: tuple[torch.Tensor, torch.Tensor] | None = None,
               n_real: int = 0) -> dict[str, torch.Tensor]:
        """One SAC step; returns detached scalars so callers decide when to synchronise.

        `real` is a batch of offline (s, a) for the behaviour term (used when `bc_weight` > 0); the first `n_real`
        rows of the batch are real transitions, so Q on data and on model rows can be reported apart."""
        cfg = self.cfg
        alpha = self.log_alpha.exp().detach()
        with torch.no_grad():
            next_act, next_logp = self.actor.sample(next_obs)
            q_next = self.critic_target(next_obs, next_act).min(0).values
            if cfg.value_bound:  # the bootstrapped value only: the entropy sample and the reward stay as drawn
                ceiling = self.value_ceiling(alpha)
                clipped = ((q_next > ceiling) & (done < 1)).float().mean()  # a terminal row bootstraps nothing
                q_next = q_next.clamp_max(ceiling)
            target = rew + cfg.gamma * (1.0 - done) * (q_next - alpha * next_logp)
        q = self.critic(obs, act)
        critic_loss = (q - target).pow(2).mean(1).sum()
        self.critic_optim.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_optim.step()

        new_act, logp = self.actor.sample(obs)
        self.critic.requires_grad_(False)
        q_new = self.critic(obs, new_act).min(0).values
        self.critic.requires_grad_(True)
        actor_loss, extra = self._actor_loss(alpha, logp, q_new, real)
        self.actor_optim.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_optim.step()
        if self.actor_average is not None:
            self.actor_average.update(self.actor)

        alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        self.alpha_optim.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_optim.step()
        if cfg.alpha_min is not None:  # projected: the step is taken, then log alpha is put back above the floor
            with torch.no_grad():
                self.log_alpha.clamp_(min=math.log(cfg.alpha_min))

        soft_update(self.critic_target, self.critic, cfg.tau)
        q = q.detach()
        metrics = {
            "sac/critic_loss": critic_loss.detach(),
            "sac/actor_loss": actor_loss.detach(),
            "sac/alpha_loss": alpha_loss.detach(),
            "sac/alpha": alpha,
            "sac/q_mean": q.mean(),
            "sac/entropy": -logp.detach().mean(),
            **extra,
        }
        if cfg.value_bound:
            metrics["sac/target_clipped"] = clipped
        if 0 < n_real < q.shape[1]:
            metrics["sac/q_data"] = q[:, :n_real].mean()
            metrics["sac/q_model"] = q[:, n_real:].mean()
        return metrics

    def _actor_loss(self, alpha, logp, q_new, real) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """SAC's actor loss, or with `bc_weight` > 0 TD3+BC's form: the Q term scaled by 1/mean|Q| so the behaviour
        term's weight means the same at any reward scale, plus the squared distance to the data's actions, or their
        negative log-likelihood under the policy."""
        loss = (alpha * logp - q_new).mean()
        if self.cfg.bc_weight == 0 or real is None:
            return loss, {}
        real_obs, real_act = real
        scaled = loss / q_new.detach().abs().mean().clamp_min(1e-6)
        if self.cfg.bc_action == "likelihood":
            # Per action dimension, so the weight does not grow with the action count (its value: QUALITY.md E23).
            bc, name = -self.actor.log_prob(real_obs, real_act).mean() / real_act.shape[-1], "sac/bc_nll"
        else:
            pulled = (self.actor.sample(real_obs)[0] if self.cfg.bc_action == "sample"
                      else self.actor.act(real_obs, True))
            bc, name = (pulled - real_act).pow(2).mean(), "sac/bc_mse"
        return scaled + self.cfg.bc_weight * bc, {name: bc.detach()}

    def optim_state(self) -> dict:
        return {name: getattr(self, name).state_dict() for name in ("actor_optim", "critic_optim", "alpha_optim")}

    def load_optim_state(self, state: dict) -> None:
        for name, value in state.items():
            getattr(self, name).load_state_dict(value)
