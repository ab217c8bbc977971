"""Offline datasets: load D4RL-layout HDF5 or .npz, validate, describe, and hand tensors to the trainer.

Every problem with a file is one `DatasetError` whose message names the key and what is wrong with it, because the
service shows that message to the person who uploaded the file.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .envs import envs_matching, get_env

REQUIRED = ("observations", "actions", "rewards", "terminals")
OPTIONAL = ("next_observations", "timeouts")
INFO_KEYS = ("infos/qpos", "infos/qvel")


class DatasetError(ValueError):
    """A dataset that cannot be used; the message says which key and why."""


@dataclass
class Dataset:
    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_observations: np.ndarray
    terminals: np.ndarray
    timeouts: np.ndarray
    attrs: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.observations)

    @property
    def obs_dim(self) -> int:
        return self.observations.shape[1]

    @property
    def act_dim(self) -> int:
        return self.actions.shape[1]

    @property
    def episodes(self) -> int:
        ends = np.logical_or(self.terminals, self.timeouts)
        return int(ends.sum()) + int(len(self) > 0 and not ends[-1])

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

    def episode_returns(self) -> np.ndarray:
        ends = np.flatnonzero(np.logical_or(self.terminals, self.timeouts))
        bounds = np.concatenate([[0], ends + 1])
        if bounds[-1] < len(self):
            bounds = np.append(bounds, len(self))
        return np.add.reduceat(self.rewards, bounds[:-1]) if len(bounds) > 1 else np.zeros(0)


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


def _read_hdf5(path: Path, max_bytes: int | None) -> tuple[dict[str, np.ndarray], dict]:
    import h5py

    from .safe_hdf5 import SafeHDF5

    try:
        handle = h5py.File(path, "r")
    except OSError as exc:
        raise DatasetError(f"file: not a readable HDF5 file ({exc})") from None
    with handle:
        reader = SafeHDF5(handle, max_bytes)
        arrays = {key: reader.read(key) for key in REQUIRED + OPTIONAL + INFO_KEYS if key in handle}
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in handle.attrs.items()}
    return arrays, attrs


def _read_npz(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files if k in REQUIRED + OPTIONAL + INFO_KEYS}
    except (OSError, ValueError) as exc:
        raise DatasetError(f"file: not a readable .npz file ({exc})") from None
    return arrays, {}


def _as_float(key: str, value: np.ndarray, ndim: int) -> np.ndarray:
    if not np.issubdtype(value.dtype, np.number) and value.dtype != np.bool_:
        raise DatasetError(f"{key}: must be numeric, found dtype {value.dtype}")
    if value.ndim != ndim:
        shape = "(N, dim)" if ndim == 2 else "(N,)"
        raise DatasetError(f"{key}: expected shape {shape}, found {value.shape}")
    value = value.astype(np.float32, copy=False)
    if not np.isfinite(value).all():
        bad = int((~np.isfinite(value)).any(axis=tuple(range(1, value.ndim))).sum())
        raise DatasetError(f"{key}: {bad} rows contain NaN or inf")
    return value


def _as_flags(key: str, value: np.ndarray) -> np.ndarray:
    value = value.reshape(-1) if value.ndim == 2 and value.shape[1] == 1 else value
    if value.ndim != 1:
        raise DatasetError(f"{key}: expected shape (N,), found {value.shape}")
    if not (np.issubdtype(value.dtype, np.number) or value.dtype == np.bool_):
        raise DatasetError(f"{key}: must be boolean or 0/1, found dtype {value.dtype}")
    if not np.isin(value, (0, 1)).all():
        raise DatasetError(f"{key}: must hold only 0/1 or booleans")
    return value.astype(bool)


def from_arrays(arrays: dict[str, np.ndarray], attrs: dict | None = None, env: str | None = None) -> Dataset:
    """Validate raw arrays and build a Dataset; `env` (if given) must match the dims."""
    for key in REQUIRED:
        if key not in arrays:
            raise DatasetError(f"{key}: missing (a D4RL dataset needs {', '.join(REQUIRED)})")
    obs = _as_float("observations", np.asarray(arrays["observations"]), 2)
    n = len(obs)
    if n == 0:
        raise DatasetError("observations: dataset is empty")
    act = _as_float("actions", np.asarray(arrays["actions"]), 2)
    rewards = np.asarray(arrays["rewards"])
    rewards = _as_float("rewards", rewards.reshape(-1) if rewards.ndim == 2 and rewards.shape[1] == 1 else rewards, 1)
    terminals = _as_flags("terminals", np.asarray(arrays["terminals"]))
    notes: list[str] = []
    if "timeouts" in arrays:
        timeouts = _as_flags("timeouts", np.asarray(arrays["timeouts"]))
    else:
        timeouts = np.zeros(n, dtype=bool)
        notes.append("timeouts: missing, assumed all false")
    for key, value in (("actions", act), ("rewards", rewards), ("terminals", terminals), ("timeouts", timeouts)):
        if len(value) != n:
            raise DatasetError(f"{key}: has {len(value)} rows but observations has {n}")
    if "next_observations" in arrays:
        next_obs = _as_float("next_observations", np.asarray(arrays["next_observations"]), 2)
        if next_obs.shape != obs.shape:
            raise DatasetError(f"next_observations: shape {next_obs.shape} differs from observations {obs.shape}")
    else:
        # Rebuild from consecutive rows; rows that end an episode have no successor in the file and are dropped,
        # and the row before each dropped one now ends its (truncated) episode.
        ends = terminals | timeouts
        ends[-1] = True
        keep = ~ends
        next_obs = np.empty_like(obs)
        next_obs[:-1] = obs[1:]
        obs, act, rewards, next_obs = obs[keep], act[keep], rewards[keep], next_obs[keep]
        terminals, timeouts = terminals[keep], np.append(ends[1:], True)[keep]
        notes.append(f"next_observations: missing, rebuilt from consecutive rows ({int((~keep).sum())} rows dropped)")
        if len(obs) == 0:
            raise DatasetError("next_observations: missing, and no rows are left after rebuilding them")
    if env is not None:
        spec = get_env(env)
        if (obs.shape[1], act.shape[1]) != (spec.obs_dim, spec.act_dim):
            raise DatasetError(
                f"observations/actions: dims ({obs.shape[1]}, {act.shape[1]}) do not match {spec.name} "
                f"({spec.obs_dim}, {spec.act_dim})"
            )
    if np.abs(act).max() > 1.0 + 1e-6:
        notes.append(f"actions: values outside [-1, 1] (max |a| = {np.abs(act).max():.3g}); the policy is tanh-bounded")
    return Dataset(obs, act, rewards, next_obs, terminals, timeouts, dict(attrs or {}), notes)


def load_dataset(path: str | Path, env: str | None = None, max_bytes: int | None = None) -> Dataset:
    """Load and validate an HDF5 (.hdf5/.h5) or .npz dataset; `max_bytes` caps what an HDF5 file may declare."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"file: {path} does not exist")
    if path.suffix == ".npz":
        arrays, attrs = _read_npz(path)
    else:
        arrays, attrs = _read_hdf5(path, max_bytes)
    return from_arrays(arrays, attrs, env)


