"""What a run will take, computed from its config and its dataset's shape before any work starts, so that a service
can refuse a job it could not hold (memory, checkpoint disk), would not finish (SAC updates) or whose record has no
bound (metric rows).

Memory is counted as the trainer holds it: float32 tensors and int64 indices on one device, plus the process itself.
The large terms (data, model buffer, cached successors, networks) are close; the transient terms are rough. Measured
on a 400,000-row hopper dataset (cpu preset, 50,000 rollouts per epoch), peak RSS: MOPO 825 MiB against an estimate of
795; DROP 1,090 to 1,340 MiB in nine runs, and 2,220 in a tenth (the allocator keeps the successor cache's chunks
fragmented), against 1,182.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from math import gcd
from typing import Sequence

from .config import TrainConfig
from .data_rows import FLOAT, DataShape

RUNTIME_BYTES = 400 << 20  # the process: Python, torch and MuJoCo loaded (340 MiB), and torch's first allocations
INDEX = 8  # bytes of an int64
TRAINED = 4  # copies of a trained parameter: its value, its gradient and Adam's two moments
SAC_METRICS = 6  # losses of the critic, actor and temperature, alpha, Q mean, entropy
ROLLOUT_METRICS = 7  # penalty mean, std, max and share, reward mean, length mean, model buffer size
DIAG_METRICS = 4  # ensemble disagreement and reward on data and on model rows
DICE_METRICS = 4  # objective, tau mean, std and negative share on the data; and the averaged tau's mean if averaged
TAU_METRICS = 3  # tau mean, min and max on the rollouts
CHECKPOINT_EXTRA = 64 << 10  # a checkpoint's config, evaluations, metric sums, RNG states and the file's framing


@dataclass(frozen=True)
class ResourceEstimate:
    parameter_bytes: int  # networks with gradients and Adam moments, SAC's target critic, the dynamics' snapshots
    data_bytes: int  # the dataset as loaded, its copy in the training buffer, DROP's cached model successors
    model_buffer_bytes: int  # rollout.batch_size x horizon x retain_epochs transitions
    working_bytes: int  # the largest transient of one phase: dynamics fit, successor cache, DICE, rollout or SAC
    runtime_bytes: int  # the process before any of the above
    eval_envs: int  # MuJoCo envs open at once while evaluating: one per episode
    sac_updates: int  # epochs x steps_per_epoch
    metric_rows: int  # rows the run records through `Callback.on_metrics`, one per metric and report
    checkpoint_bytes: int  # one checkpoint, at most
    checkpoints_at_once: int  # keep_checkpoints, and the newest, written before the oldest is removed

    @property
    def memory_bytes(self) -> int:
        """Peak memory: what lives for the whole run plus the largest transient."""
        return (self.runtime_bytes + self.parameter_bytes + self.data_bytes + self.model_buffer_bytes
                + self.working_bytes)

    @property
    def disk_bytes(self) -> int:
        """Peak disk of the run's checkpoints, what grows with the config (the policies are a few networks)."""
        return self.checkpoint_bytes * self.checkpoints_at_once

    def to_dict(self) -> dict[str, int]:
        return {**asdict(self), "memory_bytes": self.memory_bytes, "disk_bytes": self.disk_bytes}


def _linear(sizes: Sequence[int]) -> int:
    """Weights and biases of a chain of linear layers through these widths."""
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))


def parameter_counts(cfg: TrainConfig, shape: DataShape) -> dict[str, int]:
    """Parameter counts of each network, as `sum(p.numel())` of the modules the trainer builds."""
    obs, act, dyn = shape.obs_dim, shape.act_dim, cfg.dynamics
    out = obs + 1  # reward and state change
    counts = {
        # members x (body + mean and log-variance heads), plus the shared log-variance bounds
        "dynamics": dyn.members * (_linear([obs + act] + [dyn.hidden] * dyn.layers) + 2 * _linear([dyn.hidden, out]))
        + 2 * out,
        # mean and log-std heads; twice with the average of its iterates
        "actor": (1 + (cfg.sac.actor_average < 1)) * _linear([obs, *cfg.sac.hidden, 2 * act]),
        # two critics, each hidden layer with a layer norm's weight and bias if on
        "critic": 2 * (_linear([obs + act, *cfg.sac.hidden, 1]) + cfg.sac.critic_layer_norm * 2 * sum(cfg.sac.hidden)),
        "dice": 0,
    }
    if cfg.algorithm == "drop":  # tau and f per elite (and tau's average if averaged), plus nu
        nets = 2 + (cfg.dice.average < 1)
        counts["dice"] = nets * dyn.elites * _linear([obs + act, *cfg.dice.hidden, 1]) + dyn.elites
    return counts


