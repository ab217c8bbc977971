"""Algorithm 1 of DROP, with MOPO and MBPO as penalties in the same loop; checkpoints and exact resume.

First the dynamics ensemble is trained, or fetched from a model cache shared between runs (`model_cache.py`); it has
RNG streams of its own, so the rest of the run draws the same numbers either way. With `sac.target_entropy='data'`
the data's behaviour entropy is then estimated, once, from a forked RNG stream.

Order of one epoch: train the DICE estimators (DROP only; pretraining on epoch 0), roll the policy out from
`rollout.batch_size` offline start states into the FIFO model buffer, then `steps_per_epoch` SAC updates on batches
mixing real and model transitions, then evaluate every `eval_every` epochs. The whole state, RNGs included, is
checkpointed every `checkpoint_every` epochs, after the last, and whenever the caller asks to stop, so a resumed run
continues the same number stream. The caller's stop flag is asked inside every long phase (`stopping.py`); a stop
part-way through one checkpoints the state as of the boundary before it (the epoch's start, or the end of its SAC
steps), and a stop while the dynamics are fitted writes nothing, as there is nothing to resume yet. An evaluation can
peak mid-run, so the actor of the best evaluation is kept too (in the checkpoint) and exported beside the last one.
"""
from __future__ import annotations

import copy
import time
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from .bc import behaviour_entropy, estimable
from .callbacks import Callback
from .checkpoint import load_latest, save_checkpoint
from .config import TrainConfig
from .data import Dataset, Normalizer, load_dataset
from .diagnostics import exploitation_stats
from .dice import GradientDice
from .divergence import check_finite
from .dynamics import DynamicsReport, build_ensemble, dynamics_rng, train_dynamics
from .envs import DEFAULT_VERSION, get_env
from .errors import ConfigError
from .evaluation import evaluate
from .export import export_policy
from .model_cache import ModelCache, model_key
from .nn import in_row_chunks
from .replay_buffer import ReplayBuffer
from .rollout import model_rollout
from .sac import SAC, Actor
from .scores import Which, summarize
from .seeding import load_rng_state, machine, rng_state, seed_everything
from .stopping import Stopped, check

ONCE = ("dynamics", "behaviour_fit")  # timed phases before the first epoch, not per epoch
CHECKPOINT_FORMAT = 2  # 2: the best actor snapshot
READABLE_FORMATS = (1, 2)  # a run stopped before the upgrade resumes; its earlier best weights were not kept


@dataclass
class TrainResult:
    status: str  # "completed" or "stopped"
    epochs: int
    global_step: int
    last_return: float | None = None
    last_score: float | None = None
    best_score: float | None = None
    best_epoch: int | None = None
    final_score: float | None = None  # mean of the last evaluations' scores (scores.FINAL_WINDOW)
    evaluations: list[dict] = field(default_factory=list)
    policy: dict[Which, dict[str, str]] | None = None  # "last" and "best": file kind -> path
    dynamics: dict | None = None  # the DynamicsReport, and where the model came from: cache_key, from_cache, cache_path
    timings: dict[str, float] = field(default_factory=dict)
    checkpoint: str | None = None  # where a stopped run resumes from; None if it stopped before writing any
    machine: dict = field(default_factory=dict)  # seeding.machine() of the process that ended the run

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class BestActor:
    """The actor's weights at the best evaluation so far; a CPU copy, so keeping it costs no device memory."""
    epoch: int
    score: float
    state: dict[str, torch.Tensor]


def _cpu_copy(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.detach().to("cpu", copy=True) for k, v in state.items()}


