"""Smoke runs of all three algorithms, exact stop-and-resume from a stop in any phase, and exported last and best
policies that need only torch."""
import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from drop_engine import trainer as trainer_module
from drop_engine.checkpoint import checkpoint_name, list_checkpoints, load_latest
from drop_engine.config import build_config
from drop_engine.data import from_arrays
from drop_engine.dynamics import train_dynamics
from drop_engine.evaluation import Evaluation, evaluate
from drop_engine.export import load_policy
from drop_engine.rollout import model_rollout
from drop_engine.trainer import Trainer, train

from .recorder import Recorder


def _untimed(recorder):
    return [(step, {k: v for k, v in m.items() if not k.startswith("time/")}) for step, m in recorder.metrics]


def _config(algorithm, **overrides):
    return build_config(algorithm, env="hopper", preset="smoke", task="medium", overrides=overrides)


@pytest.mark.parametrize("algorithm", ["drop", "mopo", "mbpo"])
def test_smoke_run_writes_checkpoints_metrics_and_policy(tmp_path, hopper_dataset, algorithm):
    rec = Recorder()
    result = train(hopper_dataset, _config(algorithm), tmp_path, rec)
    assert result.status == "completed" and result.epochs == 2
    assert list_checkpoints(tmp_path / "checkpoints") and all(p.exists() for p in rec.checkpoints[-1:])
    names = {name for _, m in rec.metrics for name in m}
    expected = {"sac/critic_loss", "sac/actor_loss", "sac/alpha", "sac/q_mean", "rollout/penalty_mean",
                "rollout/model_buffer_size", "dynamics/holdout_mse", "time/sac", "time/rollout", "time/epochs",
                "sac/q_data", "sac/q_model", "diag/uncertainty_data", "diag/uncertainty_model", "diag/reward_data",
                "diag/reward_model", "rollout/penalty_share"}
    if algorithm == "drop":
        expected |= {"dice/objective", "dice/tau_mean", "dice/tau_min", "dice/tau_max", "time/dice",
                     "dice/tau_data_mean", "dice/tau_data_std"}
    assert expected <= names
    penalties = [m["rollout/penalty_mean"] for _, m in rec.metrics if "rollout/penalty_mean" in m]
    assert (all(p == 0 for p in penalties)) is (algorithm == "mbpo")
    assert [e[0] for e in rec.evaluations] == [1, 2]
    assert {"dynamics", "train", "export"} <= rec.phases

    for which in ("last", "best"):
        meta = json.loads((tmp_path / "policy" / which / "metadata.json").read_text())
        assert meta["algorithm"] == algorithm and meta["obs_dim"] == 11 and meta["which"] == which
        state = torch.load(result.policy[which]["state_dict"])
        assert any(k.startswith("norm.") for k in state)
    # Both TorchScript policies load with drop_engine made unimportable, and map a batch to bounded actions.
    paths = [result.policy[which]["torchscript"] for which in ("last", "best")]
    script = (
        "import sys, torch; sys.modules['drop_engine'] = None\n"
        f"for path in {paths!r}:\n"
        "    a = torch.jit.load(path)(torch.randn(5, 11)); assert a.shape == (5, 3) and a.abs().max() <= 1\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr


@pytest.mark.parametrize("recorded, override, version", [
    ("Hopper-v5", None, "v5"),  # as Minari's MuJoCo datasets record it
    ("Hopper-v5", "v4", "v4"),  # the config's choice wins
    ("Hopper-v4", None, "v4"),
    (None, "v5", "v5"),
    (None, None, "v4"),  # no record: D4RL's dynamics
    ("hopper-medium-v2", None, "v4"),  # a version no drop-rl env has
])
def test_evaluations_run_in_the_env_version_the_dataset_records(tmp_path, hopper_arrays, monkeypatch, recorded,
                                                                 override, version):
    asked = []
    monkeypatch.setattr(trainer_module, "evaluate", lambda *a, version, **k: asked.append(version) or Evaluation(
        0.0, 0.0, 0.0, [0.0], [1]))
    data = from_arrays(hopper_arrays, {"env_name": recorded} if recorded else {}, env="hopper")
    trainer = Trainer(data, _config("mbpo", **({"env_version": override} if override else {})), tmp_path)
    trainer.evaluate_now(0)
    assert asked == [version]


def test_best_policy_is_the_actor_of_the_best_evaluation(tmp_path, hopper_dataset, monkeypatch):
    """Scores scripted over real evaluations: a peak mid-run, tied once later, then a drop."""
    scripted = iter([3.0, 7.0, 7.0, 1.0])
    real = trainer_module.evaluate
    monkeypatch.setattr(trainer_module, "evaluate",
                        lambda *a, **k: dataclasses.replace(real(*a, **k), normalized_score=next(scripted)))
    cfg = _config("mopo", epochs=4, keep_checkpoints=10)
    result = train(hopper_dataset, cfg, tmp_path / "run", Recorder())

    scores = [e["normalized_score"] for e in result.evaluations]
    argmax = result.evaluations[scores.index(max(scores))]["epoch"]  # index: the first of ties
    assert argmax == result.best_epoch == 2
    assert (result.last_score, result.best_score, result.final_score) == (1.0, 7.0, 5.0)
    meta = {w: json.loads(Path(result.policy[w]["metadata"]).read_text()) for w in ("last", "best")}
    assert (meta["best"]["which"], meta["best"]["epoch"], meta["best"]["normalized_score"]) == ("best", 2, 7.0)
    selected_by = meta["best"]["selected_by"]
    assert "2 deterministic episodes" in selected_by and "an online choice" in selected_by
    assert (meta["last"]["which"], meta["last"]["epoch"], meta["last"]["normalized_score"]) == ("last", 4, 1.0)
    assert meta["best"]["dataset"] == meta["last"]["dataset"] == {"content_hash": hopper_dataset.content_hash,
                                                                  "transitions": len(hopper_dataset)}

    # Each exported policy acts as the actor did at its epoch, as that epoch's checkpoint recorded it.
    probe = Trainer(hopper_dataset, cfg, tmp_path / "probe")
    obs = torch.as_tensor(hopper_dataset.observations[:64])
    actions = {}
    for which, epoch in (("best", 2), ("last", 4)):
        checkpoint = tmp_path / "run" / "checkpoints" / checkpoint_name(epoch, 0)
        probe.load_state_dict(torch.load(checkpoint, weights_only=False))
        with torch.no_grad():
            expected = probe.sac.actor.act(obs, deterministic=True).numpy()
        actions[which] = load_policy(result.policy[which]["torchscript"])(obs.numpy())
        torch.testing.assert_close(torch.as_tensor(actions[which]), torch.as_tensor(expected), atol=1e-6, rtol=0)
    assert not torch.allclose(torch.as_tensor(actions["best"]), torch.as_tensor(actions["last"]))


def test_an_averaged_actor_changes_what_is_evaluated_and_exported_not_the_training(tmp_path, hopper_dataset):
    """The same run with and without `sac.actor_average`: the live actor ends with the same weights and its
    evaluations, recorded as `live_*`, are the plain run's; the scores and both exported policies are the average's."""
    plain = Trainer(hopper_dataset, _config("mopo", epochs=3), tmp_path / "plain")
    plain_result = plain.run()  # before the next Trainer: each seeds the process's RNGs
    averaged = Trainer(hopper_dataset, _config("mopo", epochs=3, keep_checkpoints=10, sac={"actor_average": 0.02}),
                       tmp_path / "averaged")
    result = averaged.run()

    assert [e["live_normalized_score"] for e in result.evaluations] == [
        e["normalized_score"] for e in plain_result.evaluations]
    assert [e["live_return"] for e in result.evaluations] == [e["return"] for e in plain_result.evaluations]
    for a, b in zip(averaged.sac.actor.parameters(), plain.sac.actor.parameters()):
        assert torch.equal(a, b)
    assert all("live_normalized_score" not in e for e in plain_result.evaluations)
    assert [e["normalized_score"] for e in result.evaluations] != [
        e["normalized_score"] for e in plain_result.evaluations]
    assert [e["live_return_std"] for e in result.evaluations] == [e["return_std"] for e in plain_result.evaluations]
    obs = torch.as_tensor(hopper_dataset.observations[:64])
    with torch.no_grad():
        expected = averaged.sac.policy.act(obs, deterministic=True)
        live = averaged.sac.actor.act(obs, deterministic=True)
    exported = torch.as_tensor(load_policy(result.policy["last"]["torchscript"])(obs.numpy()))
    torch.testing.assert_close(exported, expected, atol=1e-6, rtol=0)
    assert not torch.allclose(exported, live, atol=1e-3)
    # The best policy is the average as its epoch's checkpoint recorded it.
    best = torch.load(result.policy["best"]["state_dict"])
    checkpoint = tmp_path / "averaged" / "checkpoints" / checkpoint_name(result.best_epoch, 0)
    state = torch.load(checkpoint, weights_only=False)
    recorded = {k.removeprefix("actor_average.module."): v for k, v in state["sac"].items()
                if k.startswith("actor_average.module.")}
    assert best.keys() == recorded.keys() and all(torch.equal(best[k], v) for k, v in recorded.items())


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory, hopper_dataset) -> tuple[Trainer, Recorder]:
    whole = Recorder()
    # Averaged DICE estimator and actor too: their averages (and the actor's count) are state a resumed run must
    # restore, or its penalties and scores differ; and the annealed actor rate, which it must set as this run did.
    cfg = _config("drop", epochs=3, dice={"average": 0.5}, sac={"actor_lr_schedule": "cosine", "actor_average": 0.1})
    trainer = Trainer(hopper_dataset, cfg, tmp_path_factory.mktemp("whole"), whole)
    trainer.run()
    return trainer, whole


