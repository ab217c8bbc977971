"""`drop datasets ...` and `drop jobs ...`: a drop-rl server from the command line, through drop_client. Errors print
the problem's status, code and detail and exit 1."""
from __future__ import annotations

import functools
import sys
from typing import Callable, get_args

import click

from drop_client import DEFAULT_SERVER, ApiError, DropClient, DropError, JobStatus, PolicyFormat, Which, print_progress
from drop_engine.cli import Override
from drop_engine.config import PRESETS, Algorithm


def remote(command: Callable) -> Callable:
    """Give a command --server and --token (or DROP_SERVER, DROP_TOKEN) and call it with a client for them; a
    client error becomes a one-line message and exit status 1."""

    @functools.wraps(command)
    def call(server: str, token: str | None, **kw):
        try:
            with DropClient(server, token) as client:
                return command(client, **kw)
        except ApiError as exc:
            raise click.ClickException(f"{exc.status} {exc}") from exc
        except DropError as exc:
            raise click.ClickException(str(exc)) from exc

    call = click.option("--token", envvar="DROP_TOKEN", default=None,
                        help="bearer token (env DROP_TOKEN); none for `drop serve`, whose auth is off")(call)
    return click.option("--server", envvar="DROP_SERVER", default=DEFAULT_SERVER, show_default=True,
                        help="the API's base URL (env DROP_SERVER)")(call)


@click.group()
def datasets() -> None:
    """Datasets on a drop-rl server."""


@datasets.command("upload")
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
@click.option("--name", default=None, help="a label (default: the file's name)")
@remote
def datasets_upload(client: DropClient, file: str, name: str | None) -> None:
    """Upload and validate a D4RL-layout .hdf5 or .npz, or a zipped Minari dataset; print its id."""
    ds = client.upload_dataset(file, name=name)
    report = ds["report"]
    click.echo(f"{ds['name']}: env {ds['env']}, {report['transitions']} transitions, {report['episodes']} episodes",
               err=True)
    for warning in report.get("warnings") or []:
        click.echo(f"warning: {warning}", err=True)
    click.echo(ds["id"])


@datasets.command("list")
@remote
def datasets_list(client: DropClient) -> None:
    """List datasets, newest first."""
    rows = list(client.list_datasets())
    click.echo(f"{'id':<28} {'env':<12} {'transitions':>11} {'MB':>8}  {'created':<27} name")
    for ds in rows:
        click.echo(f"{ds['id']:<28} {ds['env'] or '-':<12} {ds['report']['transitions']:>11} "
                   f"{ds['size_bytes'] / 1e6:>8.1f}  {ds['created_at']:<27} {ds['name']}")


@datasets.command("rm")
@click.argument("dataset_ids", nargs=-1, required=True, metavar="DATASET_ID...")
@remote
def datasets_rm(client: DropClient, dataset_ids: tuple[str, ...]) -> None:
    """Delete datasets (refused while a job uses one)."""
    for dataset_id in dataset_ids:
        client.delete_dataset(dataset_id)
        click.echo(f"deleted {dataset_id}", err=True)


@click.group()
def jobs() -> None:
    """Training jobs on a drop-rl server."""


@jobs.command("submit")
@click.option("--dataset", "dataset_id", required=True, help="the dataset's id")
@click.option("--algorithm", type=click.Choice(get_args(Algorithm)), help="default: drop")
@click.option("--env", help="hopper | walker2d | halfcheetah (default: the env the dataset matches)")
@click.option("--preset", type=click.Choice(PRESETS), help="default: cpu")
@click.option("--task", help="dataset kind (random, medium, ...) selecting the paper's settings")
@click.option("--seed", type=int, help="default: 0")
@click.option("--set", "overrides", multiple=True, type=Override(),
              help="override a config field, e.g. --set dice.lr=1e-3 --set epochs=50")
@click.option("--max-runtime-s", type=int, help="time limit of one attempt (default: the server's)")
@click.option("--idempotency-key", help="sending the same key again returns the first request's job")
@click.option("--wait", "wait_done", is_flag=True,
              help="wait until the job ends, printing its progress; exit 1 unless it succeeded")
@remote
def jobs_submit(client: DropClient, dataset_id: str, algorithm: str | None, env: str | None, preset: str | None,
                task: str | None, seed: int | None, overrides: tuple[tuple[str, object], ...],
                max_runtime_s: int | None, idempotency_key: str | None, wait_done: bool) -> None:
    """Queue a training job; print its id."""
    job = client.create_job(dataset_id, algorithm=algorithm, env=env, preset=preset, task=task, seed=seed,
                            overrides=dict(overrides) or None, max_runtime_s=max_runtime_s,
                            idempotency_key=idempotency_key)
    click.echo(job["id"])
    if wait_done:
        _exit_by_outcome(client.wait(job["id"], progress=print_progress))


