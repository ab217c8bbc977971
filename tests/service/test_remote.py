"""The README's walkthrough with the Python client and with the `drop` CLI's remote commands, against both
deployments: `drop serve` (SQLite, filesystem broker, no auth) and `drop api` + `drop worker` (PostgreSQL, Redis,
bearer tokens): upload, submit a smoke job, follow its events, wait, download both policies, and typed errors."""
from __future__ import annotations

import json
import secrets
import subprocess
import sys

import pytest
import torch
from click.testing import CliRunner

from drop_cli import drop as drop_command
from drop_client import Conflict, DropClient, NotFound, Unauthorized, Unprocessable

from .backends import database
from .processes import REPO, Api, Serve, settings_env, start_worker, stop_worker


@pytest.fixture(scope="module", params=["serve", "api+worker"])
def deployment(request, tmp_path_factory):
    """(the server's URL, a bearer token or None where auth is off)."""
    folder = tmp_path_factory.mktemp(request.param.replace("+", "-"))
    if request.param == "serve":
        serve = Serve(folder)
        serve.start().close()
        try:
            yield serve.url, None
        finally:
            serve.stop()
        return
    from kernel.db import upgrade

    settings = request.getfixturevalue("settings")
    with database() as url:
        upgrade(url)
        own = settings.model_copy(update={"database_url": url, "queue": f"{settings.queue}-{secrets.token_hex(3)}"})
        token = subprocess.run([sys.executable, "-m", "drop_cli", "token", "create", "--name", "alice"], cwd=REPO,
                               env=settings_env(own), capture_output=True, text=True, check=True).stdout.strip()
        worker = start_worker(own, folder / "worker.log")
        api = Api(own, folder / "api.log")
        try:
            api.start()
            yield api.url, token
        finally:
            api.stop()
            stop_worker(worker)


def _policy_acts(path) -> bool:
    return torch.jit.load(path)(torch.zeros(2, 11)).shape == (2, 3)


def test_python_client(deployment, hopper_file, tmp_path):
    server, token = deployment
    with DropClient(server, token) as drop:
        ds = drop.upload_dataset(hopper_file, name="walkthrough.hdf5")
        assert (ds["name"], ds["env"], ds["report"]["transitions"]) == ("walkthrough.hdf5", "hopper", 2000)
        assert ds["id"] in [d["id"] for d in drop.list_datasets()]
        job = drop.create_job(ds["id"], algorithm="mopo", preset="smoke", overrides={"epochs": 2},
                              idempotency_key=f"walkthrough-{secrets.token_hex(4)}")

        events = list(drop.stream_events(job["id"]))  # live, until the job ends
        assert [e["data"]["status"] for e in events if e["type"] == "status"] == ["queued", "running", "succeeded"]
        assert {"progress", "evaluation", "checkpoint"} <= {e["type"] for e in events}
        assert list(drop.stream_events(job["id"], last_event_id=events[-3]["id"])) == events[-2:]
        assert list(drop.list_events(job["id"])) == events
        seen = []
        done = drop.wait(job["id"], progress=seen.append, timeout=60)
        assert done["status"] == "succeeded" and seen == [done]
        assert job["id"] in [j["id"] for j in drop.list_jobs("succeeded")]
        assert [e["epoch"] for e in drop.list_evaluations(job["id"])] == [1, 2]

        for which in ("last", "best"):
            assert _policy_acts(drop.download_policy(job["id"], tmp_path / f"{which}.pt", which=which))
            meta = drop.download_policy(job["id"], tmp_path, which=which, format="metadata")
            assert meta.name == f"{job['id']}-{which}-metadata.json" and json.loads(meta.read_text())["which"] == which
        best = json.loads((tmp_path / f"{job['id']}-best-metadata.json").read_text())
        assert (best["epoch"], best["normalized_score"]) == (done["best_epoch"], done["best_score"])

        with pytest.raises(Unprocessable) as mismatch:
            drop.create_job(ds["id"], env="walker2d", preset="smoke")
        assert mismatch.value.code == "env_mismatch" and "walker2d" in mismatch.value.detail
        with pytest.raises(Conflict) as finished:
            drop.cancel_job(job["id"])
        assert finished.value.code == "job_finished"
        drop.delete_dataset(ds["id"])
        with pytest.raises(NotFound) as gone:
            drop.delete_dataset(ds["id"])
        assert gone.value.code == "not_found"
    if token:
        with DropClient(server, "not-a-token") as stranger, pytest.raises(Unauthorized) as refused:
            list(stranger.list_jobs())
        assert refused.value.code == "unauthorized"


