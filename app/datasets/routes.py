"""Datasets: streamed upload, validation in a limited subprocess, list, get, delete."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response

from ..core.deps import AppSettings, DatasetCursor, DbSession, OwnerId
from ..core.fast_json import FastJSONResponse
from ..core.pages import Page
from ..observability.metrics import counting_rejections
from . import service
from .schemas import DatasetOut, dataset
from .upload import REQUEST_BODY

router = APIRouter(prefix="/v1/datasets", tags=["datasets"])


@router.post("", status_code=201, response_model=DatasetOut,
             summary="Upload a D4RL HDF5, .npz or Minari zip (raw body or multipart field 'file')",
             openapi_extra={"requestBody": REQUEST_BODY})
@counting_rejections
async def datasets_upload(request: Request, owner: OwnerId, s: DbSession, settings: AppSettings,
                          name: Annotated[str | None, Query(max_length=300)] = None) -> dict:
    return dataset(await service.create(request, owner, name, s, settings))


@router.get("", response_model=Page[DatasetOut], summary="List datasets, newest first")
def datasets_list(owner: OwnerId, s: DbSession, after: DatasetCursor = None,
                  limit: Annotated[int, Query(ge=1, le=100)] = 20) -> dict:
    return service.page(s, owner, after, limit)


@router.get("/{dataset_id}", response_model=DatasetOut)
async def datasets_get(dataset_id: str, request: Request, owner: OwnerId) -> FastJSONResponse:
    return FastJSONResponse(await service.get(request.app.state.fast_reads, owner, dataset_id))


@router.delete("/{dataset_id}", status_code=204, summary="Delete a dataset (409 while a job uses it)")
def datasets_delete(dataset_id: str, owner: OwnerId, s: DbSession, settings: AppSettings) -> Response:
    service.delete(s, owner, dataset_id, settings)
    return Response(status_code=204)