def test_an_averaged_estimator_reports_what_the_penalty_reads(uninterrupted):
    _, whole = uninterrupted
    averaged = [m["dice/tau_avg_data_mean"] for _, m in whole.metrics if "dice/tau_avg_data_mean" in m]
    latest = [m["dice/tau_data_mean"] for _, m in whole.metrics if "dice/tau_data_mean" in m]
    assert averaged and len(averaged) == len(latest) and all(a > 0 for a in averaged)


def test_the_actor_rate_is_annealed_by_epoch(uninterrupted):
    """The last epoch (2 of 3) trained at the half-cosine's rate for 2/3 of the run."""
    a, _ = uninterrupted
    expected = a.cfg.sac.actor_lr * 0.5 * (1 + math.cos(math.pi * 2 / 3))
    assert a.sac.actor_optim.param_groups[0]["lr"] == pytest.approx(expected)


@pytest.mark.parametrize("phase", ["sac", "dice", "rollout", "evaluate"])
def test_stop_and_resume_equals_uninterrupted(tmp_path, hopper_dataset, uninterrupted, phase):
    """Stopped mid-way through a phase, then resumed: the same numbers as a run never stopped. A stop inside the
    epoch's DICE training or rollouts checkpoints the epoch's start; one inside an evaluation, the end of the SAC steps
    before it."""
    a, whole = uninterrupted
    cfg = a.cfg
    fn = {"sac": Trainer._sac_steps, "dice": Trainer.train_dice, "rollout": model_rollout, "evaluate": evaluate}[phase]
    # sac: mid-way through epoch 2's SAC steps; the others: mid-way through all the asks the phase made in the run
    after = 35 if phase == "sac" else whole.asked_in(fn) // 2
    first = Recorder(stop_in=fn, after=after)
    b1 = Trainer(hopper_dataset, cfg, tmp_path / "b", first)
    stopped = b1.run()
    assert stopped.status == "stopped" and first.asked_in(fn) == after + 1  # it stopped inside the phase
    assert stopped.checkpoint == str(list_checkpoints(tmp_path / "b" / "checkpoints")[-1])
    if phase == "sac":
        assert b1.epoch == 1 and 0 < b1.step_in_epoch < cfg.steps_per_epoch
    else:
        assert (b1.epoch_started, b1.step_in_epoch) == {
            "dice": (False, 0), "rollout": (False, 0), "evaluate": (True, cfg.steps_per_epoch)}[phase]
    assert b1.evaluations == a.evaluations[: len(b1.evaluations)]
    assert first.progress[0] == b1.epoch, "the progress reported last is no further than where the run stopped"
    # The position and the best actor so far are in the checkpoint, so a resumed run can still export that actor.
    probe = Trainer(hopper_dataset, cfg, tmp_path / "probe")
    probe.load_state_dict(load_latest(tmp_path / "b" / "checkpoints"))
    assert (probe.epoch, probe.step_in_epoch, probe.epoch_started) == (b1.epoch, b1.step_in_epoch, b1.epoch_started)
    assert (probe.best is None) is (b1.best is None)
    if b1.best is not None:
        assert (probe.best.epoch, probe.best.score) == (b1.best.epoch, b1.best.score)
        for name, pb in b1.best.state.items():
            assert torch.equal(pb, probe.best.state[name]), name
    second = Recorder()
    b2 = Trainer(hopper_dataset, cfg, tmp_path / "b", second)
    result_b = b2.run()

    assert result_b.status == "completed"
    # Each run says where it starts, so a caller can drop what it recorded past that checkpoint, and which ensemble
    # it trains on: the resumed one the ensemble its checkpoint holds.
    assert (whole.starts, first.starts, second.starts) == ([None], [None], [(b1.epoch, b1.step_in_epoch)])
    assert first.dynamics == second.dynamics == [result_b.dynamics] and result_b.dynamics["epochs"] >= 1
    for (name, pa), pb in zip(a.sac.state_dict().items(), b2.sac.state_dict().values()):
        assert torch.equal(pa, pb), name
    for (name, pa), pb in zip(a.dice.state_dict().items(), b2.dice.state_dict().values()):
        assert torch.equal(pa, pb), name
    assert a.evaluations == result_b.evaluations
    assert (a.best.epoch, a.best.score) == (b2.best.epoch, b2.best.score)
    for name, pa in a.best.state.items():
        assert torch.equal(pa, b2.best.state[name]), name
    # One continuous history, nothing repeated (wall-clock timings aside).
    assert _untimed(whole) == _untimed(first) + _untimed(second)


