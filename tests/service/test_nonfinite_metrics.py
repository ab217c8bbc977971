"""A metric that went NaN or infinite leaves the job readable: null in the job, no metric row, never a 500."""
from __future__ import annotations

from app.core.auth import get_or_create_owner
from kernel import job_state
from kernel.ids import new_id
from kernel.models import Job
from worker.callback import DbCallback


def test_non_finite_metrics_keep_the_job_readable(app, alice):
    sessions, job_id = app.state.sessions, new_id("job")
    with sessions.begin() as s:
        owner = get_or_create_owner(s, "alice")
        s.add(Job(id=job_id, owner_id=owner.id, algorithm="drop", env="hopper", preset="smoke", overrides={},
                  seed=0, config={}, status="running", attempts=1, max_attempts=3, max_runtime_s=600))
    try:
        DbCallback(sessions, job_id, 1, app.state.settings).on_metrics(
            {"sac/q_mean": float("nan"), "sac/critic_loss": float("inf"), "sac/alpha": 0.25}, 10)
        job = alice.get(f"/v1/jobs/{job_id}")
        assert job.status_code == 200, job.text
        assert job.json()["latest_metrics"] == {"sac/q_mean": None, "sac/critic_loss": None, "sac/alpha": 0.25,
                                                "step": 10}
        assert alice.get("/v1/jobs", params={"limit": 100}).status_code == 200
        rows = alice.get(f"/v1/jobs/{job_id}/metrics").json()["data"]
        assert [(r["name"], r["value"]) for r in rows] == [("sac/alpha", 0.25)]
    finally:  # the session's app is shared: a running job left behind would hold alice's quota and meet the reaper
        with sessions.begin() as s:
            assert job_state.transition(s, job_id, job_state.FAILED, source=job_state.RUNNING)
