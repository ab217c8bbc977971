"""Record D4RL-layout datasets in the real env, and make the five D4RL kinds from an online SAC run.

Kinds (ALGORITHM.md section 7): `random` (the randomly initialised policy), `medium` (the first evaluated policy
reaching a third of the D4RL expert return), `medium-replay` (everything the agent collected up to that policy),
`expert` (the best evaluated policy of training: ALGORITHM.md's "fully trained policy", which a CPU budget's last
policy need not be) and `medium-expert` (medium then expert rows). Behaviour policies act
stochastically, as D4RL's did. Each file is written atomically and skipped when a finished one is already there, so
`collect_datasets` resumes from whatever a stopped run left.
"""
from __future__ import annotations

import importlib.metadata
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from .collect_config import KINDS, CollectConfig
from .data import from_arrays, save_hdf5
from .envs import DEFAULT_VERSION, EnvVersion, get_env, make_env
from .file_lock import exclusive
from .online import OnlineSAC, actor_fn
from .stopping import Stopped, check

BehaviourPolicy = Callable[[np.ndarray], np.ndarray]
KEYS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts", "infos/qpos", "infos/qvel")


def drop_rl_version() -> str:
    try:
        return importlib.metadata.version("drop-rl")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def random_policy(act_dim: int, seed: int) -> BehaviourPolicy:
    rng = np.random.default_rng(seed)
    return lambda obs: rng.uniform(-1.0, 1.0, size=(len(obs), act_dim)).astype(np.float32)


def collect_transitions(env: str, policy: BehaviourPolicy, transitions: int, seed: int = 0,
                        version: EnvVersion = DEFAULT_VERSION, num_envs: int = 1,
                        progress: Callable[[int], None] | None = None) -> dict[str, np.ndarray]:
    """Step `num_envs` envs side by side (one policy call per step on their batch) until `transitions` rows are done.

    Rows are stored episode by episode, so consecutive rows of an episode stay consecutive as D4RL needs; episodes
    still running at the end are dropped and the last kept one is cut to size. The k-th reset overall uses seed + k.
    qpos/qvel are the MuJoCo state of each row's observation. `progress(rows)` reports finished rows.
    """
    envs = [make_env(env, version) for _ in range(num_envs)]
    try:
        resets = 0
        obs = []
        for e in envs:
            obs.append(e.reset(seed=seed + resets)[0])
            resets += 1
        obs = np.asarray(obs, np.float32)
        running: list[dict[str, list]] = [{k: [] for k in KEYS} for _ in envs]
        done: list[dict[str, list]] = []
        rows = 0
        while rows < transitions:
            acts = np.asarray(policy(obs), dtype=np.float32)
            for i, e in enumerate(envs):
                data, ep = e.unwrapped.data, running[i]
                ep["infos/qpos"].append(data.qpos.copy())
                ep["infos/qvel"].append(data.qvel.copy())
                next_obs, rew, terminated, truncated, _ = e.step(acts[i])
                for key, value in (("observations", obs[i].copy()), ("actions", acts[i]), ("rewards", rew),
                                   ("next_observations", next_obs), ("terminals", terminated),
                                   ("timeouts", truncated and not terminated)):
                    ep[key].append(value)
                obs[i] = next_obs
                if terminated or truncated:
                    done.append(ep)
                    rows += len(ep["rewards"])
                    running[i] = {k: [] for k in KEYS}
                    obs[i] = e.reset(seed=seed + resets)[0]
                    resets += 1
                    if progress is not None:
                        progress(min(rows, transitions))
                    if rows >= transitions:
                        break
    finally:  # also when `progress` stops the collection
        for e in envs:
            e.close()
    out: dict[str, np.ndarray] = {}
    for key in KEYS:
        dtype = bool if key in ("terminals", "timeouts") else np.float64 if key.startswith("infos/") else np.float32
        out[key] = np.concatenate([np.asarray(ep[key], dtype=dtype) for ep in done])[:transitions]
    out["timeouts"][-1] = not out["terminals"][-1]  # the file ends an episode
    return out


def concatenate(*parts: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: np.concatenate([p[k] for p in parts]) for k in KEYS}


