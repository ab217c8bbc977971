"""Every random-number stream a run draws from, seeded from one number and saved whole in its checkpoints, so a
resumed run continues the same streams: Python's, numpy's (the run's own Generator) and torch's, CUDA's on a GPU."""
from __future__ import annotations

import random

import numpy as np
import torch


def seed_everything(seed: int) -> np.random.Generator:
    """Seed Python's and torch's global streams; returns the run's numpy Generator."""
    random.seed(seed)
    torch.manual_seed(seed)
    return np.random.default_rng(seed)


CPU = torch.device("cpu")


def rng_state(rng: np.random.Generator, device: torch.device = CPU) -> dict:
    state = {"torch": torch.get_rng_state(), "numpy": rng.bit_generator.state, "python": random.getstate()}
    if device.type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def load_rng_state(rng: np.random.Generator, state: dict, device: torch.device = CPU) -> None:
    torch.set_rng_state(state["torch"].cpu())  # a checkpoint loaded onto a GPU carries it there
    rng.bit_generator.state = state["numpy"]
    random.setstate(state["python"])
    if "cuda" in state and device.type == "cuda":
        torch.cuda.set_rng_state(state["cuda"].cpu(), device)
