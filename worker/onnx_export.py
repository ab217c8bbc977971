"""ONNX copy of the exported TorchScript policy (obs batch -> actions, dynamic batch), for runtimes without PyTorch."""
from __future__ import annotations

import warnings
from pathlib import Path


def export_onnx(torchscript_path: Path, obs_dim: int, out_path: Path) -> Path:
    import torch

    module = torch.jit.load(str(torchscript_path), map_location="cpu").eval()
    tmp = out_path.with_suffix(".onnx.tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript-based exporter is the one that takes a ScriptModule
        torch.onnx.export(module, (torch.zeros(1, obs_dim),), str(tmp), input_names=["obs"], output_names=["action"],
                          dynamic_axes={"obs": {0: "batch"}, "action": {0: "batch"}}, dynamo=False)
    tmp.replace(out_path)
    return out_path
