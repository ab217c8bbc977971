"""Run a behaviour policy in the real env and record D4RL-layout transitions (with MuJoCo qpos/qvel)."""
from __future__ import annotations

from typing import Callable

import numpy as np

from .envs import make_env

BehaviourPolicy = Callable[[np.ndarray], np.ndarray]


def random_policy(act_dim: int, seed: int) -> BehaviourPolicy:
    rng = np.random.default_rng(seed)
    return lambda obs: rng.uniform(-1.0, 1.0, size=(len(obs), act_dim)).astype(np.float32)


def collect_transitions(env: str, policy: BehaviourPolicy, transitions: int, seed: int = 0, version: str = "v4") -> dict[str, np.ndarray]:
    """Step one env for `transitions` steps; `policy` maps an observation batch to actions."""
    e = make_env(env, version)
    obs, _ = e.reset(seed=seed)
    cols: dict[str, list] = {k: [] for k in ("observations", "actions", "rewards", "next_observations", "terminals",
                                             "timeouts", "infos/qpos", "infos/qvel")}
    episode = 0
    for _ in range(transitions):
        data = e.unwrapped.data
        cols["infos/qpos"].append(data.qpos.copy())
        cols["infos/qvel"].append(data.qvel.copy())
        act = np.asarray(policy(obs[None].astype(np.float32))[0], dtype=np.float32)
        next_obs, rew, terminated, truncated, _ = e.step(act)
        for key, value in (("observations", obs), ("actions", act), ("rewards", rew), ("next_observations", next_obs),
                           ("terminals", terminated), ("timeouts", truncated and not terminated)):
            cols[key].append(value)
        obs = next_obs
        if terminated or truncated:
            episode += 1
            obs, _ = e.reset(seed=seed + episode)
    e.close()
    out = {k: np.asarray(v, dtype=np.float32) for k, v in cols.items() if k not in ("terminals", "timeouts")}
    out["timeouts"] = np.asarray(cols["timeouts"], dtype=bool)
    out["terminals"] = np.asarray(cols["terminals"], dtype=bool)
    out["timeouts"][-1] = not out["terminals"][-1]  # the file ends an episode
    return out
