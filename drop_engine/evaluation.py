"""Evaluation in the real MuJoCo env: episodes stepped side by side, the policy called once per step on a batch."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .envs import DEFAULT_VERSION, EnvVersion, get_env, make_env
from .stopping import StopFlag, check, never

PolicyFn = Callable[[np.ndarray], np.ndarray]


@dataclass
class Evaluation:
    mean_return: float
    std_return: float
    normalized_score: float
    returns: list[float]
    lengths: list[int]


def evaluate(policy: PolicyFn, env: str, episodes: int = 10, seed: int = 0, version: EnvVersion = DEFAULT_VERSION,
             should_stop: StopFlag = never) -> Evaluation:
    """Run `episodes` deterministic episodes; env i is reset with seed + i, so results are reproducible.

    `should_stop` is asked before each step of the episodes side by side and raises `Stopped`."""
    envs = [make_env(env, version) for _ in range(episodes)]
    try:
        obs = np.stack([e.reset(seed=seed + i)[0] for i, e in enumerate(envs)]).astype(np.float32)
        returns = np.zeros(episodes)
        lengths = np.zeros(episodes, dtype=int)
        active = np.ones(episodes, dtype=bool)
        while active.any():
            check(should_stop)
            idx = np.flatnonzero(active)
            actions = np.asarray(policy(obs[idx]), dtype=np.float64)
            for j, i in enumerate(idx):
                o, r, terminated, truncated, _ = envs[i].step(actions[j])
                obs[i] = o
                returns[i] += r
                lengths[i] += 1
                if terminated or truncated:
                    active[i] = False
    finally:
        for e in envs:
            e.close()
    mean = float(returns.mean())
    return Evaluation(mean, float(returns.std()), get_env(env).normalized_score(mean), returns.tolist(),
                      lengths.tolist())
