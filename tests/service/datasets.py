"""Small dataset files to upload, made up in memory: D4RL arrays, a .npz and a Minari zip."""
from __future__ import annotations

import io
import json
import zipfile

import h5py
import numpy as np


def d4rl_arrays(n=50, obs=11, act=3) -> dict[str, np.ndarray]:
    """`n` hopper-shaped transitions in D4RL's keys, one episode ending in a timeout."""
    rng = np.random.default_rng(0)
    return {"observations": rng.normal(size=(n, obs)).astype(np.float32),
            "actions": rng.uniform(-1, 1, size=(n, act)).astype(np.float32),
            "rewards": rng.normal(size=n).astype(np.float32),
            "terminals": np.zeros(n, bool), "timeouts": np.eye(1, n, n - 1, dtype=bool)[0]}


def tiny_npz(seed: int) -> bytes:
    """A 40-transition hopper-shaped dataset, different for each seed."""
    rng, n = np.random.default_rng(seed), 40
    buf = io.BytesIO()
    np.savez(buf, observations=rng.normal(size=(n, 11)).astype(np.float32),
             actions=rng.uniform(-1, 1, size=(n, 3)).astype(np.float32),
             rewards=rng.normal(size=n).astype(np.float32), terminals=np.zeros(n, bool))
    return buf.getvalue()


def minari_zip(n_episodes=3, length=20) -> bytes:
    """A Minari dataset zip of hopper-shaped episodes: the first ends in a termination, the others in a truncation."""
    rng = np.random.default_rng(1)
    h5 = io.BytesIO()
    with h5py.File(h5, "w") as f:
        for i in range(n_episodes):
            ep = f.create_group(f"episode_{i}")
            ep["observations"] = rng.normal(size=(length + 1, 11)).astype(np.float32)
            ep["actions"] = rng.uniform(-1, 1, size=(length, 3)).astype(np.float32)
            ep["rewards"] = rng.normal(size=length)
            ep["terminations"] = np.eye(1, length, length - 1, dtype=bool)[0] if i == 0 else np.zeros(length, bool)
            ep["truncations"] = np.zeros(length, bool) if i == 0 else np.eye(1, length, length - 1, dtype=bool)[0]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("hopper-test-v0/data/main_data.hdf5", h5.getvalue())
        z.writestr("hopper-test-v0/data/metadata.json",
                   json.dumps({"dataset_id": "hopper-test-v0", "env_spec": json.dumps({"id": "Hopper-v5"})}))
    return buf.getvalue()
