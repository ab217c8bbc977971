"""What one job may ask for: every number bounded and finite, overrides shallow, and the whole run within the server's
limits on memory, SAC updates, metric rows and evaluation episodes. Each refusal is a 422 naming the field."""
from __future__ import annotations

import json
from contextlib import ExitStack

import pytest

from app.jobs.limits import check
from drop_engine.config import PRESETS, build_config
from drop_engine.resources import DataShape
from kernel.db import upgrade
from kernel.settings import Settings

from .datasets import tiny_npz
from .private_api import private_api

PROBLEM = "application/problem+json"


@pytest.fixture(scope="module")
def apis(settings, tmp_path_factory):
    """{backend: (client, dataset id)}: a private API with a tiny hopper dataset on PostgreSQL and on SQLite."""
    sqlite = f"sqlite:///{tmp_path_factory.mktemp('sqlite') / 'bounds.db'}"
    upgrade(sqlite)
    with ExitStack() as stack:
        out = {}
        for backend, overrides in (("postgresql", {}), ("sqlite", {"database_url": sqlite})):
            _, client = stack.enter_context(private_api(settings, **overrides))
            r = client.post("/v1/datasets", content=tiny_npz(0))
            assert r.status_code == 201, r.text
            out[backend] = client, r.json()["id"]
        yield out


def _post(apis, overrides_json: str, backend: str = "postgresql", **fields):
    """A job with overrides given as JSON text, so that NaN and Infinity literals reach the server as they are."""
    client, dataset_id = apis[backend]
    head = json.dumps({"dataset_id": dataset_id, "env": "hopper", "preset": "smoke", **fields})
    return client.post("/v1/jobs", content=f'{head[:-1]}, "overrides": {overrides_json}}}',
                       headers={"Content-Type": "application/json"})


def _refused(r, code: str, field: str) -> dict:
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, r.text
    problem = r.json()
    assert problem["code"] == code and field in {e["field"] for e in problem["errors"]}, problem
    return problem


@pytest.mark.parametrize("backend", ["postgresql", "sqlite"])
@pytest.mark.parametrize("overrides, field", [
    ('{"sac.actor_lr": NaN}', "sac.actor_lr"),
    ('{"penalty": {"eta": Infinity}}', "penalty.eta"),
    ('{"sac.target_entropy": -Infinity}', "sac.target_entropy"),
    ('{"penalty.clip": [0.01, Infinity]}', "penalty.clip.1"),
    ('{"dice.discount": NaN}', "dice.discount"),
    ('{"penalty.eta": 1e400}', "penalty.eta"),  # parsed as infinity
])
def test_non_finite_numbers_are_422(apis, backend, overrides, field):
    """Once accepted on SQLite (shown back as null while the worker ran with it) and a 500 on PostgreSQL."""
    _refused(_post(apis, overrides, backend), "invalid_config", field)


@pytest.mark.parametrize("overrides, field", [
    ({"rollout.batch_size": 10**9}, "rollout.batch_size"),
    ({"sac.hidden": [256, 10**6]}, "sac.hidden.1"),
    ({"dynamics.hidden": 10**6}, "dynamics.hidden"),
    ({"sac.batch_size": 10**8}, "sac.batch_size"),
    ({"eval_episodes": 10**6}, "eval_episodes"),
    ({"epochs": 10**9}, "epochs"),
    ({"steps_per_epoch": 10**9}, "steps_per_epoch"),
    ({"log_every": 10**12}, "log_every"),
])
def test_absurd_values_are_422(apis, overrides, field):
    _refused(_post(apis, json.dumps(overrides)), "invalid_config", field)


@pytest.mark.parametrize("depth", [9, 300, 900])
@pytest.mark.parametrize("nest", [lambda d: '{"a": ' * d + "1" + "}" * d,
                                  lambda d: '{"sac.hidden": ' + "[" * d + "]" * d + "}"], ids=["dicts", "lists"])
