"""The API process killed and started again while jobs run, in the production layout (`drop api` and `drop worker` as
separate processes on PostgreSQL and Redis): the worker never notices, nothing is lost, and a client that polls, or
resumes its event stream with Last-Event-ID, carries on against the new process."""
from __future__ import annotations

import time

import pytest

from drop_client import DropClient, NetworkError

from .conftest import Api, past_first_epoch, start_worker, stop_worker


def test_jobs_and_clients_survive_an_api_restart(own_settings, hopper_file, tmp_path):
    from app.core.auth import create_token
    from kernel.db import make_engine, make_sessionmaker

    token = create_token(make_sessionmaker(make_engine(own_settings.database_url)), "alice")
    worker = start_worker(own_settings, tmp_path / "worker.log")
    api = Api(own_settings, tmp_path / "api.log")
    api.start()
    drop = DropClient(api.url, token, timeout=30)
    try:
        ds = drop.upload_dataset(hopper_file)
        spec = {"preset": "smoke", "overrides": {"epochs": 8, "steps_per_epoch": 40}}
        running = drop.create_job(ds["id"], **spec)
        queued = drop.create_job(ds["id"], seed=1, **spec)
        job = drop.wait(running["id"], until=past_first_epoch, timeout=90, poll_s=0.1)
        assert job["status"] == "running", job
        seen = list(drop.list_events(running["id"]))

        api.kill()
        with pytest.raises(NetworkError):
            drop.get_job(running["id"])
        time.sleep(2)  # the worker goes on training and recording meanwhile
        api.start()

        for job_id in (running["id"], queued["id"]):
            job = drop.wait(job_id, timeout=120, poll_s=0.25)
            assert job["status"] == "succeeded" and job["attempts"] == 1, job

        # The stream resumed from the last event seen before the restart delivers exactly the rest, in order.
        everything = list(drop.list_events(running["id"]))
        assert [e["id"] for e in everything[:len(seen)]] == [e["id"] for e in seen]
        assert list(drop.stream_events(running["id"], last_event_id=seen[-1]["id"])) == everything[len(seen):]
        assert everything[-1]["message"] == "succeeded"
        assert [e["epoch"] for e in drop.list_evaluations(running["id"])] == list(range(1, 9))
        assert drop.download_policy(running["id"], tmp_path).stat().st_size
    finally:
        drop.close()
        api.stop()
        stop_worker(worker)