def test_cli(deployment, hopper_file, tmp_path):
    server, token = deployment
    runner = CliRunner()

    def drop(*args: str, env: dict | None = None):
        return runner.invoke(drop_command, args, env={"DROP_SERVER": server, "DROP_TOKEN": token, **(env or {})})

    up = drop("datasets", "upload", str(hopper_file))
    assert up.exit_code == 0, up.output
    ds_id = up.stdout.strip()
    assert ds_id.startswith("ds_") and "env hopper, 2000 transitions" in up.stderr
    assert ds_id in drop("datasets", "list").stdout

    submitted = drop("jobs", "submit", "--dataset", ds_id, "--algorithm", "mopo", "--preset", "smoke",
                     "--set", "epochs=1")
    assert submitted.exit_code == 0, submitted.output
    job_id = submitted.stdout.strip()
    logs = drop("jobs", "logs", job_id, "--follow")
    assert logs.exit_code == 0, logs.output
    lines = logs.stdout.splitlines()
    assert "status" in lines[0] and lines[0].endswith("queued") and lines[-1].endswith("succeeded"), lines
    assert drop("jobs", "logs", job_id).stdout == logs.stdout
    status = drop("jobs", "status", job_id)
    assert status.exit_code == 0 and status.stdout.startswith(f"{job_id}: succeeded"), status.output
    with DropClient(server, token) as client:  # the model it trained on, by its cache key
        key = client.get_job(job_id)["dynamics"]["cache_key"]
    assert f"dynamics     {key[:16]} (" in status.stdout, status.output
    assert job_id in drop("jobs", "list", "--status", "succeeded").stdout

    for which in ("last", "best"):
        got = drop("jobs", "download", job_id, "--which", which, "--out", str(tmp_path / f"{which}.pt"))
        assert got.exit_code == 0 and _policy_acts(got.stdout.strip()), got.output
    meta = drop("jobs", "download", job_id, "--which", "best", "--format", "metadata", "--out", str(tmp_path))
    assert json.loads((tmp_path / f"{job_id}-best-metadata.json").read_text())["which"] == "best", meta.output

    # --wait prints the job's progress and exits 1 unless it succeeded: this one runs past its time limit.
    late = drop("jobs", "submit", "--dataset", ds_id, "--preset", "cpu", "--max-runtime-s", "5", "--wait")
    assert late.exit_code == 1, late.output
    late_id = late.stdout.strip()
    assert f"{late_id}: failed, timeout: the attempt ran past max_runtime_s=5" in late.stderr
    assert f"job {late_id} failed (timeout: the attempt ran past max_runtime_s=5)" in late.stderr

    # Errors: the problem's status, code and detail, and exit status 1 (2 for a usage error).
    cancel = drop("jobs", "cancel", job_id)
    assert cancel.exit_code == 1 and f"409 job_finished: job {job_id} has already finished" in cancel.stderr
    mismatch = drop("jobs", "submit", "--dataset", ds_id, "--env", "walker2d")
    assert mismatch.exit_code == 1 and "422 env_mismatch: env: walker2d" in mismatch.stderr
    assert drop("jobs", "download", job_id, "--which", "worst").exit_code == 2
    removed = drop("jobs", "rm", late_id, job_id)  # one failed, one succeeded: both finished, both go
    assert removed.exit_code == 0 and f"deleted {late_id}" in removed.stderr, removed.output
    again = drop("jobs", "rm", job_id)
    assert again.exit_code == 1 and "404 not_found" in again.stderr
    assert drop("datasets", "rm", ds_id).exit_code == 0
    gone = drop("datasets", "rm", ds_id)
    assert gone.exit_code == 1 and "404 not_found" in gone.stderr
    nowhere = drop("jobs", "status", job_id, "--server", "http://127.0.0.1:9")
    assert nowhere.exit_code == 1 and "http://127.0.0.1:9/v1/jobs/" in nowhere.stderr
    if token:
        refused = drop("jobs", "list", env={"DROP_TOKEN": "not-a-token"})
        assert refused.exit_code == 1 and "401 unauthorized" in refused.stderr
