"""A dataset's layout read from its arrays' headers, and its rows checked a block at a time.

The layout (keys, shapes, dtypes, row counts) is known before any row is read, so a file that declares more than a
service accepts is refused for what it declares, whatever it takes on disk. The rows are then checked and converted
a block at a time: checking an upload holds one block, not the dataset, and loading checks all rows as one block.
Arrays are anything with `shape`, `dtype` and row slicing: numpy arrays, h5py datasets, .npy members of a zip.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Mapping, Protocol

import numpy as np

from .errors import DatasetError, DatasetTooLarge

REQUIRED = ("observations", "actions", "rewards", "terminals")
OPTIONAL = ("next_observations", "timeouts")
FLAGS = ("terminals", "timeouts")
FLOAT = 4  # bytes of a float32
BLOCK_BYTES = 16 << 20  # file bytes read at once


class Rows(Protocol):
    shape: tuple[int, ...]
    dtype: np.dtype

    def __getitem__(self, rows: slice) -> np.ndarray: ...


@dataclass(frozen=True)
class DataShape:
    rows: int
    obs_dim: int
    act_dim: int

    @property
    def row_floats(self) -> int:
        """Floats of one transition: observation, action, reward, next observation, done."""
        return 2 * self.obs_dim + self.act_dim + 2

    @property
    def decoded_bytes(self) -> int:
        """The dataset as the trainer holds it (float32), whatever its file takes on disk."""
        return self.rows * self.row_floats * FLOAT


@dataclass(frozen=True)
class DatasetLimits:
    """What a caller accepts (None: no bound); checked against the declared layout before any row is read."""

    rows: int | None = None
    decoded_bytes: int | None = None
    zip_bytes: int | None = None  # a zip's entries (an .npz, a Minari dataset), expanded

    def check_rows(self, where: str, shape: tuple[int, ...]) -> None:
        if self.rows is not None and shape[0] > self.rows:
            raise DatasetTooLarge(f"{where}: declares {shape[0]} rows (shape {tuple(shape)}), over the limit of "
                                  f"{self.rows} rows per dataset", "rows")

    def check_bytes(self, where: str, shape: DataShape) -> None:
        if self.decoded_bytes is not None and shape.decoded_bytes > self.decoded_bytes:
            raise DatasetTooLarge(f"{where}: {shape.rows} rows of {shape.row_floats * FLOAT} bytes decode to "
                                  f"{shape.decoded_bytes} bytes, over the limit of {self.decoded_bytes} bytes per "
                                  "dataset", "decoded_bytes")

    def check_zip(self, total: int) -> None:
        if self.zip_bytes is not None and total > self.zip_bytes:
            raise DatasetTooLarge(f"zip: its entries expand to {total} bytes, over the limit of {self.zip_bytes}",
                                  "zip_bytes")


@dataclass(frozen=True)
class Layout:
    shape: DataShape  # rows as in the file, before rows without a successor are dropped
    has_next: bool  # next_observations present; else each row's successor is the next row
    has_timeouts: bool

    @property
    def keys(self) -> tuple[str, ...]:
        return REQUIRED + tuple(k for k, present in zip(OPTIONAL, (self.has_next, self.has_timeouts)) if present)


@dataclass
class Transitions:
    """Rows as the trainer uses them (float32 arrays, boolean flags), one per transition."""

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_observations: np.ndarray
    terminals: np.ndarray
    timeouts: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        """The six arrays by name; a subclass's own fields (attrs, dropped) are not rows, so they are left out."""
        return {f.name: getattr(self, f.name) for f in fields(Transitions)}


@dataclass
class Block(Transitions):
    """Rows checked and converted a block at a time."""

    dropped: int = 0  # rows without a successor in the file, dropped while rebuilding next observations


def _is_numeric(dtype: np.dtype) -> bool:
    return dtype == np.bool_ or np.issubdtype(dtype, np.number)


def _column_rows(key: str, array: Rows) -> int:
    """Rows of a per-transition value: shape (N,) or (N, 1)."""
    if len(array.shape) == 1 or (len(array.shape) == 2 and array.shape[1] == 1):
        return array.shape[0]
    raise DatasetError(f"{key}: expected shape (N,), found {tuple(array.shape)}")


def _matrix_rows(key: str, array: Rows) -> int:
    if len(array.shape) != 2:
        raise DatasetError(f"{key}: expected shape (N, dim), found {tuple(array.shape)}")
    return array.shape[0]