def test_stop_during_dynamics_leaves_no_checkpoint(tmp_path, hopper_dataset):
    recorder = Recorder(stop_in=train_dynamics, after=3)
    result = train(hopper_dataset, _config("mopo"), tmp_path, recorder)
    assert result.status == "stopped" and result.epochs == 0 and result.checkpoint is None
    assert not list_checkpoints(tmp_path / "checkpoints")
    assert result.dynamics is None and recorder.dynamics == [], "a half-fitted ensemble is no run's model"


def test_same_seed_same_numbers(tmp_path, hopper_dataset):
    runs = [train(hopper_dataset, _config("mopo", epochs=1), tmp_path / str(i), Recorder()) for i in range(2)]
    assert runs[0].evaluations == runs[1].evaluations
    other = train(hopper_dataset, _config("mopo", epochs=1).model_copy(update={"seed": 1}), tmp_path / "s1", Recorder())
    assert other.dynamics["holdout_mse"] != runs[0].dynamics["holdout_mse"]


def test_cached_model_gives_the_same_run(tmp_path, hopper_dataset, monkeypatch):
    cfg, cache = _config("drop"), tmp_path / "models"
    first_rec, second_rec = Recorder(), Recorder()
    first = Trainer(hopper_dataset, cfg, tmp_path / "a", first_rec, model_cache=cache)
    result_a = first.run()
    assert result_a.dynamics["from_cache"] is False
    assert result_a.dynamics["cache_path"] == str(cache / f"{result_a.dynamics['cache_key']}.pt")

    def no_training(*args, **kwargs):
        raise AssertionError("a cached model was trained again")

    monkeypatch.setattr("drop_engine.trainer.train_dynamics", no_training)
    second = Trainer(hopper_dataset, cfg, tmp_path / "b", second_rec, model_cache=cache)
    result_b = second.run()
    assert result_b.dynamics == {**result_a.dynamics, "from_cache": True}
    assert not any("dynamics/holdout_mse" in m for _, m in second_rec.metrics)
    summary = [m for _, m in second_rec.metrics if "dynamics/from_cache" in m]
    assert summary == [{"dynamics/elite_holdout_mse": pytest.approx(summary[0]["dynamics/elite_holdout_mse"]),
                        "dynamics/epochs": 3.0, "dynamics/from_cache": 1.0}]
    # The cached ensemble leaves the run's own RNG streams where training it would have: the same numbers.
    assert result_a.evaluations == result_b.evaluations
    rng_a, rng_b = (torch.load(rec.checkpoints[-1], weights_only=False)["rng"] for rec in (first_rec, second_rec))
    assert rng_a["numpy"] == rng_b["numpy"] and rng_a["python"] == rng_b["python"]
    assert torch.equal(rng_a["torch"], rng_b["torch"])
    for (name, pa), pb in zip(first.sac.state_dict().items(), second.sac.state_dict().values()):
        assert torch.equal(pa, pb), name


