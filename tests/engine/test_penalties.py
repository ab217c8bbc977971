"""The penalty functions' values: DROP's g(tau) in each form, with and without the bonus, and MOPO's u(s, a)."""
import math

import pytest
import torch

from drop_engine.config import PenaltyConfig
from drop_engine.penalties import penalized_reward, ratio_penalty, uncertainty_penalty

TAU = torch.tensor([-1.0, 0.001, 0.5, 1.0, 2.0, 100.0])


@pytest.mark.parametrize("g, clip, expected", [
    ("log", (0.01, 10.0), [math.log(0.01), math.log(0.01), math.log(0.5), 0.0, math.log(2.0), math.log(10.0)]),
    ("log", None, [math.log(2e-8), math.log(0.001 + 1e-8), math.log(0.5), 0.0, math.log(2.0), math.log(100.0)]),
    ("tanh", None, [math.tanh(t - 1) for t in TAU.tolist()]),
    ("tanh_shift", None, [math.tanh(t) - math.tanh(1) for t in TAU.tolist()]),
])
def test_ratio_penalty_values(g, clip, expected):
    with_bonus = ratio_penalty(TAU, PenaltyConfig(g=g, clip=clip, bonus=True))
    assert with_bonus.tolist() == pytest.approx(expected, abs=1e-6)
    # Without the bonus a ratio below 1 is never rewarded, and the penalty above 1 is unchanged.
    no_bonus = ratio_penalty(TAU, PenaltyConfig(g=g, clip=clip, bonus=False))
    assert no_bonus.tolist() == pytest.approx([max(v, 0.0) for v in expected], abs=1e-6)


def test_uncertainty_penalty_is_the_largest_std_norm_over_members():
    std = torch.tensor([[[1.0, 0.0], [3.0, 4.0]], [[0.0, 2.0], [1.0, 1.0]]])  # (members, N, D)
    u = uncertainty_penalty(2 * std.log())
    assert u.tolist() == pytest.approx([2.0, 5.0])


def test_penalized_reward_per_algorithm():
    reward, tau = torch.tensor([1.0, 1.0]), torch.tensor([4.0, 0.5])
    logvar = torch.zeros(3, 2, 4)  # std 1 in 4 dims: u = 2
    cfg = PenaltyConfig(eta=2.0, g="log", clip=(0.01, 10.0), bonus=False, mopo_lambda=0.5)
    r, pen = penalized_reward("drop", reward, cfg, tau, None)
    assert pen.tolist() == pytest.approx([2 * math.log(4.0), 0.0])
    assert r.tolist() == pytest.approx((reward - pen).tolist())
    r, pen = penalized_reward("mopo", reward, cfg, None, logvar)
    assert pen.tolist() == pytest.approx([1.0, 1.0]) and r.tolist() == pytest.approx([0.0, 0.0])
    r, pen = penalized_reward("mbpo", reward, cfg, None, None)
    assert pen.tolist() == [0.0, 0.0] and r.tolist() == [1.0, 1.0]
