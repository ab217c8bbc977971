"""Datasets: streamed upload, validation in a limited subprocess, list, get, delete."""
from __future__ import annotations

from fastapi import APIRouter, Query, Request, Response
from sqlalchemy.orm import Session

from kernel.settings import Settings

from ..core.deps import DB, Config, DatasetCursor, Owner
from ..core.pages import Page
from ..observability.metrics import counting_rejections
from . import service
from .schemas import DatasetOut, dataset

router = APIRouter(prefix="/v1/datasets", tags=["datasets"])


@router.post("", status_code=201, response_model=DatasetOut,
             summary="Upload a D4RL HDF5, .npz or Minari zip (raw body or multipart field 'file')")
@counting_rejections
async def upload_dataset(request: Request, name: str | None = Query(None, max_length=300),
                         owner: str = Owner, s: Session = DB, settings: Settings = Config) -> dict:
    return dataset(await service.create(request, owner, name, s, settings))


@router.get("", response_model=Page[DatasetOut], summary="List datasets, newest first")
def list_datasets(after: DatasetCursor = None, limit: int = Query(20, ge=1, le=100), owner: str = Owner,
                  s: Session = DB) -> dict:
    return service.page(s, owner, after, limit)


@router.get("/{dataset_id}", response_model=DatasetOut)
def get_dataset(dataset_id: str, owner: str = Owner, s: Session = DB) -> dict:
    return dataset(service.owned_dataset(s, owner, dataset_id))


@router.delete("/{dataset_id}", status_code=204, summary="Delete a dataset (409 while a job uses it)")
def delete_dataset(dataset_id: str, owner: str = Owner, s: Session = DB, settings: Settings = Config) -> Response:
    service.delete(s, owner, dataset_id, settings)
    return Response(status_code=204)