@pytest.mark.parametrize("change", [{"seed": 1}, {"dynamics": {"patience": 4}}])
def test_other_seed_or_dynamics_config_is_a_miss(tmp_path, hopper_dataset, change):
    cfg, cache = _config("mopo"), tmp_path / "models"
    assert Trainer(hopper_dataset, cfg, tmp_path / "a", model_cache=cache).train_dynamics()
    if "dynamics" in change:
        change = {"dynamics": cfg.dynamics.model_copy(update=change["dynamics"])}
    other = Trainer(hopper_dataset, cfg.model_copy(update=change), tmp_path / "b", model_cache=cache)
    assert other.train_dynamics() and other.dynamics_source["from_cache"] is False
    assert len(list(cache.glob("*.pt"))) == 2


def test_a_checkpoint_of_format_1_still_resumes(tmp_path, hopper_dataset):
    """A run stopped before the best snapshot existed resumes after the upgrade, and its best policy says why it is the
    last one when the best evaluation came before the resume."""
    cfg = _config("mopo", epochs=3)
    stop = Recorder(stop_in=Trainer._sac_steps, after=35)
    assert Trainer(hopper_dataset, cfg, tmp_path, stop).run().status == "stopped"
    path = list_checkpoints(tmp_path / "checkpoints")[-1]
    state = torch.load(path, weights_only=False)
    state["format"] = 1
    del state["best"], state["dynamics_source"]
    torch.save(state, path)
    recorder = Recorder()
    result = Trainer(hopper_dataset, cfg, tmp_path, recorder).run()
    assert result.status == "completed" and len(result.evaluations) == 3
    # Where its ensemble came from was not recorded then: None, with every key a caller reads present.
    assert recorder.dynamics == [result.dynamics] and result.dynamics["epochs"] >= 1
    assert (result.dynamics["cache_key"], result.dynamics["from_cache"], result.dynamics["cache_path"]) == (None,) * 3
    meta = json.loads((tmp_path / "policy" / "best" / "metadata.json").read_text())
    assert meta["epoch"] == result.best_epoch or "not kept" in meta["selected_by"]


