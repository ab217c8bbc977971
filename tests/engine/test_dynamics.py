"""The ensemble must learn a known linear-Gaussian system: means, variances, and elite choice."""
import numpy as np
import torch

from drop_engine.config import DynamicsConfig
from drop_engine.data import Dataset
from drop_engine.dynamics import GaussianEnsemble, build_ensemble, train_dynamics


def _linear_system(n, rng, obs_dim=3, act_dim=2, noise=0.1):
    A = np.array([[0.9, 0.1, 0.0], [0.0, 0.8, -0.2], [0.1, 0.0, 0.7]])
    B = np.array([[0.5, 0.0], [0.0, 0.3], [0.2, -0.4]])
    w = np.array([1.0, -0.5, 0.25])
    obs = rng.normal(size=(n, obs_dim)).astype(np.float32)
    act = rng.uniform(-1, 1, size=(n, act_dim)).astype(np.float32)
    delta = obs @ (A - np.eye(obs_dim)).T + act @ B.T
    next_obs = obs + delta + noise * rng.normal(size=delta.shape)
    rew = obs @ w + noise * rng.normal(size=n)
    data = Dataset(obs, act, rew.astype(np.float32), next_obs.astype(np.float32), np.zeros(n, bool), np.zeros(n, bool))
    mean = np.concatenate([(obs @ w)[:, None], delta], 1)
    return data, mean, noise


def test_ensemble_learns_linear_gaussian_system():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    data, _, noise = _linear_system(4000, rng)
    cfg = DynamicsConfig(members=4, elites=2, hidden=64, layers=2, max_epochs=60, batch_size=128)
    model = GaussianEnsemble(3, 2, cfg)
    report = train_dynamics(model, data, cfg, rng, torch.device("cpu"))

    test, truth, _ = _linear_system(2000, np.random.default_rng(1))
    with torch.no_grad():
        mean, logvar = model(torch.as_tensor(test.observations), torch.as_tensor(test.actions))
    mean_err = (mean - torch.as_tensor(truth, dtype=torch.float32)).abs().mean().item()
    std = logvar.exp().sqrt().mean().item()
    assert mean_err < 0.05, mean_err  # the noise std is 0.1: the means are well inside it
    assert abs(std - noise) < 0.03, std

    # Elites are the members with the lowest holdout MSE.
    order = np.argsort(report.holdout_mse)
    assert sorted(report.elites) == sorted(order[: cfg.elites].tolist())
    assert model.elites.tolist() == sorted(report.elites)


def test_early_stopping_restores_best_snapshot():
    torch.manual_seed(0)
    rng = np.random.default_rng(2)
    data, _, _ = _linear_system(600, rng)
    cfg = DynamicsConfig(members=3, elites=2, hidden=32, layers=2, patience=2, max_epochs=500)
    model = GaussianEnsemble(3, 2, cfg)
    report = train_dynamics(model, data, cfg, rng, torch.device("cpu"))
    assert report.stopped_by == "patience"
    assert report.epochs < 500


def test_initial_ensemble_depends_on_its_seed_only():
    """What a cached model is keyed by; and building it leaves the run's torch stream alone."""
    cfg = DynamicsConfig(members=2, elites=1, hidden=8, layers=1)
    models = []
    for global_seed in (1, 2):
        torch.manual_seed(global_seed)
        before = torch.get_rng_state()
        models.append(build_ensemble(3, 2, cfg, 5, torch.device("cpu")))
        assert torch.equal(torch.get_rng_state(), before)
    for (name, a), b in zip(models[0].state_dict().items(), models[1].state_dict().values()):
        assert torch.equal(a, b), name
    other = build_ensemble(3, 2, cfg, 6, torch.device("cpu"))
    assert not torch.equal(other.body[0].weight, models[0].body[0].weight)
