"""SAC must learn a one-step continuous task whose optimum is known: a*(s) = 0.5 s."""
import numpy as np
import pytest
import torch

from drop_engine.config import SACConfig
from drop_engine.sac import SAC


def test_sac_learns_known_optimum():
    torch.manual_seed(0)
    sac = SAC(1, 1, SACConfig(hidden=(64, 64), batch_size=128, actor_lr=1e-3, critic_lr=1e-3))
    for _ in range(1500):
        s = torch.rand(128, 1) * 2 - 1
        a, _ = sac.actor.sample(s)
        a = a.detach()
        r = -(a[:, 0] - 0.5 * s[:, 0]).pow(2) * 10
        sac.update(s, a, r, s, torch.ones(128))  # every episode ends after one step
    s = torch.linspace(-1, 1, 21)[:, None]
    with torch.no_grad():
        act = sac.actor.act(s, deterministic=True)
    err = (act - 0.5 * s).abs().max().item()
    assert err < 0.1, err
    # The temperature was tuned towards the target entropy, not left at its start.
    assert sac.log_alpha.item() < -0.25


def test_target_entropy_default_and_override():
    assert SAC(3, 4, SACConfig()).target_entropy == -4.0
    assert SAC(3, 4, SACConfig(target_entropy=-3.0)).target_entropy == -3.0
    assert SAC(3, 4, SACConfig(target_entropy="data")).target_entropy == -4.0  # until the trainer estimates it


def test_alpha_min_holds_the_temperature_where_its_loss_would_take_it_lower():
    """A target entropy far under the policy's makes the temperature loss push alpha down at every step; the floor
    stops it there, and without one it falls through."""
    def alpha_after(alpha_min):
        torch.manual_seed(0)
        sac = SAC(2, 2, SACConfig(hidden=(16, 16), alpha_lr=0.05, target_entropy=-50.0, alpha_min=alpha_min))
        s, a = torch.rand(64, 2), torch.rand(64, 2) * 2 - 1
        for _ in range(100):
            sac.update(s, a, torch.zeros(64), s, torch.zeros(64))
        return sac.log_alpha.exp().item()

    assert alpha_after(None) < 0.05
    assert alpha_after(0.2) == pytest.approx(0.2)


def test_behaviour_cloning_recovers_a_deterministic_policy(hopper_dataset):
    """Cloning data whose actions are a known function of the state gives back that function."""
    from drop_engine.bc import train_bc
    from drop_engine.data import Dataset

    obs = hopper_dataset.observations
    target = torch.tanh(torch.as_tensor(obs[:, :3]) * 2).numpy()
    data = Dataset(obs, target, hopper_dataset.rewards, hopper_dataset.next_observations,
                   hopper_dataset.terminals, hopper_dataset.timeouts)
    actor = train_bc(data, steps=1500, hidden=(64, 64))
    with torch.no_grad():
        pred = actor.act(torch.as_tensor(obs), deterministic=True).numpy()
    assert abs(pred - target).mean() < 0.05


def test_behaviour_cloning_finds_a_stochastic_policys_mode_not_its_mean_action():
    """Data from a tanh-Gaussian policy: the clone acts with that policy's mode tanh(mu(s)), whose distance to the
    data's mean action E[a|s] (what a squared-error clone fits) is far larger than the clone's error."""
    from drop_engine.bc import train_bc
    from drop_engine.data import Dataset

    gen = np.random.default_rng(0)
    n = 20_000
    obs = gen.uniform(-1, 1, (n, 1)).astype(np.float32)
    mu = 1.0 + 1.5 * obs
    act = np.tanh(mu + gen.normal(size=(n, 1))).astype(np.float32)
    zeros = np.zeros(n, np.float32)
    data = Dataset(obs, act, zeros, obs, zeros.astype(bool), zeros.astype(bool))
    actor = train_bc(data, steps=1500, hidden=(64, 64))

    grid = np.linspace(-0.9, 0.9, 10, dtype=np.float32)[:, None]
    with torch.no_grad():
        pred = actor.act(torch.as_tensor(grid), deterministic=True).numpy()
    mode = np.tanh(1.0 + 1.5 * grid)
    mean = np.tanh(1.0 + 1.5 * grid + gen.normal(size=(10, 20_000))).mean(1, keepdims=True)
    assert abs(pred - mode).mean() < 0.03 and abs(mean - mode).mean() > 0.1


