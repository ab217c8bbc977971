"""The service's limits on one job, checked at creation against the engine's resource estimate: the engine's own
bounds suit one user's machine, while the service's workers are shared, so a job they could not hold (in memory or on
disk), would not finish or whose metrics would grow without bound is refused before it is queued."""
from __future__ import annotations

from drop_engine.config import TrainConfig
from drop_engine.resources import DataShape, ResourceEstimate, estimate
from kernel.settings import Settings

from ..core.problems import Problem


def _size(n: int) -> str:
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


def _count(n: int) -> str:
    return f"{n:,}"


def _memory(est: ResourceEstimate) -> str:
    parts = (("process", est.runtime_bytes), ("parameters", est.parameter_bytes), ("data", est.data_bytes),
             ("model buffer", est.model_buffer_bytes), ("largest phase", est.working_bytes))
    return f"estimated memory {_size(est.memory_bytes)} ({', '.join(f'{k} {_size(v)}' for k, v in parts)})"


def check(config: TrainConfig, shape: DataShape, settings: Settings) -> None:
    """Raise a 422 naming each limit the job would exceed (the config's field where one field is limited, the
    estimate's name where the whole run is), with the estimate; or return."""
    est = estimate(config, shape)
    checks = (
        ("eval_episodes", config.eval_episodes, "max_job_eval_episodes", f"eval_episodes {config.eval_episodes}",
         _count),
        ("estimate.memory_bytes", est.memory_bytes, "max_job_memory_bytes", _memory(est), _size),
        ("estimate.disk_bytes", est.disk_bytes, "max_job_disk_bytes",
         f"estimated checkpoint disk {_size(est.disk_bytes)} ({est.checkpoints_at_once} checkpoints of "
         f"{_size(est.checkpoint_bytes)}: keep_checkpoints and the newest, written before the oldest goes)", _size),
        ("estimate.sac_updates", est.sac_updates, "max_job_sac_updates",
         f"{_count(est.sac_updates)} SAC updates (epochs x steps_per_epoch)", _count),
        ("estimate.metric_rows", est.metric_rows, "max_job_metric_rows",
         f"an estimated {_count(est.metric_rows)} metric rows (mostly SAC reports every log_every steps)",
         _count),
    )
    errors = []
    for field, value, setting, what, show in checks:
        limit = getattr(settings, setting)
        if value > limit:
            message = f"{what} exceeds the server's limit of {show(limit)} (DROP_{setting.upper()})"
            errors.append({"field": field, "message": message, "limit": limit})
    if errors:
        raise Problem(422, "job_over_limit", "; ".join(e["message"] for e in errors), errors=errors,
                      estimate=est.to_dict())
