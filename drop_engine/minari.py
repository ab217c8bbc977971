"""Convert a Minari dataset (a zip of its directory) to the D4RL layout, a block of rows at a time.

What the episodes declare is checked against the caller's limits before any row is read, and rows are copied a block
at a time, so a conversion holds one block whatever the dataset's size: the service runs it on uploads in a child with
a memory limit. The env id in the dataset's metadata is kept as the `env_name` attribute, which names the env version.
"""
from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import h5py
import numpy as np

from .data_rows import BLOCK_BYTES, DatasetLimits, DataShape, read_rows
from .errors import DatasetError
from .safe_hdf5 import SafeHDF5
from .safe_zip import open_zip

EPISODE_KEYS = ("observations", "actions", "rewards", "terminations", "truncations")


def _env_id(zf: zipfile.ZipFile) -> str | None:
    """The env id recorded in the dataset's metadata.json, if any."""
    members = {Path(n).name: n for n in zf.namelist() if Path(n).parent.name == "data" or "/" not in n}
    if "metadata.json" not in members:
        return None
    try:
        meta = json.loads(zf.read(members["metadata.json"]))
        spec = meta.get("env_spec")
        spec = json.loads(spec) if isinstance(spec, str) else spec
        return (spec or {}).get("id")
    except (ValueError, AttributeError):
        return None


def _episodes(reader: SafeHDF5) -> list[tuple[str, dict[str, h5py.Dataset]]]:
    """Each episode's arrays, checked from their headers: present, safe, and of consistent lengths and dims."""
    names = sorted((k for k in reader.handle if k.startswith("episode_") and k[8:].isdigit()), key=lambda k: int(k[8:]))
    if not names:
        raise DatasetError("main_data.hdf5: no episode_N groups")
    episodes, dims = [], None
    for name in names:
        group = reader.handle[name]
        for key in EPISODE_KEYS:
            if key not in group or not isinstance(group[key], h5py.Dataset):
                raise DatasetError(f"{name}/{key}: missing or not an array (only Box observation spaces are supported)")
        arrays = {key: reader.array(f"{name}/{key}") for key in EPISODE_KEYS}
        obs, actions = arrays["observations"], arrays["actions"]
        if obs.ndim != 2 or actions.ndim != 2:
            raise DatasetError(f"{name}: observations and actions must be (N, dim) arrays")
        n = actions.shape[0]
        if obs.shape[0] != n + 1:
            raise DatasetError(f"{name}/observations: expected {n + 1} rows (actions + 1), found {obs.shape[0]}")
        for key in ("rewards", "terminations", "truncations"):
            if arrays[key].shape not in ((n,), (n, 1)):
                raise DatasetError(f"{name}/{key}: expected shape ({n},) like actions' rows, found {arrays[key].shape}")
        dims = dims or (obs.shape[1], actions.shape[1])
        if (obs.shape[1], actions.shape[1]) != dims:
            raise DatasetError(f"{name}: (obs, act) dims ({obs.shape[1]}, {actions.shape[1]}) differ from the first "
                               f"episode's {dims}")
        episodes.append((name, arrays))
    return episodes


class _Appender:
    """Columns of the D4RL layout, grown as blocks arrive."""

    def __init__(self, out: h5py.File, obs_dim: int, act_dim: int):
        widths = {"observations": (obs_dim,), "next_observations": (obs_dim,), "actions": (act_dim,), "rewards": (),
                  "terminals": (), "timeouts": ()}
        self.columns = {key: out.create_dataset(key, shape=(0, *w), maxshape=(None, *w), chunks=True,
                                                dtype=bool if key in ("terminals", "timeouts") else np.float32,
                                                compression="gzip")
                        for key, w in widths.items()}

    def append(self, **values: np.ndarray) -> None:
        for key, value in values.items():
            column = self.columns[key]
            start = column.shape[0]
            column.resize(start + len(value), axis=0)
            column[start:] = value


def _copy(name: str, arrays: dict[str, h5py.Dataset], out: _Appender) -> None:
    n = arrays["actions"].shape[0]
    row_bytes = sum(a.dtype.itemsize * (a.shape[1] if a.ndim == 2 else 1) for a in arrays.values())
    step = max(1, BLOCK_BYTES // row_bytes)
    for start in range(0, n, step):
        stop = min(start + step, n)
        rows = {key: read_rows(f"{name}/{key}", arrays[key], start, stop + (key == "observations"))
                for key in EPISODE_KEYS}
        terminals = rows["terminations"].reshape(-1).astype(bool)
        out.append(observations=rows["observations"][:-1], next_observations=rows["observations"][1:],
                   actions=rows["actions"], rewards=rows["rewards"].reshape(-1), terminals=terminals,
                   timeouts=rows["truncations"].reshape(-1).astype(bool) & ~terminals)


def convert(src: Path, dest: Path, limits: DatasetLimits) -> None:
    """Write the Minari zip `src` as a D4RL-layout HDF5 file at `dest` (terminations as terminals, truncations as
    timeouts, observations[:-1] and [1:] of each episode as observations and next observations)."""
    raw = dest.with_name("minari_main.hdf5")
    try:
        with open_zip(src, limits) as zf:
            main = next((n for n in zf.namelist() if n.endswith("main_data.hdf5")), None)
            if main is None:
                raise DatasetError("file: not a Minari dataset (no data/main_data.hdf5 in the zip)")
            # zipfile stops at the entry's declared size (and then fails its CRC), which `limits` has bounded.
            with zf.open(main) as fin, raw.open("wb") as fout:
                shutil.copyfileobj(fin, fout, 1 << 20)
            env_id = _env_id(zf)
        try:
            handle = h5py.File(raw, "r")
        except OSError as exc:
            raise DatasetError(f"main_data.hdf5: not a readable HDF5 file ({exc})") from None
        with handle, h5py.File(dest, "w") as out:
            episodes = _episodes(SafeHDF5(handle))
            obs_dim, act_dim = episodes[0][1]["observations"].shape[1], episodes[0][1]["actions"].shape[1]
            total = sum(arrays["actions"].shape[0] for _, arrays in episodes)
            where = f"main_data.hdf5 ({len(episodes)} episodes)"
            limits.check_rows(where, (total, obs_dim))
            limits.check_bytes(where, DataShape(total, obs_dim, act_dim))
            appender = _Appender(out, obs_dim, act_dim)
            for name, arrays in episodes:
                _copy(name, arrays, appender)
            if env_id:
                out.attrs["env_name"] = env_id
    finally:
        raw.unlink(missing_ok=True)