def test_behaviour_entropy_recovers_a_known_policys_entropy():
    """Data from tanh-Gaussians of known spread: the estimate is their entropy at the data (the actions' mean negative
    log-likelihood under the true policy, where actions clipped to a bound are left out), a three times wider policy
    reads about 2 ln 3 nats higher, and the caller's torch RNG stream is left where it was."""
    from drop_engine.bc import behaviour_entropy
    from drop_engine.data import Dataset
    from drop_engine.sac import _squashed_log_prob

    gen = np.random.default_rng(0)
    n = 20_000
    obs = gen.uniform(-1, 1, (n, 2)).astype(np.float32)
    mu = np.stack([1.0 + 1.5 * obs[:, 0], -0.5 * obs[:, 1]], 1)
    zeros = np.zeros(n, np.float32)
    found, truth = [], []
    for scale in (1.0, 3.0):
        std = np.array([0.1, 0.05]) * scale
        u = mu + std * gen.normal(size=(n, 2))
        act = np.tanh(u).astype(np.float32)
        act[:400, 0] = 1.0  # clipped on a bound: no density there, so the estimate reads the other rows
        data = Dataset(obs, act, zeros, obs, zeros.astype(bool), zeros.astype(bool))
        before = torch.get_rng_state()
        found.append(behaviour_entropy(data, steps=4000))
        assert torch.equal(torch.get_rng_state(), before)
        log_p = _squashed_log_prob(torch.as_tensor(u), torch.as_tensor(mu), torch.as_tensor(np.log(std)).expand(n, 2))
        truth.append(-log_p[400:].mean().item())
    assert found == pytest.approx(truth, abs=0.1)
    assert found[1] - found[0] == pytest.approx(2 * np.log(3), abs=0.2)


@pytest.mark.parametrize("bc_weight, expected", [(0.0, 0.5), (10.0, -0.5)])
def test_behaviour_term_holds_the_actor_at_the_data(bc_weight, expected):
    """The reward's optimum is a = 0.5, the data's action is -0.5: a strong behaviour term wins, none lets Q win."""
    torch.manual_seed(0)
    sac = SAC(1, 1, SACConfig(hidden=(64, 64), batch_size=128, actor_lr=1e-3, critic_lr=1e-3, bc_weight=bc_weight))
    data_act = torch.full((128, 1), -0.5)
    for _ in range(1500):
        s = torch.rand(128, 1) * 2 - 1
        a = torch.rand(128, 1) * 2 - 1
        r = -(a[:, 0] - 0.5).pow(2) * 10
        metrics = sac.update(s, a, r, s, torch.ones(128), real=(s, data_act), n_real=64)
    with torch.no_grad():
        act = sac.actor.act(torch.linspace(-1, 1, 11)[:, None], deterministic=True)
    assert (act - expected).abs().max().item() < 0.15
    assert {"sac/q_data", "sac/q_model"} <= set(metrics)
    assert ("sac/bc_mse" in metrics) == (bc_weight > 0)


def _trained_against_data(mode: str, data_actions) -> tuple[SAC, dict]:
    """A 1-D SAC whose reward peaks at a = 0.5, with a strong behaviour term of the given form toward
    `data_actions(n)`."""
    torch.manual_seed(0)
    sac = SAC(1, 1, SACConfig(hidden=(64, 64), batch_size=128, actor_lr=1e-3, critic_lr=1e-3, bc_weight=10.0,
                              bc_action=mode))
    for _ in range(800):
        s, a = torch.rand(128, 1) * 2 - 1, torch.rand(128, 1) * 2 - 1
        r = -(a[:, 0] - 0.5).pow(2) * 10
        metrics = sac.update(s, a, r, s, torch.ones(128), real=(s, data_actions(128)), n_real=64)
    return sac, metrics


def test_behaviour_term_on_samples_also_holds_the_spread():
    """Data with one action: a term on the policy's samples narrows them around it; one on the mean does not."""
    spread = {}
    for mode in ("mean", "sample"):
        sac, _ = _trained_against_data(mode, lambda n: torch.full((n, 1), -0.5))
        with torch.no_grad():
            samples = sac.actor.act(torch.zeros(4096, 1))
            assert (sac.actor.act(torch.zeros(1, 1), deterministic=True) + 0.5).abs().item() < 0.15, mode
        spread[mode] = (samples + 0.5).pow(2).mean().sqrt().item()  # how far samples fall from the data's action
    assert spread["sample"] < 0.5 * spread["mean"], spread


