"""Behaviour cloning, the floor every offline method should clear: regress the data's actions from its states."""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from .data import Dataset, Normalizer
from .envs import DEFAULT_VERSION, EnvVersion
from .evaluation import Evaluation, evaluate
from .nn import adam
from .sac import ACTION_EDGE, Actor
from .stopping import StopFlag, check, never


def train_bc(data: Dataset, steps: int = 100_000, batch_size: int = 256, lr: float = 1e-3, seed: int = 0,
             hidden: tuple[int, ...] = (256, 256), should_stop: StopFlag = never,
             on_step: Callable[[int, int], None] | None = None) -> Actor:
    """A tanh-Gaussian actor fitted to the dataset's actions by maximum likelihood; it acts with its mode tanh(mu(s)).

    Likelihood, not squared error: the data of a stochastic policy (a SAC actor's samples) has the mean action
    E[a|s], pulled inward from the bounds, where the policy's own deterministic action is its mode, and walker2d
    falls over with the mean (bench/QUALITY.md E20: 25.6 against 38.4-50.8 at 100,000 steps, the data 37.8).
    `should_stop` is asked every 100 steps and raises `Stopped`; `on_step(step, steps)`, where given, is told there and
    at the end, for progress."""
    torch.manual_seed(seed)
    actor = Actor(data.obs_dim, data.act_dim, hidden)
    norm = Normalizer.fit(data.observations)
    actor.norm.set(norm.mean, norm.std)
    obs = torch.as_tensor(data.observations)
    act = torch.as_tensor(data.actions)
    optim = adam(actor.parameters(), lr)
    gen = torch.Generator().manual_seed(seed)
    for step in range(steps):
        if step % 100 == 0:
            check(should_stop)
            if on_step is not None:
                on_step(step, steps)
        idx = torch.randint(0, len(obs), (batch_size,), generator=gen)
        loss = -actor.log_prob(obs[idx], act[idx]).mean()
        optim.zero_grad(set_to_none=True)
        loss.backward()
        optim.step()
    if on_step is not None:
        on_step(steps, steps)
    return actor


# Fewer rows inside the bounds, as in a bang-bang policy's data, and a fit of the behaviour's spread reads almost
# nothing: the data then says nothing about how narrow its policy is.
MIN_FIT_ROWS = 1_000


def _inside(data: Dataset) -> np.ndarray:
    """Rows whose actions are all inside the tanh bounds. A tanh-Gaussian has no density on a bound: an action clipped
    there is read at the bound's edge, where each such dimension adds about -13 nats and pulls a fit's spread out."""
    return np.flatnonzero(np.abs(data.actions).max(1) < ACTION_EDGE)


def estimable(data: Dataset) -> bool:
    """Whether enough rows are inside the bounds (`MIN_FIT_ROWS`) for `behaviour_entropy`."""
    return len(_inside(data)) >= MIN_FIT_ROWS


def entropy_rows(data: Dataset, samples: int = 10_000, seed: int = 0) -> np.ndarray:
    """The rows a behaviour entropy is read on: a fixed subsample of `_inside`'s."""
    inside = _inside(data)
    return np.sort(np.random.default_rng(seed).choice(inside, size=min(samples, len(inside)), replace=False))


def behaviour_entropy(data: Dataset, steps: int, seed: int = 0, should_stop: StopFlag = never,
                      on_step: Callable[[int, int], None] | None = None) -> float:
    """An estimate, in nats, of the entropy of the policy that chose the data's actions: their mean negative
    log-likelihood over `entropy_rows` under a tanh-Gaussian fitted to the `_inside` rows (`train_bc`, on the CPU).

    Where the data came from one stochastic policy this is its entropy plus the fit's KL to it, so it errs high
    (bench/QUALITY.md E28 measures it against the behaviour policies the bench files were recorded with). The fit draws
    from a forked CPU RNG stream, so a run that asks for it draws the same numbers after it as one that does not.
    Only for `estimable` data."""
    inside = _inside(data)
    if len(inside) < MIN_FIT_ROWS:
        raise ValueError(f"{len(inside)} rows have every action inside the bounds; an estimate needs {MIN_FIT_ROWS}")
    fit_on = data if len(inside) == len(data) else data.take(inside)
    with torch.random.fork_rng(devices=[]):
        actor = train_bc(fit_on, steps, seed=seed, should_stop=should_stop, on_step=on_step)
    rows = entropy_rows(data, seed=seed)
    with torch.no_grad():
        nll = -actor.log_prob(torch.as_tensor(data.observations[rows]), torch.as_tensor(data.actions[rows]))
    return float(nll.mean())


def evaluate_actor(actor: Actor, env: str, episodes: int, seed: int,
                   version: EnvVersion = DEFAULT_VERSION) -> Evaluation:
    def policy(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return actor.act(torch.as_tensor(obs), deterministic=True).numpy()

    return evaluate(policy, env, episodes, seed, version)
