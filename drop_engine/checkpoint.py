"""Checkpoint files: atomic writes, newest-first lookup, pruning. Files are ordered by the epoch and step their names
hold, read as numbers: zero-padding alone would put epoch 1,000,000 before epoch 999,999."""
from __future__ import annotations

import re
from pathlib import Path

import torch

from .atomic import save_durably

_NAME = re.compile(r"^ckpt-e(\d{6,})-s(\d{6,})\.pt$")


def checkpoint_name(epoch: int, step: int) -> str:
    return f"ckpt-e{epoch:06d}-s{step:06d}.pt"


def _position(path: Path) -> tuple[int, int] | None:
    """(epoch, step) of a checkpoint's name; None for any other file."""
    match = _NAME.match(path.name)
    return (int(match[1]), int(match[2])) if match else None


def list_checkpoints(directory: str | Path) -> list[Path]:
    """Oldest first."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    return sorted((p for p in directory.iterdir() if _position(p) is not None), key=_position)


def save_checkpoint(state: dict, directory: str | Path, epoch: int, step: int, keep: int) -> Path:
    """Write to a temporary name, fsync, rename: a crash never leaves a half-written checkpoint under a real name, and
    a failed write (a full disk) leaves no file at all."""
    directory = Path(directory)
    path = directory / checkpoint_name(epoch, step)
    save_durably(state, path)
    for old in list_checkpoints(directory)[:-keep]:
        old.unlink(missing_ok=True)
    return path


def load_latest(directory: str | Path, device: torch.device | str = "cpu") -> dict | None:
    found = list_checkpoints(directory)
    if not found:
        return None
    return torch.load(found[-1], map_location=device, weights_only=False)
