"""Datasets: streamed upload, validation in a limited subprocess, list, get, delete."""
from __future__ import annotations

from fastapi import APIRouter, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import select
from sqlalchemy.orm import Session

from .. import quotas, serialize
from ..deps import DB, Config, Owner, DatasetCursor, owned_dataset
from ..ids import new_id
from ..metrics import UPLOAD_BYTES, VALIDATION_SECONDS, counting_rejections
from ..models import ACTIVE_STATUSES, Dataset, Job
from ..problems import Problem
from ..schemas import DatasetOut, Page
from ..settings import Settings
from ..storage import dataset_dir, remove_tree, upload_dir
from ..upload import receive
from ..validate import Invalid, validate_file

router = APIRouter(prefix="/v1/datasets", tags=["datasets"])


def _save(s: Session, row: Dataset, settings: Settings) -> None:
    quotas.check_storage(s, row.owner_id, settings, row.size_bytes)
    s.add(row)
    s.commit()


@router.post("", status_code=201, response_model=DatasetOut,
             summary="Upload a D4RL HDF5, .npz or Minari zip (raw body or multipart field 'file')")
@counting_rejections
async def upload_dataset(request: Request, name: str | None = Query(None, max_length=300),
                         owner: str = Owner, s: Session = DB, settings: Settings = Config) -> dict:
    dataset_id = new_id("ds")
    part = upload_dir(settings) / f"{dataset_id}.part"
    limit, too_large = await run_in_threadpool(quotas.upload_limit, s, owner, settings)
    upload = await receive(request, part, limit, name, too_large)
    UPLOAD_BYTES.inc(upload.size)
    target = dataset_dir(settings, dataset_id)
    try:
        target.mkdir(parents=True)
        try:
            with VALIDATION_SECONDS.time():
                result = await validate_file(part, target, memory=settings.validate_memory_bytes,
                                             timeout=settings.validate_timeout_s, max_bytes=settings.max_upload_bytes)
        except Invalid as exc:
            raise Problem(422, "invalid_dataset", str(exc)) from None
        report = result["report"]
        row = Dataset(id=dataset_id, owner_id=owner, name=upload.filename[:300], format=result["format"],
                      sha256=upload.sha256, size_bytes=upload.size, path=str((target / result["file"]).resolve()),
                      env=report.get("env"), obs_dim=report["obs_dim"], act_dim=report["act_dim"], report=report)
        await run_in_threadpool(_save, s, row, settings)  # a busy SQLite must not block the event loop
    except BaseException:
        remove_tree(target)
        raise
    finally:
        part.unlink(missing_ok=True)
    return serialize.dataset(row)


@router.get("", response_model=Page[DatasetOut], summary="List datasets, newest first")
def list_datasets(after: DatasetCursor = None, limit: int = Query(20, ge=1, le=100), owner: str = Owner,
                  s: Session = DB) -> dict:
    q = select(Dataset).where(Dataset.owner_id == owner)
    if after:
        q = q.where(Dataset.id < after)
    return serialize.fetch_page(s, q.order_by(Dataset.id.desc()), serialize.dataset, limit)


@router.get("/{dataset_id}", response_model=DatasetOut)
def get_dataset(dataset_id: str, owner: str = Owner, s: Session = DB) -> dict:
    return serialize.dataset(owned_dataset(s, owner, dataset_id))


@router.delete("/{dataset_id}", status_code=204, summary="Delete a dataset (409 while a job uses it)")
def delete_dataset(dataset_id: str, owner: str = Owner, s: Session = DB, settings: Settings = Config) -> Response:
    row = owned_dataset(s, owner, dataset_id, lock=True)  # serialises with job creation on this dataset
    busy = s.scalar(select(Job.id).where(Job.dataset_id == dataset_id, Job.status.in_(ACTIVE_STATUSES)).limit(1))
    if busy:
        raise Problem(409, "dataset_in_use", f"dataset {dataset_id} is used by job {busy}, which has not finished")
    s.delete(row)
    s.commit()
    remove_tree(dataset_dir(settings, dataset_id))
    return Response(status_code=204)
