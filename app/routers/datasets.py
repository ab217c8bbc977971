"""Datasets: streamed upload, validation in a limited subprocess, list, get, delete."""
from __future__ import annotations

from fastapi import APIRouter, Query, Request, Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from .. import dataset_store, serialize
from ..deps import DB, Config, Owner, DatasetCursor, owned_dataset
from ..metrics import counting_rejections
from kernel.models import Dataset
from ..schemas import DatasetOut, Page
from kernel.settings import Settings

router = APIRouter(prefix="/v1/datasets", tags=["datasets"])


@router.post("", status_code=201, response_model=DatasetOut,
             summary="Upload a D4RL HDF5, .npz or Minari zip (raw body or multipart field 'file')")
@counting_rejections
async def upload_dataset(request: Request, name: str | None = Query(None, max_length=300),
                         owner: str = Owner, s: Session = DB, settings: Settings = Config) -> dict:
    return serialize.dataset(await dataset_store.create(request, owner, name, s, settings))


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
    dataset_store.delete(s, owner, dataset_id, settings)
    return Response(status_code=204)
