"""Termination functions must agree with the real gymnasium envs; scores follow D4RL's normalisation."""
import logging
from typing import get_args

import numpy as np
import pytest
import torch

from drop_engine import envs
from drop_engine.collect import collect_transitions, random_policy
from drop_engine.envs import ENVS, EnvName, get_env, make_env


@pytest.mark.parametrize("env", ["hopper", "walker2d", "halfcheetah"])
@pytest.mark.parametrize("version", ["v4", "v5"])
def test_termination_matches_env(env, version):
    spec = get_env(env)
    arrays = collect_transitions(env, random_policy(spec.act_dim, seed=1), 3000, seed=1, version=version)
    predicted = spec.termination(*(torch.as_tensor(arrays[k])
                                   for k in ("observations", "actions", "next_observations")))
    assert np.array_equal(predicted.numpy(), arrays["terminals"])
    if env != "halfcheetah":  # a random policy falls often, so both outcomes are exercised
        assert arrays["terminals"].sum() > 20


def test_hopper_termination_edge_cases():
    done = get_env("hopper").termination
    ok = torch.tensor([1.2, 0.0] + [0.0] * 9)
    cases = {
        "healthy": (ok, False),
        "low": (torch.tensor([0.7, 0.0] + [0.0] * 9), True),
        "tilted": (torch.tensor([1.2, 0.2] + [0.0] * 9), True),
        "fast": (torch.tensor([1.2, 0.0] + [0.0] * 8 + [100.0]), True),
        "nan": (torch.tensor([1.2, float("nan")] + [0.0] * 9), True),
    }
    for name, (obs, expected) in cases.items():
        assert bool(done(ok, torch.zeros(3), obs)) is expected, name


def test_normalized_score_endpoints():
    for spec in ENVS.values():
        assert spec.normalized_score(spec.random_score) == pytest.approx(0.0)
        assert spec.normalized_score(spec.expert_score) == pytest.approx(100.0)
    assert get_env("Hopper-v5").gym_id("v5") == "Hopper-v5"
    with pytest.raises(KeyError):
        get_env("ant")


@pytest.mark.parametrize("env", ["hopper", "walker2d", "halfcheetah"])
def test_true_step_reproduces_recorded_transitions(env):
    from drop_engine.true_dynamics import true_step

    spec = get_env(env)
    arrays = collect_transitions(env, random_policy(spec.act_dim, seed=2), 300, seed=2)
    rew, nxt = true_step(env, arrays["observations"], arrays["actions"], arrays["infos/qpos"], arrays["infos/qvel"])
    np.testing.assert_allclose(nxt, arrays["next_observations"], atol=1e-5)
    np.testing.assert_allclose(rew, arrays["rewards"], atol=1e-5)
    # From the observation alone (x position unknown, velocities as observed) the next state is the same
    # wherever the observation did not clip a velocity.
    _, from_obs = true_step(env, arrays["observations"], arrays["actions"])
    unclipped = np.abs(arrays["infos/qvel"]).max(1) < 10
    np.testing.assert_allclose(from_obs[unclipped], arrays["next_observations"][unclipped], atol=1e-4)


def test_every_env_name_has_its_spec():
    """The API offers exactly the names of `EnvName` (its schema's enum): each must be a known env."""
    assert sorted(ENVS) == sorted(get_args(EnvName)) and all(name == spec.name for name, spec in ENVS.items())


def test_mujoco_warnings_are_logged_once_and_write_no_file(tmp_path, monkeypatch, caplog):
    """gymnasium's half_cheetah.xml trips a MuJoCo deprecation warning on every compile; by default MuJoCo appends it
    to MUJOCO_LOG.TXT in the working directory, a file that grows with every evaluation a worker runs."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(envs, "_warned", set())
    with caplog.at_level(logging.WARNING, logger="drop.mujoco"):
        for _ in range(3):
            make_env("halfcheetah").close()
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    texts = [r.getMessage() for r in caplog.records if r.name == "drop.mujoco"]
    assert len(texts) == 1 and "settotalmass" in texts[0]