def describe(dataset: Dataset) -> DatasetReport:
    """The report the service returns for an upload."""
    candidates = envs_matching(dataset.obs_dim, dataset.act_dim)
    recorded = str(dataset.attrs.get("env_name") or dataset.attrs.get("env") or "")
    env = None
    if recorded:
        try:
            env = get_env(recorded).name
        except KeyError:
            env = None
    if env is None and len(candidates) == 1:
        env = candidates[0]
    return DatasetReport(
        transitions=len(dataset),
        episodes=dataset.episodes,
        obs_dim=dataset.obs_dim,
        act_dim=dataset.act_dim,
        reward_min=float(dataset.rewards.min()),
        reward_max=float(dataset.rewards.max()),
        reward_mean=float(dataset.rewards.mean()),
        terminals=int(dataset.terminals.sum()),
        timeouts=int(dataset.timeouts.sum()),
        env=env,
        env_candidates=candidates,
        warnings=list(dataset.warnings),
    )


def save_hdf5(path: str | Path, arrays: dict[str, np.ndarray], attrs: dict | None = None, compress: bool = True) -> None:
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
    def fit(cls, x: np.ndarray, eps: float = 1e-6) -> "Normalizer":
        std = x.std(0)
        return cls(x.mean(0).astype(np.float32), np.where(std < eps, 1.0, std).astype(np.float32))

    @classmethod
    def identity(cls, dim: int) -> "Normalizer":
        return cls(np.zeros(dim, np.float32), np.ones(dim, np.float32))


def split_sizes(n: int, ratio: float, cap: int) -> tuple[int, int]:
    """(train, holdout) sizes; holdout is min(ratio*n, cap) but leaves at least one training row."""
    holdout = min(int(math.floor(n * ratio)), cap, max(n - 1, 0))
    return n - holdout, holdout
