"""Offline datasets: load any format `formats` reads, validate, describe, and hand tensors to the trainer.

Every problem with a file is one `DatasetError` whose message names the key and what is wrong with it, because the
service shows that message to the person who uploaded the file. `scan` checks a file a block of rows at a time for
that service, and reports what `describe(load_dataset(...))` would, without holding the dataset in memory.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Mapping

import numpy as np

from .atomic import atomic_path
from .data_rows import BLOCK_BYTES, DatasetLimits, Layout, Rows, Transitions, check_rows, layout, require_rows
from .envs import EnvVersion, envs_matching, get_env, gym_version
from .errors import DatasetError
from .formats import open_arrays


@dataclass
class Dataset(Transitions):
    attrs: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.observations)

    def take(self, rows: np.ndarray) -> Dataset:
        """The transitions at `rows` (indices or a mask), with this dataset's attrs: what the file says of where it
        came from (its env, its behaviour policy), not a description of the subset. No validation warnings: they were
        about the whole file."""
        return Dataset(**{name: array[rows] for name, array in self.arrays().items()}, attrs=dict(self.attrs))

    @property
    def obs_dim(self) -> int:
        return self.observations.shape[1]

    @property
    def act_dim(self) -> int:
        return self.actions.shape[1]

    @property
    def env_version(self) -> EnvVersion | None:
        """The version of the gymnasium id the file records, e.g. v5 for 'Hopper-v5'; None without one."""
        return gym_version(_recorded_env(self.attrs))

    @cached_property
    def content_hash(self) -> str:
        """sha256 of the arrays a trained model depends on (names, dtypes, shapes and bytes); computed once, as the
        arrays are not changed after loading."""
        digest = hashlib.sha256()
        for name in ("observations", "actions", "rewards", "next_observations", "terminals"):
            array = np.ascontiguousarray(getattr(self, name))
            digest.update(f"{name}:{array.dtype.str}:{array.shape};".encode())
            digest.update(memoryview(array).cast("B"))
        return digest.hexdigest()


@dataclass
class DatasetReport:
    transitions: int
    episodes: int
    obs_dim: int
    act_dim: int
    reward_min: float
    reward_max: float
    reward_mean: float
    terminals: int
    timeouts: int
    env: str | None
    env_candidates: list[str]
    warnings: list[str]

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class _Tally:
    """What a report says about rows, added up block by block."""

    transitions: int = 0
    reward_min: float = math.inf
    reward_max: float = -math.inf
    reward_sum: float = 0.0
    terminals: int = 0
    timeouts: int = 0
    ends: int = 0
    last_ends: bool = True  # the last row so far ends an episode
    max_abs_action: float = 0.0
    dropped: int = 0

    def add(self, rows: Transitions, dropped: int = 0) -> None:
        self.dropped += dropped
        if not len(rows.rewards):
            return
        ends = rows.terminals | rows.timeouts
        self.transitions += len(rows.rewards)
        self.reward_min = min(self.reward_min, float(rows.rewards.min()))
        self.reward_max = max(self.reward_max, float(rows.rewards.max()))
        self.reward_sum += float(rows.rewards.sum(dtype=np.float64))
        self.terminals += int(rows.terminals.sum())
        self.timeouts += int(rows.timeouts.sum())
        self.ends += int(ends.sum())
        self.last_ends = bool(ends[-1])
        self.max_abs_action = max(self.max_abs_action, float(np.abs(rows.actions).max(initial=0.0)))

    def warnings(self, lay: Layout) -> list[str]:
        notes = [] if lay.has_timeouts else ["timeouts: missing, assumed all false"]
        if not lay.has_next:
            notes.append(f"next_observations: missing, rebuilt from consecutive rows ({self.dropped} rows dropped)")
        if self.max_abs_action > 1.0 + 1e-6:
            notes.append(f"actions: values outside [-1, 1] (max |a| = {self.max_abs_action:.3g}); the policy is "
                         "tanh-bounded")
        return notes

    def report(self, obs_dim: int, act_dim: int, attrs: Mapping, warnings: list[str]) -> DatasetReport:
        env, candidates, note = _env(attrs, obs_dim, act_dim)
        return DatasetReport(
            transitions=self.transitions,
            episodes=self.ends + int(not self.last_ends),
            obs_dim=obs_dim,
            act_dim=act_dim,
            reward_min=self.reward_min,
            reward_max=self.reward_max,
            reward_mean=self.reward_sum / self.transitions,
            terminals=self.terminals,
            timeouts=self.timeouts,
            env=env,
            env_candidates=candidates,
            warnings=warnings + note,
        )


def _recorded_env(attrs: Mapping) -> str:
    """The env the file says it was recorded in ('' if none): D4RL-style files and Minari's converted ones name its
    gymnasium id in `env_name`."""
    return str(attrs.get("env_name") or attrs.get("env") or "")


def _env(attrs: Mapping, obs_dim: int, act_dim: int) -> tuple[str | None, list[str], list[str]]:
    """(the env the dataset matches, every env of its dims, a warning). The env the file records is believed only if
    its dims agree; otherwise a job would be refused for the recorded env, so the dims choose, as without a record."""
    candidates = envs_matching(obs_dim, act_dim)
    recorded = _recorded_env(attrs)
    try:
        spec = get_env(recorded) if recorded else None
    except KeyError:
        spec = None
    if spec is not None and (spec.obs_dim, spec.act_dim) == (obs_dim, act_dim):
        return spec.name, candidates, []
    env = candidates[0] if len(candidates) == 1 else None
    if spec is None:
        return env, candidates, []
    matched = f"matched by dims instead: {env}" if env else f"dims match: {', '.join(candidates) or 'no known env'}"
    return env, candidates, [
        f"env_name: the file says {recorded}, whose (obs, act) dims are ({spec.obs_dim}, {spec.act_dim}), but the data "
        f"has ({obs_dim}, {act_dim}); {matched}"]


def from_arrays(arrays: Mapping[str, Rows], attrs: dict | None = None, env: str | None = None) -> Dataset:
    """Validate arrays (all rows, as one block) and build a Dataset; `env` (if given) must match the dims."""
    lay = layout(arrays)
    block = check_rows(arrays, lay, 0, lay.shape.rows)
    require_rows(len(block.observations))
    if env is not None:
        spec = get_env(env)
        if (lay.shape.obs_dim, lay.shape.act_dim) != (spec.obs_dim, spec.act_dim):
            raise DatasetError(
                f"observations/actions: dims ({lay.shape.obs_dim}, {lay.shape.act_dim}) do not match {spec.name} "
                f"({spec.obs_dim}, {spec.act_dim})"
            )
    tally = _Tally()
    tally.add(block, block.dropped)
    return Dataset(**block.arrays(), attrs=dict(attrs or {}), warnings=tally.warnings(lay))


def load_dataset(path: str | Path, env: str | None = None) -> Dataset:
    """Load and validate a dataset: D4RL-layout HDF5, .npz, or a Minari dataset zipped as a directory."""
    with open_arrays(path) as (arrays, attrs):
        return from_arrays(arrays, attrs, env)


def scan(path: str | Path, limits: DatasetLimits = DatasetLimits(), block_bytes: int = BLOCK_BYTES) -> DatasetReport:
    """Validate a file and report on it as `describe(load_dataset(path))` would, holding one block of rows at a time;
    a file that declares more than `limits` is refused (DatasetTooLarge) before any row is read."""
    with open_arrays(path, limits) as (arrays, attrs):
        lay = layout(arrays, limits)
        row_bytes = sum(arrays[k].dtype.itemsize * math.prod(arrays[k].shape[1:]) for k in lay.keys)
        step = max(1, block_bytes // row_bytes)
        tally = _Tally()
        for start in range(0, lay.shape.rows, step):
            block = check_rows(arrays, lay, start, min(start + step, lay.shape.rows))
            tally.add(block, block.dropped)
    require_rows(tally.transitions)
    return tally.report(lay.shape.obs_dim, lay.shape.act_dim, attrs, tally.warnings(lay))


def describe(dataset: Dataset) -> DatasetReport:
    """The upload report of a dataset in memory: the reference that `scan`, which the service runs on uploads without
    loading them whole, must match."""
    tally = _Tally()
    tally.add(dataset)
    return tally.report(dataset.obs_dim, dataset.act_dim, dataset.attrs, list(dataset.warnings))


def save_hdf5(path: str | Path, arrays: dict[str, np.ndarray], attrs: dict | None = None,
              compress: bool = True) -> None:
    """Write D4RL layout (nested keys such as 'infos/qpos' become groups)."""
    import h5py

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as handle:
        for key, value in arrays.items():
            handle.create_dataset(key, data=value, compression="gzip" if compress else None)
        for key, value in (attrs or {}).items():
            handle.attrs[key] = value


@dataclass
class Normalizer:
    """Per-dimension mean/std; constant dimensions keep std 1 so they pass through unscaled."""

    mean: np.ndarray
    std: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray, eps: float = 1e-6) -> Normalizer:
        std = x.std(0)
        return cls(x.mean(0).astype(np.float32), np.where(std < eps, 1.0, std).astype(np.float32))

    @classmethod
    def identity(cls, dim: int) -> Normalizer:
        return cls(np.zeros(dim, np.float32), np.ones(dim, np.float32))


def split_sizes(n: int, ratio: float, cap: int) -> tuple[int, int]:
    """(train, holdout) sizes; holdout is min(ratio*n, cap) but leaves at least one training row."""
    holdout = min(int(math.floor(n * ratio)), cap, max(n - 1, 0))
    return n - holdout, holdout
