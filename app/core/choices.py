"""The engine's choices under the names the API's schema gives them: each is one named enum that requests and
responses share, so a client generated from the schema has one `Algorithm` type rather than one per field. (Job
statuses are `kernel.job_state.JobStatus`, an enum already.)"""
from __future__ import annotations

from typing_extensions import TypeAliasType

from drop_engine import config, envs, formats

Algorithm = TypeAliasType("Algorithm", config.Algorithm)
Preset = TypeAliasType("Preset", config.Preset)
Task = TypeAliasType("Task", config.Task)
EnvName = TypeAliasType("EnvName", envs.EnvName)
DatasetFormat = TypeAliasType("DatasetFormat", formats.Format)