@jobs.command("list")
@click.option("--status", type=click.Choice(get_args(JobStatus)), help="only jobs of this status")
@remote
def jobs_list(client: DropClient, status: str | None) -> None:
    """List jobs, newest first."""
    rows = list(client.list_jobs(status))
    click.echo(f"{'id':<28} {'status':<11} {'algorithm':<9} {'env':<12} {'preset':<6} {'best':>6}  created")
    for job in rows:
        best = "-" if job["best_score"] is None else f"{job['best_score']:.1f}"
        click.echo(f"{job['id']:<28} {job['status']:<11} {job['algorithm']:<9} {job['env']:<12} {job['preset']:<6} "
                   f"{best:>6}  {job['created_at']}")


@jobs.command("status")
@click.argument("job_id")
@remote
def jobs_status(client: DropClient, job_id: str) -> None:
    """Show a job: status, progress, scores, error."""
    job = client.get_job(job_id)
    print_progress(job, sys.stdout)
    final = job["final_score"]
    fields = {"dataset": job["dataset_id"], "algorithm": job["algorithm"], "env": job["env"],
              "preset": job["preset"], "seed": job["seed"], "attempts": f"{job['attempts']}/{job['max_attempts']}",
              "best epoch": job["best_epoch"], "final score": None if final is None else f"{final:.1f}",
              "dynamics": _dynamics(job["dynamics"]),
              "created": job["created_at"], "started": job["started_at"], "finished": job["finished_at"]}
    for key, value in fields.items():
        if value is not None:
            click.echo(f"  {key:<12} {value}")


def _dynamics(dynamics: dict | None) -> str | None:
    """The ensemble a job trains on, in one line: its model-cache key and where it came from."""
    if dynamics is None:
        return None
    source = {True: "from the model cache", False: "trained for this job", None: "source unknown"}
    return (f"{(dynamics['cache_key'] or '-')[:16]} ({source[dynamics['from_cache']]}; {dynamics['epochs']} epochs, "
            f"stopped by {dynamics['stopped_by']})")


@jobs.command("logs")
@click.argument("job_id")
@click.option("--follow", "-f", is_flag=True,
              help="stream new events until the job ends; exit 1 unless it succeeded")
@click.option("--after", type=int, default=None, metavar="EVENT_ID", help="only events after this one")
@remote
def jobs_logs(client: DropClient, job_id: str, follow: bool, after: int | None) -> None:
    """Print a job's events."""
    events = client.stream_events(job_id, after) if follow else client.list_events(job_id, after or 0)
    for event in events:
        click.echo(f"{event['id']:>6}  {event['created_at']}  {event['type']:<10}  {event['message']}")
    if follow:
        _exit_by_outcome(client.get_job(job_id))


@jobs.command("cancel")
@click.argument("job_id")
@remote
def jobs_cancel(client: DropClient, job_id: str) -> None:
    """Cancel a job. A queued one at once, a running one at its next step."""
    job = client.cancel_job(job_id)
    click.echo(f"{job['id']}: {job['status']}")


@jobs.command("rm")
@click.argument("job_ids", nargs=-1, required=True, metavar="JOB_ID...")
@remote
def jobs_rm(client: DropClient, job_ids: tuple[str, ...]) -> None:
    """Delete finished jobs with their checkpoints and policies (refused while one is queued or running)."""
    for job_id in job_ids:
        client.delete_job(job_id)
        click.echo(f"deleted {job_id}", err=True)


@jobs.command("download")
@click.argument("job_id")
@click.option("--which", type=click.Choice(get_args(Which)), default="last", show_default=True,
              help="last: the policy after the final epoch; best: that of the best evaluation")
@click.option("--format", "fmt", type=click.Choice(get_args(PolicyFormat)),
              default="torchscript", show_default=True)
@click.option("--out", type=click.Path(), default=".", show_default=True,
              help="the file to write, or a directory to write it into under the server's name for it")
@remote
def jobs_download(client: DropClient, job_id: str, which: str, fmt: str, out: str) -> None:
    """Download a succeeded job's policy; print where it went."""
    click.echo(client.download_policy(job_id, out, which=which, format=fmt))


def _exit_by_outcome(job: dict) -> None:
    if job["status"] != "succeeded":
        error = f" ({job['error']['code']}: {job['error']['message']})" if job["error"] else ""
        raise click.ClickException(f"job {job['id']} {job['status']}{error}")

