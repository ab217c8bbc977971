"""The file names of an exported policy, one directory per policy (`policy/last/`, `policy/best/`): one home for the
engine that writes them, the worker that adds the ONNX copy and the API that serves them. No torch here: the API
imports this."""
from __future__ import annotations

from typing import Literal

PolicyFormat = Literal["torchscript", "state_dict", "onnx", "metadata"]
FILE_NAMES: dict[PolicyFormat, str] = {"torchscript": "policy.pt", "state_dict": "policy_state_dict.pt",
                                       "onnx": "policy.onnx", "metadata": "metadata.json"}
