"""The resource estimate: by hand for a tiny config, and against the networks and metric reports of real runs."""
import pytest

from drop_engine.callbacks import Callback
from drop_engine.config import TrainConfig, build_config
from drop_engine.resources import RUNTIME_BYTES, DataShape, estimate, parameter_counts
from drop_engine.trainer import Trainer


def test_a_tiny_config_by_hand():
    cfg = TrainConfig(
        algorithm="drop", epochs=3, steps_per_epoch=5, log_every=2, eval_every=2, eval_episodes=3,
        dynamics={"members": 2, "elites": 1, "hidden": 4, "layers": 2, "batch_size": 8, "max_epochs": 4},
        sac={"hidden": (4,), "batch_size": 10, "real_ratio": 0.1},
        dice={"hidden": (2,), "batch_size": 5, "pretrain_steps": 1, "steps_per_epoch": 0},
        rollout={"batch_size": 6, "horizon": 2, "retain_epochs": 3},
    )
    shape = DataShape(rows=100, obs_dim=3, act_dim=2)  # a transition is 3 + 2 + 1 + 3 + 1 = 10 floats
    # dynamics: 2 members x (5->4: 24, 4->4: 20, two heads 4->4: 40) + log-variance bounds 2 x 4
    # actor 3->4->4: 16 + 20; critics 2 x (5->4->1: 24 + 5); DICE tau and f for 1 elite 2 x (5->2->1: 12 + 3) + nu
    assert parameter_counts(cfg, shape) == {"dynamics": 176, "actor": 36, "critic": 58, "dice": 31}
    est = estimate(cfg, shape)
    # values, gradients, Adam's two moments; plus the dynamics' snapshots and the target critic
    assert est.parameter_bytes == 4 * (5 * 176 + 4 * 36 + 5 * 58 + 4 * 31)
    # dataset and training buffer 2 x 100 x 10, successors and alive flags 1 elite x 100 x (3 + 1)
    assert est.data_bytes == 4 * (2000 + 400)
    assert est.model_buffer_bytes == 4 * (6 * 2 * 3 * 10)
    # the largest phase is the dynamics fit: 100 rows x 2 members x 4 int64, inputs, targets and the normaliser's
    # copy 100 x (5 + 4 + 5) floats, and activations and gradients 3 x 2 members x 8 rows x (4 x 2 + 2 x 4) floats
    assert est.working_bytes == 100 * 2 * 32 + 4 * 100 * 14 + 4 * 3 * 2 * 8 * 16
    assert est.memory_bytes == RUNTIME_BYTES + est.parameter_bytes + est.data_bytes + 1440 + 15072
    assert (est.eval_envs, est.sac_updates) == (3, 15)
    # dynamics 4 epochs + 3; per epoch 7 rollout, 4 diagnostic, 3 ratio rows, and 4 DICE rows after pretraining;
    # SAC flushes at global steps 2, 4, 5 (epoch end), 6, 8, 10, 12, 14, 15 of 6 metrics + Q on data and on model;
    # timings of dice, rollout, sac, epochs each epoch, and of evaluation from epoch 2 on
    assert est.metric_rows == 7 + (3 * 14 + 4) + 9 * 8 + (3 * 4 + 2)


class _Rows(Callback):
    def __init__(self):
        self.rows = 0

    def on_metrics(self, metrics, step):
        self.rows += len(metrics)


@pytest.mark.parametrize("algorithm", ["drop", "mopo", "mbpo"])
@pytest.mark.parametrize("overrides", [{"log_every": 3}, {"log_every": 7, "sac.bc_weight": 0.5,
                                                           "dice.steps_per_epoch": 0, "sac.target_entropy": "data",
                                                           "sac.behaviour_fit_steps": 200, "sac.value_bound": True,
                                                           "sac.critic_layer_norm": True, "dice.average": 0.1,
                                                           "sac.actor_average": 0.01}])
def test_counts_match_a_real_run(tmp_path, hopper_dataset, algorithm, overrides):
    """Networks as built and metric rows as reported; patience past max_epochs fixes the dynamics epochs."""
    cfg = build_config(algorithm, env="hopper", preset="smoke", task="medium",
                       overrides={"dynamics.patience": 10, **overrides})
    shape = DataShape(len(hopper_dataset), hopper_dataset.obs_dim, hopper_dataset.act_dim)
    rows = _Rows()
    trainer = Trainer(hopper_dataset, cfg, tmp_path, rows)
    trainer.run()

    def size(module) -> int:
        return sum(p.numel() for p in module.parameters()) if module is not None else 0

    built = {"dynamics": size(trainer.model), "actor": size(trainer.sac.actor) + size(trainer.sac.actor_average),
             "critic": size(trainer.sac.critic), "dice": size(trainer.dice)}
    assert parameter_counts(cfg, shape) == built
    est = estimate(cfg, shape)
    assert est.metric_rows == rows.rows
    # checkpoints (the smoke preset writes one an epoch): none larger than the estimate, no more at once than it
    # counts (keep_checkpoints, as the newest had replaced the oldest), and the estimate not far over
    files = list((tmp_path / "checkpoints").iterdir())
    largest = max(f.stat().st_size for f in files)
    assert len(files) == est.checkpoints_at_once - 1 and est.checkpoint_bytes / 4 < largest <= est.checkpoint_bytes
