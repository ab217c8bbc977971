"""The service behind /v1/datasets: an upload streamed, validated and saved within the owner's limits, the owner's
datasets, and a delete that cannot pass a job being created on the same dataset."""
from __future__ import annotations

import logging
from pathlib import Path

from fastapi import Request
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import bindparam, select
from sqlalchemy.orm import Session

from drop_engine.data_rows import DataShape
from drop_engine.envs import ENVS
from kernel.fast_reads import FastReads
from kernel.ids import is_id, new_id
from kernel.job_state import ACTIVE, status_in
from kernel.models import Dataset, DeletedDataset, Job
from kernel.settings import Settings
from kernel.storage import dataset_dir, remove_tree, to_stored, upload_dir

from ..core.pages import fetch_page
from ..core.problems import Problem
from ..observability.metrics import UPLOAD_BYTES, VALIDATION_SECONDS
from ..owners import quotas
from ..owners.lock import lock_owner
from .schemas import dataset as dataset_dict
from .upload import Upload, receive
from .validate import Invalid

log = logging.getLogger("drop.api")

DATASET = select(Dataset.__table__).where(Dataset.id == bindparam("dataset_id"),
                                          Dataset.owner_id == bindparam("owner"))


def _not_found(dataset_id: str) -> Problem:
    return Problem(404, "not_found", f"dataset {dataset_id} not found")


def owned_dataset(s: Session, owner_id: str, dataset_id: str) -> Dataset:
    """The owner's dataset or 404 (for the changes, which hold an ORM session)."""
    q = select(Dataset).where(Dataset.id == dataset_id, Dataset.owner_id == owner_id)
    row = s.scalar(q) if is_id(dataset_id, "ds") else None
    if row is None:
        raise _not_found(dataset_id)
    return row


async def get(reads: FastReads, owner: str, dataset_id: str) -> dict:
    """The owner's dataset, read as the job reads are (app/jobs/reads.py), or 404."""
    row = await reads.one(DATASET, dataset_id=dataset_id, owner=owner) if is_id(dataset_id, "ds") else None
    if row is None:
        raise _not_found(dataset_id)
    return dataset_dict(row)


def page(s: Session, owner: str, after: str | None, limit: int) -> dict:
    """The owner's datasets, newest first, after the cursor `after`."""
    q = select(Dataset).where(Dataset.owner_id == owner)
    if after:
        q = q.where(Dataset.id < after)
    return fetch_page(s, q.order_by(Dataset.id.desc()), dataset_dict, limit)


def _save(s: Session, row: Dataset, settings: Settings) -> None:
    quotas.check_storage(s, row.owner_id, settings, row)
    s.add(row)
    s.commit()


def _staging(target: Path) -> Path:
    return target.with_name(f"{target.name}.part")


async def _validate(request: Request, upload: Upload, dataset_id: str, owner: str) -> Dataset:
    """The dataset row of a received upload, once the validator has accepted it and written its file: into a `.part`
    folder, which takes the dataset's name only when complete, so a process killed while validating leaves only
    `.part`s (killed between the rename and the row's commit, it leaves the folder)."""
    settings = request.app.state.settings
    target = dataset_dir(settings, dataset_id)
    staging = _staging(target)
    staging.mkdir(parents=True)
    try:
        result = await request.app.state.validator.validate(upload.path, staging, VALIDATION_SECONDS.time())
    except Invalid as exc:
        raise Problem(422, "invalid_dataset", str(exc)) from None
    report = result["report"]
    if not report["env_candidates"]:  # no job could ever run on it: every job trains and evaluates in one of these
        known = ", ".join(f"{spec.name} ({spec.obs_dim}, {spec.act_dim})" for spec in ENVS.values())
        raise Problem(422, "invalid_dataset", f"observations, actions: dims ({report['obs_dim']}, {report['act_dim']}) "
                                              f"match no supported env; (obs, act) dims of each: {known}")
    staging.rename(target)
    return Dataset(id=dataset_id, owner_id=owner, name=upload.filename[:300], format=result["format"],
                   sha256=upload.sha256, size_bytes=upload.size,
                   decoded_bytes=DataShape(report["transitions"], report["obs_dim"], report["act_dim"]).decoded_bytes,
                   path=to_stored(settings, target / result["file"]), env=report.get("env"), obs_dim=report["obs_dim"],
                   act_dim=report["act_dim"], report=report)