def test_deep_overrides_are_422(apis, depth, nest):
    """300 levels once overflowed the serialiser's depth limit: a 500."""
    problem = _refused(_post(apis, nest(depth)), "validation_error", "overrides")
    assert "nested more than 8 levels deep" in problem["detail"]


@pytest.mark.parametrize("overrides, field, setting", [
    ({"eval_episodes": 500}, "eval_episodes", "DROP_MAX_JOB_EVAL_EPISODES"),
    ({"rollout.batch_size": 1_000_000, "rollout.horizon": 1_000}, "estimate.memory_bytes",
     "DROP_MAX_JOB_MEMORY_BYTES"),
    ({"epochs": 100_000, "steps_per_epoch": 1_000}, "estimate.sac_updates", "DROP_MAX_JOB_SAC_UPDATES"),
    ({"keep_checkpoints": 100, "rollout.batch_size": 200_000}, "estimate.disk_bytes", "DROP_MAX_JOB_DISK_BYTES"),
    ({"epochs": 1_000, "steps_per_epoch": 1_000, "log_every": 1}, "estimate.metric_rows", "DROP_MAX_JOB_METRIC_ROWS"),
])
def test_jobs_over_the_server_limits_are_422(apis, overrides, field, setting):
    problem = _refused(_post(apis, json.dumps(overrides)), "job_over_limit", field)
    limit = getattr(Settings(), setting.removeprefix("DROP_").lower())
    assert [e["limit"] for e in problem["errors"] if e["field"] == field] == [limit]
    assert "exceeds the server's limit of" in problem["detail"] and f"({setting})" in problem["detail"]
    value = problem["estimate"][field.removeprefix("estimate.")] if "." in field else overrides[field]
    assert value > limit


def test_the_memory_detail_says_where_it_goes(apis):
    """Smoke DROP on 39 rows: a model buffer of 10^6 rollouts x 1,000 steps x 2 epochs x 108-byte rows, and rollouts
    holding their 1,000 transitions until complete, with 3 floats per step for the statistics besides each start
    state's tensors; and that buffer in each of the 3 checkpoints at once."""
    r = _post(apis, '{"rollout": {"batch_size": 1000000, "horizon": 1000}}')
    memory, disk = _refused(r, "job_over_limit", "estimate.memory_bytes")["detail"].split("; ")
    assert disk.startswith("estimated checkpoint disk 603 GiB (3 checkpoints of 201 GiB")
    assert memory == (
        "estimated memory 314 GiB (process 400 MiB, parameters 257 KiB, data 11.9 KiB, model buffer 201 GiB, "
        "largest phase 112 GiB) exceeds the server's limit of 8 GiB (DROP_MAX_JOB_MEMORY_BYTES)")


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_is_accepted(apis, preset):
    r = _post(apis, '{"sac": {"hidden": [256, 256]}}', preset=preset)
    assert r.status_code == 201, r.text


def test_the_limits_are_settings(settings):
    with private_api(settings, max_job_memory_bytes=300 << 20, max_job_eval_episodes=1) as (_, client):
        dataset_id = client.post("/v1/datasets", content=tiny_npz(1)).json()["id"]
        r = client.post("/v1/jobs", json={"dataset_id": dataset_id, "env": "hopper", "preset": "smoke"})
        problem = _refused(r, "job_over_limit", "estimate.memory_bytes")
        assert {e["field"] for e in problem["errors"]} == {"estimate.memory_bytes", "eval_episodes"}
        assert "limit of 300 MiB (DROP_MAX_JOB_MEMORY_BYTES)" in problem["detail"]


@pytest.mark.parametrize("preset", PRESETS)
def test_default_limits_admit_every_preset_on_a_large_dataset(preset):
    """2 million rows of 17-dim observations and 6-dim actions (halfcheetah-medium-expert's shape)."""
    shape = DataShape(2_000_000, 17, 6)
    for algorithm in ("drop", "mopo", "mbpo"):
        for env in ("hopper", "walker2d", "halfcheetah"):
            for task in ("random", "medium", "medium-replay", "medium-expert"):
                check(build_config(algorithm, env=env, preset=preset, task=task), shape, Settings())
