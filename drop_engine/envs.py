"""Environments drop-rl knows: gymnasium ids, dims, D4RL reference scores, and which termination function each uses.

No torch here: the API imports this to check job specs, and importing torch would cost it ~300 MB and seconds.
"""
from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, get_args

if TYPE_CHECKING:
    from .termination import TerminationFn

EnvName = Literal["hopper", "walker2d", "halfcheetah"]  # the short names; get_env also takes gymnasium ids
EnvVersion = Literal["v4", "v5"]
VERSIONS: tuple[EnvVersion, ...] = get_args(EnvVersion)
DEFAULT_VERSION: EnvVersion = "v4"  # D4RL's dynamics


@dataclass(frozen=True)
class EnvSpec:
    name: EnvName
    gym_name: str
    obs_dim: int
    act_dim: int
    random_score: float
    expert_score: float
    # Online SAC steps `drop collect` trains for by default: enough for a third of the expert return (the medium
    # bar). Hopper passed it near 65k steps on some machines and not by 120k on another (bench/QUALITY.md E31);
    # walker2d first passed it at 165k (ALGORITHM.md section 7).
    collect_steps: int = 200_000

    @property
    def termination(self) -> TerminationFn:
        from .termination import BY_ENV

        return BY_ENV[self.name]

    def gym_id(self, version: str = DEFAULT_VERSION) -> str:
        if version not in VERSIONS:
            raise ValueError(f"unknown env version {version!r}; use 'v4' or 'v5'")
        return f"{self.gym_name}-{version}"

    def normalized_score(self, ret: float) -> float:
        """D4RL normalised score: 0 is a random policy, 100 an expert."""
        return 100.0 * (ret - self.random_score) / (self.expert_score - self.random_score)


ENVS: dict[EnvName, EnvSpec] = {
    "hopper": EnvSpec("hopper", "Hopper", 11, 3, -20.272305, 3234.3),
    "walker2d": EnvSpec("walker2d", "Walker2d", 17, 6, 1.629008, 4592.3),
    "halfcheetah": EnvSpec("halfcheetah", "HalfCheetah", 17, 6, -280.178953, 12135.0),
}


def get_env(name: str) -> EnvSpec:
    """Look up by short name ('hopper') or gymnasium id ('Hopper-v4')."""
    key = name.lower().split("-")[0]
    if key not in ENVS:
        raise KeyError(f"unknown env {name!r}; known: {', '.join(sorted(ENVS))}")
    return ENVS[key]


def gym_version(gym_id: str) -> EnvVersion | None:
    """The version of a gymnasium id ('Hopper-v5' -> 'v5'), if it is one drop-rl makes; None for any other id."""
    name, _, version = gym_id.rpartition("-")
    return next((known for known in VERSIONS if name and known == version), None)


def envs_matching(obs_dim: int, act_dim: int) -> list[str]:
    return [spec.name for spec in ENVS.values() if (spec.obs_dim, spec.act_dim) == (obs_dim, act_dim)]


log = logging.getLogger("drop.mujoco")
_MAX_WARNINGS = 64  # distinct texts logged per process; MuJoCo's can carry a time, so the set must not grow forever
_warned: set[str] = set()


def _log_mujoco_warning(message: str) -> None:
    """MuJoCo's default handler prints each warning and appends it to MUJOCO_LOG.TXT in the working directory: with
    gymnasium's half_cheetah.xml (a deprecated `settotalmass` in MuJoCo 4) that is a line per env made, ten per
    evaluation, in a file no one rotates. Log each text once instead."""
    if message not in _warned and len(_warned) < _MAX_WARNINGS:
        _warned.add(message)
        log.warning("mujoco: %s", message)


def make_env(name: str, version: str = DEFAULT_VERSION):
    """A real gymnasium MuJoCo env for `name`."""
    import gymnasium as gym
    import mujoco

    mujoco.set_mju_user_warning(_log_mujoco_warning)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return gym.make(get_env(name).gym_id(version))
