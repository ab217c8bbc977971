"""A client generated from the service's own /openapi.json, with openapi-python-client and offline, runs the whole
path against `drop api` and a worker: upload a dataset (multipart and raw), create a smoke job, wait for it, and
download its policy, with its bearer token; a bad token comes back as a parsed problem."""
from __future__ import annotations

import importlib
import json
import secrets
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest

from .datasets import tiny_npz
from .processes import Api

PACKAGE = "drop_api_client"
# No formatter run after generating (nothing to format for a test), and the learning curve's PNG read as bytes.
GENERATOR_CONFIG = {"post_hooks": [], "content_type_overrides": {"image/png": "application/octet-stream"}}


@pytest.fixture
def api_url(settings, worker, tmp_path):
    """`drop api` over the session's database and the queue the session's worker reads."""
    api = Api(settings, tmp_path / "api.log")
    api.start()
    try:
        yield api.url
    finally:
        api.stop()


@pytest.fixture
def generated(api_url, tmp_path, monkeypatch):
    """The client package generated from the running service's schema, imported; any generator warning (an
    operation or a body it could not read) fails the test."""
    spec, config = tmp_path / "openapi.json", tmp_path / "generator.json"
    spec.write_text(httpx.get(f"{api_url}/openapi.json").text)
    config.write_text(json.dumps(GENERATOR_CONFIG))
    run = subprocess.run([sys.executable, "-m", "openapi_python_client", "generate", "--path", str(spec), "--config",
                          str(config), "--meta", "none", "--output-path", str(tmp_path / PACKAGE), "--fail-on-warning"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        yield lambda name: importlib.import_module(f"{PACKAGE}.{name}")
    finally:
        for name in [m for m in sys.modules if m == PACKAGE or m.startswith(f"{PACKAGE}.")]:
            del sys.modules[name]


def test_a_generated_client_trains_and_downloads(generated, api_url, app, hopper_file, tmp_path):
    from app.core.auth import create_token
    from drop_engine.export import load_policy

    client_module, models, types = generated("client"), generated("models"), generated("types")
    api = {name: generated(f"api.{group}.{name}") for group, name in (
        ("datasets", "datasets_upload"), ("datasets", "datasets_list"), ("jobs", "jobs_create"), ("jobs", "jobs_get"),
        ("job_outputs", "jobs_get_policy"))}
    token = create_token(app.state.sessions, f"generated-{secrets.token_hex(4)}")
    client = client_module.AuthenticatedClient(base_url=api_url, token=token, timeout=httpx.Timeout(60.0))

    stranger = client_module.AuthenticatedClient(base_url=api_url, token="drop_unknown")
    refused = api["datasets_list"].sync(client=stranger)
    assert isinstance(refused, models.Problem) and (refused.status, refused.code) == (401, "unauthorized"), refused

    with open(hopper_file, "rb") as fh:
        body = models.DatasetsUploadFilesBody(file=types.File(payload=fh, file_name=hopper_file.name))
        dataset = api["datasets_upload"].sync(client=client, body=body)
    assert isinstance(dataset, models.DatasetOut), dataset
    assert (dataset.format_, dataset.env, dataset.name) == (models.DatasetFormat.HDF5, models.EnvName.HOPPER,
                                                         hopper_file.name)
    raw = api["datasets_upload"].sync(client=client, body=types.File(payload=tiny_npz(7)), name="raw.npz")
    assert isinstance(raw, models.DatasetOut) and (raw.format_, raw.name) == (models.DatasetFormat.NPZ, "raw.npz"), raw

    job = api["jobs_create"].sync(client=client, body=models.JobRequest(dataset_id=dataset.id,
                                                                        preset=models.Preset.SMOKE))
    assert isinstance(job, models.JobOut) and job.algorithm == models.Algorithm.DROP, job
    finished = {models.JobStatus.SUCCEEDED, models.JobStatus.FAILED, models.JobStatus.CANCELLED}
    deadline = time.monotonic() + 300
    while (job := api["jobs_get"].sync(client=client, job_id=job.id)).status not in finished:
        assert time.monotonic() < deadline, job
        time.sleep(0.5)
    assert job.status == models.JobStatus.SUCCEEDED, job

    which = generated("models.jobs_get_policy_which").JobsGetPolicyWhich
    formats = generated("models.jobs_get_policy_format").JobsGetPolicyFormat
    policy = api["jobs_get_policy"].sync(client=client, job_id=job.id, which=which.BEST, format_=formats.TORCHSCRIPT)
    path = tmp_path / "policy.pt"
    path.write_bytes(policy.payload.read())
    assert load_policy(path)(np.zeros((2, dataset.obs_dim), np.float32)).shape == (2, dataset.act_dim)
    metadata = api["jobs_get_policy"].sync(client=client, job_id=job.id, which=which.BEST, format_=formats.METADATA)
    assert json.loads(metadata.payload.read())["which"] == "best"
