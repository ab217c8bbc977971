"""On a GPU, skipped without one (CI has none): each method trains with `device=cuda` and exports CPU policies, and a
run stopped mid-way resumes on the GPU. The first run on a GPU (bench/QUALITY.md E53) found both broken: a rollout
statistic made on the CPU beside CUDA ones, and a checkpoint's RNG state carried onto the GPU by its map_location."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from drop_engine.checkpoint import list_checkpoints
from drop_engine.config import build_config
from drop_engine.export import load_policy
from drop_engine.trainer import Trainer, train

from .recorder import Recorder

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def _config(algorithm: str, **overrides):
    return build_config(algorithm, env="hopper", preset="smoke", task="medium", overrides=overrides, device="cuda")


@pytest.mark.parametrize("algorithm", ["drop", "mopo", "mbpo"])
def test_a_run_trains_on_the_gpu_and_exports_cpu_policies(tmp_path, hopper_dataset, algorithm):
    torch.cuda.reset_peak_memory_stats()
    result = train(hopper_dataset, _config(algorithm), tmp_path, Recorder())
    assert result.status == "completed" and result.epochs == 2
    assert torch.cuda.max_memory_allocated() > 0
    for which in ("last", "best"):
        act = load_policy(result.policy[which]["torchscript"])
        actions = act(np.zeros((4, 11), np.float32))
        assert actions.shape == (4, 3) and np.all(np.abs(actions) <= 1)


def test_a_run_stopped_on_the_gpu_resumes_there(tmp_path, hopper_dataset):
    cfg = _config("drop", epochs=3)
    stopped = Trainer(hopper_dataset, cfg, tmp_path, Recorder(stop_in=Trainer._sac_steps, after=35)).run()
    assert stopped.status == "stopped" and list_checkpoints(tmp_path / "checkpoints")
    second = Recorder()
    resumed = Trainer(hopper_dataset, cfg, tmp_path, second).run()
    assert second.starts[0] is not None, "it resumed from the checkpoint rather than starting over"
    assert resumed.status == "completed" and [e["epoch"] for e in resumed.evaluations] == [1, 2, 3]
