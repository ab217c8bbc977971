"""Trained dynamics ensembles stored by what determines them, so runs on the same data share one training.

An ensemble depends only on the dataset's content, the dynamics config and the seed (see `build_ensemble` and
`dynamics_rng`), so those, hashed, are its key. One file per key, written through a temporary name and renamed in: a
crash never leaves part of a model under a real name. A per-key `flock` is held while looking up, training and writing,
so of several processes that need the same model one trains it and the others wait, then load it.
"""
from __future__ import annotations

import hashlib
import json
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import Callable

import torch

from .atomic import save_durably
from .config import DynamicsConfig
from .data import Dataset
from .dynamics import DynamicsReport, GaussianEnsemble
from .file_lock import exclusive
from .stopping import StopFlag

FORMAT = 1  # bump when the artifact or the way an ensemble is built or trained changes: old files become misses


def model_key(data: Dataset, cfg: DynamicsConfig, seed: int, device: str = "cpu") -> str:
    """sha256 over everything the trained ensemble depends on, as canonical JSON: the same seed trains other weights on
    another kind of device or another torch build, so those are part of it too."""
    fields = {"format": FORMAT, "dataset": data.content_hash, "dynamics": cfg.model_dump(mode="json"), "seed": seed,
              "obs_dim": data.obs_dim, "act_dim": data.act_dim, "device": torch.device(device).type,
              "torch": torch.__version__}
    return hashlib.sha256(json.dumps(fields, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


class ModelCache:
    def __init__(self, directory: str | Path):
        self.directory = Path(directory).expanduser()

    def path(self, key: str) -> Path:
        return self.directory / f"{key}.pt"

    def load(self, key: str, model: GaussianEnsemble) -> DynamicsReport | None:
        """The stored report, with `model` loaded; None (model untouched) if there is no usable file."""
        path = self.path(key)
        if not path.is_file():
            return None
        try:
            # weights_only: the directory may be shared, and a file in it must not be able to run code.
            stored = torch.load(path, map_location=next(model.parameters()).device, weights_only=True)
            state, expected = stored["state_dict"], model.state_dict()
            if stored["format"] != FORMAT or stored["key"] != key or state.keys() != expected.keys() or any(
                    state[k].shape != v.shape for k, v in expected.items()):
                raise ValueError("not a model for this key")
            report = DynamicsReport(**stored["report"])
        except Exception as exc:  # truncated, corrupt, or foreign: whatever it is, it is not this model
            warnings.warn(f"model cache: ignoring unusable {path} ({type(exc).__name__}: {exc}); training anew",
                          stacklevel=2)
            return None
        model.load_state_dict(state)  # checked above, so this cannot fail half-way and leave a mixed model
        return report

    def fetch_or_train(self, key: str, model: GaussianEnsemble, fit: Callable[[], DynamicsReport],
                       should_stop: StopFlag) -> tuple[DynamicsReport, bool]:
        """(report, from_cache): the stored model, or `fit()` trains `model` and it is stored. `Stopped`, from the
        wait for another process's lock or from `fit`, goes through and stores nothing."""
        with exclusive(self.directory / f"{key}.lock", should_stop):
            report = self.load(key, model)
            if report is not None:
                return report, True
            report = fit()
            self._store(key, model, report)
            return report, False

    def _store(self, key: str, model: GaussianEnsemble, report: DynamicsReport) -> None:
        """Best effort: a full or read-only cache costs later runs a training, never this run its result."""
        try:
            save_durably({"format": FORMAT, "key": key, "state_dict": model.state_dict(), "report": asdict(report)},
                         self.path(key))
        except OSError as exc:
            warnings.warn(f"model cache: could not store {self.path(key)}: {exc}", stacklevel=2)