def layout(arrays: Mapping[str, Rows], limits: DatasetLimits = DatasetLimits()) -> Layout:
    """Check keys, dtypes and shapes from the headers alone, and the declared size against `limits`."""
    for key in REQUIRED:
        if key not in arrays:
            raise DatasetError(f"{key}: missing (a D4RL dataset needs {', '.join(REQUIRED)})")
    for key in REQUIRED + OPTIONAL:
        if key in arrays and not _is_numeric(arrays[key].dtype):
            kind = "boolean or 0/1" if key in FLAGS else "numeric"
            raise DatasetError(f"{key}: must be {kind}, found dtype {arrays[key].dtype}")
    obs = arrays["observations"]
    n = _matrix_rows("observations", obs)
    limits.check_rows("observations", obs.shape)
    if n == 0:
        raise DatasetError("observations: dataset is empty")
    counts = {"actions": _matrix_rows("actions", arrays["actions"])}
    for key in ("rewards", *FLAGS):
        if key in arrays:
            counts[key] = _column_rows(key, arrays[key])
    for key, count in counts.items():
        if count != n:
            raise DatasetError(f"{key}: has {count} rows but observations has {n}")
    if "next_observations" in arrays and tuple(arrays["next_observations"].shape) != tuple(obs.shape):
        raise DatasetError(f"next_observations: shape {tuple(arrays['next_observations'].shape)} differs from "
                           f"observations {tuple(obs.shape)}")
    shape = DataShape(n, obs.shape[1], arrays["actions"].shape[1])
    limits.check_bytes("file", shape)
    return Layout(shape, "next_observations" in arrays, "timeouts" in arrays)


def read_rows(key: str, array: Rows, start: int, stop: int) -> np.ndarray:
    """Rows [start, stop) of `array`; a damaged chunk or a failing filter is a DatasetError naming the key."""
    try:
        return np.asarray(array[start:stop])
    except (OSError, ValueError, TypeError) as exc:
        raise DatasetError(f"{key}: cannot be read ({exc})") from None


def _floats(key: str, array: Rows, start: int, stop: int) -> np.ndarray:
    value = read_rows(key, array, start, stop)
    value = value.reshape(-1) if value.ndim == 2 and key == "rewards" else value
    value = value.astype(np.float32, copy=False)
    finite = np.isfinite(value)
    if not finite.all():
        first = int(np.flatnonzero(~finite.reshape(len(value), -1).all(axis=1))[0])
        raise DatasetError(f"{key}: row {start + first} contains NaN or inf")
    return value


def _flags(key: str, array: Rows, start: int, stop: int) -> np.ndarray:
    value = read_rows(key, array, start, stop).reshape(-1)
    if not np.isin(value, (0, 1)).all():
        raise DatasetError(f"{key}: must hold only 0/1 or booleans")
    return value.astype(bool)


def check_rows(arrays: Mapping[str, Rows], lay: Layout, start: int, stop: int) -> Block:
    """Rows [start, stop), checked and converted. Without next_observations each row's successor is the next row, so
    the block reads one row past `stop`; a row that ends an episode or the file has no successor and is dropped, and
    the row before it now ends its (truncated) episode."""
    n = lay.shape.rows
    reach = stop if lay.has_next else min(stop + 1, n)
    obs = _floats("observations", arrays["observations"], start, reach)
    act = _floats("actions", arrays["actions"], start, stop)
    rewards = _floats("rewards", arrays["rewards"], start, stop)
    terminals = _flags("terminals", arrays["terminals"], start, reach)
    timeouts = (_flags("timeouts", arrays["timeouts"], start, reach) if lay.has_timeouts
                else np.zeros(reach - start, dtype=bool))
    if lay.has_next:
        return Block(obs, act, rewards, _floats("next_observations", arrays["next_observations"], start, stop),
                     terminals, timeouts)
    m = stop - start
    ends = terminals | timeouts
    if reach == n:
        ends[-1] = True  # the file's last row has no successor
    keep = ~ends[:m]
    successors = obs[1:] if reach > stop else np.concatenate([obs[1:], obs[-1:]])  # the file's last row is dropped
    return Block(obs[:m][keep], act[keep], rewards[keep], successors[keep], terminals[:m][keep],
                 np.append(ends[1:], True)[:m][keep], dropped=int((~keep).sum()))


def require_rows(transitions: int) -> None:
    if transitions == 0:
        raise DatasetError("next_observations: missing, and no rows are left after rebuilding them")
