"""drop_engine: DROP, MOPO and MBPO offline policy optimisation, with no web or database code.

The public surface: `build_config` composes a validated `TrainConfig`; `load_dataset` reads a D4RL-layout HDF5 file,
an .npz or a Minari zip; `train` runs a config on a dataset (resumable, reporting to a `Callback`); `load_policy` loads
an exported policy and `evaluate` runs it in the real env. Each is imported on first use, so that importing the
package, or a light module of it such as `envs` (as the API does), does not load torch.
"""
from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .callbacks import Callback
    from .config import TrainConfig, build_config
    from .data import load_dataset
    from .evaluation import evaluate
    from .export import load_policy
    from .trainer import train

__all__ = ["build_config", "TrainConfig", "train", "Callback", "load_dataset", "evaluate", "load_policy"]
_HOMES = {"build_config": "config", "TrainConfig": "config", "train": "trainer", "Callback": "callbacks",
          "load_dataset": "data", "evaluate": "evaluation", "load_policy": "export"}


def __getattr__(name: str):
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f".{_HOMES[name]}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
