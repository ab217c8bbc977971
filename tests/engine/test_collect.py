"""`drop collect`: online SAC in the real hopper, the five D4RL kinds, validation, resume. Short runs, small nets."""
from __future__ import annotations

import fcntl

import h5py
import numpy as np
import pytest
import torch

import drop_engine.collect
from drop_engine import seeding
from drop_engine.cli import main
from drop_engine.collect import collect_datasets, collect_transitions, random_policy, read_arrays
from drop_engine.collect_config import KINDS, CollectConfig, OnlineConfig
from drop_engine.config import SACConfig
from drop_engine.data import describe, load_dataset
from drop_engine.envs import get_env, make_env
from drop_engine.online import OnlineSAC
from drop_engine.stopping import Stopped

SMALL = SACConfig(hidden=(64, 64), batch_size=64)


def small_online(**kw) -> OnlineConfig:
    # medium_return 100: reachable in ~1k updates of a small net, while the initial policy gets ~10.
    base = dict(env="hopper", steps=1500, warmup=300, eval_every=300, eval_episodes=3, medium_return=100.0, sac=SMALL)
    return OnlineConfig(**{**base, **kw})


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    out = tmp_path_factory.mktemp("collect")
    cfg = CollectConfig(small_online(), transitions=2000, num_envs=4)
    rows = collect_datasets(cfg, out, progress=False)
    return out, cfg, {r["kind"]: r for r in rows}


def test_every_kind_passes_upload_validation_and_round_trips(collected):
    out, cfg, rows = collected
    assert set(rows) == set(KINDS)
    for kind in KINDS:
        path = out / f"hopper-{kind}.hdf5"
        arrays, attrs = read_arrays(path)
        dataset = load_dataset(path, env="hopper")
        report = describe(dataset)
        assert report.env == "hopper" and report.warnings == []
        assert report.transitions == rows[kind]["transitions"] == len(arrays["rewards"])
        assert report.episodes == attrs["episodes"] == rows[kind]["episodes"]
        np.testing.assert_array_equal(dataset.observations, arrays["observations"])
        np.testing.assert_array_equal(dataset.next_observations, arrays["next_observations"])
        np.testing.assert_array_equal(dataset.terminals, arrays["terminals"])
        assert attrs["env_name"] == "Hopper-v4" and attrs["kind"] == kind and attrs["seed"] == 0
        assert attrs["drop_rl_version"] and np.isfinite(attrs["policy_return"])
        score = get_env("hopper").normalized_score(attrs["policy_return"])
        assert attrs["policy_normalized_score"] == pytest.approx(score)
        assert not (dataset.terminals & dataset.timeouts).any() and (dataset.terminals | dataset.timeouts)[-1]
        with h5py.File(path) as handle:
            assert handle["observations"].compression == "gzip"
    assert rows["random"]["transitions"] == rows["medium"]["transitions"] == rows["expert"]["transitions"] == 2000
    assert rows["medium-expert"]["transitions"] == 4000


def test_random_alone_skips_online_training_and_makes_the_same_file(collected, tmp_path):
    out, cfg, _ = collected
    [row] = collect_datasets(cfg, tmp_path, kinds=("random",), progress=False)
    assert row["kind"] == "random" and OnlineSAC(cfg.online, tmp_path / "hopper-sac").step == 0
    alone, full = read_arrays(tmp_path / "hopper-random.hdf5"), read_arrays(out / "hopper-random.hdf5")
    for key in alone[0]:
        np.testing.assert_array_equal(alone[0][key], full[0][key])
    assert alone[1]["policy_steps"].tolist() == full[1]["policy_steps"].tolist() == [0]


def test_medium_kinds_alone_stop_training_at_the_medium_policy_and_make_the_same_files(collected, tmp_path):
    """Nothing after the medium policy's evaluation changes `medium` or `medium-replay`, so training stops there; a
    later collection of `expert` continues from that checkpoint to the full run's files."""
    out, cfg, _ = collected
    collect_datasets(cfg, tmp_path, kinds=("medium", "medium-replay"), progress=False)
    agent = OnlineSAC(cfg.online, tmp_path / "hopper-sac")
    assert agent.medium is not None and agent.step == agent.medium.step < cfg.online.steps
    agent.close()
    collect_datasets(cfg, tmp_path, kinds=("expert",), progress=False)
    for kind in ("medium", "medium-replay", "expert"):
        alone, full = read_arrays(tmp_path / f"hopper-{kind}.hdf5"), read_arrays(out / f"hopper-{kind}.hdf5")
        assert alone[1]["policy_steps"].tolist() == full[1]["policy_steps"].tolist()
        for key in full[0]:
            np.testing.assert_array_equal(alone[0][key], full[0][key])


def test_medium_kinds_alone_train_to_the_end_when_no_policy_reaches_the_bar(tmp_path):
    cfg = CollectConfig(small_online(steps=600, medium_return=1e9), transitions=200, num_envs=2)
    with pytest.warns(UserWarning, match="no evaluation reached the medium return"):
        [row] = collect_datasets(cfg, tmp_path, kinds=("medium",), progress=False)
    agent = OnlineSAC(cfg.online, tmp_path / "hopper-sac")
    assert agent.step == 600 and agent.medium is None
    agent.close()
    assert not read_arrays(tmp_path / "hopper-medium.hdf5")[1]["medium_threshold_reached"]


