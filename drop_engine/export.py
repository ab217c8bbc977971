"""Policy export: a TorchScript module that needs only torch to load, plus state_dict and metadata beside it."""
from __future__ import annotations

import copy
import json
import warnings
from pathlib import Path

import torch
from torch import nn

from .atomic import atomic_path, write_text
from .policy_files import FILE_NAMES
from .sac import Actor


class DeterministicPolicy(nn.Module):
    """Observation batch in, deterministic tanh actions out; the observation normaliser is inside."""

    def __init__(self, actor: Actor):
        super().__init__()
        self.norm = actor.norm
        self.net = actor.net

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        mu, _ = self.net(self.norm(obs.to(torch.float32))).chunk(2, -1)
        return torch.tanh(mu)


def export_policy(actor: Actor, out_dir: str | Path, metadata: dict) -> dict[str, Path]:
    """Write policy.pt (TorchScript), policy_state_dict.pt and metadata.json; returns their paths."""

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    policy = DeterministicPolicy(copy.deepcopy(actor).cpu()).eval().requires_grad_(False)
    paths = {fmt: out / FILE_NAMES[fmt] for fmt in ("torchscript", "state_dict", "metadata")}
    with warnings.catch_warnings():  # TorchScript is deprecated upstream but is still the one torch-only format
        warnings.simplefilter("ignore", DeprecationWarning)
        scripted = torch.jit.script(policy)
    with atomic_path(paths["torchscript"]) as tmp:
        scripted.save(str(tmp))
    with atomic_path(paths["state_dict"]) as tmp:
        torch.save(policy.state_dict(), tmp)
    write_text(paths["metadata"], json.dumps(metadata, indent=2, default=str))
    return paths


def load_policy(path: str | Path):
    """Load an exported TorchScript policy as a numpy -> numpy function."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        module = torch.jit.load(str(path), map_location="cpu").eval()

    def act(obs):
        with torch.no_grad():
            return module(torch.as_tensor(obs, dtype=torch.float32)).numpy()

    return act


def export_onnx(torchscript_path: str | Path, obs_dim: int, out_path: str | Path) -> Path:
    """An ONNX copy of an exported policy (input "obs", output "action", dynamic batch) for runtimes without torch."""
    module = torch.jit.load(str(torchscript_path), map_location="cpu").eval()
    out_path = Path(out_path)
    with atomic_path(out_path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript-based exporter is the one that takes a ScriptModule
        torch.onnx.export(module, (torch.zeros(1, obs_dim),), str(tmp), input_names=["obs"], output_names=["action"],
                          dynamic_axes={"obs": {0: "batch"}, "action": {0: "batch"}}, dynamo=False)
    return out_path
