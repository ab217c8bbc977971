"""The real simulator as a function of (s, a): set MuJoCo's state from an observation and step it.

Used to measure a learned model's true error (the paper's Fig. 2). The observation omits the x position, which does
not change the dynamics; where the data carries `infos/qpos` and `infos/qvel` those are used instead, since the
observation clips velocities."""
from __future__ import annotations

import numpy as np

from .envs import DEFAULT_VERSION, EnvVersion, make_env


def true_step(
    env: str, obs: np.ndarray, act: np.ndarray, qpos: np.ndarray | None = None, qvel: np.ndarray | None = None,
    version: EnvVersion = DEFAULT_VERSION,
) -> tuple[np.ndarray, np.ndarray]:
    """(rewards (N,), next observations (N, obs_dim)) of the real env for each row."""
    e = make_env(env, version)
    e.reset(seed=0)
    sim = e.unwrapped
    nq = sim.model.nq
    rewards = np.empty(len(obs))
    next_obs = np.empty_like(obs, dtype=np.float64)
    for i in range(len(obs)):
        if qpos is not None and qvel is not None:
            pos, vel = qpos[i], qvel[i]
        else:
            pos, vel = np.concatenate([[0.0], obs[i, : nq - 1]]), obs[i, nq - 1 :]
        sim.set_state(np.asarray(pos, np.float64), np.asarray(vel, np.float64))
        next_obs[i], rewards[i], *_ = e.step(np.asarray(act[i], np.float64))
    e.close()
    return rewards, next_obs.astype(np.float32)
