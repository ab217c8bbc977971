"""The model cache: one training per key across processes, nothing half-written ever loaded, cancellation honoured."""
from __future__ import annotations

import fcntl
import multiprocessing
import os
import time
from pathlib import Path

import pytest
import torch

from drop_engine.config import DynamicsConfig
from drop_engine.data import Dataset
from drop_engine.dynamics import DynamicsReport, build_ensemble, dynamics_rng, train_dynamics
from drop_engine.model_cache import ModelCache, model_key
from drop_engine.stopping import Stopped

CPU = torch.device("cpu")
TINY = DynamicsConfig(members=2, elites=1, hidden=8, layers=1, max_epochs=2, batch_size=256)


def _fetch(directory: Path, data: Dataset, seed: int = 0, *, trained: Path | None = None, hold_s: float = 0.0):
    """Fetch-or-train as the trainer does; `trained` gets one file per actual training."""
    model = build_ensemble(data.obs_dim, data.act_dim, TINY, seed, CPU)

    def fit() -> DynamicsReport:
        if trained is not None:
            (trained / f"{os.getpid()}-{time.monotonic_ns()}").touch()
        time.sleep(hold_s)  # keep the lock long enough that a concurrent caller surely asks meanwhile
        return train_dynamics(model, data, TINY, dynamics_rng(seed), CPU)

    report, from_cache = ModelCache(directory).fetch_or_train(model_key(data, TINY, seed), model, fit, lambda: False)
    return model, report, from_cache


def _fetch_in_process(directory: Path, data: Dataset, trained: Path, out: Path, barrier) -> None:
    torch.set_num_threads(1)
    barrier.wait()
    model, _, from_cache = _fetch(directory, data, trained=trained, hold_s=1.0)
    torch.save({"state": model.state_dict(), "from_cache": from_cache}, out)


def test_concurrent_requests_train_once(tmp_path, hopper_dataset):
    trained = tmp_path / "trained"
    trained.mkdir()
    ctx = multiprocessing.get_context("spawn")
    barrier = ctx.Barrier(2)
    outs = [tmp_path / f"{name}.pt" for name in "ab"]
    procs = [ctx.Process(target=_fetch_in_process, args=(tmp_path / "models", hopper_dataset, trained, out, barrier))
             for out in outs]
    for proc in procs:
        proc.start()
    for proc in procs:
        proc.join(120)
        assert proc.exitcode == 0
    assert len(list(trained.iterdir())) == 1
    a, b = (torch.load(out) for out in outs)
    assert sorted([a["from_cache"], b["from_cache"]]) == [False, True]
    for name, value in a["state"].items():
        assert torch.equal(value, b["state"][name]), name


def test_half_written_files_are_never_loaded(tmp_path, hopper_dataset):
    directory, trained = tmp_path / "models", tmp_path / "trained"
    trained.mkdir()
    reference, _, _ = _fetch(tmp_path / "reference", hopper_dataset)
    key = model_key(hopper_dataset, TINY, 0)
    final = ModelCache(directory).path(key)
    directory.mkdir()
    # A writer killed before its rename: the temporary file holds a complete-looking model, never at the final name.
    torch.save(torch.load(ModelCache(tmp_path / "reference").path(key)), final.with_name(f".{final.name}.tmp"))
    _, _, from_cache = _fetch(directory, hopper_dataset, trained=trained)
    assert not from_cache and len(list(trained.iterdir())) == 1

    # A final file cut short (a disk that lied about fsync): a miss with a warning, then replaced by a whole model.
    final.write_bytes(final.read_bytes()[: final.stat().st_size // 2])
    with pytest.warns(UserWarning, match="ignoring unusable"):
        model, _, from_cache = _fetch(directory, hopper_dataset, trained=trained)
    assert not from_cache and len(list(trained.iterdir())) == 2
    for name, value in reference.state_dict().items():
        assert torch.equal(value, model.state_dict()[name]), name
    _, _, from_cache = _fetch(directory, hopper_dataset, trained=trained)
    assert from_cache and len(list(trained.iterdir())) == 2


def test_key_follows_data_config_and_seed(hopper_dataset):
    key = model_key(hopper_dataset, TINY, 0)
    assert key == model_key(hopper_dataset, TINY.model_copy(), 0)
    assert key != model_key(hopper_dataset, TINY, 1)
    assert key == model_key(hopper_dataset, TINY, 0, "cpu") != model_key(hopper_dataset, TINY, 0, "cuda:0")
    assert key != model_key(hopper_dataset, TINY.model_copy(update={"max_epochs": 3}), 0)
    rewards = hopper_dataset.rewards.copy()
    rewards[7] += 1.0
    other = Dataset(hopper_dataset.observations, hopper_dataset.actions, rewards, hopper_dataset.next_observations,
                    hopper_dataset.terminals, hopper_dataset.timeouts)
    assert key != model_key(other, TINY, 0)


def test_stop_while_another_process_trains(tmp_path, hopper_dataset):
    cache = ModelCache(tmp_path)
    key = model_key(hopper_dataset, TINY, 0)
    model = build_ensemble(hopper_dataset.obs_dim, hopper_dataset.act_dim, TINY, 0, CPU)
    with open(tmp_path / f"{key}.lock", "a") as other:  # another open file: flock treats it as another process
        fcntl.flock(other, fcntl.LOCK_EX)
        with pytest.raises(Stopped):
            cache.fetch_or_train(key, model, lambda: pytest.fail("trained without the lock"), lambda: True)


def test_cancelled_training_is_not_stored(tmp_path, hopper_dataset):
    cache = ModelCache(tmp_path)
    key = model_key(hopper_dataset, TINY, 0)
    model = build_ensemble(hopper_dataset.obs_dim, hopper_dataset.act_dim, TINY, 0, CPU)

    epochs = []

    def fit() -> DynamicsReport:
        return train_dynamics(model, hopper_dataset, TINY, dynamics_rng(0), CPU, lambda epoch, _: epochs.append(epoch),
                              should_stop=lambda: len(epochs) == 1)  # stopped at the first batch of the second epoch

    with pytest.raises(Stopped):
        cache.fetch_or_train(key, model, fit, lambda: False)
    assert epochs == [1] and not cache.path(key).exists()


def test_a_failed_store_warns_and_keeps_the_run(tmp_path, hopper_dataset, monkeypatch):
    """A full or read-only cache costs later runs a training, never this run its model."""
    import errno

    import drop_engine.model_cache as module

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(module, "save_durably", full)
    cache = ModelCache(tmp_path)
    key = model_key(hopper_dataset, TINY, 0)
    model = build_ensemble(hopper_dataset.obs_dim, hopper_dataset.act_dim, TINY, 0, CPU)
    with pytest.warns(UserWarning, match="could not store"):
        report, from_cache = cache.fetch_or_train(
            key, model, lambda: train_dynamics(model, hopper_dataset, TINY, dynamics_rng(0), CPU), lambda: False)
    assert report.epochs == TINY.max_epochs and not from_cache and not cache.path(key).exists()
