"""The transitions SAC samples from (the dataset's, the model rollouts', online SAC's), held on the training device."""
from __future__ import annotations

import torch

FIELDS = ("obs", "act", "rew", "next_obs", "done")


class ReplayBuffer:
    """Preallocated FIFO ring of transitions, sampled by index tensors."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, device: torch.device | str = "cpu"):
        self.capacity, self.ptr, self.size = capacity, 0, 0
        dims = {"obs": (obs_dim,), "act": (act_dim,), "rew": (), "next_obs": (obs_dim,), "done": ()}
        self.data = {k: torch.zeros((capacity, *dims[k]), device=device) for k in FIELDS}

    @classmethod
    def from_tensors(cls, **fields: torch.Tensor) -> ReplayBuffer:
        obs = fields["obs"]
        buf = cls(len(obs), obs.shape[1], fields["act"].shape[1], obs.device)
        buf.add(**fields)
        return buf

    def add(self, obs, act, rew, next_obs, done) -> None:
        values = {"obs": obs, "act": act, "rew": rew, "next_obs": next_obs, "done": done}
        n = len(obs)
        if n > self.capacity:  # only the newest rows fit
            values = {k: v[-self.capacity :] for k, v in values.items()}
            n = self.capacity
        idx = (self.ptr + torch.arange(n, device=obs.device)) % self.capacity
        for k in FIELDS:
            self.data[k].index_copy_(0, idx, values[k].to(self.data[k].dtype))
        self.ptr = (self.ptr + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample_indices(self, n: int) -> torch.Tensor:
        return torch.randint(0, self.size, (n,), device=self.data["obs"].device)

    def take(self, idx: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(self.data[k][idx] for k in FIELDS)

    def sample(self, n: int) -> tuple[torch.Tensor, ...]:
        return self.take(self.sample_indices(n))

    def __len__(self) -> int:
        return self.size

    def state_dict(self) -> dict:
        return {"ptr": self.ptr, "size": self.size, "data": {k: v[: self.size].clone() for k, v in self.data.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.ptr, self.size = state["ptr"], state["size"]
        for k in FIELDS:
            self.data[k][: self.size] = state["data"][k].to(self.data[k].device)
