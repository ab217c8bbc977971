"""A worker killed mid-job: its heartbeat goes stale, another worker's reaper re-queues the job, and the second
attempt resumes from the newest checkpoint instead of starting over, with one continuous metrics history. Real
worker processes, killed with SIGKILL."""
from __future__ import annotations

import secrets
import time

import pytest

from .conftest import _Authed, kill_group, start_worker, stop_worker


@pytest.fixture
def crash_settings(settings):
    # A queue of its own, so the session's worker never takes these jobs; fast crash detection.
    return settings.model_copy(update={"queue": f"drop-crash-{secrets.token_hex(4)}", "stale_after_s": 6.0,
                                       "reap_every_s": 1.0})


def test_killed_worker_job_resumes_on_another(crash_settings, tokens, hopper_file, tmp_path):
    from fastapi.testclient import TestClient

    from app.main import create_app

    log = tmp_path / "workers.log"
    first = start_worker(crash_settings, log)
    second = None
    try:
        with TestClient(create_app(crash_settings), raise_server_exceptions=False) as client:
            alice = _Authed(client, tokens["alice"])
            ds = alice.api.upload_dataset(hopper_file)
            job = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke",
                                               "overrides": {"epochs": 6, "steps_per_epoch": 40}}).json()
            deadline = time.monotonic() + 90
            while time.monotonic() < deadline:
                cur = alice.get(f"/v1/jobs/{job['id']}").json()
                if cur["status"] == "running" and (cur["progress"] or {}).get("epoch", 0) >= 2:
                    break
                assert cur["status"] in ("queued", "running"), cur
                time.sleep(0.1)
            assert cur["status"] == "running", cur
            kill_group(first)
            killed_at_epoch = cur["progress"]["epoch"]

            second = start_worker(crash_settings, log)
            done = alice.api.wait(job["id"], timeout=150)
            assert done["status"] == "succeeded", (done, alice.get(f"/v1/jobs/{job['id']}/events").json())
            assert done["attempts"] == 2

            events = alice.get(f"/v1/jobs/{job['id']}/events", params={"limit": 1000}).json()["data"]
            messages = [e["message"] for e in events]
            requeued = next(i for i, m in enumerate(messages) if m.startswith("re-queued"))
            second_start = next(i for i, m in enumerate(messages) if m.startswith("running (attempt 2"))
            assert requeued < second_start
            after = events[second_start + 1:]
            assert not any(e["type"] == "progress" and e["data"]["phase"] == "dynamics" for e in after)
            first_epoch = next(e["data"]["epoch"] for e in after if e["type"] == "progress")
            assert 1 <= first_epoch <= killed_at_epoch + 1, "resumed from a checkpoint, not from scratch"

            # One continuous history: what the killed attempt reported after its checkpoint was replaced, not doubled.
            steps = [m["step"] for m in alice.get(f"/v1/jobs/{job['id']}/metrics",
                                                  params={"name": "sac/critic_loss", "limit": 1000}).json()["data"]]
            assert sorted(steps) == list(range(10, 6 * 40 + 1, 10)), steps  # smoke preset: logged every 10 steps
            evaluations = alice.get(f"/v1/jobs/{job['id']}/evaluations").json()["data"]
            assert sorted(e["epoch"] for e in evaluations) == [1, 2, 3, 4, 5, 6], evaluations
            scores = [e["normalized_score"] for e in sorted(evaluations, key=lambda e: e["epoch"])]
            assert (done["last_score"], done["best_score"]) == (scores[-1], max(scores))
            assert (done["best_epoch"], done["final_score"]) == (scores.index(max(scores)) + 1, sum(scores[-3:]) / 3)
            assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204
    finally:
        kill_group(first)
        if second is not None:
            stop_worker(second)