def _working_bytes(cfg: TrainConfig, shape: DataShape) -> int:
    """The largest of the phases' transients; the phases run one after another."""
    obs, act, rows, dyn = shape.obs_dim, shape.act_dim, shape.rows, cfg.dynamics
    out = obs + 1
    phases = {
        # per member and row: the bootstrap index, its random sort keys, their order and the shuffled index; per row:
        # inputs, targets and the normaliser's copy of the inputs; per batch row: activations and their gradients
        "dynamics": rows * dyn.members * 4 * INDEX + rows * (2 * (obs + act) + out) * FLOAT
        + 3 * dyn.members * dyn.batch_size * (dyn.hidden * dyn.layers + 2 * out) * FLOAT,
        # every elite's mean and log-variance on every row, as chunks and joined, and the termination check's copy
        "successors": 5 * dyn.elites * rows * out * FLOAT if cfg.algorithm == "drop" else 0,
        # tau on one batch and f on three, per elite: inputs, activations and gradients
        "dice": 2 * 4 * dyn.elites * cfg.dice.batch_size * (obs + act + sum(cfg.dice.hidden)) * FLOAT
        if cfg.algorithm == "drop" else 0,
        # per start state: its transitions over the horizon (added to the model buffer once the rollout is complete),
        # one step's tensors (twice, as chunks and joined), the penalties, rewards and ratios kept over the horizon for
        # the statistics; MOPO runs every member on every row
        "rollout": cfg.rollout.batch_size * FLOAT * (
            cfg.horizon * shape.row_floats + 8 * (obs + act + 1) + 3 * cfg.horizon
            + (4 * dyn.members * out if cfg.algorithm == "mopo" else 0)),
        # the real and model batches and their join, the behaviour batch; the actor on three batches and both
        # critics on three, each layer's output and its gradient
        "sac": cfg.sac.batch_size * FLOAT * (3 * shape.row_floats + obs + act + 2 * 9 * sum(cfg.sac.hidden)),
    }
    return max(phases.values())


def _metric_rows(cfg: TrainConfig) -> int:
    """Rows of metrics, following the trainer's reports: one row per dynamics epoch (counted when `max_epochs`
    bounds them; early stopping ends them otherwise) and three for its result (holdout, epochs, from the cache); two
    for the behaviour-entropy fit of target_entropy 'data'; per epoch the rollout statistics, the time of each phase,
    and SAC's averages (with the behaviour term's and the value bound's where they are on) every `log_every` global
    steps and at each epoch end in between."""
    epochs, steps, every = cfg.epochs, cfg.steps_per_epoch, cfg.log_every
    drop = cfg.algorithm == "drop"
    n_real = round(cfg.sac.batch_size * cfg.sac.real_ratio)
    per_flush = (SAC_METRICS + (cfg.sac.bc_weight > 0) + cfg.sac.value_bound
                 + 2 * (0 < n_real < cfg.sac.batch_size))
    # A flush at every multiple of log_every, plus one at each epoch end that is not such a multiple: epoch e ends on
    # one exactly when e is a multiple of log_every / gcd(steps, log_every).
    flushes = epochs * steps // every + epochs - epochs // (every // gcd(steps, every))
    starts = epochs * (ROLLOUT_METRICS + DIAG_METRICS + TAU_METRICS * drop)
    if drop:
        reports = (cfg.dice.pretrain_steps > 0) + (epochs - 1) * (cfg.dice.steps_per_epoch > 0)
        starts += (DICE_METRICS + (cfg.dice.average < 1)) * reports
    # rollout, sac, epochs (and dice) every epoch; evaluate from the first evaluation on
    timings = epochs * (3 + drop) + epochs - min(cfg.eval_every, epochs) + 1
    fit = 2 * (cfg.sac.target_entropy == "data")
    return (cfg.dynamics.max_epochs or 0) + 3 + fit + starts + flushes * per_flush + timings


def estimate(cfg: TrainConfig, shape: DataShape) -> ResourceEstimate:
    """The resources `cfg` takes on a dataset of this shape."""
    params = parameter_counts(cfg, shape)
    # the dynamics keep each member's best snapshot, SAC a target critic; tau's average, where on, is counted as
    # trained though it has no gradient or Adam moments (over by three copies of the elites' tau networks)
    parameter_floats = ((TRAINED + 1) * (params["dynamics"] + params["critic"])
                        + TRAINED * (params["actor"] + params["dice"]))
    data_floats = 2 * shape.rows * shape.row_floats
    if cfg.algorithm == "drop":  # each elite's successor and alive flag per row
        data_floats += cfg.dynamics.elites * shape.rows * (shape.obs_dim + 1)
    buffer_rows = cfg.rollout.batch_size * cfg.horizon * cfg.rollout.retain_epochs
    return ResourceEstimate(
        parameter_bytes=parameter_floats * FLOAT,
        data_bytes=data_floats * FLOAT,
        model_buffer_bytes=buffer_rows * shape.row_floats * FLOAT,
        working_bytes=_working_bytes(cfg, shape),
        runtime_bytes=RUNTIME_BYTES,
        eval_envs=cfg.eval_episodes,
        sac_updates=cfg.epochs * cfg.steps_per_epoch,
        metric_rows=_metric_rows(cfg),
        # the dynamics once (its fit is over); actor, critics and DICE with Adam's two moments, the critics' target
        # copy (an average's copy has no moments: counted with them, over); a full model buffer
        checkpoint_bytes=FLOAT * (params["dynamics"] + 3 * (params["actor"] + params["dice"]) + 4 * params["critic"]
                                  + buffer_rows * shape.row_floats) + CHECKPOINT_EXTRA,
        checkpoints_at_once=cfg.keep_checkpoints + 1,
    )
