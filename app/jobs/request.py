"""Turn a job request into a validated engine config, or a 422 that names the bad field."""
from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from drop_engine.envs import get_env
from kernel.models import Dataset
from kernel.settings import Settings

from ..core.choices import Algorithm, EnvName, Preset, Task
from ..core.problems import Problem, one_of
from . import limits

# Identity fields are job fields, and the device and threads belong to the worker: not overridable.
RESERVED_OVERRIDES = {"algorithm", "env", "preset", "seed", "device", "task", "threads"}
# Overrides nest two levels ({"sac": {"hidden": [64, 64]}}); hundreds of levels overflow the serialiser's depth limit.
MAX_OVERRIDE_DEPTH = 8
# The engine's choices; a value outside them is refused with a code of its own.
AlgorithmChoice = one_of(Algorithm, "unknown_algorithm")
EnvChoice = one_of(EnvName, "unknown_env")
PresetChoice = one_of(Preset, "unknown_preset")
TaskChoice = one_of(Task, "unknown_task")


def _depth(value: Any) -> int:
    """Nesting depth of lists and dicts, walked without recursion, so no input can overflow the stack."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, (dict, list)):
            deepest = max(deepest, depth + 1)
            if deepest > MAX_OVERRIDE_DEPTH:
                break
            stack.extend((child, depth + 1) for child in (node.values() if isinstance(node, dict) else node))
    return deepest


class JobRequest(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    dataset_id: str
    algorithm: AlgorithmChoice = "drop"
    env: EnvChoice | None = Field(None, description="default: the env the dataset matches; a gymnasium id "
                                                    "(Hopper-v4) names its env too")
    preset: PresetChoice = "cpu"
    task: TaskChoice | None = Field(None, description="dataset kind selecting the paper's settings (default: "
                                                      "medium's)")
    overrides: dict[str, Any] = Field(default_factory=dict, description='dotted keys, e.g. {"epochs": 50}')
    seed: int = Field(0, ge=0, le=2**31 - 1)
    max_runtime_s: int | None = Field(None, ge=5, le=30 * 24 * 3600, description="time limit of one attempt")

    @field_validator("env", mode="before")
    @classmethod
    def _short_name(cls, env: Any) -> Any:
        """'Hopper-v4' and 'HOPPER' mean hopper, as the engine reads them."""
        try:
            return get_env(env).name if isinstance(env, str) else env
        except KeyError:
            return env  # refused as unknown_env

    @field_validator("overrides")
    @classmethod
    def _shallow(cls, overrides: dict[str, Any]) -> dict[str, Any]:
        if _depth(overrides) > MAX_OVERRIDE_DEPTH:
            raise ValueError(f"nested more than {MAX_OVERRIDE_DEPTH} levels deep")
        return overrides


def _invalid(code: str, detail: str, field: str) -> Problem:
    return Problem(422, code, detail, errors=[{"field": field, "message": detail}])


def build(req: JobRequest, dataset: Dataset, settings: Settings) -> tuple[str, dict]:
    """(env name, config as JSON) for this request on this dataset, within the server's limits on a job."""
    from drop_engine.config import build_config
    from drop_engine.errors import ConfigError
    from drop_engine.resources import DataShape

    env_name = req.env or dataset.env
    if env_name is None:
        candidates = ", ".join(dataset.report.get("env_candidates") or []) or "none"
        raise _invalid("env_required", f"env: the dataset matches no single env (candidates: {candidates}); set env",
                       "env")
    spec = get_env(env_name)
    if (spec.obs_dim, spec.act_dim) != (dataset.obs_dim, dataset.act_dim):
        raise _invalid("env_mismatch", f"env: {spec.name} has (obs, act) dims ({spec.obs_dim}, {spec.act_dim}) but "
                       f"dataset {dataset.id} has ({dataset.obs_dim}, {dataset.act_dim})", "env")
    bad = sorted(k for k in req.overrides if str(k).split(".")[0] in RESERVED_OVERRIDES)
    if bad:
        raise _invalid("invalid_override", f"overrides: {', '.join(bad)} cannot be overridden; use the job fields",
                       "overrides")
    try:
        config = build_config(req.algorithm, env=spec.name, preset=req.preset, task=req.task, overrides=req.overrides,
                              seed=req.seed, device="cpu")
    except ConfigError as exc:
        message = str(exc)
        field = message.split(":", 1)[0] if ":" in message else "overrides"
        raise _invalid("invalid_config", message, field) from None
    limits.check(config, DataShape(dataset.report["transitions"], dataset.obs_dim, dataset.act_dim), settings)
    return spec.name, config.model_dump(mode="json")