def test_behaviour_term_on_the_likelihood_spreads_the_policy_over_the_data():
    """Data actions spread around -0.5, the reward's optimum at 0.5: the likelihood term keeps the policy's density
    high at the data's actions, where the mean term leaves the spread to the entropy bonus and the sample term
    narrows it; the density at the data is what a ratio pi/beta on the data reads (bench/QUALITY.md E3)."""
    def data_actions(n: int) -> torch.Tensor:
        return torch.tanh(-0.55 + 0.6 * torch.randn(n, 1))

    data_nll = {}
    for mode in ("mean", "sample", "likelihood"):
        sac, metrics = _trained_against_data(mode, data_actions)
        assert ("sac/bc_nll" in metrics) == (mode == "likelihood")
        with torch.no_grad():
            data_nll[mode] = -sac.actor.log_prob(torch.rand(4096, 1) * 2 - 1, data_actions(4096)).mean().item()
    assert data_nll["likelihood"] < min(data_nll["mean"], data_nll["sample"]) - 0.5, data_nll


def test_likelihood_term_is_per_dimension_and_finite_at_saturated_actions():
    """Collected SAC data holds actions of exactly +-1 (float32 tanh rounds there): the term reads them just inside
    the bound, so the step stays finite, and it is the data's mean negative log-likelihood per action dimension."""
    torch.manual_seed(0)
    sac = SAC(4, 3, SACConfig(hidden=(32, 32), batch_size=64, bc_weight=0.4, bc_action="likelihood"))
    obs, act = torch.randn(64, 4), torch.rand(64, 3) * 2 - 1
    act[:8] = torch.sign(act[:8])
    with torch.no_grad():
        expected = -sac.actor.log_prob(obs, act).mean().item() / 3
    metrics = sac.update(obs, act, torch.zeros(64), obs, torch.zeros(64), real=(obs, act))
    assert metrics["sac/bc_nll"].item() == pytest.approx(expected, rel=1e-5)
    assert all(torch.isfinite(p.grad).all() and torch.isfinite(p).all() for p in sac.actor.parameters())


def test_critic_layer_norm_bounds_extrapolation():
    """With layer norm every hidden row has unit scale, so Q stays within a bound set by the output layer however far
    the input lies from the data; a plain ReLU critic's Q grows with the input's scale."""
    torch.manual_seed(0)
    obs, act = torch.randn(256, 3), torch.rand(256, 2) * 2 - 1
    growth = {}
    for layer_norm in (False, True):
        critic = SAC(3, 2, SACConfig(hidden=(64, 64), critic_layer_norm=layer_norm)).critic
        with torch.no_grad():
            growth[layer_norm] = (critic(obs * 1e4, act).abs().max() / critic(obs, act).abs().max()).item()
    assert growth[False] > 100
    assert growth[True] < 10


def test_cosine_schedule_takes_only_the_actor_lr_to_zero():
    """The actor's rate follows lr * (1 + cos(pi * progress)) / 2 and the critics' and temperature's stay; with the
    constant schedule (the paper's) nothing changes."""
    rates = {}
    for schedule in ("constant", "cosine"):
        sac = SAC(3, 2, SACConfig(hidden=(16, 16), actor_lr=4e-4, actor_lr_schedule=schedule))
        for progress in (0.0, 0.5, 0.9):
            sac.anneal(progress)
            rates[schedule, progress] = [g["lr"] for o in (sac.actor_optim, sac.critic_optim, sac.alpha_optim)
                                         for g in o.param_groups]
    assert {tuple(r) for (schedule, _), r in rates.items() if schedule == "constant"} == {(4e-4, 3e-4, 3e-4)}
    for progress, actor in ((0.0, 4e-4), (0.5, 2e-4), (0.9, 4e-4 * (1 - 0.9511) / 2)):
        assert rates["cosine", progress] == pytest.approx([actor, 3e-4, 3e-4], rel=1e-3)


