"""Measurements that tell a learning policy from one exploiting its model, reported once per epoch.

Model exploitation shows as rollout rows that look unlike the data: the ensemble disagrees more there (MOPO's u), the
model's rewards run above the data's, and Q on model rows outgrows Q on real rows (reported by SAC itself)."""
from __future__ import annotations

import torch

from .dynamics import GaussianEnsemble
from .nn import in_row_chunks
from .penalties import uncertainty_penalty
from .replay_buffer import ReplayBuffer

SAMPLE = 2048


@torch.no_grad()
def exploitation_stats(model: GaussianEnsemble, real: ReplayBuffer, rollouts: ReplayBuffer) -> dict[str, torch.Tensor]:
    """Ensemble disagreement and reward on a sample of data rows against a sample of model-buffer rows."""
    out = {}
    for name, buffer in (("data", real), ("model", rollouts)):
        obs, act, rew = buffer.sample(SAMPLE)[:3]
        _, logvar = in_row_chunks(model, obs, act, out_dim=1)
        out[f"diag/uncertainty_{name}"] = uncertainty_penalty(logvar).mean()
        out[f"diag/reward_{name}"] = rew.mean()
    return out