async def create(request: Request, owner: str, name: str | None, s: Session, settings: Settings) -> Dataset:
    """Receive, validate and record an upload, holding one of the owner's upload slots throughout (429 past them);
    nothing is left behind on any failure."""
    with request.app.state.upload_slots.hold(owner):
        dataset_id = new_id("ds")
        part = upload_dir(settings) / f"{dataset_id}.part"
        limit, too_large = await run_in_threadpool(quotas.upload_limit, s, owner, settings)
        try:
            upload = await receive(request, part, limit, name, too_large)
            UPLOAD_BYTES.inc(upload.size)
            try:
                row = await _validate(request, upload, dataset_id, owner)
                await run_in_threadpool(_save, s, row, settings)  # a busy SQLite must not block the event loop
            except BaseException:
                target = dataset_dir(settings, dataset_id)
                remove_tree(_staging(target))
                remove_tree(target)
                raise
        finally:
            part.unlink(missing_ok=True)
    return row


def delete(s: Session, owner: str, dataset_id: str, settings: Settings) -> None:
    """Delete the dataset, or 409 while a job uses it. The owner's lock, taken before anything is read, orders this
    against a job's creation on any backend: either the job exists first and this answers 409, or the dataset is gone
    first and the job's creation answers 404. The row goes before the folder, and a tombstone stays until the folder is
    gone: a crash in between leaves a folder the next API start removes, never a listed dataset without its file."""
    lock_owner(s, owner)
    row = owned_dataset(s, owner, dataset_id)
    busy = s.scalar(select(Job.id).where(Job.dataset_id == dataset_id, status_in(ACTIVE)).limit(1))
    if busy:
        raise Problem(409, "dataset_in_use", f"dataset {dataset_id} is used by job {busy}, which has not finished")
    s.add(DeletedDataset(id=row.id))  # until its folder is gone too
    s.delete(row)
    s.commit()
    try:
        remove_deleted_folders(s, settings, [dataset_id])
    except Exception:  # the dataset is deleted: its tombstone stays, and the next API start removes the folder
        log.warning("dataset %s: deleted, but its folder was not removed", dataset_id, exc_info=True)


def remove_deleted_folders(s: Session, settings: Settings, ids: list[str]) -> list[Path]:
    """Remove the folders of deleted datasets, then the tombstones of those now gone. A tombstone whose folder was not
    there stays: on a DROP_DATA_DIR other than the one the delete used (a volume not mounted) every folder looks gone,
    and dropping their tombstones would leak the real ones for good."""
    found = [folder for folder in (dataset_dir(settings, dataset_id) for dataset_id in ids) if folder.exists()]
    for folder in found:
        remove_tree(folder)
    removed = [folder for folder in found if not folder.exists()]  # rmtree ignores what it could not remove
    for start in range(0, len(removed), 500):  # under SQLite's limit on bound parameters
        names = [folder.name for folder in removed[start:start + 500]]
        s.execute(DeletedDataset.__table__.delete().where(DeletedDataset.id.in_(names)))
    s.commit()
    return removed


def longest_quiet_s(settings: Settings) -> float:
    """The longest an upload in progress leaves its files untouched: a body's idle timeout, then a wait for a validator
    behind every other upload this process holds, then its own validation."""
    waits = -(-settings.max_concurrent_uploads // settings.max_concurrent_validations)
    return settings.body_idle_timeout_s + (waits + 1) * settings.validate_timeout_s
