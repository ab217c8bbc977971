"""What `drop collect` runs: the online SAC run behind the behaviour policies and the recording of their files.
Torch-free, so the CLI shows these defaults without importing the engine."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from .config import SACConfig
from .envs import DEFAULT_VERSION, EnvVersion, get_env

KINDS = ("random", "medium", "medium-replay", "expert", "medium-expert")
# Recording ~0.3 ms a transition on one core: 3 x 200k recorded rows take a few minutes after training.
DEFAULT_TRANSITIONS = 200_000


@dataclass
class OnlineConfig:
    env: str = "hopper"
    version: EnvVersion = DEFAULT_VERSION
    seed: int = 0
    # Default: the env's `collect_steps`. One SAC update (256-256, batch 256) costs ~12-20 ms on one core and an env
    # step ~0.1-0.3 ms, so 200k steps take 40-75 min.
    steps: int | None = None
    warmup: int = 5_000
    eval_every: int = 5_000
    eval_episodes: int = 10
    medium_return: float | None = None  # default: a third of the env's D4RL expert return
    sac: SACConfig = field(default_factory=SACConfig)

    def __post_init__(self) -> None:
        spec = get_env(self.env)  # fail early on an unknown env
        if self.steps is None:
            self.steps = spec.collect_steps
        if self.steps < 1 or self.eval_every < 1 or self.eval_episodes < 1 or self.warmup < 0:
            raise ValueError("steps, eval_every and eval_episodes must be positive and warmup non-negative")
        if self.sac.value_bound:
            raise ValueError("sac.value_bound reads an offline dataset's largest reward; online collection has none")

    @property
    def threshold(self) -> float:
        return self.medium_return if self.medium_return is not None else get_env(self.env).expert_score / 3.0

    def identity(self) -> dict:
        """The settings a resumed run must share with the checkpoint (steps may grow: training just continues), and
        the machine in use: another thread count or CPU kind sums in another order and makes other files (QUALITY.md
        E22, E62), so a checkpoint carried to another machine does not resume into files the table refuses."""
        import torch

        from .seeding import cpu_kind

        out = asdict(self)
        out.pop("steps")
        out["sac"] = self.sac.model_dump()
        out["threads"] = torch.get_num_threads()
        out["cpu"] = cpu_kind()
        return out


@dataclass
class CollectConfig:
    """What `drop collect` makes: an online SAC run (`online`) and `transitions` recorded rows per policy kind."""

    online: OnlineConfig
    transitions: int = DEFAULT_TRANSITIONS
    num_envs: int = 8

    def dataset_path(self, out: Path, kind: str) -> Path:
        return out / f"{self.online.env}-{kind}.hdf5"