def test_target_entropy_from_the_data_is_fitted_once_and_survives_a_stop(tmp_path, hopper_dataset, monkeypatch):
    """A stop inside the fit keeps nothing of it; the resumed run fits, holds the policy at the estimate where that is
    below -|A| (actions close to a function of the state), reports both, and a later resume reads the estimate from
    the checkpoint instead of fitting again."""
    from drop_engine.bc import train_bc
    from drop_engine.data import Dataset

    d = hopper_dataset
    noise = np.random.default_rng(0).normal(0, 0.05, d.actions.shape)
    narrow = np.tanh(2 * d.observations[:, :3] + noise).astype(np.float32)
    data = Dataset(d.observations, narrow, d.rewards, d.next_observations, d.terminals, d.timeouts)
    cfg = _config("mopo", epochs=2, sac={"target_entropy": "data", "behaviour_fit_steps": 300})
    first = Recorder(stop_in=train_bc, after=1)
    stopped = Trainer(data, cfg, tmp_path, first).run()
    assert stopped.status == "stopped" and stopped.checkpoint is not None
    assert load_latest(tmp_path / "checkpoints")["behaviour_entropy"] is None

    second = Recorder(stop_in=Trainer._sac_steps, after=5)
    b = Trainer(data, cfg, tmp_path, second)
    assert b.run().status == "stopped"
    [fitted] = [m for _, m in second.metrics if "sac/behaviour_entropy" in m]
    estimate = fitted["sac/behaviour_entropy"]
    assert b.sac.target_entropy == fitted["sac/target_entropy"] == estimate < -3.0
    assert b.timings["behaviour_fit"] > 0
    assert second.steps["behaviour_fit"] == [(0, 300), (100, 300), (200, 300), (300, 300)], "the fit's progress"

    def no_fit(*args, **kwargs):
        raise AssertionError("the behaviour entropy was estimated again")

    monkeypatch.setattr("drop_engine.trainer.behaviour_entropy", no_fit)
    c = Trainer(data, cfg, tmp_path, Recorder())
    assert c.run().status == "completed"
    assert (c.behaviour_entropy, c.sac.target_entropy) == (estimate, b.sac.target_entropy)


