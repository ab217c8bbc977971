"""The engine callback that records a run in the database: progress, metrics, evaluations, checkpoints, and the
cancellation check. Writes are fenced by the attempt number so a worker that lost its job cannot overwrite it."""
from __future__ import annotations

import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable, Mapping

from sqlalchemy import delete, func, select, update
from sqlalchemy.orm import Session, sessionmaker

from drop_engine.callbacks import Callback
from drop_engine.scores import summarize
from kernel.job_state import JobStatus, still_attempt
from kernel.models import Job, JobCheckpoint, JobEvaluation, JobEvent, JobMetric
from kernel.settings import Settings
from kernel.storage import from_stored, to_stored

PROGRESS_EVERY_S = 1.0


def describe_progress(phase: str, epoch: int, step: int, total: int) -> tuple[dict[str, Any], str]:
    """The job's `progress` and its event's message. `fraction` is of the phase's budget: a dynamics fit's epochs
    against its cap (it may stop earlier, by patience), SAC's updates against the run's. A fit without an epoch cap
    (the paper preset) has no budget: null, and no "/0" in the message."""
    fraction = round(min(step / total, 1.0), 4) if total else None
    progress = {"phase": phase, "epoch": epoch, "step": step, "total": total, "fraction": fraction}
    if phase == "train":
        return progress, f"train: epoch {epoch}"
    return progress, f"{phase}: step {step}/{total}" if total else f"{phase}: step {step}"


