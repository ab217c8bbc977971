"""What one job may ask for: every number bounded and finite, and overrides shallow. Each refusal is a 422 naming the
field."""
from __future__ import annotations

import json
from contextlib import ExitStack

import pytest

from app.db import upgrade

from .private_api import private_api, tiny_npz

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