class Trainer:
    def __init__(self, dataset: str | Path | Dataset, config: TrainConfig, out_dir: str | Path,
                 callback: Callback | None = None, model_cache: str | Path | None = None):
        """`model_cache`: a directory of trained ensembles shared between runs (None: always train). It is not part of
        the config because it does not change the result."""
        self.cfg = config
        self.out = Path(out_dir)
        self.ckpt_dir = self.out / "checkpoints"
        self.cb = callback or Callback()
        self.device = torch.device(config.device)
        if config.threads:
            torch.set_num_threads(config.threads)
        self.spec = get_env(config.env)
        self.data = dataset if isinstance(dataset, Dataset) else load_dataset(dataset, env=config.env)
        self.env_version = config.env_version or self.data.env_version or DEFAULT_VERSION  # the config's wins
        self.rng = seed_everything(config.seed)
        obs_dim, act_dim = self.data.obs_dim, self.data.act_dim

        dev = self.device
        t = lambda a: torch.as_tensor(a, device=dev)  # noqa: E731
        self.real = ReplayBuffer.from_tensors(
            obs=t(self.data.observations), act=t(self.data.actions), rew=t(self.data.rewards),
            next_obs=t(self.data.next_observations), done=t(self.data.terminals.astype(np.float32)),
        )
        norm = Normalizer.fit(self.data.observations) if config.normalize_obs else Normalizer.identity(obs_dim)
        self.model = build_ensemble(obs_dim, act_dim, config.dynamics, config.seed, dev)
        self.model_cache = ModelCache(model_cache) if model_cache is not None else None
        self.sac = SAC(obs_dim, act_dim, config.sac).to(dev)
        self.sac.set_obs_normalizer(norm.mean, norm.std)
        self.sac.set_reward_bound(float(self.data.rewards.max()))
        self.dice = None
        if config.algorithm == "drop":
            self.dice = GradientDice(config.dynamics.elites, obs_dim, act_dim, config.dice,
                                     config.dice_discount).to(dev)
            self.dice.norm.set(norm.mean, norm.std)
        self.termination = self.spec.termination
        self.successors: torch.Tensor | None = None  # (elites, N, obs_dim), filled on first DICE use
        self.successor_alive: torch.Tensor | None = None
        capacity = config.rollout.batch_size * config.horizon * config.rollout.retain_epochs
        self.model_buffer = ReplayBuffer(capacity, obs_dim, act_dim, dev)

        self.epoch, self.step_in_epoch, self.global_step = 0, 0, 0
        self.epoch_started = False  # DICE and rollouts of the current epoch are done
        self.evaluations: list[dict] = []
        self.best: BestActor | None = None
        self.dynamics_report: DynamicsReport | None = None
        self.dynamics_source: dict | None = None  # cache_key, from_cache, cache_path
        self.behaviour_entropy: float | None = None  # the data's, estimated once when target_entropy is 'data'
        self.metric_sums: dict[str, torch.Tensor] = {}
        self.metric_count = 0
        self.timings: dict[str, float] = defaultdict(float)

    # ---------------------------------------------------------------- state
    def state_dict(self) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "config": self.cfg.model_dump(mode="json"),
            "epoch": self.epoch, "step_in_epoch": self.step_in_epoch, "global_step": self.global_step,
            "epoch_started": self.epoch_started,
            "dynamics": self.model.state_dict(),
            "dynamics_report": asdict(self.dynamics_report) if self.dynamics_report else None,
            "dynamics_source": self.dynamics_source, "behaviour_entropy": self.behaviour_entropy,
            "sac": self.sac.state_dict(), "sac_optim": self.sac.optim_state(),
            "dice": self.dice.state_dict() if self.dice else None,
            "dice_optim": self.dice.optim_state() if self.dice else None,
            "model_buffer": self.model_buffer.state_dict(),
            "evaluations": self.evaluations,
            "best": asdict(self.best) if self.best else None,
            "metric_sums": self.metric_sums, "metric_count": self.metric_count,
            "rng": rng_state(self.rng, self.device),
        }

    def load_state_dict(self, state: dict) -> None:
        if state.get("format") not in READABLE_FORMATS:
            raise ValueError(f"checkpoint format {state.get('format')} is not one of {READABLE_FORMATS}")
        self.epoch, self.step_in_epoch, self.global_step = state["epoch"], state["step_in_epoch"], state["global_step"]
        self.epoch_started = state["epoch_started"]
        self.model.load_state_dict(state["dynamics"])
        self.dynamics_report = DynamicsReport(**state["dynamics_report"]) if state["dynamics_report"] else None
        self.dynamics_source = state.get("dynamics_source")  # absent from format 1
        self._set_behaviour_entropy(state.get("behaviour_entropy"))  # absent before target_entropy='data'
        self.sac.load_state_dict(state["sac"])
        self.sac.load_optim_state(state["sac_optim"])
        if self.dice is not None:
            self.dice.load_state_dict(state["dice"])
            self.dice.load_optim_state(state["dice_optim"])
        self.model_buffer.load_state_dict(state["model_buffer"])
        self.evaluations = list(state["evaluations"])
        best = state.get("best")
        self.best = BestActor(best["epoch"], best["score"], _cpu_copy(best["state"])) if best else None
        self.metric_sums, self.metric_count = dict(state["metric_sums"]), state["metric_count"]
        load_rng_state(self.rng, state["rng"], self.device)

    def checkpoint(self) -> Path:
        path = save_checkpoint(self.state_dict(), self.ckpt_dir, self.epoch, self.step_in_epoch,
                               self.cfg.keep_checkpoints)
        self.cb.on_checkpoint(path, self.epoch, self.step_in_epoch)
        return path

    # ---------------------------------------------------------------- phases
    def train_dynamics(self) -> bool:
        """Fit the ensemble, or load it from the model cache; False if the caller stopped it, in its training or while
        waiting for another run's (nothing is checkpointed or cached then). Either way the run's own RNG streams are
        untouched, so what follows is the same."""
        cfg, seed = self.cfg.dynamics, self.cfg.seed
        total = cfg.max_epochs or 0

        def on_epoch(epoch: int, holdout: float) -> None:
            self.cb.on_progress("dynamics", 0, epoch, total)
            self._report({"dynamics/holdout_mse": holdout}, -epoch)

        def fit() -> DynamicsReport:
            return train_dynamics(self.model, self.data, cfg, dynamics_rng(seed), self.device, on_epoch,
                                  self.cb.should_stop)

        start = time.perf_counter()
        key = model_key(self.data, cfg, seed, self.device)
        try:
            if self.model_cache is None:
                report, from_cache = fit(), False
            else:
                report, from_cache = self.model_cache.fetch_or_train(key, self.model, fit, self.cb.should_stop)
        except Stopped:
            return False
        self.timings["dynamics"] += time.perf_counter() - start
        self.dynamics_report = report
        self.dynamics_source = {"cache_key": key, "from_cache": from_cache,
                                "cache_path": str(self.model_cache.path(key)) if self.model_cache else None}
        if from_cache:
            self.cb.on_progress("dynamics", 0, report.epochs, report.epochs)
        self._report({"dynamics/elite_holdout_mse": float(np.mean(sorted(report.holdout_mse)[: len(report.elites)])),
                      "dynamics/epochs": float(report.epochs), "dynamics/from_cache": float(from_cache)}, 0)
        return True

    def _set_behaviour_entropy(self, value: float | None) -> None:
        """Keep the estimate (it is checkpointed) and, where the config asks for it, take the target from it."""
        self.behaviour_entropy = value
        if value is not None and self.cfg.sac.target_entropy == "data":
            self.sac.target_entropy = min(-float(self.data.act_dim), value)

    def fit_target_entropy(self) -> bool:
        """With target_entropy 'data', estimate the data's behaviour entropy (once: it is checkpointed) and hold the
        policy at no more than it; False if the caller stopped the fit (nothing of it is kept then). Only at the run's
        start: a run that trained past it at another target would change target part-way. Data with too few actions
        inside the bounds to estimate it (`estimable`) keeps the default target, -|A|."""
        if self.cfg.sac.target_entropy != "data" or self.behaviour_entropy is not None or not estimable(self.data):
            return True
        if self.global_step > 0:
            raise ConfigError(f"this run trained {self.global_step} steps without sac.target_entropy='data'; resume it "
                              "with the target it started with (e.g. --set sac.target_entropy=null)")
        start = time.perf_counter()
        try:
            value = behaviour_entropy(self.data, self.cfg.sac.behaviour_fit_steps, self.cfg.seed,
                                      should_stop=self.cb.should_stop,
                                      on_step=lambda step, total: self.cb.on_progress("behaviour_fit", 0, step, total))
        except Stopped:
            return False
        self.timings["behaviour_fit"] += time.perf_counter() - start
        self._set_behaviour_entropy(value)
        self._report({"sac/behaviour_entropy": value, "sac/target_entropy": self.sac.target_entropy}, 0)
        return True

    @torch.no_grad()
    def _cache_model_successors(self) -> None:
        """Each elite's mean next state and non-terminal mask for every offline (s, a).

        The ensemble is frozen after its training, so these are computed once instead of once per DICE step."""
        elites, obs, act = self.model.elites, self.real.data["obs"], self.real.data["act"]
        mean, _ = in_row_chunks(lambda o, a: self.model(o, a, elites), obs, act, out_dim=1,
                                should_stop=self.cb.should_stop)
        self.successors = obs + mean[..., 1:]
        self.successor_alive = (~self.termination(obs, act, self.successors)).float()

    def train_dice(self, steps: int) -> dict[str, torch.Tensor]:
        """`steps` updates of the estimators; the stop flag is asked before each and raises `Stopped`."""
        cfg, actor, dice = self.cfg.dice, self.sac.actor, self.dice
        if self.successors is None:
            self._cache_model_successors()
        out: dict[str, torch.Tensor] = {}
        for _ in range(steps):
            check(self.cb.should_stop)
            idx = self.real.sample_indices(cfg.batch_size)
            obs, act = self.real.data["obs"][idx], self.real.data["act"][idx]
            next_obs, not_done = self.successors[:, idx], self.successor_alive[:, idx]
            obs0 = self.real.data["obs"][self.real.sample_indices(cfg.batch_size)]
            with torch.no_grad():
                next_act = actor.act(next_obs)
                act0 = actor.act(obs0)
            out = dice.update(obs, act, next_obs, next_act, obs0, act0, not_done)
        if out and dice.tau_avg is not None:  # what the penalty reads, on the last batch: once, not every step
            with torch.no_grad():
                out["dice/tau_avg_data_mean"] = dice.tau(obs, act).mean()
        return out

    def sac_batch(self) -> tuple[tuple[torch.Tensor, ...], int]:
        """A batch of real rows then model rows, and how many are real."""
        n = self.cfg.sac.batch_size
        n_real = int(round(n * self.cfg.sac.real_ratio)) if len(self.model_buffer) else n
        real = self.real.sample(n_real)
        if n_real == n:
            return real, n_real
        fake = self.model_buffer.sample(n - n_real)
        return tuple(torch.cat([a, b]) for a, b in zip(real, fake)), n_real

    def sac_update(self) -> dict[str, torch.Tensor]:
        batch, n_real = self.sac_batch()
        behaviour = self.real.sample(self.cfg.sac.batch_size)[:2] if self.cfg.sac.bc_weight > 0 else None
        return self.sac.update(*batch, real=behaviour, n_real=n_real)

    def _accumulate(self, metrics: dict[str, torch.Tensor]) -> None:
        for k, v in metrics.items():
            self.metric_sums[k] = self.metric_sums.get(k, 0.0) + v
        self.metric_count += 1

    def _report(self, metrics: dict[str, float], step: int) -> None:
        """Every metric goes to the callback through here, once checked to be finite (`divergence.py`)."""
        check_finite(metrics, step)
        self.cb.on_metrics(metrics, step)

    def _flush_metrics(self) -> None:
        if self.metric_count:
            values = torch.stack(list(self.metric_sums.values())).cpu() / self.metric_count
            self._report(dict(zip(self.metric_sums, values.tolist())), self.global_step)
        self.metric_sums, self.metric_count = {}, 0

    def _evaluate(self, actor: Actor, epoch: int):
        """`actor`'s deterministic episodes of `epoch`; its time counts to `evaluate`, so with an averaged actor,
        which is evaluated beside the latest iterate, that phase takes twice as long."""
        dev = self.device

        def policy(obs: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return actor.act(torch.as_tensor(obs, device=dev), deterministic=True).cpu().numpy()

        start = time.perf_counter()
        try:
            return evaluate(policy, self.cfg.env, self.cfg.eval_episodes, seed=10_000 * (self.cfg.seed + 1) + epoch,
                            version=self.env_version, should_stop=self.cb.should_stop)
        finally:
            self.timings["evaluate"] += time.perf_counter() - start

    def evaluate_now(self, epoch: int) -> dict:
        """Evaluate the policy as that of `epoch` (which seeds the episodes); `Stopped` if the caller stops it. With an
        averaged actor the latest iterate is evaluated too, on the same episodes, and recorded as `live_*`."""
        actor = self.sac.policy
        result = self._evaluate(actor, epoch)
        record = {"epoch": epoch, "step": self.global_step, "return": result.mean_return,
                  "return_std": result.std_return, "normalized_score": result.normalized_score}
        if actor is not self.sac.actor:
            live = self._evaluate(self.sac.actor, epoch)
            record.update(live_return=live.mean_return, live_return_std=live.std_return,
                          live_normalized_score=live.normalized_score)
        self.evaluations.append(record)
        if summarize(self._scores()).best_epoch == epoch:
            self.best = BestActor(epoch, result.normalized_score, _cpu_copy(actor.state_dict()))
        self.cb.on_evaluation(epoch, result.mean_return, result.normalized_score)
        return record

    def _timed(self, name: str, fn, *args):
        start = time.perf_counter()
        out = fn(*args)
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self.timings[name] += time.perf_counter() - start
        return out

    def _start_epoch(self) -> bool:
        """The epoch's DICE training and rollouts; False if stopped part-way. What they had changed by then is put
        back (the estimators and their optimisers, the RNG streams; the rollouts fill the model buffer only once
        complete), so the state is the epoch boundary's again and a resumed run does them exactly as this one would
        have."""
        cfg = self.cfg
        rng = rng_state(self.rng, self.device)
        dice = copy.deepcopy((self.dice.state_dict(), self.dice.optim_state())) if self.dice is not None else None
        stats: dict[str, torch.Tensor] = {}
        try:
            if self.dice is not None:
                steps = cfg.dice.pretrain_steps if self.epoch == 0 else cfg.dice.steps_per_epoch
                stats.update(self._timed("dice", self.train_dice, steps))
            starts = self.real.sample(cfg.rollout.batch_size)[0]
            stats.update(self._timed("rollout", model_rollout, self.sac.actor, self.model, self.dice, starts,
                                     cfg.horizon, cfg.algorithm, cfg.penalty, self.termination, self.model_buffer,
                                     self.cb.should_stop))
        except Stopped:
            load_rng_state(self.rng, rng, self.device)
            if dice is not None:
                self.dice.load_state_dict(dice[0])
                self.dice.load_optim_state(dice[1])
            return False
        stats.update(exploitation_stats(self.model, self.real, self.model_buffer))
        values = torch.stack([v.float() for v in stats.values()]).cpu().tolist()
        self._report(dict(zip(stats, values)), self.global_step)
        self.epoch_started = True
        return True

    def _sac_steps(self) -> bool:
        """Run the rest of this epoch's SAC updates; False if stopped at a step boundary."""
        cfg = self.cfg
        total = cfg.epochs * cfg.steps_per_epoch
        start = time.perf_counter()
        self.sac.anneal(self.epoch / cfg.epochs)
        try:
            while self.step_in_epoch < cfg.steps_per_epoch:
                if self.cb.should_stop():
                    return False
                self._accumulate(self.sac_update())
                self.step_in_epoch += 1
                self.global_step += 1
                if self.global_step % cfg.log_every == 0:
                    self._flush_metrics()
                    self.cb.on_progress("train", self.epoch, self.global_step, total)
            return True
        finally:
            self.timings["sac"] += time.perf_counter() - start

    def _end_epoch(self) -> bool:
        """After the epoch's SAC steps: report them, evaluate if due, move on to the next epoch. False if stopped in
        the evaluation: the position stays at the end of the SAC steps, from where a resumed run evaluates, and the
        progress reported says so."""
        cfg = self.cfg
        self._flush_metrics()
        epoch = self.epoch + 1
        if epoch % cfg.eval_every == 0 or epoch == cfg.epochs:
            try:
                self.evaluate_now(epoch)
            except Stopped:
                return False
        self.epoch, self.step_in_epoch, self.epoch_started = epoch, 0, False
        self.cb.on_progress("train", epoch, self.global_step, cfg.epochs * cfg.steps_per_epoch)
        return True

    def _epoch(self) -> bool:
        """The rest of the current epoch, from wherever the run is in it; False if the caller stopped it."""
        if self.cb.should_stop() or not (self.epoch_started or self._start_epoch()):
            return False
        return self._sac_steps() and self._end_epoch()

    # ---------------------------------------------------------------- the loop
    def run(self) -> TrainResult:
        """Train to the end, resuming from the newest checkpoint if there is one."""
        cfg = self.cfg
        state = load_latest(self.ckpt_dir, self.device)
        if state is not None:
            self.load_state_dict(state)
        self.cb.on_start((self.epoch, self.step_in_epoch) if state is not None else None)
        if state is None:
            if not self.train_dynamics():
                return self._result("stopped")
            self.checkpoint()
        if self.dynamics_report is not None:
            self.cb.on_dynamics(self.dynamics())
        if not self.fit_target_entropy():
            return self._result("stopped", checkpoint=str(self.checkpoint()))
        while self.epoch < cfg.epochs:
            epoch_start, before = time.perf_counter(), dict(self.timings)
            if not self._epoch():
                return self._result("stopped", checkpoint=str(self.checkpoint()))
            self.timings["epochs"] += time.perf_counter() - epoch_start
            self._report({f"time/{k}": v - before.get(k, 0.0) for k, v in self.timings.items() if k not in ONCE},
                         self.global_step)
            if self.epoch % cfg.checkpoint_every == 0 or self.epoch == cfg.epochs:
                self.checkpoint()
        self.cb.on_progress("export", self.epoch, 0, 1)
        policy = self.export()
        self.cb.on_progress("export", self.epoch, 1, 1)
        return self._result("completed", policy)

    def dynamics(self) -> dict:
        """The fitted ensemble's report and where it came from, as `Callback.on_dynamics` and `TrainResult` give it.
        A run resumed from a checkpoint of format 1 (before the model cache) knows no source: its keys are None."""
        return {"cache_key": None, "from_cache": None, "cache_path": None, **asdict(self.dynamics_report),
                **(self.dynamics_source or {})}

    def _scores(self) -> list[tuple[int, float]]:
        return [(e["epoch"], e["normalized_score"]) for e in self.evaluations]

    def export(self) -> dict[Which, dict[str, str]]:
        """OUT/policy/last (the policy now: the actor, or the average of its iterates) and OUT/policy/best (the best
        evaluated policy; the last if none was)."""
        cfg = self.cfg
        policy = self.sac.policy
        last = self._export("last", policy, self.epoch, dict(self._scores()).get(self.epoch), {})
        if self.best is None:
            why = ("the best evaluation's weights were not kept (the run resumed from a checkpoint of format 1)"
                   if self.evaluations else "no evaluation ran")
            best = self._export("best", policy, self.epoch, None,
                                {"selected_by": f"{why}: this is the last policy"})
        else:
            actor = copy.deepcopy(policy)  # not a new Actor: its initialisation would draw from the RNG
            actor.load_state_dict(self.best.state)
            best = self._export("best", actor, self.best.epoch, self.best.score, {"selected_by": (
                f"the highest normalised score (the earliest of ties) over the run's simulator evaluations: "
                f"{cfg.eval_episodes} deterministic episodes in the real env per evaluation, every {cfg.eval_every} "
                f"epochs and after the last; an online choice, not an offline one")})
        return {"last": last, "best": best}

    def _export(self, which: Which, actor: Actor, epoch: int, score: float | None, extra: dict) -> dict[str, str]:
        metadata = {
            "which": which, "epoch": epoch, "normalized_score": score, **extra,
            "env": self.cfg.env, "gym_id": self.spec.gym_id(self.env_version),
            "obs_dim": self.data.obs_dim, "act_dim": self.data.act_dim, "algorithm": self.cfg.algorithm,
            # What it was trained on, which outlives the dataset (a deleted upload, a file remade elsewhere).
            "dataset": {"content_hash": self.data.content_hash, "transitions": len(self.data)},
            "config": self.cfg.model_dump(mode="json"), "epochs": self.epoch, **asdict(summarize(self._scores())),
        }
        return {k: str(v) for k, v in export_policy(actor, self.out / "policy" / which, metadata).items()}

    def _result(self, status: str, policy: dict[Which, dict[str, str]] | None = None,
                checkpoint: str | None = None) -> TrainResult:
        last = self.evaluations[-1] if self.evaluations else None
        return TrainResult(
            status=status, epochs=self.epoch, global_step=self.global_step,
            last_return=last["return"] if last else None, **asdict(summarize(self._scores())),
            evaluations=list(self.evaluations), policy=policy,
            dynamics=self.dynamics() if self.dynamics_report else None,
            timings=dict(self.timings), checkpoint=checkpoint, machine=machine(),
        )


def train(dataset: str | Path | Dataset, config: TrainConfig, out_dir: str | Path, callback: Callback | None = None,
          model_cache: str | Path | None = None) -> TrainResult:
    """The engine's entry point for the service and the CLI; `model_cache` as for `Trainer`."""
    return Trainer(dataset, config, out_dir, callback, model_cache).run()
