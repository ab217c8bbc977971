"""GradientDICE must recover the exact discounted occupancy ratio of a small tabular MDP."""
import numpy as np
import torch

from drop_engine.config import DiceConfig
from drop_engine.dice import GradientDice


def _occupancy(P, mu0, policy, gamma):
    """d(s, a) = (1 - gamma) (I - gamma P_pi^T)^-1 p0, solved exactly."""
    S, A = policy.shape
    P_pi = np.einsum("sat,tb->satb", P, policy).reshape(S * A, S * A)
    p0 = (mu0[:, None] * policy).reshape(S * A)
    return (1 - gamma) * np.linalg.solve(np.eye(S * A) - gamma * P_pi.T, p0)


def test_gradient_dice_recovers_tabular_ratio():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    S, A, gamma = 5, 2, 0.9
    X = S * A
    P = rng.dirichlet(np.ones(S), size=(S, A))
    mu0 = rng.dirichlet(np.ones(S))
    behaviour = rng.dirichlet(np.ones(A), size=S)
    target = rng.dirichlet(np.ones(A) * 0.5, size=S)
    d_data = 0.5 * _occupancy(P, mu0, behaviour, gamma) + 0.5 / X  # full support
    ratio = _occupancy(P, mu0, target, gamma) / d_data
    assert ratio.max() / ratio.min() > 5  # a ratio far from uniform, so the test can fail

    n = 50_000
    x = rng.choice(X, size=n, p=d_data)
    s_next = (P[x // A, x % A].cumsum(1) > rng.random((n, 1))).argmax(1)
    a_next = (target[s_next].cumsum(1) > rng.random((n, 1))).argmax(1)
    s0 = rng.choice(S, size=n, p=mu0)
    a0 = (target[s0].cumsum(1) > rng.random((n, 1))).argmax(1)
    onehot = torch.eye(X)
    feats, feats_next, feats0 = onehot[x], onehot[s_next * A + a_next], onehot[s0 * A + a0]
    none = torch.zeros(256, 0)

    dice = GradientDice(1, X, 0, DiceConfig(hidden=(), lr=3e-3, lam=1.0), gamma)
    gen = torch.Generator().manual_seed(0)
    for step in range(6000):
        if step == 3000:  # a smaller step size shrinks the noise of the final stochastic iterate
            for group in [*dice.tau_optim.param_groups, *dice.f_optim.param_groups]:
                group["lr"] = 3e-4
        i = torch.randint(0, n, (256,), generator=gen)
        dice.update(feats[i], none, feats_next[i][None], none[None], feats0[i], none, torch.ones(256))
    estimate = dice.tau(onehot, torch.zeros(X, 0)).detach().numpy()[0]
    weighted_rel_error = (d_data * np.abs(estimate - ratio)).sum() / (d_data * ratio).sum()
    assert weighted_rel_error < 0.10, (estimate.round(2), ratio.round(2))


def test_members_are_independent():
    """Each member trains on its own next states: changing member 1's inputs leaves member 0's update unchanged."""
    torch.manual_seed(1)
    cfg = DiceConfig(hidden=(8,), lr=1e-3)
    a = GradientDice(2, 3, 1, cfg, 0.99)
    b = GradientDice(2, 3, 1, cfg, 0.99)
    b.load_state_dict(a.state_dict())
    obs, act = torch.randn(16, 3), torch.randn(16, 1)
    nxt, nact = torch.randn(2, 16, 3), torch.randn(2, 16, 1)
    nxt_b = nxt.clone()
    nxt_b[1] += 5.0
    for d, n in ((a, nxt), (b, nxt_b)):
        d.update(obs, act, n, nact, obs, act, torch.ones(2, 16))
    ta, tb = a.tau(obs, act), b.tau(obs, act)
    assert torch.allclose(ta[0], tb[0])
    assert not torch.allclose(ta[1], tb[1])