def test_kinds_are_what_they_say(collected):
    out, cfg, rows = collected
    attrs = {k: read_arrays(out / f"hopper-{k}.hdf5")[1] for k in KINDS}
    assert attrs["random"]["policy_steps"].tolist() == [0]
    assert attrs["medium"]["medium_threshold_reached"] and attrs["medium"]["policy_return"] >= 100.0
    assert 0 < attrs["medium"]["policy_steps"][0] <= cfg.online.steps
    # expert is the best evaluated policy (the latest of equals), so medium-expert is never below medium.
    snapshots = torch.load(out / "hopper-sac" / "online.pt", weights_only=False)["snapshots"]
    best = max(snapshots[1:], key=lambda s: (s["mean_return"], s["step"]))
    assert attrs["expert"]["policy_steps"].tolist() == [best["step"]]
    assert attrs["expert"]["policy_return"] == best["mean_return"] >= attrs["medium"]["policy_return"]
    # A random policy falls at once; the medium one keeps hopping for much longer.
    assert rows["medium"]["mean_return"] > 2 * rows["random"]["mean_return"]
    assert rows["medium"]["episodes"] < rows["random"]["episodes"]
    # medium-replay is the agent's own experience up to the medium policy: the warm-up then the learning actor.
    assert rows["medium-replay"]["transitions"] == attrs["medium"]["policy_steps"][0]
    state = torch.load(out / "hopper-sac" / "online.pt", weights_only=False)
    replay, _ = read_arrays(out / "hopper-medium-replay.hdf5")
    np.testing.assert_array_equal(replay["actions"], state["history"]["actions"][: len(replay["actions"])])
    medium, _ = read_arrays(out / "hopper-medium.hdf5")
    expert, _ = read_arrays(out / "hopper-expert.hdf5")
    mixed, _ = read_arrays(out / "hopper-medium-expert.hdf5")
    np.testing.assert_array_equal(mixed["observations"],
                                  np.concatenate([medium["observations"], expert["observations"]]))


def test_qpos_qvel_recompute_the_next_state(collected):
    """infos/qpos and infos/qvel are each row's MuJoCo state: setting it and stepping gives next_observations."""
    out, _, _ = collected
    for kind in ("medium", "medium-replay"):
        arrays, _ = read_arrays(out / f"hopper-{kind}.hdf5")
        env = make_env("hopper")
        env.reset(seed=0)
        raw = env.unwrapped
        for i in range(0, len(arrays["rewards"]), 97):
            raw.set_state(arrays["infos/qpos"][i], arrays["infos/qvel"][i])
            next_obs, reward, *_ = raw.step(arrays["actions"][i].astype(np.float64))
            np.testing.assert_allclose(next_obs, arrays["next_observations"][i], atol=1e-5)
            assert reward == pytest.approx(arrays["rewards"][i], abs=1e-4)
        env.close()


def test_collect_transitions_batches_envs_and_keeps_episodes_contiguous():
    one = collect_transitions("hopper", random_policy(3, seed=1), 300, seed=5)
    again = collect_transitions("hopper", random_policy(3, seed=1), 300, seed=5)
    many = collect_transitions("hopper", random_policy(3, seed=1), 300, seed=5, num_envs=4)
    np.testing.assert_array_equal(one["observations"], again["observations"])
    for arrays in (one, many):
        assert len(arrays["rewards"]) == 300
        ends = arrays["terminals"] | arrays["timeouts"]
        # inside an episode each row starts where the previous one ended
        inside = ~ends[:-1]
        np.testing.assert_array_equal(arrays["observations"][1:][inside], arrays["next_observations"][:-1][inside])
        assert ends[-1]


def test_a_stopped_collection_closes_its_envs(monkeypatch):
    """`progress` raises Stopped when the user stops `drop collect`: the MuJoCo envs are closed on the way out."""
    made, closed = [], []

    def tracked(*args):
        env = make_env(*args)
        made.append(env)
        close = env.close
        env.close = lambda: (closed.append(env), close())
        return env

    def stop(rows: int) -> None:
        raise Stopped

    monkeypatch.setattr(drop_engine.collect, "make_env", tracked)
    with pytest.raises(Stopped):
        collect_transitions("hopper", random_policy(3, seed=0), 5000, num_envs=3, progress=stop)
    assert len(made) == 3 and closed == made


def test_online_sac_refuses_a_value_bound_it_has_no_rewards_for():
    """The bound reads an offline dataset's largest reward; online, it would be infinite and silently do nothing."""
    with pytest.raises(ValueError, match="value_bound"):
        small_online(sac=SACConfig(hidden=(64, 64), value_bound=True))


def _params(agent: OnlineSAC) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in agent.sac.parameters()])