def episode_returns(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """Returns of the file's episodes; the last one is left out when others exist, since it may be cut short."""
    ends = np.flatnonzero(arrays["terminals"] | arrays["timeouts"])
    starts = np.concatenate([[0], ends[:-1] + 1])
    returns = np.add.reduceat(arrays["rewards"].astype(np.float64), starts)
    return returns[:-1] if len(returns) > 1 else returns


def read_arrays(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    import h5py

    with h5py.File(path, "r") as handle:
        arrays = {k: handle[k][()] for k in KEYS}
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in handle.attrs.items()}
    return arrays, attrs


def _attrs(cfg: CollectConfig, kind: str, arrays: dict[str, np.ndarray], behaviour: list) -> dict:
    spec, online = get_env(cfg.online.env), cfg.online
    rets = episode_returns(arrays)
    policy_return = float(np.mean([s.mean_return for s in behaviour]))
    return {
        "env_name": spec.gym_id(online.version), "env": spec.name, "kind": kind, "seed": online.seed,
        "policy_return": policy_return, "policy_normalized_score": spec.normalized_score(policy_return),
        "policy_steps": np.asarray([s.step for s in behaviour], np.int64),
        "dataset_return": float(rets.mean()), "dataset_normalized_score": spec.normalized_score(float(rets.mean())),
        "episodes": int((arrays["terminals"] | arrays["timeouts"]).sum()),  # the last row always ends one
        "medium_threshold": online.threshold,
        "medium_threshold_reached": bool(behaviour[0].mean_return >= online.threshold)
        if kind.startswith("medium") else False,
        "train_steps": online.steps, "transitions_per_policy": cfg.transitions, "eval_episodes": online.eval_episodes,
        "drop_rl_version": drop_rl_version(), "behaviour": "stochastic SAC actor" if kind != "medium-replay"
        else "online SAC replay (uniform warm-up, then the learning actor) up to the medium policy",
    }


def _behaviour(agent: OnlineSAC, kind: str) -> list:
    """The snapshots whose actions fill a kind's rows."""
    if kind == "medium-expert":
        return [agent.policy("medium"), agent.policy("expert")]
    return [agent.policy("medium" if kind == "medium-replay" else kind)]


def _matches(path: Path, cfg: CollectConfig, behaviour: list) -> bool:
    """A finished file from this same collection and these behaviour policies (so a resumed run keeps it, and a
    file an older rule made from other policies is made again)."""
    import h5py

    if not path.is_file():
        return False
    try:
        with h5py.File(path, "r") as handle:
            a = handle.attrs
            return (str(a["env_name"]) == get_env(cfg.online.env).gym_id(cfg.online.version)
                    and int(a["seed"]) == cfg.online.seed and int(a["train_steps"]) == cfg.online.steps
                    and int(a["transitions_per_policy"]) == cfg.transitions
                    and a["policy_steps"].tolist() == [s.step for s in behaviour])
    except (OSError, KeyError):
        return False


def _record(cfg: CollectConfig, agent: OnlineSAC, kind: str, bar_factory) -> dict[str, np.ndarray]:
    """The rows of one kind; torch is reseeded per kind so each file is reproducible alone."""
    [snap] = _behaviour(agent, kind)
    if kind == "medium-replay":
        return agent.history.arrays(snap.step)
    index = KINDS.index(kind) + 1
    torch.manual_seed(cfg.online.seed * 100 + index)
    bar = bar_factory(kind, cfg.transitions)
    try:
        arrays = collect_transitions(cfg.online.env, actor_fn(agent.actor(snap), False), cfg.transitions,
                                     seed=1_000_000 * index + cfg.online.seed, version=cfg.online.version,
                                     num_envs=cfg.num_envs, progress=bar.update_to)
    finally:
        bar.close()
    return arrays


class _Bar:
    """tqdm bar (or nothing) that accepts absolute progress."""

    def __init__(self, desc: str, total: int, enabled: bool, should_stop: Callable[[], bool] | None = None):
        self.bar, self.should_stop = None, should_stop
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="step", dynamic_ncols=True)

    def update_to(self, n: int) -> None:
        if self.should_stop is not None:
            check(self.should_stop)  # raises Stopped inside recording; files already written stay
        if self.bar is not None:
            self.bar.n = n
            self.bar.refresh()

    def postfix(self, **values) -> None:
        if self.bar is not None:
            self.bar.set_postfix(values, refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def collect_datasets(cfg: CollectConfig, out_dir: str | Path, kinds: tuple[str, ...] = KINDS, progress: bool = True,
                     should_stop: Callable[[], bool] | None = None) -> list[dict] | None:
    """Train (or resume) online SAC under `out_dir/<env>-sac/`, then write `out_dir/<env>-<kind>.hdf5` for `kinds`.

    Returns one summary row per kind, or None when `should_stop` interrupted training (its checkpoint is saved).
    Raises `Busy` if another process is collecting the same env into `out_dir`: both would write one checkpoint and
    the same files.
    """
    out = Path(out_dir)
    sac_dir = out / f"{cfg.online.env}-sac"
    busy = f"another collection of {cfg.online.env} is writing into {out}; wait for it to end, or use another --out"
    with exclusive(sac_dir / "collect.lock", busy=busy):
        return _collect(cfg, out, sac_dir, kinds, progress, should_stop)


def _collect(cfg: CollectConfig, out: Path, sac_dir: Path, kinds: tuple[str, ...], progress: bool,
             should_stop: Callable[[], bool] | None) -> list[dict] | None:
    agent = OnlineSAC(cfg.online, sac_dir)
    # Without an expert kind, training ends at the medium policy: on halfcheetah that is 70,000 of 200,000 steps.
    until_medium = not {"expert", "medium-expert"} & set(kinds)
    try:
        if set(kinds) <= {"random"}:  # the untrained actor: no need to wait for online training
            agent.begin()
        elif not agent.done and not (until_medium and agent.medium is not None):
            bar = _Bar(f"{cfg.online.env} sac", cfg.online.steps, progress)
            bar.update_to(agent.step)

            def show(a: OnlineSAC) -> None:
                last = a.snapshots[-1]
                bar.postfix(eval_ret=f"{last.mean_return:.0f}", score=f"{last.normalized_score:.1f}",
                            ep_ret=f"{a.last_episode_return:.0f}" if a.last_episode_return is not None else "-")
                bar.update_to(a.step)

            try:
                finished = agent.run(show, should_stop, until_medium)
            finally:
                bar.close()
            if not finished:
                return None
        started = time.perf_counter()
        made: dict[str, dict[str, np.ndarray]] = {}
        rows = []
        wanted = [k for k in KINDS if k in kinds or (k in ("medium", "expert") and "medium-expert" in kinds)]
        for kind in wanted:
            path, behaviour = cfg.dataset_path(out, kind), _behaviour(agent, kind)
            if _matches(path, cfg, behaviour):
                arrays, attrs = read_arrays(path)
            else:
                if kind == "medium-expert":
                    arrays = concatenate(made["medium"], made["expert"])
                else:
                    try:
                        arrays = _record(cfg, agent, kind, lambda k, n: _Bar(f"{cfg.online.env}-{k}", n, progress,
                                                                             should_stop))
                    except Stopped:
                        return None
                attrs = _attrs(cfg, kind, arrays, behaviour)
                from_arrays(arrays, attrs, env=cfg.online.env)  # the validation an upload gets, before writing
                if kind in kinds:
                    save_hdf5(path, arrays, attrs)
            made[kind] = arrays
            if kind in kinds:
                rows.append({"kind": kind, "path": str(path), "transitions": len(arrays["rewards"]),
                             "episodes": int(attrs["episodes"]), "mean_return": float(attrs["dataset_return"]),
                             "normalized_score": float(attrs["dataset_normalized_score"]),
                             "policy_return": float(attrs["policy_return"]),
                             "policy_normalized_score": float(attrs["policy_normalized_score"])})
        for row in rows:
            row["train_seconds"] = round(agent.seconds, 1)
            row["record_seconds"] = round(time.perf_counter() - started, 1)  # this invocation's recording
        return rows
    finally:
        agent.close()


def summary_table(rows: list[dict]) -> str:
    head = f"{'kind':<14}{'transitions':>12}{'episodes':>10}{'mean return':>13}{'norm. score':>13}{'policy score':>14}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['kind']:<14}{r['transitions']:>12}{r['episodes']:>10}{r['mean_return']:>13.1f}"
                     f"{r['normalized_score']:>13.1f}{r['policy_normalized_score']:>14.1f}")
    return "\n".join(lines)
