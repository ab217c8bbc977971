"""Model rollouts with penalised rewards, on the training device, into a `ReplayBuffer`."""
from __future__ import annotations

import torch

from .config import PenaltyConfig
from .dice import GradientDice
from .dynamics import GaussianEnsemble
from .nn import RowsByMember, in_row_chunks
from .penalties import penalized_reward
from .replay_buffer import ReplayBuffer
from .sac import Actor
from .stopping import StopFlag, check, never
from .termination import TerminationFn


def sample_members(
    model: GaussianEnsemble, obs: torch.Tensor, act: torch.Tensor, all_members: bool, should_stop: StopFlag = never
) -> tuple[torch.Tensor, torch.Tensor, RowsByMember | None, torch.Tensor | None]:
    """One model step per sample from a uniformly drawn elite: (reward, next_obs, rows by elite, logvar).

    With `all_members` (MOPO, whose penalty needs every member's logvar) all members run on every row and logvar is
    (members, N, D); otherwise each row runs through its own elite only, and the grouping is returned so DICE's
    estimators can follow the same assignment."""
    n = obs.shape[0]
    pos = torch.randint(0, model.num_elites, (n,), device=obs.device)
    if all_members:
        mean, logvar = in_row_chunks(model, obs, act, out_dim=1, should_stop=should_stop)
        rows = torch.arange(n, device=obs.device)
        member = model.elites[pos]
        mu, lv, groups = mean[member, rows], logvar[member, rows], None
    else:
        groups = RowsByMember(pos, model.num_elites)
        mean, lv = in_row_chunks(lambda o, a: model(o, a, model.elites), groups.gather(obs), groups.gather(act),
                                 in_dim=1, out_dim=1, should_stop=should_stop)
        mu, lv, logvar = groups.scatter(mean), groups.scatter(lv), None
    sample = mu + torch.exp(0.5 * lv) * torch.randn_like(mu)
    return sample[:, 0], obs + sample[:, 1:], groups, logvar


@torch.no_grad()
def model_rollout(
    actor: Actor,
    model: GaussianEnsemble,
    dice: GradientDice | None,
    starts: torch.Tensor,
    horizon: int,
    algorithm: str,
    penalty: PenaltyConfig,
    termination: TerminationFn,
    buffer: ReplayBuffer,
    should_stop: StopFlag = never,
) -> dict[str, torch.Tensor]:
    """Roll the stochastic policy through the model for `horizon` steps; terminated samples stop.

    `should_stop` is asked before each step and row chunk and raises `Stopped`. The steps' transitions go into `buffer`
    only once all are made, step by step as they were made, so a stopped rollout leaves the buffer as it was."""
    obs = starts
    steps, pens, taus, rews, added = [], [], [], [], 0
    for _ in range(horizon):
        check(should_stop)
        act = in_row_chunks(actor.act, obs, should_stop=should_stop)
        rew, next_obs, groups, logvar = sample_members(model, obs, act, algorithm == "mopo", should_stop)
        tau = None
        if dice is not None:
            tau = groups.scatter(in_row_chunks(dice.tau, groups.gather(obs), groups.gather(act), in_dim=1, out_dim=1,
                                               should_stop=should_stop))
            taus.append(tau)
        rew_pen, pen = penalized_reward(algorithm, rew, penalty, tau, logvar)
        done = termination(obs, act, next_obs)
        steps.append((obs, act, rew_pen, next_obs, done.float()))
        pens.append(pen)
        rews.append(rew)
        added += len(obs)
        keep = ~done
        obs = next_obs[keep]
        if obs.shape[0] == 0:
            break
    for step in steps:
        buffer.add(*step)
    pen_all, rew_all = torch.cat(pens), torch.cat(rews)
    stats = {
        "rollout/penalty_mean": pen_all.mean(),
        "rollout/penalty_std": pen_all.std(),
        "rollout/penalty_max": pen_all.max(),
        "rollout/penalty_share": pen_all.abs().mean() / rew_all.abs().mean().clamp_min(1e-8),
        "rollout/reward_mean": rew_all.mean(),
        "rollout/length_mean": torch.tensor(added / len(starts), device=starts.device),
        "rollout/model_buffer_size": torch.tensor(float(len(buffer)), device=starts.device),
    }
    if taus:
        tau_all = torch.cat(taus)
        stats.update({"dice/tau_mean": tau_all.mean(), "dice/tau_min": tau_all.min(), "dice/tau_max": tau_all.max()})
    return stats
