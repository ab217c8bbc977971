"""A job's progress is a fraction of its phase's budget, and a phase without one says so rather than "step N/0"."""
from __future__ import annotations

import io

from drop_client import print_progress
from worker.callback import describe_progress


def test_fractions_are_of_the_phases_budget():
    assert describe_progress("dynamics", 0, 3, 60) == (
        {"phase": "dynamics", "epoch": 0, "step": 3, "total": 60, "fraction": 0.05}, "dynamics: step 3/60")
    progress, message = describe_progress("train", 4, 3000, 90_000)
    assert progress["fraction"] == 0.0333 and message == "train: epoch 4"
    assert describe_progress("export", 90, 1, 1)[0]["fraction"] == 1.0


def test_a_phase_without_a_budget_has_no_fraction():
    """The paper preset fits its ensemble until the holdout error stops improving: no epoch cap, so no total."""
    progress, message = describe_progress("dynamics", 0, 7, 0)
    assert progress["fraction"] is None and message == "dynamics: step 7"
    job = {"id": "job_1", "status": "running", "progress": progress, "last_score": None, "best_score": None,
           "error": None}
    out = io.StringIO()
    print_progress(job, out)
    assert out.getvalue() == "job_1: running, dynamics 7\n"
