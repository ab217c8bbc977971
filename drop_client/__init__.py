"""drop-rl's Python client: upload datasets, run training jobs, follow them and download their policies over the REST
API. Needs only httpx and httpx-sse; it imports nothing of the service or the engine.

    with DropClient("http://127.0.0.1:8000", token) as drop:
        dataset = drop.upload_dataset("hopper-medium.hdf5")
        job = drop.create_job(dataset["id"], algorithm="drop", preset="smoke")
        drop.wait(job["id"], progress=print_progress)
        drop.download_policy(job["id"], "policy.pt", which="best")
"""
from .client import DEFAULT_SERVER, FINISHED, DropClient, JobStatus, PolicyFormat, Which, print_progress
from .errors import (
    ApiError,
    BadRequest,
    Conflict,
    DropError,
    NetworkError,
    NotFound,
    PayloadTooLarge,
    RateLimited,
    ServerError,
    StreamInterrupted,
    Unauthorized,
    Unprocessable,
    WaitTimeout,
)

__all__ = ["DEFAULT_SERVER", "FINISHED", "DropClient", "JobStatus", "PolicyFormat", "Which", "print_progress",
           "ApiError", "BadRequest", "Conflict", "DropError", "NetworkError", "NotFound", "PayloadTooLarge",
           "RateLimited", "ServerError", "StreamInterrupted", "Unauthorized", "Unprocessable", "WaitTimeout"]