def test_a_data_entropy_above_the_default_target_changes_nothing(tmp_path, hopper_dataset):
    """The smoke file's actions are broad (estimate above -|A|): the run keeps -|A| and, as the fit draws from a forked
    RNG stream, gives the numbers of a run without the option."""
    plain = Trainer(hopper_dataset, _config("drop", epochs=1), tmp_path / "plain")
    a = plain.run()  # before the next Trainer seeds the process's RNG streams again
    fitted = Trainer(hopper_dataset, _config("drop", epochs=1, sac={"target_entropy": "data"}), tmp_path / "data")
    b = fitted.run()
    assert fitted.behaviour_entropy > -3.0 and fitted.sac.target_entropy == plain.sac.target_entropy == -3.0
    assert a.evaluations == b.evaluations
    for (name, pa), pb in zip(plain.sac.state_dict().items(), fitted.sac.state_dict().values()):
        assert torch.equal(pa, pb), name


def test_a_resume_follows_its_own_target_setting(tmp_path, hopper_dataset):
    """A checkpointed estimate sets the target only while the config asks for 'data'; a run that trained at another
    target cannot switch to 'data' part-way, and the error says how to resume it."""
    from drop_engine.errors import ConfigError

    data_cfg = _config("mopo", epochs=2, sac={"target_entropy": "data", "behaviour_fit_steps": 200})
    stop = Recorder(stop_in=Trainer._sac_steps, after=5)
    assert Trainer(hopper_dataset, data_cfg, tmp_path / "a", stop).run().status == "stopped"
    other = data_cfg.model_copy(update={"sac": data_cfg.sac.model_copy(update={"target_entropy": -5.0})})
    resumed = Trainer(hopper_dataset, other, tmp_path / "a")
    resumed.load_state_dict(load_latest(tmp_path / "a" / "checkpoints"))
    assert resumed.behaviour_entropy is not None and resumed.sac.target_entropy == -5.0

    plain = _config("mopo", epochs=2)
    stop = Recorder(stop_in=Trainer._sac_steps, after=5)
    assert Trainer(hopper_dataset, plain, tmp_path / "b", stop).run().status == "stopped"
    with pytest.raises(ConfigError, match="sac.target_entropy=null"):
        Trainer(hopper_dataset, data_cfg, tmp_path / "b").run()


def test_data_with_every_action_on_a_bound_keeps_the_default_target(tmp_path, hopper_dataset):
    """A bang-bang policy's data (one action dimension always at -1 or 1) gives a tanh-Gaussian no density to fit, so
    target_entropy='data' keeps -|A| and the run trains; a resume after a stop does not take the missing estimate for
    a run that trained at another target."""
    from drop_engine.data import Dataset

    d = hopper_dataset
    bang = d.actions.copy()
    bang[:, 0] = np.where(d.observations[:, 0] > np.median(d.observations[:, 0]), 1.0, -1.0)
    data = Dataset(d.observations, bang, d.rewards, d.next_observations, d.terminals, d.timeouts)
    cfg = _config("mopo", epochs=2, sac={"target_entropy": "data", "behaviour_fit_steps": 200})
    stop = Recorder(stop_in=Trainer._sac_steps, after=5)
    first = Trainer(data, cfg, tmp_path, stop)
    assert first.run().status == "stopped"
    assert first.behaviour_entropy is None and first.sac.target_entropy == -3.0
    assert "behaviour_fit" not in stop.phases
    assert Trainer(data, cfg, tmp_path, Recorder()).run().status == "completed"


def test_value_bound_reads_the_datas_largest_reward(tmp_path, hopper_dataset):
    """The ceiling on the critics' target is set from the data the run trains on, and its clipped share reported."""
    recorder = Recorder()
    t = Trainer(hopper_dataset, _config("mbpo", epochs=1, sac={"value_bound": True}), tmp_path, recorder)
    assert t.sac.max_reward == float(hopper_dataset.rewards.max())
    assert t.run().status == "completed"
    assert any("sac/target_clipped" in m for _, m in recorder.metrics)
