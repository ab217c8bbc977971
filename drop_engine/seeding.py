"""Every random-number stream a run draws from, seeded from one number and saved whole in its checkpoints, so a
resumed run continues the same streams: Python's, numpy's (the run's own Generator) and torch's, CUDA's on a GPU.
And what else a seed's numbers depend on: the machine that sums the floats."""
from __future__ import annotations

import platform
import random
from pathlib import Path

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


def cpu_kind() -> str:
    """The CPU a run's floats were summed on: the same file, seed and config give other numbers, and other times, on
    another kind of CPU (bench/QUALITY.md E9, E22), so a result names it beside its thread count."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        lines = []
    model = next((line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")), None)
    return f"{model or platform.processor() or platform.machine()} ({torch.backends.cpu.get_cpu_capability()})"


def machine() -> dict:
    """What, besides the seed and the config, made a run's numbers: the CPU kind, torch's thread count and version."""
    return {"cpu": cpu_kind(), "threads": torch.get_num_threads(), "torch": torch.__version__}
