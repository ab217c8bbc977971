"""Online SAC in the real MuJoCo env: the behaviour policies behind the datasets drop-rl makes itself.

One env step then one SAC update per step after a uniform-random warm-up, as standard SAC. Every `eval_every` steps
the deterministic policy is evaluated and snapshotted; the first snapshot whose return reaches the medium threshold
(a third of the D4RL expert return) is the `medium` policy. Every transition is kept in order, with its MuJoCo state,
because D4RL's `medium-replay` is exactly the agent's experience up to the medium policy.

The whole run (networks, optimisers, transitions, RNG states and the env's physics state mid-episode) is checkpointed
atomically, so a stopped run resumes the same number stream it would have produced uninterrupted.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from pydantic import ValidationError

from .atomic import save_durably
from .collect_config import OnlineConfig
from .config import SACConfig
from .envs import get_env, make_env
from .evaluation import evaluate
from .replay_buffer import ReplayBuffer
from .sac import SAC, Actor
from .seeding import load_rng_state, rng_state, seed_everything

CHECKPOINT_FORMAT = 1
CHECKPOINT_NAME = "online.pt"


def _with_new_defaults(identity: dict) -> dict:
    """A checkpoint's settings with the SAC options added since it was written at their defaults, which keep the
    behaviour that code had (a new option defaults to what was done before); an option since removed stays a
    difference."""
    try:
        return {**identity, "sac": SACConfig(**identity["sac"]).model_dump()}
    except ValidationError:
        return identity


@dataclass
class Snapshot:
    """A behaviour policy taken during training, with its deterministic evaluation."""

    step: int
    mean_return: float
    normalized_score: float
    actor: dict

    def to_dict(self) -> dict:
        return {"step": self.step, "mean_return": self.mean_return, "normalized_score": self.normalized_score}


class _Physics:
    """The raw MuJoCo env with the time limit kept here, so a mid-episode state can be saved and restored exactly."""

    def __init__(self, env: str, version: str):
        self.wrapped = make_env(env, version)
        self.env = self.wrapped.unwrapped
        self.max_steps = self.wrapped.spec.max_episode_steps or 1000
        self.obs = np.zeros(self.env.observation_space.shape, np.float32)
        self.t = 0

    def reset(self, seed: int) -> None:
        self.obs = np.asarray(self.env.reset(seed=seed)[0], np.float32)
        self.t = 0

    def step(self, act: np.ndarray) -> tuple[np.ndarray, float, bool, bool, np.ndarray, np.ndarray]:
        """(next_obs, reward, terminal, timeout, qpos, qvel) with qpos/qvel the state *before* the step."""
        data = self.env.data
        qpos, qvel = data.qpos.copy(), data.qvel.copy()
        next_obs, rew, terminated, _, _ = self.env.step(act.astype(np.float64))
        self.t += 1
        next_obs = np.asarray(next_obs, np.float32)
        timeout = (not terminated) and self.t >= self.max_steps
        self.obs = next_obs
        return next_obs, float(rew), bool(terminated), timeout, qpos, qvel

    def state_dict(self) -> dict:
        import mujoco

        spec = mujoco.mjtState.mjSTATE_INTEGRATION  # qpos, qvel, warm start, time...: all mj_step reads
        buf = np.empty(mujoco.mj_stateSize(self.env.model, spec))
        mujoco.mj_getState(self.env.model, self.env.data, buf, spec)
        return {"mj_state": buf, "obs": self.obs.copy(), "t": self.t}

    def load_state_dict(self, state: dict) -> None:
        import mujoco

        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        mujoco.mj_setState(self.env.model, self.env.data, np.asarray(state["mj_state"]), spec)
        self.obs, self.t = np.asarray(state["obs"], np.float32), int(state["t"])

    def close(self) -> None:
        self.wrapped.close()


class History:
    """Every transition the agent collected, in order, in D4RL columns (preallocated, grown by doubling)."""

    def __init__(self, obs_dim: int, act_dim: int, nq: int, nv: int, capacity: int = 1024):
        self.n = 0
        self.cols = {
            "observations": np.zeros((capacity, obs_dim), np.float32),
            "actions": np.zeros((capacity, act_dim), np.float32),
            "rewards": np.zeros(capacity, np.float32), "next_observations": np.zeros((capacity, obs_dim), np.float32),
            "terminals": np.zeros(capacity, bool), "timeouts": np.zeros(capacity, bool),
            "infos/qpos": np.zeros((capacity, nq)), "infos/qvel": np.zeros((capacity, nv)),
        }

    def append(self, **row) -> None:
        if self.n == len(self.cols["rewards"]):
            self.cols = {k: np.concatenate([v, np.zeros_like(v)]) for k, v in self.cols.items()}
        for key, value in row.items():
            self.cols[key][self.n] = value
        self.n += 1

    def arrays(self, upto: int | None = None) -> dict[str, np.ndarray]:
        """Rows [0, upto) as a D4RL dict; the last row ends an episode (a timeout where it was cut)."""
        upto = self.n if upto is None else upto
        out = {k: v[:upto].copy() for k, v in self.cols.items()}
        if upto:
            out["timeouts"][-1] = not out["terminals"][-1]
        return out

    def state_dict(self) -> dict:
        return {k: v[: self.n].copy() for k, v in self.cols.items()}

    def load_state_dict(self, state: dict) -> None:
        n = len(state["rewards"])
        capacity = max(len(self.cols["rewards"]), n)
        self.cols = {k: np.zeros((capacity, *v.shape[1:]), v.dtype) for k, v in self.cols.items()}
        for key, value in state.items():
            self.cols[key][:n] = value
        self.n = n


def actor_fn(actor: Actor, deterministic: bool) -> Callable[[np.ndarray], np.ndarray]:
    """numpy batch in, numpy actions out; stochastic actions draw from torch's global RNG."""

    def act(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return actor.act(torch.as_tensor(obs, dtype=torch.float32), deterministic).numpy()

    return act


class OnlineSAC:
    """Online SAC with periodic evaluation, behaviour-policy snapshots and exact resume from `out_dir`."""

    def __init__(self, cfg: OnlineConfig, out_dir: str | Path):
        self.cfg = cfg
        self.out = Path(out_dir)
        self.spec = get_env(cfg.env)
        self.rng = seed_everything(cfg.seed)
        self.physics = _Physics(cfg.env, cfg.version)
        obs_dim = self.physics.env.observation_space.shape[0]
        act_dim = self.physics.env.action_space.shape[0]
        self.act_dim = act_dim
        self.sac = SAC(obs_dim, act_dim, cfg.sac)
        self.history = History(obs_dim, act_dim, self.physics.env.model.nq, self.physics.env.model.nv)
        self.step = 0
        self.episodes = 0
        self.episode_return = 0.0
        self.last_episode_return: float | None = None
        self.snapshots: list[Snapshot] = []
        self.medium: Snapshot | None = None
        self.resumed = False
        self.seconds = 0.0  # training wall time over all invocations
        self._clock = time.perf_counter()
        self.physics.reset(seed=cfg.seed)
        try:
            state = self._load()
            if state is not None:
                self.load_state_dict(state)
                self.resumed = True
        except BaseException:  # a checkpoint of another run: nobody will close this half-made agent
            self.physics.close()
            raise
        self.buffer = ReplayBuffer(max(cfg.steps, self.history.n, 1), obs_dim, act_dim)
        if self.history.n:
            cols = self.history.state_dict()
            self.buffer.add(*(torch.as_tensor(cols[k], dtype=torch.float32) for k in
                              ("observations", "actions", "rewards", "next_observations", "terminals")))

    # ------------------------------------------------------------------ state
    @property
    def checkpoint_path(self) -> Path:
        return self.out / CHECKPOINT_NAME

    def _load(self) -> dict | None:
        if not self.checkpoint_path.is_file():
            return None
        state = torch.load(self.checkpoint_path, map_location="cpu", weights_only=False)
        if state.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"{self.checkpoint_path}: checkpoint format {state.get('format')} is not "
                             f"{CHECKPOINT_FORMAT}")
        now, saved = self.cfg.identity(), _with_new_defaults(state["config"])
        if saved != now:
            diff = sorted(k for k in saved.keys() | now.keys() if saved.get(k) != now.get(k))
            raise ValueError(f"{self.checkpoint_path}: made with different settings ({', '.join(diff)}); "
                             "use another --out")
        if state["step"] > self.cfg.steps:
            raise ValueError(f"{self.checkpoint_path}: already at step {state['step']} > --steps {self.cfg.steps}")
        return state

    def state_dict(self) -> dict:
        return {
            "format": CHECKPOINT_FORMAT, "config": self.cfg.identity(), "step": self.step, "episodes": self.episodes,
            "episode_return": self.episode_return, "last_episode_return": self.last_episode_return,
            "seconds": self.seconds, "sac": self.sac.state_dict(), "sac_optim": self.sac.optim_state(),
            "history": self.history.state_dict(), "physics": self.physics.state_dict(),
            "snapshots": [asdict(s) for s in self.snapshots], "medium": self.medium.step if self.medium else None,
            "rng": rng_state(self.rng),
        }

    def load_state_dict(self, state: dict) -> None:
        self.step, self.episodes = state["step"], state["episodes"]
        self.episode_return, self.last_episode_return = state["episode_return"], state["last_episode_return"]
        self.seconds = state["seconds"]
        self.sac.load_state_dict(state["sac"])
        self.sac.load_optim_state(state["sac_optim"])
        self.history.load_state_dict(state["history"])
        self.physics.load_state_dict(state["physics"])
        self.snapshots = [Snapshot(**s) for s in state["snapshots"]]
        self.medium = next((s for s in self.snapshots if s.step == state["medium"]), None)
        load_rng_state(self.rng, state["rng"])

    def save(self) -> Path:
        now = time.perf_counter()
        self.seconds, self._clock = self.seconds + now - self._clock, now
        save_durably(self.state_dict(), self.checkpoint_path)
        return self.checkpoint_path

    # ------------------------------------------------------------------ training
    @property
    def done(self) -> bool:
        return self.step >= self.cfg.steps

    def _snapshot(self) -> Snapshot:
        """Evaluate the current deterministic policy (fixed seeds, so policies compare fairly) and keep a copy."""
        result = evaluate(actor_fn(self.sac.policy, True), self.cfg.env, self.cfg.eval_episodes,
                          seed=10_000 + self.cfg.seed, version=self.cfg.version)
        actor = {k: v.detach().clone() for k, v in self.sac.policy.state_dict().items()}
        snap = Snapshot(self.step, result.mean_return, result.normalized_score, actor)
        self.snapshots.append(snap)
        if self.medium is None and self.step > 0 and snap.mean_return >= self.cfg.threshold:  # step 0 is `random`
            self.medium = snap
        return snap

    def _env_step(self) -> None:
        phys = self.physics
        if self.step < self.cfg.warmup:
            act = self.rng.uniform(-1.0, 1.0, self.act_dim).astype(np.float32)
        else:
            act = actor_fn(self.sac.actor, False)(phys.obs[None])[0]
        obs = phys.obs
        next_obs, rew, terminal, timeout, qpos, qvel = phys.step(act)
        self.history.append(observations=obs, actions=act, rewards=rew, next_observations=next_obs, terminals=terminal,
                            timeouts=timeout, **{"infos/qpos": qpos, "infos/qvel": qvel})
        t = lambda x: torch.as_tensor(np.asarray(x, np.float32))[None]  # noqa: E731
        self.buffer.add(t(obs), t(act), t(rew), t(next_obs), t(float(terminal)))
        self.episode_return += rew
        self.step += 1
        if terminal or timeout:
            self.episodes += 1
            self.last_episode_return, self.episode_return = self.episode_return, 0.0
            phys.reset(seed=self.cfg.seed + self.episodes)

    def begin(self) -> None:
        """Evaluate and keep the randomly initialised policy, the `random` behaviour policy, before any step."""
        if not self.snapshots:
            self._snapshot()
            self.save()

    def run(self, progress: Callable[[OnlineSAC], None] | None = None,
            should_stop: Callable[[], bool] | None = None, until_medium: bool = False) -> bool:
        """Train to `cfg.steps`, or with `until_medium` to the first evaluation that finds the medium policy; True
        when finished, False when `should_stop` asked (a checkpoint is written either way).

        Stopping at the medium policy changes none of the steps before it, so `medium` and `medium-replay` come out
        as a full run's, and a later `run()` continues to `cfg.steps` as if never stopped.
        `progress(self)` is called every 100 steps and after each evaluation.
        """
        cfg = self.cfg
        self._clock = time.perf_counter()
        self.begin()
        if until_medium and self.medium is not None:
            return True
        while self.step < cfg.steps:
            if should_stop is not None and should_stop():
                self.save()
                return False
            self._env_step()
            if self.step > cfg.warmup:
                self.sac.update(*self.buffer.sample(cfg.sac.batch_size))
            if self.step % cfg.eval_every == 0 or self.step == cfg.steps:
                if self.snapshots[-1].step != self.step:
                    self._snapshot()
                self.save()
                if progress is not None:
                    progress(self)
                if until_medium and self.medium is not None:
                    return True
            elif progress is not None and self.step % 100 == 0:
                progress(self)
        return True

    # ------------------------------------------------------------------ results
    def policy(self, kind: str) -> Snapshot:
        """The behaviour policy for 'random', 'medium' or 'expert' (training must have finished for `expert`, and for
        `medium` until an evaluation has reached its threshold).

        `expert` is the best evaluated policy of the run (the latest of equals), not its last one: SAC at these
        budgets is not monotone, and on hopper the last policy scored 33.6 where the medium one had 65.4, which made
        a `medium-expert` file worse than `medium`. Where the medium threshold was never reached, `medium` is that
        same best policy, with a warning.
        """
        if kind == "random":
            return self.snapshots[0]
        if kind == "medium" and self.medium is not None:  # found: the steps after it cannot change it
            return self.medium
        if not self.done:
            raise RuntimeError(f"training stopped at step {self.step} of {self.cfg.steps}")
        best = max(self.snapshots[1:] or self.snapshots, key=lambda s: (s.mean_return, s.step))
        if kind == "expert":
            return best
        if kind == "medium":
            if not getattr(self, "_warned", False):
                warnings.warn(f"{self.cfg.env}: no evaluation reached the medium return {self.cfg.threshold:.0f}; "
                              f"using the best evaluated policy (step {best.step}, return {best.mean_return:.0f})",
                              stacklevel=2)
                self._warned = True
            return best
        raise KeyError(kind)

    def actor(self, snap: Snapshot) -> Actor:
        obs_dim = self.physics.env.observation_space.shape[0]
        actor = Actor(obs_dim, self.act_dim, self.cfg.sac.hidden)
        actor.load_state_dict(snap.actor)
        return actor.eval()

    def close(self) -> None:
        self.physics.close()