def _one_update(value_bound: bool, runaway: bool, terminal: int = 0) -> tuple[SAC, dict]:
    """One update on 64 random rows, the first `terminal` of them terminal."""
    torch.manual_seed(0)
    sac = SAC(3, 2, SACConfig(hidden=(16, 16), value_bound=value_bound))
    sac.set_reward_bound(1.0)
    if runaway:
        with torch.no_grad():
            list(sac.critic_target.parameters())[-1].fill_(1e4)  # the output bias of both target critics
    n = 64
    gen = torch.Generator().manual_seed(1)
    obs, next_obs = torch.randn(n, 3, generator=gen), torch.randn(n, 3, generator=gen)
    act = torch.rand(n, 2, generator=gen) * 2 - 1
    return sac, sac.update(obs, act, torch.zeros(n), next_obs, (torch.arange(n) < terminal).float())


def test_value_bound_clips_only_a_runaway_bootstrap():
    """A target critic whose values ran away (1e4) teaches the critics those values unless the bound caps the
    bootstrapped Q at the largest soft Q rewards of at most 1 allow, (1 + gamma alpha |A| log 2) / (1 - gamma), 237.2
    at alpha 1; a target critic within the bound is left exactly as it is. Terminal rows bootstrap nothing, so the
    clipped share leaves them out."""
    ceiling = (1.0 + 0.99 * 2 * np.log(2.0)) / (1 - 0.99)
    sac, bounded = _one_update(True, runaway=True)
    assert float(sac.value_ceiling(torch.tensor(1.0))) == pytest.approx(ceiling)
    assert float(bounded["sac/target_clipped"]) == 1.0
    assert float(bounded["sac/critic_loss"]) < 2 * (ceiling + 10) ** 2
    assert float(_one_update(True, runaway=True, terminal=16)[1]["sac/target_clipped"]) == 0.75
    _, plain = _one_update(False, runaway=True)
    assert "sac/target_clipped" not in plain and float(plain["sac/critic_loss"]) > 1e7

    _, within = _one_update(True, runaway=False)
    _, unbounded = _one_update(False, runaway=False)
    assert float(within["sac/target_clipped"]) == 0.0
    assert float(within["sac/critic_loss"]) == float(unbounded["sac/critic_loss"])


def test_value_ceiling_is_never_below_a_terminal_reward():
    """With rewards all below -alpha |A| log 2, the bootstrapped bound falls below the largest reward, which a terminal
    step earns alone: the ceiling is then that reward."""
    sac = SAC(3, 2, SACConfig(value_bound=True))
    sac.set_reward_bound(-5.0)
    assert float(sac.value_ceiling(torch.tensor(0.1))) == -5.0
    sac.set_reward_bound(5.0)
    assert float(sac.value_ceiling(torch.tensor(0.1))) == pytest.approx((5.0 + 0.099 * 2 * np.log(2.0)) / 0.01)


def test_averaged_actor_is_the_running_mean_then_an_exponential_one():
    """The n-th iterate enters with weight max(actor_average, 1/n): the mean of the first four, then weight 1/4; the
    input standardisation is the live actor's, not averaged; with 1 the policy is the live actor."""
    plain = SAC(3, 2, SACConfig(hidden=(16, 16)))
    assert plain.policy is plain.actor and plain.actor_average is None
    torch.manual_seed(0)
    sac = SAC(3, 2, SACConfig(hidden=(16, 16), actor_average=0.25))
    sac.actor.norm.set(np.full(3, 2.0), np.full(3, 3.0))  # the live actor's alone: the update copies it
    gen = torch.Generator().manual_seed(1)
    expected = None
    for n in range(1, 8):
        obs, next_obs = torch.randn(32, 3, generator=gen), torch.randn(32, 3, generator=gen)
        sac.update(obs, torch.rand(32, 2, generator=gen) * 2 - 1, torch.randn(32, generator=gen), next_obs,
                   torch.zeros(32))
        live = [p.detach().clone() for p in sac.actor.parameters()]
        weight = max(0.25, 1 / n)
        expected = live if expected is None else [e + weight * (x - e) for e, x in zip(expected, live)]
    for averaged, want, live_p in zip(sac.policy.parameters(), expected, sac.actor.parameters()):
        torch.testing.assert_close(averaged, want)
        assert not torch.equal(averaged, live_p)
    assert sac.policy is not sac.actor and not any(p.requires_grad for p in sac.policy.parameters())
    torch.testing.assert_close(sac.policy.norm.mean, torch.full((3,), 2.0))
    torch.testing.assert_close(sac.policy.norm.std, torch.full((3,), 3.0))
