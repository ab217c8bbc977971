"""The dataset object the API answers with: its response model, for the OpenAPI schema, and the dict a row becomes."""
from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

from kernel.models import Dataset

from ..core.choices import DatasetFormat, EnvName
from ..core.pages import iso, timestamp


class DatasetOut(BaseModel):
    id: str
    object: Literal["dataset"]
    created_at: str = timestamp()
    name: str
    format: DatasetFormat
    size_bytes: int
    decoded_bytes: int = Field(description="rows x bytes of a float32 transition: what it takes once loaded; it counts "
                                           "toward the storage quota when larger than size_bytes")
    sha256: str
    env: EnvName | None = Field(description="the env the dataset's dimensions match, if exactly one")
    obs_dim: int
    act_dim: int
    report: dict[str, Any] = Field(description="what validation found: sizes, episodes, returns, warnings")


def dataset(row: Dataset) -> dict:
    return {
        "id": row.id, "object": "dataset", "created_at": iso(row.created_at), "name": row.name,
        "format": row.format, "size_bytes": row.size_bytes, "decoded_bytes": row.decoded_bytes, "sha256": row.sha256,
        "env": row.env, "obs_dim": row.obs_dim, "act_dim": row.act_dim, "report": row.report,
    }