def test_resume_continues_the_same_run(tmp_path, monkeypatch):
    """Stopped mid-episode and restarted, the run picks up at its checkpoint and ends exactly where an uninterrupted
    one does (networks, optimiser moments, replay, env physics and RNGs all restored)."""
    cfg = small_online(steps=700, warmup=200, eval_every=350)
    straight = OnlineSAC(cfg, tmp_path / "a")
    assert straight.run()
    stopped = OnlineSAC(cfg, tmp_path / "b")
    assert not stopped.run(should_stop=lambda: stopped.step == 437)
    stopped.close()
    resumed = OnlineSAC(cfg, tmp_path / "b")
    assert resumed.resumed and resumed.step == 437 and resumed.history.n == 437 and len(resumed.buffer) == 437
    seen = []
    assert resumed.run(progress=lambda a: seen.append(a.step))
    assert seen[0] > 437  # continued, not restarted
    assert torch.equal(_params(straight), _params(resumed))
    for key, value in straight.history.state_dict().items():
        np.testing.assert_array_equal(value, resumed.history.state_dict()[key])
    assert [s.to_dict() for s in straight.snapshots] == [s.to_dict() for s in resumed.snapshots]
    with pytest.raises(ValueError, match="different settings"):
        OnlineSAC(small_online(steps=700, warmup=200, eval_every=350, seed=1), tmp_path / "b")
    # A checkpoint written before a SAC option existed resumes where the option is at its default, and not otherwise.
    path = resumed.checkpoint_path
    state = torch.load(path, weights_only=False)
    del state["config"]["sac"]["value_bound"]
    torch.save(state, path)
    assert OnlineSAC(cfg, tmp_path / "b").resumed
    with pytest.raises(ValueError, match=r"different settings \(sac\)"):
        OnlineSAC(small_online(steps=700, warmup=200, eval_every=350, sac=SMALL.model_copy(update={"tau": 0.01})),
                  tmp_path / "b")
    threads = torch.get_num_threads()
    torch.set_num_threads(threads + 1)
    try:
        with pytest.raises(ValueError, match=r"different settings \(threads\)"):
            OnlineSAC(cfg, tmp_path / "b")
    finally:
        torch.set_num_threads(threads)
    # On another kind of CPU the checkpoint would resume into other files (QUALITY.md E62).
    monkeypatch.setattr(seeding, "cpu_kind", lambda: "Another CPU (AVX2)")
    with pytest.raises(ValueError, match=r"different settings \(cpu\)"):
        OnlineSAC(cfg, tmp_path / "b")


def test_cli_collect_writes_summary_and_resumes(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["collect", "--env", "hopper", "--out", str(out), "--steps", "250", "--warmup", "200", "--eval-every", "125",
            "--eval-episodes", "1", "--transitions", "400", "--kinds", "random,medium-expert", "--no-progress"]
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        assert main(args) == 0
        assert torch.get_num_threads() == 1  # the default: a thread count is part of the files (QUALITY.md E22)
    finally:
        torch.set_num_threads(threads)
    table = capsys.readouterr().out
    assert "random" in table and "medium-expert" in table and "norm. score" in table
    assert sorted(p.name for p in out.glob("*.hdf5")) == ["hopper-medium-expert.hdf5", "hopper-random.hdf5"]
    written = {p.name: p.stat().st_mtime_ns for p in out.glob("*.hdf5")}
    assert main(args) == 0  # finished files are kept, not remade
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.hdf5")} == written
    with h5py.File(out / "hopper-medium-expert.hdf5", "r+") as handle:  # as an older rule's last-policy expert
        steps = handle.attrs["policy_steps"]
        handle.attrs["policy_steps"] = np.asarray([steps[0], steps[1] + 1], np.int64)
    stale = (out / "hopper-medium-expert.hdf5").stat().st_mtime_ns
    assert main(args) == 0  # a file made from other behaviour policies is made again
    assert (out / "hopper-medium-expert.hdf5").stat().st_mtime_ns != stale
    assert read_arrays(out / "hopper-medium-expert.hdf5")[1]["policy_steps"].tolist() == steps.tolist()
    assert main([*args[:-1], "--kinds", "nonsense"]) == 2


def test_a_second_collection_of_the_same_env_and_out_is_refused(tmp_path, capsys):
    """Two collections of one env into one directory would write one checkpoint through one temporary name: the
    second is refused at once, before it touches anything, and may run once the first has ended."""
    out = tmp_path / "out"
    args = ["collect", "--env", "hopper", "--out", str(out), "--steps", "250", "--warmup", "200", "--eval-every", "125",
            "--eval-episodes", "1", "--transitions", "200", "--kinds", "random", "--no-progress"]
    (out / "hopper-sac").mkdir(parents=True)
    with open(out / "hopper-sac" / "collect.lock", "a") as first:  # another open file: as another process's flock
        fcntl.flock(first, fcntl.LOCK_EX)
        assert main(args) == 75
        assert "another collection of hopper is writing into" in capsys.readouterr().err
        assert sorted(p.name for p in out.rglob("*")) == ["collect.lock", "hopper-sac"]
    assert main(args) == 0
    assert (out / "hopper-random.hdf5").is_file()