class DbCallback(Callback):
    def __init__(self, sessions: sessionmaker[Session], job_id: str, attempt: int, settings: Settings,
                 shutting_down: Callable[[], bool] = lambda: False):
        self.sessions, self.job_id, self.attempt, self.settings = sessions, job_id, attempt, settings
        self.cancel_poll_s = settings.cancel_poll_s
        self.shutting_down = shutting_down
        self._last_check = 0.0
        self._last_progress = 0.0
        self._phase_epoch: tuple[str, int] | None = None
        self.stop_reason: str | None = None  # "cancelled", "lost" or "shutdown"

    def _mine(self):
        return (Job.id == self.job_id) & still_attempt(self.attempt)

    def _score_columns(self, s: Session, *new: tuple[int, float]) -> dict:
        """The job's last, best, best_epoch and final score columns from its recorded evaluations plus `new` ones,
        by the engine's own rule, so the job agrees with the exported best policy."""
        rows = s.execute(select(JobEvaluation.epoch, JobEvaluation.normalized_score)
                         .where(JobEvaluation.job_id == self.job_id).order_by(JobEvaluation.epoch, JobEvaluation.id))
        return asdict(summarize([*map(tuple, rows), *new]))

    def on_start(self, resumed: tuple[int, int] | None) -> None:
        """Drop what a lost attempt recorded after the point this one starts from, so the job keeps one continuous
        metrics and evaluation history. Rows are ordered by their creation time: the lost attempt wrote both the
        checkpoint's row and the rows after it, with one clock."""
        with self.sessions.begin() as s:
            if s.scalar(select(Job.id).where(self._mine())) is None:
                return
            since = None
            if resumed is not None:
                since = s.scalar(select(func.max(JobCheckpoint.created_at)).where(
                    JobCheckpoint.job_id == self.job_id, JobCheckpoint.epoch == resumed[0],
                    JobCheckpoint.step == resumed[1]))
                if since is None:  # killed between writing the file and recording it: nothing came after it
                    return
            for table in (JobMetric, JobEvaluation):
                stale = delete(table).where(table.job_id == self.job_id)
                s.execute(stale if since is None else stale.where(table.created_at > since))
            s.execute(update(Job).where(self._mine()).values(**self._score_columns(s)))

    def on_progress(self, phase: str, epoch: int, step: int, total: int) -> None:
        now = time.monotonic()
        key = (phase, epoch)
        changed = key != self._phase_epoch
        if not changed and now - self._last_progress < PROGRESS_EVERY_S and step != total:
            return
        self._last_progress = now
        progress, message = describe_progress(phase, epoch, step, total)
        with self.sessions.begin() as s:
            if s.execute(update(Job).where(self._mine()).values(progress=progress)).rowcount and changed:
                s.add(JobEvent(job_id=self.job_id, type="progress", message=message, data=progress))
        self._phase_epoch = key

    def on_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        """A non-finite value shows as null in the job and writes no metric row: JSON has no NaN (PostgreSQL refuses
        it, and the API could not send it back)."""
        values = {k: float(v) for k, v in metrics.items()}
        finite = {k: v for k, v in values.items() if math.isfinite(v)}
        with self.sessions.begin() as s:
            latest = s.scalar(select(Job.latest_metrics).where(Job.id == self.job_id)) or {}
            latest = {**latest, **{k: finite.get(k) for k in values}, "step": step}
            if s.execute(update(Job).where(self._mine()).values(latest_metrics=latest)).rowcount:
                s.add_all(JobMetric(job_id=self.job_id, name=k, step=step, value=v) for k, v in finite.items())

    def on_dynamics(self, dynamics: Mapping[str, Any]) -> None:
        """The job shows which ensemble it trains on; the cache's path on the server stays out of it. The flag apart
        is what /metrics counts cache hits and misses by."""
        shown = {k: v for k, v in dynamics.items() if k != "cache_path"}
        with self.sessions.begin() as s:
            s.execute(update(Job).where(self._mine()).values(dynamics=shown, dynamics_from_cache=shown["from_cache"]))

    def on_evaluation(self, epoch: int, mean_return: float, normalized_score: float) -> None:
        with self.sessions.begin() as s:
            scores = self._score_columns(s, (epoch, normalized_score))
            if s.execute(update(Job).where(self._mine()).values(**scores)).rowcount:
                s.add(JobEvaluation(job_id=self.job_id, epoch=epoch, mean_return=mean_return,
                                    normalized_score=normalized_score))
                s.add(JobEvent(job_id=self.job_id, type="evaluation",
                               message=f"epoch {epoch}: return {mean_return:.1f}, score {normalized_score:.1f}",
                               data={"epoch": epoch, "mean_return": mean_return, "normalized_score": normalized_score}))

    def on_checkpoint(self, path: Path, epoch: int, step: int) -> None:
        stored = to_stored(self.settings, path)
        written = from_stored(self.settings, stored)
        with self.sessions.begin() as s:
            # A worker that lost the job (re-queued and claimed by another) must not touch the new attempt's rows.
            if s.scalar(select(Job.id).where(self._mine()).with_for_update()) is None:
                return
            for row in s.scalars(select(JobCheckpoint).where(JobCheckpoint.job_id == self.job_id)):
                # pruned by the trainer, or rewritten: a stop at an epoch boundary saves that epoch's name again
                earlier = from_stored(self.settings, row.path)  # a row of before may hold an absolute path
                if earlier == written or not earlier.exists():
                    s.delete(row)
            s.add(JobCheckpoint(job_id=self.job_id, epoch=epoch, step=step, path=stored,
                                size_bytes=path.stat().st_size if path.exists() else 0))
            s.add(JobEvent(job_id=self.job_id, type="checkpoint", message=f"checkpoint at epoch {epoch}, step {step}",
                           data={"epoch": epoch, "step": step}))

    def should_stop(self) -> bool:
        if self.stop_reason:
            return True
        now = time.monotonic()
        if now - self._last_check < self.cancel_poll_s:
            return False
        self._last_check = now
        if self.shutting_down():
            self.stop_reason = "shutdown"
            return True
        with self.sessions() as s:
            status = s.scalar(select(Job.status).where(self._mine()))
        if status is None:
            self.stop_reason = "lost"
        elif status == JobStatus.CANCELLING:
            self.stop_reason = "cancelled"
        return self.stop_reason is not None
